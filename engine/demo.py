"""`tracemap demo`: the whole pipeline on the bundled synthetic outcrop, checked against its exact answer.

Builds the outcrop (engine.synthetic), writes it as a user would bring a survey (mesh, camera file, photos,
a CSV of 2D traces), creates a project, extracts the traces to 3D, exports them and reports how far the
extracted vertices lie from the true 3D traces, in metres and in pixel footprints.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from engine.errors import Progress, report
from engine.project import Project, new_project
from engine.traces import Trace3D

if TYPE_CHECKING:
    from engine.sight import Sight

DEMO_OUTCROP = {"mesh_noise": 0.002}
"""make_outcrop settings of the demo: defaults (20 m × 8 m wall, 5 photos) with 2 mm photogrammetric noise."""


DEMO_RADIUS = 0.5  # m, the P21/P32 sphere
DEMO_WINDOW = 2.0  # m, the radius of the grid of scan circles


@dataclass(frozen=True)
class ExtractionError:
    """Distance of extracted 3D vertices to the true traces: metres and pixel footprints (distance / f)."""

    n_vertices: int
    median_m: float
    p95_m: float
    median_footprints: float
    p95_footprints: float


def extraction_error(traces: list[Trace3D], project_origin: np.ndarray, outcrop) -> ExtractionError:
    """Compare extracted traces (project local frame) with the outcrop's exact 3D traces."""
    from engine.synthetic import distance_to_true_traces

    world = np.vstack([t.points for t in traces]) + project_origin
    distance, _ = distance_to_true_traces(world, outcrop)
    footprint = np.concatenate([_footprints(t, project_origin, outcrop) for t in traces])
    ratio = distance / footprint
    return ExtractionError(len(world), float(np.median(distance)), float(np.percentile(distance, 95)),
                           float(np.median(ratio)), float(np.percentile(ratio, 95)))


def _footprints(trace: Trace3D, origin: np.ndarray, outcrop) -> np.ndarray:
    """Size of one pixel at each vertex: its distance from the camera that saw it, over the focal length."""
    out = np.empty(len(trace.points))
    for k, name in enumerate(trace.images):
        sel = trace.image_index == k
        cam = outcrop.cameras[name]
        out[sel] = np.linalg.norm(trace.points[sel] + origin - cam.centre, axis=1) / cam.K[0, 0]
    return out


def _merge(project: Project, sight: Sight) -> int:
    """`tracemap merge --auto`: one trace per fracture where overlapping photos saw it twice, or where an
    occlusion cut it in every photo."""
    from engine.merge import auto_merge

    result = auto_merge(project.traces3d(), tolerance=0.03, sight=sight)
    merged = sorted({i for group in result.merged_groups for i in group})
    with project.transaction() as db:
        project.remove_traces3d(merged, db)
        project.add_traces3d([t for t in result.traces if t.id == 0], db)
    return len(project.traces3d())


def _orient(project: Project, mesh):
    """`tracemap orient` on the demo project: eigen + probabilistic poles, then sets (Terzaghi-weighted)."""
    from engine.analysis import orient_and_classify

    run = orient_and_classify(project.traces3d(), mesh, facets=project.facets())
    with project.transaction() as db:
        project.update_traces3d(run.traces, db)
        for name, value in run.results.items():
            project.set_result(name, value, db)
        project.record_basis(list(run.results), project.traces3d(), db)
    return run.model.sets


def _nearest_true(normal: np.ndarray, true) -> tuple[int, float]:
    """The true set nearest a pole, and the angle to it (axial: near-vertical planes can be written with dip
    directions 180° apart, 87/052 is 5° from 88/232)."""
    from engine.orientation import axial_angle, dip_dipdir_to_normal

    poles = dip_dipdir_to_normal(np.array([t.dip for t in true]), np.array([t.dip_direction for t in true]))
    angles = axial_angle(normal, poles)
    k = int(np.argmin(angles))
    return k, float(angles[k])


def _sets_against_truth(found, true) -> str:
    """Each found set with the angle from its mean pole to the nearest true one."""
    parts = []
    for s in found:
        k, angle = _nearest_true(s.normal, true)
        parts.append(f"{s.dip:.0f}/{s.dip_direction:03.0f} κ {s.kappa:.1f} (n {s.n}, {angle:.1f}° from "
                     f"{true[k].dip:.0f}/{true[k].dip_direction:03.0f})")
    return ", ".join(parts)


