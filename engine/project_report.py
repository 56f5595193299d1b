"""`tracemap info PROJECT`: what a project holds, which of its inputs are missing or changed, which stored
results are older than its traces, and the step that comes next, without reading the mesh or the photos.

A survey is built over days and several sessions; this is the command that says where it stands, as
`git status` does for a repository. Lengths, orientations and registered quantities are in the GCPs' frame
once the project is registered, as everything else tracemap prints.
"""

from __future__ import annotations

from collections import Counter

import numpy as np

from engine.errors import TracemapError
from engine.orientation import normal_to_dip_dipdir, upward
from engine.project import SCHEMA_VERSION, Project
from engine.register import length_scale, rotate_directions
from engine.traces import KINDS

RESULTS = ("sets", "topology", "lengths", "intensity")
"""The stored results `info` lists, in the order the pipeline makes them."""


def project_report(project: Project) -> dict:
    """What `tracemap info` prints (and `--json` writes): inputs, traces, results, samples and the next step."""
    traces2d, traces3d = project.traces2d(), project.traces3d()
    registration = project.registration()
    sim = None if registration is None else registration.similarity
    scale = length_scale(sim)
    stale = project.stale_results(traces3d)
    report = {
        "project": str(project.path), "schema": project.schema_version, "inputs": _inputs(project),
        "traces2d": {"n": len(traces2d), "photos": len({t.image for t in traces2d}),
                     "by_source": dict(Counter(t.source for t in traces2d)),
                     "by_photo": dict(Counter(t.image for t in traces2d)),
                     "untraced": sorted(set(project.cameras(local=False)) - {t.image for t in traces2d}),
                     "not_in_3d": _not_in_3d(traces2d, traces3d)},
        "traces3d": {"n": len(traces3d), "oriented": sum(t.normal is not None for t in traces3d),
                     "in_sets": sum(t.set_id >= 0 for t in traces3d),
                     "length_m": scale * float(sum(t.surface_length for t in traces3d)),
                     "by_kind": {k: n for k in KINDS if (n := sum(t.kind == k for t in traces3d))}},
        "sets": [_set(s, sim) for s in project.result("sets") or []],
        "results": {name: ("out of date" if name in stale else "stored" if project.result(name) is not None
                           else "not yet") for name in RESULTS},
        "maps": project.map_names(),
        "registration": None if registration is None else {"gcps": len(registration.names),
                                                            "scale": sim.scale, "rmse_m": sim.rmse},
        "gcps": len(project.gcps()),
        "samples": {"facets": len(project.facets()), "scanlines": len(project.scanlines()),
                    "scan_circles": len(project.scan_circles())},
    }
    report["next"] = next_step(report)
    return report


def _not_in_3d(traces2d: list, traces3d: list) -> dict[str, int]:
    """Per photo, the 2D traces no 3D trace comes from: drawn since the last extraction, or whose rays
    missed the mesh (`tracemap extract` says which)."""
    parents = {p for t in traces3d for p in t.parents}
    return dict(Counter(t.image for t in traces2d if t.id not in parents))


def _inputs(project: Project) -> dict:
    """The mesh and photos: each one found unchanged, or why not (moved, edited: `Project`'s checks)."""
    try:
        mesh = {"path": str(project.mesh_path), "problem": None}
    except TracemapError as exc:
        mesh = {"path": None, "problem": str(exc)}
    cameras = project.cameras(local=False)
    unlinked, problems = [], []
    for name in cameras:
        try:
            if project.image_path(name) is None:
                unlinked.append(name)
        except TracemapError as exc:
            problems.append(str(exc))
    return {"mesh": mesh, "cameras": len(cameras), "photos_unlinked": unlinked, "photo_problems": problems}


def _set(s: dict, sim) -> dict:
    dip, dip_direction = normal_to_dip_dipdir(upward(rotate_directions(np.asarray(s["normal"]), sim)))
    return {"id": s["id"], "n": s["n"], "dip": float(dip), "dip_direction": float(dip_direction),
            "kappa": s["kappa"]}


