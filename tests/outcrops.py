"""Noisy synthetic outcrops merged as `tracemap merge --auto` does, for the merge acceptance tests and
tests/benchmarks/bench_merge.py: every photo's true 2D traces extracted onto the noisy mesh, then merged."""

from __future__ import annotations

from dataclasses import replace

from engine.extract import extract_traces
from engine.merge import MergeResult, auto_merge
from engine.raytrace import RayTracer
from engine.sight import Sight
from engine.synthetic import QUICK, SyntheticOutcrop, make_outcrop
from engine.traces import Trace2D, Trace3D

FIG6_SETS = ((85.0, 137.0, 43.0, 0.5), (88.0, 232.0, 16.0, 0.5))
"""κ 43 and 16 as in Seers & Hodgetts 2016b Fig. 6, on Table 1's steep orientations."""


def extract_every_photo(outcrop: SyntheticOutcrop, mesh) -> list[Trace3D]:
    """Every photo's true 2D traces extracted to 3D on `mesh` (duplicates where photos overlap), ids 1, 2, …"""
    runs = [Trace2D(t.id, t.image, t.polyline) for ts in outcrop.traces2d.values() for t in ts]
    extracted = extract_traces(runs, outcrop.local_cameras(), RayTracer(mesh.vertices, mesh.faces)).traces
    return [replace(t, id=k + 1) for k, t in enumerate(extracted)]


def merge_noisy_outcrop(model: str, seed: int, sets=None) -> tuple[SyntheticOutcrop, list[Trace3D], Sight,
                                                                   MergeResult]:
    """Outcrop `seed` with `model` ("planar" or "undulating") fractures from `sets` (default Table 1), its
    photos at the demo's resolution (1600×1200) and 2 mm of mesh noise; the extracted traces, the survey,
    and their merge at the demo's tolerance (3 cm: 2–3 × the ray-casting error on this mesh)."""
    outcrop = make_outcrop(seed, **{**QUICK, "image_size": (1600, 1200), "mesh_noise": 0.002,
                                    "fracture_model": model}, **({} if sets is None else {"sets": sets}))
    mesh = outcrop.noisy_mesh
    traces = extract_every_photo(outcrop, mesh)
    sight = Sight(mesh, outcrop.local_cameras(), RayTracer(mesh.vertices, mesh.faces))
    return outcrop, traces, sight, auto_merge(traces, tolerance=0.03, sight=sight)


def seen_traces(outcrop: SyntheticOutcrop) -> int:
    """How many true traces some photo shows: the most any merge of the photos' traces can recover."""
    return len({run.trace_id for runs in outcrop.traces2d.values() for run in runs})


def mixed_groups(outcrop: SyntheticOutcrop, traces: list[Trace3D], result: MergeResult) -> list[tuple[int, ...]]:
    """Merged groups whose 2D traces come from more than one fracture (by the photos' truth)."""
    by_id = {t.id: t for t in traces}
    fracture = {run.id: run.fracture_id for runs in outcrop.traces2d.values() for run in runs}
    return [g for g in result.merged_groups if len({fracture[p] for i in g for p in by_id[i].parents}) > 1]


def lost_traces(outcrop: SyntheticOutcrop, traces: list[Trace3D], result: MergeResult) -> int:
    """How many of the true traces some photo shows no merged trace comes from (extraction dropped every
    piece of them, or merging left them out)."""
    by_id = {t.id: t for t in traces}
    trace_of = {run.id: run.trace_id for runs in outcrop.traces2d.values() for run in runs}
    kept = {trace_of[p] for t in result.traces
            for i in (t.extra["merged_from"] if t.id == 0 else [t.id]) for p in by_id[i].parents}
    return seen_traces(outcrop) - len(kept)
