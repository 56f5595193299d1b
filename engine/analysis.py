"""`tracemap orient` and `tracemap analyse`: the measurements of a project's 3D trace map, each in one atomic step.

Orientation: the traces' poles (engine.orientation) and their sets (engine.sets), `orient_and_classify`.
Analysis: terminations and connectivity (engine.topology), censored trace lengths per set (engine.lengths),
`measure_traces`, and, with a radius, P21/P32 maps on the mesh (engine.intensity). Both compute on copies
of the traces, so the command line and the desktop application (which stores them as one undoable edit)
share them. `analyse_project` stores its results in the project — codes and group labels on the traces,
the rest as JSON results and per-vertex maps — in one transaction, so a failed or cancelled analysis
leaves the project as it was.
"""

from __future__ import annotations

import copy
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, replace

import numpy as np

from engine.cameras import Camera
from engine.errors import InputError, Progress, report
from engine.intensity import imaged_faces, p21_map, p32_map
from engine.lengths import LengthAnalysis, analyse_lengths, by_set, length_table
from engine.mesh import Mesh
from engine.orientation import orient_traces
from engine.project import Project
from engine.raytrace import RayTracer
from engine.relations import SetRelations, contacts_result, outcrop_relations
from engine.plots import Plot, project_plots
from engine.scan_circle import ScanCircle, WindowMeasure, measure_scan_circle, scan_circle_plot
from engine.scanline import Scanline, ScanlineMeasure, measure_scanline, scanline_plot
from engine.sets import Facet, SetModel, classify_traces
from engine.sight import Sight
from engine.topology import TOLERANCE_SCALE, Topology, analyse_topology, apply_components, apply_terminations
from engine.traces import NETWORK_KINDS, Trace3D, network

K_THRESHOLD = 0.8
"""Collinearity K above which a trace is oriented by the probabilistic solver (`tracemap orient`'s default)."""

N_BOOTSTRAP = 199
"""Parametric-bootstrap samples of the Anderson–Darling p-values (`tracemap analyse`'s default)."""


@dataclass(frozen=True)
class Orientation:
    """What `orient_and_classify` found: the oriented traces with their sets, the traces left as they were
    (under 3 vertices: a plane needs three points) and the set model."""

    traces: list[Trace3D]
    short: list[Trace3D]
    model: SetModel

    @property
    def results(self) -> dict[str, list[dict]]:
        """The project results it makes, by name."""
        return {"sets": [asdict(s) for s in self.model.sets],
                "density_peaks": [asdict(p) for p in self.model.peaks]}

    @property
    def summary(self) -> str:
        """One line for a person: how the traces were oriented and the sets found."""
        methods = {m: sum(t.method == m for t in self.traces) for m in ("eigen", "probabilistic")}
        fractures = network(self.traces)
        flat = sum(bool(t.extra.get("surface_plane")) for t in fractures)
        bedding = len(self.traces) - len(fractures)
        return (f"oriented {len(self.traces)} traces ({methods['eigen']} eigen, {methods['probabilistic']} "
                f"probabilistic); {self.model.n_sets} sets, {sum(t.set_id < 0 for t in fractures)} traces "
                "non-systematic" + (f" ({flat} of them lie in the outcrop surface's own plane)" if flat else "")
                + (f"; {bedding} bedding traces oriented apart, in no set" if bedding else "")
                + (f"; {len(self.short)} traces of under 3 vertices left unoriented" if self.short else ""))


def orient_and_classify(traces: Sequence[Trace3D], mesh: Mesh | None, *, facets: Sequence[Facet] = (),
                        n_sets: int | None = None, k_threshold: float = K_THRESHOLD,
                        progress: Progress | None = None) -> Orientation:
    """Orient copies of the traces of 3 or more vertices (`engine.orientation.orient_traces`) and fit the
    fractures' sets, poles weighted against the outcrop's sampling bias (`engine.sets.classify_traces` with
    Terzaghi weights; the accepted `facets` seed them); `traces` are left as they are. Bedding traces are
    oriented apart (their own set priors) and put in no set: bedding is no fracture set.

    n_sets : the number of sets, None to choose it (BIC); InputError when the traces cannot make that many.
    """
    short = [t for t in traces if len(t.points) < 3]
    kept = _copies(t for t in traces if len(t.points) >= 3)
    if not kept:
        raise InputError(None, f"none of the {len(traces)} traces has the 3 vertices a plane needs")
    fractures = network(kept)
    if not fractures:
        raise InputError(None, f"all {len(kept)} traces of 3 or more vertices are bedding; sets are fitted to "
                               f"the {', '.join(NETWORK_KINDS)} traces")
    bedding = [t for t in kept if t.kind not in NETWORK_KINDS]
    share = len(fractures) / len(kept)
    orient_traces(fractures, mesh, n_sets=n_sets, k_threshold=k_threshold,
                  progress=lambda f, m: report(progress, 0.9 * share * f, m))
    if bedding:
        orient_traces(bedding, mesh, k_threshold=k_threshold,
                      progress=lambda f, m: report(progress, 0.9 * (share + (1 - share) * f), m))
        for t in bedding:
            t.set_id = -1
    report(progress, 0.9, "fitting the sets")
    model = classify_traces(fractures, n_sets=n_sets, facets=facets, terzaghi=True)
    report(progress, 1.0, "orientation and sets done")
    return Orientation(kept, short, model)