def next_step(report: dict) -> str:
    """The command that moves the survey on, judged from the report."""
    inputs = report["inputs"]
    if inputs["mesh"]["problem"]:
        return "put the mesh back where the project expects it (or make a new project)"
    if report["traces2d"]["n"] == 0:
        return "trace fractures on the photos: tracemap autotrace, tracemap import-traces, or tracemap gui"
    if report["traces3d"]["n"] == 0:
        return "tracemap extract (ray-trace the 2D traces onto the mesh), then tracemap merge --auto"
    results = report["results"]
    if results["sets"] != "stored":
        return "tracemap orient (orientations and sets)"
    if results["topology"] != "stored" or results["lengths"] != "stored":
        return "tracemap analyse (terminations, connectivity, lengths; --radius R for P21/P32 maps)"
    if results["intensity"] == "out of date":
        return "tracemap analyse --radius R (the intensity maps are older than the traces)"
    return "tracemap export (and tracemap plot)"


def report_lines(report: dict) -> list[str]:
    """The report for people, one fact a line."""
    inputs, t2, t3 = report["inputs"], report["traces2d"], report["traces3d"]
    frame = " (GCPs' frame)" if report["registration"] else ""
    mesh = inputs["mesh"]
    upgrade = "" if report["schema"] >= SCHEMA_VERSION else f", upgraded to {SCHEMA_VERSION} by the next edit"
    lines = [f"{report['project']} (schema {report['schema']}{upgrade})",
             f"mesh: {mesh['path']}" if mesh["problem"] is None else f"mesh: {mesh['problem']}",
             f"cameras: {inputs['cameras']}" + (f", {len(inputs['photos_unlinked'])} without a photo linked"
                                                 if inputs["photos_unlinked"] else ", every photo linked")]
    lines += [f"photo: {p}" for p in inputs["photo_problems"]]
    sources = ", ".join(f"{n} {s}" for s, n in sorted(t2["by_source"].items()))
    lines.append(f"2D traces: {t2['n']} on {_count(t2['photos'], 'photo')}" + (f" ({sources})" if sources else ""))
    if t2["untraced"] and t2["n"]:
        shown = ", ".join(t2["untraced"][:5]) + (", …" if len(t2["untraced"]) > 5 else "")
        lines.append(f"  no traces yet on {_count(len(t2['untraced']), 'photo')}: {shown}")
    waiting = t2["not_in_3d"]
    if waiting and t3["n"]:
        lines.append(f"  {_count(sum(waiting.values()), '2D trace')} not in 3D (drawn since the last extraction, or "
                     f"off the mesh): " + ", ".join(f"{n} on {name}" for name, n in sorted(waiting.items())))
    kinds = t3["by_kind"]
    lines.append(f"3D traces: {t3['n']}, {t3['oriented']} oriented, {t3['in_sets']} in sets, "
                 f"{t3['length_m']:.1f} m of trace{frame}"
                 + ("" if set(kinds) <= {"fracture"} else " (" + ", ".join(f"{n} {k}" for k, n in kinds.items()) + ")"))
    for s in report["sets"]:
        lines.append(f"  set {s['id']}: {_count(s['n'], 'trace')}, dip {s['dip']:.0f}° / {s['dip_direction']:03.0f}°, "
                     f"κ {s['kappa']:.1f}{frame}")
    lines.append("results: " + ", ".join(f"{name} {state}" for name, state in report["results"].items())
                 + (f"; maps {', '.join(report['maps'])}" if report["maps"] else ""))
    reg = report["registration"]
    lines.append("registration: none" + (f" ({report['gcps']} GCPs picked)" if report["gcps"] else "") if reg is None
                 else f"registration: {_count(reg['gcps'], 'GCP')}, scale {reg['scale']:.5f}, RMSE {reg['rmse_m']:.3f} m")
    samples = report["samples"]
    lines.append(f"samples: {_count(samples['facets'], 'facet')}, {_count(samples['scanlines'], 'scanline')}, "
                 f"{_count(samples['scan_circles'], 'scan circle')}")
    lines.append(f"next: {report['next']}")
    return lines


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}" + ("" if n == 1 else "s")
