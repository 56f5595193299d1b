"""Reading and writing the files other tools exchange: trace CSVs and the project's exports.

Writers never leave partial output: files are written into a hidden folder beside the destination and
moved into place only when all of them are complete.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import tempfile
from collections.abc import Iterator, Sequence
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from engine.cameras import Camera
from engine.csvfile import csv_number, read_csv
from engine.delineate.params import SETTING as AUTOTRACE_SETTING
from engine.errors import InputError
from engine.orientation import normal_to_dip_dipdir
from engine.register import Registration, Similarity, length_scale, rotate_directions, to_world
from engine.relations import PAIR_COLUMNS, SetRelations, outcrop_relations
from engine.traces import KINDS, NETWORK_KINDS, SOURCES, Trace2D, Trace3D, first_outside, network

if TYPE_CHECKING:
    from engine.project import Project
    from engine.scan_circle import WindowMeasure
    from engine.scanline import ScanlineMeasure

TRACE_CSV_COLUMNS = ("image", "trace", "u", "v")


def read_traces_csv(path: str | Path, cameras: dict[str, Camera]) -> list[Trace2D]:
    """2D traces from a CSV with columns image,trace,u,v (optional source and kind, as `export` writes
    them in traces2d.csv: a file written by tracemap reads back as it was), one row per vertex.

    Pixel convention: (0, 0) is the centre of the top-left pixel, u right, v down. Rows of one
    (image, trace) pair are the vertices in order. Raises InputError naming the line and column.
    """
    path = Path(path)
    rows = read_csv(path, TRACE_CSV_COLUMNS)
    groups: dict[tuple[str, str], list[tuple[float, float]]] = {}
    sources: dict[tuple[str, str], str] = {}
    kinds: dict[tuple[str, str], str] = {}
    for line, row in enumerate(rows, start=2):
        key = (row["image"], row["trace"])
        if row["image"] not in cameras:
            raise InputError(path, f"line {line}: image {row['image']!r} is not in the project")
        groups.setdefault(key, []).append((csv_number(path, line, "u", row["u"]), csv_number(path, line, "v", row["v"])))
        source = (row.get("source") or "manual").strip()
        if source not in SOURCES:
            raise InputError(path, f"line {line}: source {source!r} must be one of {', '.join(SOURCES)}")
        sources[key] = source
        kind = (row.get("kind") or "fracture").strip()
        if kind not in KINDS:
            raise InputError(path, f"line {line}: kind {kind!r} must be one of {', '.join(KINDS)}")
        if kinds.setdefault(key, kind) != kind:
            raise InputError(path, f"line {line}: trace {row['trace']!r} on image {row['image']!r} is "
                                   f"{kinds[key]} on an earlier line and {kind} here; a trace has one kind")
    traces = []
    for (image, name), uv in groups.items():
        if len(uv) < 2:
            raise InputError(path, f"trace {name!r} on image {image!r} has {len(uv)} vertex; at least 2 needed")
        trace = Trace2D(0, image, np.array(uv), sources[(image, name)], kind=kinds[(image, name)])
        _check_inside(path, name, trace, cameras[image])
        traces.append(trace)
    return traces


def _check_inside(path: Path, name: str, trace: Trace2D, camera: Camera) -> None:
    k = first_outside(trace.polyline, camera.width, camera.height)
    if k is not None:
        uv = trace.polyline
        raise InputError(path, f"trace {name!r} on image {trace.image!r}: vertex ({uv[k, 0]:g}, {uv[k, 1]:g}) "
                               f"is outside the {camera.width}×{camera.height} photo "
                               "(pixel centres run from 0 to size − 1)")


@contextmanager
def atomic_directory(outdir: str | Path) -> Iterator[Path]:
    """Yield a scratch folder; on success its files replace those of the same name in `outdir`.

    All or nothing: a file that cannot take its place (a folder of that name is in the way, the disk is
    full) puts back the files already replaced, and folders made for the output are removed again. The
    scratch folder is named after this process, so one that a killed export left behind is removed by the
    next (never one of an export still running)."""
    outdir = Path(outdir)
    if outdir.exists() and not outdir.is_dir():
        raise InputError(outdir, "is a file; the output must go to a folder")
    made = [p for p in (outdir, *outdir.parents) if not p.exists()]
    outdir.mkdir(parents=True, exist_ok=True)
    try:
        for left in outdir.glob(".tracemap-*-*"):
            if left.is_dir() and not _running(left.name.split("-")[1]):
                shutil.rmtree(left, ignore_errors=True)
        scratch = Path(tempfile.mkdtemp(prefix=f".tracemap-{os.getpid()}-", dir=outdir))
        try:
            yield scratch
            _replace_all(scratch, outdir)
        finally:
            shutil.rmtree(scratch, ignore_errors=True)
    except BaseException:
        for folder in made:  # deepest first; only if still empty (never another writer's files)
            with suppress(OSError):
                folder.rmdir()
        raise


def _replace_all(scratch: Path, outdir: Path) -> None:
    """Move every file of `scratch` into `outdir`, keeping the files replaced until all are in place."""
    items = sorted(scratch.iterdir())
    blocked = [outdir / i.name for i in items if (outdir / i.name).is_dir() and not (outdir / i.name).is_symlink()]
    if blocked:
        raise InputError(blocked[0], "is a folder where the output writes a file; move it away or choose "
                                     "another output folder (nothing was written)")
    kept = scratch / ".replaced"
    kept.mkdir()
    done: list[Path] = []
    try:
        for item in items:
            target = outdir / item.name
            done.append(target)  # before anything moves: an interrupt between the two moves is undone too
            if os.path.lexists(target):
                os.replace(target, kept / item.name)
            os.replace(item, target)
    except BaseException:
        for target in reversed(done):  # put the earlier files back (a symlink as the link itself)
            with suppress(OSError):
                if os.path.lexists(kept / target.name):
                    os.replace(kept / target.name, target)
                elif os.path.lexists(target) and not (scratch / target.name).exists():
                    target.unlink()  # a new file that had no earlier one
        raise


def _running(pid: str) -> bool:
    """Whether a process of this id runs (an id that is not a number is taken as running: left alone)."""
    if not pid.isdigit():
        return True
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def write_csv(path: Path, header: tuple[str, ...], rows: Iterator[tuple] | list[tuple]) -> None:
    with open(path, "w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f)
        writer.writerow(header)
        writer.writerows(rows)


def _fmt(x: float, digits: int = 6) -> str:
    return "" if x is None or not np.isfinite(x) else f"{x:.{digits}f}"


def traces_rows(traces: list[Trace3D], similarity: Similarity | None = None) -> Iterator[tuple]:
    """One row per 3D trace (the `traces.csv` columns of DESIGN.md, with the eigen solution's dip and dip
    direction beside the final one, as issue 4 asks); orientations and lengths in the export frame."""
    scale = length_scale(similarity)
    for t in traces:
        dip, dipdir = dip_dipdir(t.normal, similarity)
        eigen_dip, eigen_dipdir = dip_dipdir(t.extra.get("eigen_normal"), similarity)
        yield (t.id, t.set_id, _fmt(dip, 2), _fmt(dipdir, 2), _fmt(eigen_dip, 2), _fmt(eigen_dipdir, 2),
               t.method, _fmt(t.K, 4), _fmt(t.M, 4), _fmt(scale * t.chord_length),
               _fmt(scale * t.surface_length), t.term_start, t.term_end, int(t.censored), t.component, t.kind)


def dip_dipdir(normal: np.ndarray | list | None, similarity: Similarity | None = None) -> tuple[float, float]:
    """Dip and dip direction (degrees) of a pole in the export frame; NaN for none (not yet oriented)."""
    if normal is None or not np.all(np.isfinite(normal)):
        return np.nan, np.nan
    dip, dipdir = normal_to_dip_dipdir(rotate_directions(np.asarray(normal, dtype=float), similarity))
    return float(dip), float(dipdir)


TRACES_HEADER = ("id", "set", "dip", "dip_direction", "eigen_dip", "eigen_dip_direction", "method", "K", "M",
                 "chord_length", "surface_length", "term_start", "term_end", "censored", "component", "kind")
VERTICES_HEADER = ("trace", "vertex", "x", "y", "z", "image", "u", "v", "face")
TRACES2D_HEADER = ("image", "trace", "u", "v", "source", "kind")


def vertex_rows(traces: list[Trace3D], origin: np.ndarray, similarity: Similarity | None = None) -> Iterator[tuple]:
    """One row per 3D trace vertex, in the export frame (local + origin, then any registration), with its
    source pixel."""
    for t in traces:
        world = to_world(t.points, origin, similarity)
        names = t.vertex_images
        for k in range(len(world)):
            x, y, z = world[k]
            yield (t.id, k, f"{x:.4f}", f"{y:.4f}", f"{z:.4f}", names[k], f"{t.uv[k, 0]:.3f}",
                   f"{t.uv[k, 1]:.3f}", int(t.face[k]))


def traces2d_rows(traces: list[Trace2D]) -> Iterator[tuple]:
    for t in traces:
        for u, v in t.polyline:
            yield (t.image, t.id, f"{u:.3f}", f"{v:.3f}", t.source, t.kind)


def write_json(path: Path, data: dict) -> None:
    path.write_text(json.dumps(data, indent=2, default=jsonable) + "\n", encoding="utf-8")


def jsonable(x: object) -> object:
    """`json.dumps(default=...)` for numpy scalars and arrays."""
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(f"cannot write {type(x).__name__} to JSON")



EXPORT_FORMATS = ("csv", "ply", "gpkg", "vtp")


def export_tables(project: Project, outdir: str | Path, formats: tuple[str, ...] = ("csv", "ply")) -> list[Path]:
    """Write the project's results into `outdir`, all or nothing.

    csv: traces.csv, trace_vertices.csv, traces2d.csv, summary.json, (after `orient`) sets.csv, (after
    `orient` and `analyse`) relations.csv, the abutting and crossing between sets (`engine.relations`), (with
    facets) planes.csv in CloudCompare Compass's plane columns, (with scanlines) scanlines.csv, a row per
    trace crossing one (summary.json has their P10 and spacings), (with scan circles) scan_circles.csv, a
    row per window with Mauldon's counts and estimators;
    ply: connectivity.ply and (after `analyse --radius`) intensity.ply; gpkg: traces.gpkg (layers traces and
    scanlines, LINESTRING Z, and scan_circles, POINT Z);
    vtp: traces.vtp and (with scanlines, scan circles) scanlines.vtp, scan_circles.vtp. Coordinates are world coordinates (local + origin),
    moved into the GCPs' frame and orientations turned with it when the project is registered (`tracemap
    register`).
    """
    from engine import exports
    from engine.analysis import measure_samples
    from engine.scan_circle import WINDOWS_HEADER, window_report, window_row
    from engine.scanline import CROSSINGS_HEADER, crossing_rows, scanline_report

    unknown = set(formats) - set(EXPORT_FORMATS)
    if unknown:
        raise InputError(None, f"--format: unknown format(s) {', '.join(sorted(unknown))}; "
                               f"available: {', '.join(EXPORT_FORMATS)}")
    traces3d = project.traces3d()
    traces2d = project.traces2d()
    sets = project.result("sets") or []
    registration = project.registration()
    sim = None if registration is None else registration.similarity
    scanlines, windows = measure_samples(project) if {"csv", "vtp", "gpkg"} & set(formats) else ([], [])
    with atomic_directory(outdir) as scratch:
        if "csv" in formats:
            write_csv(scratch / "traces.csv", TRACES_HEADER, traces_rows(traces3d, sim))
            write_csv(scratch / "trace_vertices.csv", VERTICES_HEADER, vertex_rows(traces3d, project.origin, sim))
            write_csv(scratch / "traces2d.csv", TRACES2D_HEADER, traces2d_rows(traces2d))
            write_json(scratch / "summary.json", summary(project, traces2d, traces3d, sim, scanlines, windows))
            if scanlines:
                write_csv(scratch / "scanlines.csv", CROSSINGS_HEADER,
                          [row for m in scanlines for row in crossing_rows(m, project.origin, sim)])
            if windows:
                write_csv(scratch / "scan_circles.csv", WINDOWS_HEADER,
                          [window_row(window_report(m, project.origin, sim)) for m in windows])
            if (relations := stored_relations(project, traces3d)) is not None and relations.sets:
                write_csv(scratch / "relations.csv", PAIR_COLUMNS, relations.rows())
            if sets:
                exports.write_sets_csv(scratch / "sets.csv", [[s["id"], s["n"], *dip_dipdir(s["normal"], sim),
                                                               s["kappa"], s["alpha95"]] for s in sets])
            if facets := project.facets():
                exports.write_planes_csv(scratch / "planes.csv", facets, project.origin, similarity=sim)
        if "ply" in formats:
            exports.write_connectivity_ply(scratch / "connectivity.ply", traces3d, project.origin, similarity=sim)
            if project.map_names():
                maps = {name.replace(":", "_"): project.vertex_map(name)[0] for name in project.map_names()}
                exports.write_intensity_ply(scratch / "intensity.ply", project.load_mesh(), maps, similarity=sim)
        if "gpkg" in formats:
            exports.write_geopackage(scratch / "traces.gpkg", traces3d, project.origin, similarity=sim,
                                     scanlines=[scanline_report(m, project.origin, sim) for m in scanlines],
                                     windows=[window_report(m, project.origin, sim) for m in windows])
        if "vtp" in formats:
            exports.write_vtp(scratch / "traces.vtp", traces3d, project.origin, similarity=sim)
            if scanlines:
                exports.write_scanlines_vtp(scratch / "scanlines.vtp", scanlines, project.origin, similarity=sim)
            if windows:
                exports.write_scan_circles_vtp(scratch / "scan_circles.vtp", windows, project.origin, similarity=sim)
        names = sorted(p.name for p in scratch.iterdir())
    return [Path(outdir) / n for n in names]


SUMMARY_SECTION = {"sets": "sets", "density_peaks": "sets", "topology": "nodes", "lengths": "kaplan_meier",
                   "intensity": "intensity"}


def summary(project: Project, traces2d: list[Trace2D], traces3d: list[Trace3D],
            similarity: Similarity | None = None, scanlines: Sequence[ScanlineMeasure] = (),
            windows: Sequence[WindowMeasure] = ()) -> dict:
    """Counts and totals a user checks first, as written to summary.json: traces, sets, node counts,
    Kaplan–Meier medians and P21 (null until `orient` or `analyse` has run), and the parameters of the last
    auto-trace. Lengths, areas and intensities are in the export frame (the registration's scale applied)."""
    from engine.scan_circle import counts_report, pooled_windows, window_report
    from engine.scanline import pooled, scanline_report

    scale = length_scale(similarity)
    lengths = scale * np.array([t.surface_length for t in traces3d])
    return {
        "project": str(project.path),
        "origin": project.origin,
        "images": len(project.cameras(local=False)),
        "frame": _frame(project.registration()),
        "traces2d": {"total": len(traces2d), "manual": sum(t.source == "manual" for t in traces2d),
                     "auto": sum(t.source == "auto" for t in traces2d)},
        "traces3d": {"total": len(traces3d), "censored": sum(t.censored for t in traces3d),
                     "by_kind": {k: sum(t.kind == k for t in traces3d) for k in KINDS},
                     "vertices": int(sum(len(t.points) for t in traces3d)),
                     "total_surface_length_m": float(lengths.sum()),
                     "median_surface_length_m": float(np.median(lengths)) if len(lengths) else None},
        "sets": _sets_summary(project.result("sets"), project.result("density_peaks"), traces3d, similarity),
        "nodes": _nodes_summary(project.result("topology")),
        "kaplan_meier": _km_summary(project.result("lengths"), scale),
        "intensity": _intensity_summary(project.result("intensity"), scale),
        "relations": _relations_summary(stored_relations(project, traces3d)),
        "scanlines": [scanline_report(m, project.origin, similarity) for m in scanlines],
        "scanlines_pooled": pooled(scanlines, similarity) if len(scanlines) > 1 else None,
        "scan_circles": [window_report(m, project.origin, similarity) for m in windows],
        "scan_circles_pooled": counts_report(pooled_windows(windows), scale) if len(windows) > 1 else None,
        # the sections above that were computed before the 3D traces last changed (a merge, a trim, an edit)
        "out_of_date": sorted({SUMMARY_SECTION[n] for n in project.stale_results(traces3d)}),
        "autotrace_parameters": project.setting(AUTOTRACE_SETTING),  # of the last run, for a methods section
    }


def _sets_summary(sets: list[dict] | None, peaks: list[dict] | None, traces3d: list[Trace3D],
                  similarity: Similarity | None) -> dict | None:
    """Traces per set with each set's mean orientation (export frame) and κ, the rest non-systematic, and the
    pole density's peaks (export frame; density in multiples of uniform), and the bedding traces (in no set)."""
    if not sets:
        return None
    counts = {}
    for t in network(traces3d):
        counts[t.set_id] = counts.get(t.set_id, 0) + 1
    rows = [{"set": int(s["id"]), "traces": counts.get(int(s["id"]), 0),
             **dict(zip(("dip", "dip_direction"), dip_dipdir(s["normal"], similarity))),
             "kappa": float(s["kappa"])} for s in sets]
    maxima = [{**dict(zip(("dip", "dip_direction"), dip_dipdir(p["normal"], similarity))),
               "density": float(p["density"])} for p in peaks or ()]
    return {"sets": rows, "non_systematic": counts.get(-1, 0), "density_peaks": maxima,
            "bedding": sum(t.kind not in NETWORK_KINDS for t in traces3d)}


def stored_relations(project: Project, traces3d: list[Trace3D]) -> SetRelations | None:
    """Abutting and crossing between the sets as they are now, over the contacts of the last analysis
    (`engine.relations.outcrop_relations`); None before an analysis that stored them."""
    topology = project.result("topology")
    return None if topology is None or "contacts" not in topology else outcrop_relations(traces3d, topology["contacts"])


def _relations_summary(relations: SetRelations | None) -> dict | None:
    return relations.to_dict() if relations is not None and relations.sets else None


def _nodes_summary(topology: dict | None) -> dict | None:
    """End codes B/T/X/C, fractopo's nodes and connections per line and branch, and the connected groups."""
    if topology is None:
        return None
    nodes = topology["nodes"]
    keep = ("B", "T", "X", "C", "N_I", "N_Y", "N_X", "N_E", "N_L", "N_B", "C_L", "C_B")
    return {**{k: nodes[k] for k in keep}, "components": topology["components"],
            "largest_vertex_fraction": topology["largest_vertex_fraction"]}


def _km_summary(lengths: dict | None, scale: float) -> dict | None:
    """Kaplan–Meier median trace length (m) with its confidence interval, per group ("all", "set0", …,
    "non_systematic")."""
    if lengths is None:
        return None
    out = {}
    for group, analysis in lengths.items():
        group = group if group == "all" else "non_systematic" if group == "-1" else f"set{group}"
        km = analysis["kaplan_meier"]
        median = None if km is None else _finite_or_none(scale * km["median"])
        interval = None if km is None else [_finite_or_none(scale * x) for x in km["median_ci"]]
        out[group] = {"traces": analysis["n"], "censored": analysis["n_censored"], "median_m": median,
                      "median_ci_m": interval}
    return out


def _intensity_summary(intensity: dict | None, scale: float) -> dict | None:
    """`analysis.intensity_summary` in the export frame: radius and area scaled, P21 and P32 divided."""
    if intensity is None:
        return None
    per_length = 1.0 / scale
    maps = {name: None if stats is None else {k: v * per_length for k, v in stats.items()}
            for name, stats in intensity["maps"].items()}
    return {"radius_m": intensity["radius_m"] * scale, "imaged_area_m2": intensity["imaged_area_m2"] * scale**2,
            "p21_outcrop": {k: None if v is None else v * per_length for k, v in intensity["p21_outcrop"].items()},
            "maps": maps}


def _finite_or_none(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def _frame(registration: Registration | None) -> dict:
    """Which frame the exported coordinates are in: the mesh's, or the GCPs' after registration."""
    if registration is None:
        return {"registered": False}
    return {"registered": True, "gcps": len(registration.names), "rmse_m": registration.similarity.rmse,
            "scale": registration.similarity.scale}