@dataclass(frozen=True)
class Measurement:
    """What `measure_traces` found: the traces with their termination codes and connected groups, their
    topology and their lengths ("all" and per set), and the contacts by trace id (`contacts_result`)."""

    traces: list[Trace3D]
    topology: Topology
    lengths: dict[str, LengthAnalysis]
    contacts: dict

    @property
    def relations(self) -> SetRelations:
        """Abutting and crossing between the traces' sets and bedding (`engine.relations`)."""
        return outcrop_relations(self.traces, self.contacts)

    @property
    def results(self) -> dict[str, dict]:
        """The project results it makes, by name."""
        return {"topology": _topology_result(self.topology, self.contacts),
                "lengths": {k: asdict(v) for k, v in self.lengths.items()}}


def measure_traces(traces: Sequence[Trace3D], mesh: Mesh, cameras: Mapping[str, Camera], *,
                   tracer: RayTracer | None = None, scale: float = TOLERANCE_SCALE, n_bootstrap: int = N_BOOTSTRAP,
                   progress: Progress | None = None) -> Measurement:
    """Terminations and connectivity (codes set by hand are kept, engine.topology) and censored lengths of
    copies of the fracture, vein and fault traces; `traces` are left as they are. Bedding traces bound the
    network (an end on one abuts it) and are measured for nothing else.

    tracer : a RayTracer of `mesh`, built here if not given (to see whether a trace's continuation is hidden).
    scale : topology tolerance in ground sampling distances (MATHS §6).
    n_bootstrap : parametric-bootstrap samples of the Anderson–Darling p-values (MATHS §9).
    """
    traces = _copies(traces)
    fractures = network(traces)
    if not fractures:
        raise InputError(None, f"all {len(traces)} traces are bedding; the analysis measures the "
                               f"{', '.join(NETWORK_KINDS)} traces")
    bedding = [t for t in traces if t.kind not in NETWORK_KINDS]
    report(progress, 0.0, "terminations and connectivity")
    tracer = RayTracer(mesh.vertices, mesh.faces) if tracer is None else tracer
    topology = analyse_topology(fractures, mesh=mesh, cameras=cameras, tracer=tracer, scale=scale,
                                boundaries=bedding)
    apply_terminations(fractures, topology.terminations)
    apply_components(fractures, topology.connectivity)
    report(progress, 0.6, "trace lengths")
    table = length_table(fractures)
    lengths = {"all": analyse_lengths(table.surface, table.censored, n_bootstrap=n_bootstrap)}
    if np.any(table.set_id >= 0):
        lengths.update(by_set(table, n_bootstrap=n_bootstrap))
    report(progress, 1.0, "terminations and lengths done")
    contacts = contacts_result([*fractures, *bedding], topology.abutting, topology.crossings.traces)
    return Measurement(traces, topology, lengths, contacts)


def _copies(traces: Iterable[Trace3D]) -> list[Trace3D]:
    """Traces to orient or measure: the engine sets their fields and edits `extra` in place (the arrays are
    replaced, never written to, so they are shared)."""
    return [replace(t, extra=copy.deepcopy(t.extra)) for t in traces]


@dataclass(frozen=True)
class Analysis:
    """What `analyse_project` measured and stored."""

    topology: Topology
    lengths: dict[str, LengthAnalysis]
    maps: dict[str, np.ndarray]
    relations: SetRelations