def _p32_against_truth(measure, found, true) -> str:
    """Each found set's P32 from the scanline beside the realised P32 of the nearest true set."""
    parts = []
    for s in found:
        if s.id in measure.sets:
            k, _ = _nearest_true(s.normal, true)
            parts.append(f"set {s.id} {measure.sets[s.id].p32:.2f} /m (true {true[k].p32:.2f})")
    return ", ".join(parts) or "no set crossed"


FIGURES = ("traces_by_set.png", "traces_on_photo.png")


def _scanline(project: Project, mesh, sight: Sight):
    """Lay a level scanline along the outcrop a third of the way up (clear of the bench edge at mid-height,
    where extraction drops the trace pixels), between the mesh vertices nearest 1 m in from either end;
    store it and return its measure (on the rock the photos see)."""
    from engine.analysis import measure_scanlines
    from engine.scanline import Scanline

    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    z = lo[2] + (hi[2] - lo[2]) / 3
    ends = [mesh.vertices[np.argmin(np.hypot(mesh.vertices[:, 0] - x, mesh.vertices[:, 2] - z))]
            for x in (lo[0] + 1.0, hi[0] - 1.0)]
    line = Scanline(*ends, name="a third of the way up")
    (measure,) = measure_scanlines(project, mesh=mesh, lines=[line], tracer=sight.tracer)
    project.add_scanline(line)
    return measure


def _scan_circles(project: Project, mesh, sight: Sight, outcrop) -> str:
    """A grid of scan circles over the face (`engine.scan_circle.grid_scan_circles`): their pooled estimates
    beside those of the same windows on the true traces. Not stored: their marks would crowd the demo's
    view (the 3D viewer's Lay grid, or `tracemap scan-circle --grid`, lays them)."""
    from engine.scan_circle import grid_scan_circles, measure_scan_circle, pooled_windows
    from engine.traces import Trace3D

    circles = grid_scan_circles(mesh, DEMO_WINDOW)
    found = pooled_windows([measure_scan_circle(mesh, project.traces3d(), c, sight=sight) for c in circles])
    true = [Trace3D(t.id, t.points - project.origin, np.zeros((len(t.points), 2)), t.face,
                    np.zeros(len(t.points), int), ("truth",), term_start=t.ends[0], term_end=t.ends[1])
            for t in outcrop.traces3d if not t.closed]
    truth = pooled_windows([measure_scan_circle(mesh, true, c) for c in circles])
    return (f"{len(circles)} scan circles of r {DEMO_WINDOW:g} m: pooled P21 {found.p21:.2f} /m, mean trace length "
            f"{found.mean_length:.2f} m (the true traces in them: {truth.p21:.2f} /m, {truth.mean_length:.2f} m)")


