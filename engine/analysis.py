"""`tracemap analyse`: the measurements of a project's 3D trace map, in one atomic step.

Terminations and connectivity (engine.topology), censored trace lengths per set (engine.lengths) and, with
a radius, P21/P32 maps on the mesh (engine.intensity). Results are stored in the project — codes and group
labels on the traces, the rest as JSON results and per-vertex maps — in one transaction, so a failed or
cancelled analysis leaves the project as it was.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from engine.errors import InputError, Progress, report
from engine.intensity import imaged_faces, p21_map, p32_map
from engine.lengths import LengthAnalysis, analyse_lengths, by_set, length_table
from engine.mesh import Mesh
from engine.project import Project
from engine.raytrace import RayTracer
from engine.topology import Topology, analyse_topology, apply_components, apply_terminations
from engine.traces import Trace3D


@dataclass(frozen=True)
class Analysis:
    """What `analyse_project` measured and stored."""

    topology: Topology
    lengths: dict[str, LengthAnalysis]
    maps: dict[str, np.ndarray]


def analyse_project(project: Project, *, radius: float | None = None, scale: float = 2.5,
                    n_bootstrap: int = 199, progress: Progress | None = None) -> Analysis:
    """Analyse the project's 3D traces and store the results (see module docstring).

    radius : P21/P32 sphere radius in metres (None: no intensity maps).
    scale : topology tolerance in ground sampling distances (MATHS §6).
    n_bootstrap : parametric-bootstrap samples of the Anderson–Darling p-values (MATHS §9).
    """
    traces = project.traces3d()
    if not traces:
        raise InputError(project.path, "no 3D traces to analyse; run `tracemap extract` first")
    report(progress, 0.0, "reading the mesh")
    mesh = project.load_mesh()
    cameras = project.cameras()
    tracer = RayTracer(mesh.vertices, mesh.faces)
    report(progress, 0.2, "terminations and connectivity")
    topology = analyse_topology(traces, mesh=mesh, cameras=cameras, tracer=tracer, scale=scale)
    apply_terminations(traces, topology.terminations)
    apply_components(traces, topology.connectivity)
    report(progress, 0.5, "trace lengths")
    table = length_table(traces)
    lengths = {"all": analyse_lengths(table.surface, table.censored, n_bootstrap=n_bootstrap)}
    if np.any(table.set_id >= 0):
        lengths.update(by_set(table, n_bootstrap=n_bootstrap))
    maps, intensity = {}, None
    if radius is not None:
        report(progress, 0.7, "P21/P32 maps")
        imaged = imaged_faces(mesh, cameras, tracer)
        maps = intensity_maps(mesh, traces, radius=radius, imaged=imaged, sets=project.result("sets") or [])
        intensity = intensity_summary(traces, maps, radius=radius, imaged_area=float(mesh.face_areas[imaged].sum()))
    report(progress, 0.95, "storing")
    with project.transaction() as db:
        project.update_traces3d(traces, db)
        project.set_result("topology", _topology_result(topology), db)
        project.set_result("lengths", {k: asdict(v) for k, v in lengths.items()}, db)
        if maps:
            project.set_vertex_maps(maps, {"radius": radius}, db)
            project.set_result("intensity", intensity, db)
        project.record_basis(["topology", "lengths", *(["intensity"] if maps else [])], traces, db)
    report(progress, 1.0, "done")
    return Analysis(topology, lengths, maps)


def intensity_maps(mesh: Mesh, traces: list[Trace3D], *, radius: float, imaged: np.ndarray,
                   sets: list[dict], progress: Progress | None = None) -> dict[str, np.ndarray]:
    """P21 for all traces and per set, and P32 = Σ C(κ, θ)·P21 over the sets with a mean and κ (MATHS §8).

    sets : the stored set statistics of `tracemap orient` (id, normal, kappa); without them only P21.
    Map names: "p21", "p21:set<k>", "p32", "p32:set<k>".
    """
    p21 = p21_map(mesh, traces, radius=radius, imaged_faces=imaged, progress=progress)
    maps = {"p21": p21.p21, **{f"p21:set{k}": v for k, v in p21.p21_by_set.items()}}
    known = {int(s["id"]): s for s in sets if int(s["id"]) in p21.p21_by_set}
    if known:
        p32 = p32_map({k: p21.p21_by_set[k] for k in known}, {k: np.asarray(s["normal"]) for k, s in known.items()},
                      {k: float(s["kappa"]) for k, s in known.items()}, p21.normal)
        maps.update({"p32": p32.p32, **{f"p32:set{k}": v for k, v in p32.p32_by_set.items()}})
    return maps


def intensity_summary(traces: list[Trace3D], maps: dict[str, np.ndarray], *, radius: float,
                      imaged_area: float) -> dict:
    """The outcrop's P21 as one number per set and for all traces (their surface length over the imaged mesh
    area, m⁻¹), and the median and mean of each vertex map where it is defined (a summary of `maps`)."""
    lengths = {"all": sum(t.surface_length for t in traces)}
    for t in traces:
        if t.set_id >= 0:
            lengths[f"set{t.set_id}"] = lengths.get(f"set{t.set_id}", 0.0) + t.surface_length
    outcrop = {k: v / imaged_area if imaged_area > 0 else None for k, v in lengths.items()}
    stats = {}
    for name, values in maps.items():
        defined = values[np.isfinite(values)]
        stats[name.replace(":", "_")] = ({"median": float(np.median(defined)), "mean": float(defined.mean())}
                                         if len(defined) else None)
    return {"radius_m": radius, "imaged_area_m2": imaged_area, "p21_outcrop": outcrop, "maps": stats}


def _topology_result(topology: Topology) -> dict:
    return {"tolerance_m": topology.tolerance, "nodes": asdict(topology.nodes),
            "crossings": len(topology.crossings.distance),
            "components": int(len(topology.connectivity.sizes)),
            "largest_vertex_fraction": topology.connectivity.largest_vertex_fraction,
            "largest_length_fraction": topology.connectivity.largest_length_fraction}