def analyse_project(project: Project, *, radius: float | None = None, scale: float = TOLERANCE_SCALE,
                    n_bootstrap: int = N_BOOTSTRAP, progress: Progress | None = None) -> Analysis:
    """Analyse the project's 3D traces and store the results (see module docstring).

    radius : P21/P32 sphere radius in metres (None: no intensity maps).
    scale, n_bootstrap : as in `measure_traces`.
    """
    traces = project.traces3d()
    if not traces:
        raise InputError(project.path, "no 3D traces to analyse; run `tracemap extract` first")
    report(progress, 0.0, "reading the mesh")
    mesh = project.load_mesh()
    cameras = project.cameras()
    tracer = RayTracer(mesh.vertices, mesh.faces)
    measured = measure_traces(traces, mesh, cameras, tracer=tracer, scale=scale, n_bootstrap=n_bootstrap,
                              progress=lambda f, m: report(progress, 0.2 + 0.5 * f, m))
    traces = measured.traces
    maps, intensity = {}, None
    if radius is not None:
        report(progress, 0.7, "P21/P32 maps")
        imaged = imaged_faces(mesh, cameras, tracer)
        maps = intensity_maps(mesh, traces, radius=radius, imaged=imaged, sets=project.result("sets") or [])
        intensity = intensity_summary(traces, maps, radius=radius, imaged_area=float(mesh.face_areas[imaged].sum()))
    report(progress, 0.95, "storing")
    with project.transaction() as db:
        project.update_traces3d(traces, db)
        for name, value in measured.results.items():
            project.set_result(name, value, db)
        if maps:
            project.set_vertex_maps(maps, {"radius": radius}, db)
            project.set_result("intensity", intensity, db)
        project.record_basis([*measured.results, *(["intensity"] if maps else [])], traces, db)
    report(progress, 1.0, "done")
    return Analysis(measured.topology, measured.lengths, maps, measured.relations)


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
    area, m⁻¹), and the median and mean of each vertex map where it is defined (a summary of `maps`); bedding
    traces count in none."""
    traces = network(traces)
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


def measure_scanlines(project: Project, *, mesh: Mesh | None = None, lines: Sequence[Scanline] | None = None,
                      tracer: RayTracer | None = None) -> list[ScanlineMeasure]:
    """The stored scanlines (or `lines`) measured on the project's 3D traces as they are now, with the stored
    sets, on the rock the photos see (`project_sight`)."""
    lines = project.scanlines() if lines is None else lines
    if not lines:
        return []
    mesh = project.load_mesh() if mesh is None else mesh
    sight = project_sight(project, mesh, tracer)
    traces, sets = project.traces3d(), project.result("sets") or []
    return [measure_scanline(mesh, traces, line, sets=sets, sight=sight) for line in lines]


def project_figures(project: Project, *, mesh: Mesh | None = None, tracer: RayTracer | None = None) -> dict[str, Plot]:
    """What `tracemap plot` writes: the analysis plots (`engine.plots.project_plots`), each scanline's
    cumulative crossings (`engine.scanline.scanline_plot`) and the scan circles on the face
    (`engine.scan_circle.scan_circle_plot`), in the readouts' frame."""
    plots = project_plots(project)
    registration = project.registration()
    similarity = None if registration is None else registration.similarity
    scanlines, windows = measure_samples(project, mesh=mesh, tracer=tracer)
    for plot in [scanline_plot(m, similarity) for m in scanlines] + ([scan_circle_plot(windows, similarity)]
                                                                     if windows else []):
        plots[plot.name] = plot
    return plots


def measure_scan_circles(project: Project, *, mesh: Mesh | None = None, circles: Sequence[ScanCircle] | None = None,
                         tracer: RayTracer | None = None) -> list[WindowMeasure]:
    """The stored scan circles (or `circles`) measured on the project's 3D traces as they are now, with the
    share of each window the photos see (`project_sight`)."""
    circles = project.scan_circles() if circles is None else circles
    if not circles:
        return []
    mesh = project.load_mesh() if mesh is None else mesh
    sight, traces = project_sight(project, mesh, tracer), project.traces3d()
    return [measure_scan_circle(mesh, traces, circle, sight=sight) for circle in circles]


def measure_samples(project: Project, *, mesh: Mesh | None = None,
                    tracer: RayTracer | None = None) -> tuple[list[ScanlineMeasure], list[WindowMeasure]]:
    """The stored scanlines and scan circles measured (`measure_scanlines`, `measure_scan_circles`), the mesh
    read and its ray tracer built once for both (1 s and 250 MB at 3.2M faces), and only if there are any."""
    lines, circles = project.scanlines(), project.scan_circles()
    if not lines and not circles:
        return [], []
    mesh = project.load_mesh() if mesh is None else mesh
    tracer = RayTracer(mesh.vertices, mesh.faces) if tracer is None else tracer
    return (measure_scanlines(project, mesh=mesh, lines=lines, tracer=tracer),
            measure_scan_circles(project, mesh=mesh, circles=circles, tracer=tracer))


def project_sight(project: Project, mesh: Mesh, tracer: RayTracer | None = None) -> Sight:
    """The survey scanlines and scan circles sample the rock of: the project's cameras over its mesh."""
    return Sight(mesh, project.cameras(), RayTracer(mesh.vertices, mesh.faces) if tracer is None else tracer)


def describe_topology(topology: Topology) -> str:
    """One line for a person: the termination counts and the connected groups."""
    n = topology.nodes
    return (f"terminations: {n.B} B, {n.T} T, {n.X} X, {n.C} C; connections per line {n.C_L:.2f}, "
            f"per branch {n.C_B:.2f}; {len(topology.connectivity.sizes)} connected groups")


def _topology_result(topology: Topology, contacts: dict) -> dict:
    return {"tolerance_m": topology.tolerance, "nodes": asdict(topology.nodes),
            "crossings": len(topology.crossings.distance), "contacts": contacts,
            "components": int(len(topology.connectivity.sizes)),
            "largest_vertex_fraction": topology.connectivity.largest_vertex_fraction,
            "largest_length_fraction": topology.connectivity.largest_length_fraction}