def _figures(project: Project, mesh, sight, folder: Path) -> None:
    """The traces by set from where the photos were taken, with a scale bar, a north arrow and the scanline;
    and on the middle photo itself, draped and seen from it (the paper's Fig. 5A)."""
    from engine.analysis import measure_scanlines
    from engine.delineate import read_photo
    from engine.drape import drape_photo
    from engine.render import SceneStyle, offscreen_texture_size, photo_size, render_to_file
    from engine.scale_bar import scale_bar

    cameras = project.cameras()
    centres = np.array([c.centre for c in cameras.values()])
    traces = project.traces3d()
    render_to_file(folder / FIGURES[0], mesh, traces, SceneStyle(color_by="set"), camera_centres=centres,
                   bar=scale_bar(mesh, toward=centres.mean(axis=0)),
                   scanlines=measure_scanlines(project, mesh=mesh, tracer=sight.tracer))
    middle = cameras[sorted(cameras)[len(cameras) // 2]]
    drape = drape_photo(mesh, middle, read_photo(project.image_path(middle.name), middle), sight.tracer,
                        max_size=offscreen_texture_size())
    render_to_file(folder / FIGURES[1], mesh, traces, SceneStyle(color_by="set", size=photo_size(middle)),
                   view=middle, drape=drape)


def run_demo(out: Path, *, seed: int = 1, outcrop_settings: dict | None = None,
             progress: Progress | None = None, say: Callable[[str], None] = print) -> ExtractionError:
    """Run the demo into folder `out` (data/, demo.tracemap, export/, plots/); returns the extraction error."""
    from engine.extract import extract_traces
    from engine.io import export_tables, read_traces_csv
    from engine.analysis import analyse_project, project_figures
    from engine.plots import write_plots
    from engine.raytrace import RayTracer
    from engine.sight import Sight
    from engine.synthetic import make_outcrop, write_outcrop

    out.mkdir(parents=True, exist_ok=True)
    report(progress, 0.0, "building the synthetic outcrop")
    outcrop = make_outcrop(seed, **(outcrop_settings or DEMO_OUTCROP),
                           progress=lambda f, m: report(progress, 0.6 * f, m))
    files = write_outcrop(outcrop, out / "data")
    say(f"synthetic outcrop: {len(outcrop.fractures)} fractures, {len(outcrop.traces3d)} true 3D traces, "
        f"{len(outcrop.cameras)} photos, {len(outcrop.noisy_mesh.faces):,} mesh faces -> {out / 'data'}")
    project_path = out / "demo.tracemap"
    for stale in out.glob("demo.tracemap*"):  # the demo owns its folder: start afresh
        stale.unlink()
    with new_project(project_path, files["mesh"], files["cameras"], images=files["images"]) as project:
        traces2d = read_traces_csv(files["traces2d"], project.cameras(local=False))
        project.add_traces2d(traces2d)
        report(progress, 0.65, "ray tracing the traces onto the mesh")
        mesh = project.load_mesh()
        sight = Sight(mesh, project.cameras(), RayTracer(mesh.vertices, mesh.faces))
        result = extract_traces(project.traces2d(), sight.cameras, sight.tracer,
                                progress=lambda f, m: report(progress, 0.65 + 0.3 * f, m))
        project.add_traces3d(result.traces)
        traces3d = project.traces3d()
        error = extraction_error(traces3d, project.origin, outcrop)
        report(progress, 0.8, "merging, orientation, sets and analysis")
        n_merged = _merge(project, sight)
        sets = _orient(project, mesh)
        analysis = analyse_project(project, radius=DEMO_RADIUS, n_bootstrap=99)
        scanline = _scanline(project, mesh, sight)
        windows = _scan_circles(project, mesh, sight, outcrop)
        written = export_tables(project, out / "export")
        _figures(project, mesh, sight, out / "export")
        plots = write_plots(project_figures(project, mesh=mesh, tracer=sight.tracer), out / "plots")
    report(progress, 1.0, "done")
    say(f"project {project_path}: {len(traces2d)} 2D traces -> {len(traces3d)} 3D traces "
        f"({result.n_rays:,} rays, {result.n_missed:,} missed, {result.n_edge:,} on occluding edges, "
        f"{result.n_split} split at gaps)")
    say(f"3D error against the truth over {error.n_vertices:,} vertices: median {error.median_m * 1000:.2f} mm "
        f"({error.median_footprints:.2f} pixel footprints), 95th percentile {error.p95_m * 1000:.2f} mm "
        f"({error.p95_footprints:.2f} footprints)")
    say(f"merged duplicates across photos: {n_merged} 3D traces ({len(outcrop.traces3d)} true traces)")
    truth = ", ".join(f"{s.dip:.0f}/{s.dip_direction:03.0f} κ {s.kappa:.1f}" for s in outcrop.sets)
    say(f"sets: true {truth}; found {_sets_against_truth(sets, outcrop.sets)}")
    n = analysis.topology.nodes
    say(f"terminations {n.B} B, {n.T} T, {n.X} X, {n.C} C; P21 map radius {DEMO_RADIUS} m, "
        f"median P21 {np.nanmedian(analysis.maps['p21']):.2f} /m")
    say(f"scanline a third of the way up: {scanline.line.length:.1f} m, {scanline.all.n} traces crossed, "
        f"P10 {scanline.all.p10:.2f} /m; P32 from it {_p32_against_truth(scanline, sets, outcrop.sets)}")
    say(windows)
    say(f"exported {', '.join(p.name for p in written)}, {FIGURES[0]} and {FIGURES[1]} -> {out / 'export'}")
    say(f"plots {', '.join(p.name for p in plots)} -> {out / 'plots'}")
    return error
