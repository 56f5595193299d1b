"""The `tracemap` command line (DESIGN.md "Command line": the contract scripts rely on).

Every command either completes or leaves the project as it was; errors print one message that says
which file and what to fix, and exit with status 2 (never a traceback).
"""

from __future__ import annotations

import argparse
import math
import os
import sqlite3
import sys
import tempfile
import time
import traceback
from collections.abc import Callable, Mapping, MutableMapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from engine import __version__
from engine.errors import Cancelled, InputError, TracemapError

if TYPE_CHECKING:  # the commands import what they need when they run, so `tracemap --help` stays fast
    from engine.merge import MergeSuggestion
    from engine.project import Project
    from engine.raytrace import RayTracer
    from engine.register import Similarity
    from engine.sight import Sight
    from engine.traces import Trace3D

FRAME_SCALE_NOTE, FRAME_ANGLE_NOTE = 0.01, 1.0  # a registration beyond these is told apart from the mesh frame
MIN_RENDER, MAX_RENDER = 16, 16384  # pixels a side (engine.render): the largest offscreen framebuffer drivers allow
COLOR_BY = ("set", "component", "termination", "method", "kind", "p21", "p32")  # engine.render.COLOR_BY, without pyvista
KINDS = ("fracture", "vein", "fault", "bedding")  # engine.traces.KINDS, without numpy

EXIT_ERROR = 2
EXIT_INTERRUPTED = 130


class ProgressBar:
    """A one-line progress bar on stderr (only when stderr is a terminal); a `Progress` callback."""

    def __init__(self, stream=sys.stderr, width: int = 30):
        self.stream, self.width = stream, width
        self.live = stream.isatty()
        self._last = 0.0

    def __call__(self, fraction: float, message: str) -> None:
        if not self.live or (fraction < 1.0 and time.monotonic() - self._last < 0.1):
            return
        self._last = time.monotonic()
        filled = int(round(fraction * self.width))
        bar = "#" * filled + "-" * (self.width - filled)
        end = "\n" if fraction >= 1.0 else ""
        self.stream.write(f"\r[{bar}] {fraction:4.0%} {message[:60]:<60}{end}")
        self.stream.flush()


class _Report:
    """What `say` could not print: the command's work stands, so the error is told apart at the end."""

    lost: OSError | None = None


def say(message: str) -> None:
    """Print one line of the command's report. A closed pipe or a full disk on standard output must not undo
    a command half-way (its edit may be committed already): the rest of the report is dropped instead."""
    if _Report.lost is not None:
        return
    try:
        print(message, flush=True)
    except OSError as exc:
        _Report.lost = exc
        _silence_stdout()


def _silence_stdout() -> None:
    """Send what stdout still buffers to /dev/null, so Python's flush at exit does not fail again."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError, AttributeError):  # no file descriptor (captured output): nothing to flush at exit
        pass


# -- commands ----------------------------------------------------------------------------------------

def cmd_new(args: argparse.Namespace) -> None:
    from engine.project import new_project

    with new_project(args.project, args.mesh, args.cameras, images=args.images, image_list=args.image_list,
                     image_size=None if args.image_size is None else tuple(args.image_size)) as project:
        say(f"created {project.path}: {len(project.cameras())} cameras, mesh {args.mesh}, local origin "
            f"{', '.join(f'{x:.0f}' for x in project.origin)} m"
            + ("" if args.images else "; no photos linked (use --images DIR to link them)"))


def cmd_info(args: argparse.Namespace) -> None:
    from engine.project import Project
    from engine.project_report import project_report, report_lines

    with Project.open(args.project) as project:
        report = project_report(project)
    if args.json:
        import json

        print(json.dumps(report, indent=1))
    else:
        for line in report_lines(report):
            say(line)


def cmd_import_traces(args: argparse.Namespace) -> None:
    from engine.io import read_traces_csv
    from engine.project import Project

    with Project.open(args.project) as project:
        traces = read_traces_csv(args.traces, project.cameras(local=False))
        ids = project.add_traces2d(traces)
        say(f"imported {len(ids)} 2D traces from {args.traces} on "
            f"{len({t.image for t in traces})} images")


def cmd_kind(args: argparse.Namespace) -> None:
    from engine.project import Project
    from engine.traces import kind_edit

    if not args.trace and not args.trace2d and args.set is None:
        raise TracemapError("kind: say which traces: --trace ID (a 3D trace), --trace2d ID (a 2D trace) or --set ID "
                            "(every 3D trace of a set), each repeatable")
    with Project.open(args.project) as project:
        traces2d, traces3d = project.traces2d(), project.traces3d()
        known = sorted({t.set_id for t in traces3d if t.set_id >= 0})
        unknown = sorted(set(args.set or ()) - set(known))
        if unknown:
            raise TracemapError(f"{project.path}: --set {', '.join(map(str, unknown))}: no such set; the traces' sets "
                                f"are {', '.join(map(str, known)) or 'none yet (run `tracemap orient`)'}")
        of_sets = [t.id for t in traces3d if t.set_id in set(args.set or ())]
        for flag, asked, known in (("--trace", args.trace, traces3d), ("--trace2d", args.trace2d, traces2d)):
            unknown = sorted(set(asked or ()) - {t.id for t in known})
            if unknown:
                raise TracemapError(f"{project.path}: {flag} {', '.join(map(str, unknown))}: no such "
                                    f"{'3D' if flag == '--trace' else '2D'} trace")
        changed2d, changed3d = kind_edit(args.kind, traces2d, traces3d, ids2d=args.trace2d or (),
                                         ids3d=[*(args.trace or ()), *of_sets])
        with project.transaction() as db:
            project.update_traces2d(changed2d, db)
            project.update_traces3d(changed3d, db)
        stale = project.stale_results()
    say(f"{len(changed3d)} 3D and {len(changed2d)} 2D traces made {args.kind}" if changed2d or changed3d
        else f"those traces are {args.kind} already")
    if stale:
        say(f"warning: the stored {', '.join(stale)} are out of date with the new kinds; run `tracemap "
            f"{'orient` and `tracemap analyse' if 'sets' in stale else 'analyse'}` again")


def cmd_autotrace(args: argparse.Namespace) -> None:
    from dataclasses import asdict, fields

    from engine.delineate import DelineationParams, autotrace, params_from_dict, read_params, read_photo, silhouette
    from engine.delineate.params import SETTING
    from engine.project import Project

    base = asdict(read_params(args.params) if args.params else DelineationParams())
    given = {f.name: getattr(args, f.name) for f in fields(DelineationParams) if getattr(args, f.name) is not None}
    params = params_from_dict({**base, **given})
    with Project.open(args.project) as project:
        cameras = project.cameras(local=False)
        names = args.image or sorted(cameras)
        unknown = sorted(set(names) - set(cameras))
        if unknown:
            raise TracemapError(f"{project.path}: no image named {', '.join(map(repr, unknown))}")
        bar, found, rejected, skeletons = ProgressBar(), {}, {}, _Skeletons()
        if params.silhouette or params.support:
            bar(0.0, "reading the mesh (for its silhouette in the photos and the support between them)")
        tracer = _mesh_tracer(project) if params.silhouette or params.support else None
        local = project.cameras()
        for k, name in enumerate(names):
            path = project.image_path(name)
            if path is None:
                raise TracemapError(f"{project.path}: image {name!r} has no photo linked; create the project "
                                    "with --images DIR to link the photos")
            done = lambda f, m, k=k, name=name: bar((k + f) / len(names), f"{name}: {m}")  # noqa: E731
            photo = read_photo(path, cameras[name])
            outline = silhouette(local[name], tracer, depth_step=params.silhouette_step) if params.silhouette else None
            result = autotrace(photo, params=params, image_name=name, progress=done, silhouette=outline)
            found[name], rejected[name] = result.traces, result.segments.rejected
            skeletons[name] = result.skeleton
        supported, carried = _support(project, found, rejected, skeletons, local, tracer, params) \
            if params.support else (0, 0)
        kinds = _kinds(project, found, local, tracer, params) if params.support else {}
        with project.transaction() as db:  # the earlier auto traces of these photos are replaced
            removed = [i for name in found for i in project.delete_traces2d(name, "auto", db)]
            project.delete_traces3d_of(removed, db)
            for traces in found.values():
                project.add_traces2d(traces, db)
            project.set_setting(SETTING, asdict(params), db)  # the editor's auto-trace panel starts from them
    total = sum(len(t) for t in found.values())
    say(f"auto-traced {len(found)} images: {total} traces ("
        + ", ".join(f"{name} {len(t)}" for name, t in found.items())
        + (f"; replaced {len(removed)} earlier auto traces)" if removed else ")")
        + (f"; {supported} of them kept on the support of other photos" if supported else "")
        + (f"; {carried} carried from the other photos' traces" if carried else "")
        + "".join(f"; {n} proposed as {kind}, as the other photos trace them" for kind, n in kinds.items()))


def _kinds(project: Project, found: dict[str, list], cameras: dict, tracer: RayTracer, params) -> dict[str, int]:
    """Give each photo's proposals the kind the other photos' traces of them have, where they show them
    (`engine.delineate.kinds_traced_elsewhere`: a line traced as bedding in one photo is proposed as
    bedding in the next); the traces read are those that stay. Returns how many took each kind."""
    from engine.delineate import kinds_traced_elsewhere

    kept = [t for t in project.traces2d() if t.image not in found or t.source == "manual"]
    counts: dict[str, int] = {}
    for name in found:
        found[name] = kinds_traced_elsewhere(found[name], name, kept, cameras, tracer,
                                             tolerance=params.support_tolerance, share=params.support_share)
        for t in found[name]:
            if t.kind != "fracture":
                counts[t.kind] = counts.get(t.kind, 0) + 1
    return counts


def _mesh_tracer(project: Project) -> RayTracer:
    """A ray tracer of the project's mesh (local frame), for auto-trace's silhouette and support."""
    from engine.raytrace import RayTracer

    try:
        mesh = project.load_mesh()
    except TracemapError as exc:
        raise TracemapError(f"{exc} (auto-trace uses the mesh for its silhouette in the photos and the support "
                            "between photos; --no-silhouette --no-support runs without it)") from None
    return RayTracer(mesh.vertices, mesh.faces)


class _Skeletons(MutableMapping):
    """Each traced photo's auto-trace skeleton, kept at one bit a pixel until `carried_traces` reads it (24 MB
    a 24 MP photo as booleans, 3 MB as bits)."""

    def __init__(self) -> None:
        self._bits: dict[str, tuple] = {}

    def __setitem__(self, name: str, mask) -> None:
        import numpy as np

        self._bits[name] = np.packbits(mask), mask.shape

    def __getitem__(self, name: str):
        import numpy as np

        bits, shape = self._bits[name]
        return np.unpackbits(bits, count=shape[0] * shape[1]).reshape(shape).astype(bool)

    def __delitem__(self, name: str) -> None:
        del self._bits[name]

    def __iter__(self):
        return iter(self._bits)

    def __len__(self) -> int:
        return len(self._bits)


def _support(project: Project, found: dict[str, list], rejected: dict[str, list], skeletons: Mapping,
             cameras: dict, tracer: RayTracer, params) -> int:
    """Add to `found` (auto traces by photo) the segments they turned down that the other photos' traces show
    (`engine.delineate.supported_traces`), then, with `params.carry`, the other photos' traces each photo
    sees but has not traced where its skeleton (`skeletons`, by photo) lies along them
    (`carried_traces`). The other photos' traces are the new auto traces and the manual ones, and every trace
    of the photos not traced now; bedding traces neither support nor carry (auto-trace proposes fractures).
    Returns how many were kept on the support and how many carried."""
    from engine.delineate import carried_traces, supported_traces
    from engine.traces import Trace2D, network

    traces: dict[str, list] = {}
    for trace in network(project.traces2d()):  # the manual traces stay beside the new auto ones; earlier auto go
        if trace.image not in found or trace.source == "manual":
            traces.setdefault(trace.image, []).append(trace.polyline)
    for name in found:
        traces.setdefault(name, []).extend(t.polyline for t in found[name])
    extra = supported_traces(rejected, traces, cameras, tracer, min_length=params.support_min_length,
                             tolerance=params.support_tolerance, share=params.support_share,
                             simplify=params.simplify)
    for name, lines in extra.items():
        traces[name] = traces[name] + lines
    if params.carry:
        carried = carried_traces(traces, cameras, tracer, skeletons, tolerance=params.support_tolerance,
                                 share=params.support_share, evidence=params.carry_evidence,
                                 min_length=params.carry_min_length, simplify=params.simplify)
    else:
        carried = {name: [] for name in extra}
    for name in found:
        found[name] = found[name] + [Trace2D(0, name, line, "auto") for line in extra[name] + carried[name]]
    return sum(map(len, extra.values())), sum(map(len, carried.values()))


def cmd_extract(args: argparse.Namespace) -> None:
    from engine.extract import extract_traces
    from engine.project import Project
    from engine.raytrace import RayTracer

    with Project.open(args.project) as project:
        cameras = project.cameras()
        unknown = sorted(set(args.image or ()) - set(cameras))
        if unknown:
            raise TracemapError(f"{project.path}: no image named {', '.join(map(repr, unknown))}")
        traces = project.traces2d(args.image)
        if not traces:
            say("no 2D traces to extract")
            return
        mesh = project.load_mesh()
        tracer = RayTracer(mesh.vertices, mesh.faces)
        result = extract_traces(traces, cameras, tracer, spacing=args.spacing, min_run=args.min_run,
                                edge_px=args.edge_px,
                                progress=ProgressBar())
        with project.transaction() as db:
            removed = project.delete_traces3d_of((t.id for t in traces), db)
            project.add_traces3d(result.traces, db)
        say(f"extracted {len(result.traces)} 3D traces from {len(traces)} 2D traces "
            f"({result.n_rays} rays, {result.n_missed} missed the mesh, {result.n_edge} on occluding edges, "
            f"{result.n_split} traces split, {result.n_dropped} slivers dropped"
            + (f"; replaced {removed} earlier 3D traces)" if removed else ")"))


def cmd_export(args: argparse.Namespace) -> None:
    from engine.io import SUMMARY_SECTION, export_tables
    from engine.project import Project

    with Project.open(args.project) as project:
        written = export_tables(project, args.outdir, tuple(args.format.split(",")))
        stale = project.stale_results()
    say(f"wrote {', '.join(p.name for p in written)} to {args.outdir}")
    if stale:
        _warn_out_of_date("summary.json's " + ", ".join(dict.fromkeys(SUMMARY_SECTION[n] for n in stale)) +
                          " (listed under out_of_date)", stale)


def _warn_out_of_date(what: str, stale: list[str]) -> None:
    say(f"warning: {what} were computed before the 3D traces last changed; run `tracemap "
        f"{'orient' if 'sets' in stale else 'analyse'}` again")


def cmd_merge(args: argparse.Namespace) -> None:
    from engine.merge import auto_merge, relabel_components, suggest_merges
    from engine.project import Project

    if not args.auto and not args.pair and not args.list:
        raise TracemapError("merge: say what to merge: --auto, or --pair A B (3D trace ids); or --list")
    if args.list and (args.auto or args.pair):
        raise TracemapError("merge: --list only lists the suggestions; give it without --auto or --pair")
    with Project.open(args.project) as project:
        traces = {t.id: t for t in project.traces3d()}
        for a, b in args.pair or ():
            missing = list(dict.fromkeys(i for i in (a, b) if i not in traces))
            if missing:
                raise TracemapError(f"{project.path}: no 3D trace with id {', '.join(map(str, missing))}")
            if a == b:
                raise TracemapError(f"--pair {a} {b}: a trace cannot be merged with itself")
        sight = _survey(project)
        if args.list:
            _list_suggestions(suggest_merges(list(traces.values()), tolerance=args.tolerance, sight=sight,
                                             review=True))
            return
        removed, added = _merge_pairs(traces, args.pair or (), tolerance=args.tolerance, sight=sight)
        if args.auto:
            rest = [t for i, t in traces.items() if i not in removed]
            result = auto_merge(rest, tolerance=args.tolerance, sight=sight)
            merged = {i for group in result.merged_groups for i in group}
            removed += sorted(merged)
            added += [t for t in result.traces if t.id == 0]
        kept = [t for i, t in traces.items() if i not in removed]
        labelled = relabel_components([*kept, *added], args.tolerance)  # a merge can join two groups
        with project.transaction() as db:
            project.remove_traces3d(removed, db)
            project.update_traces3d([new for old, new in zip(kept, labelled) if new.component != old.component], db)
            project.add_traces3d(labelled[len(kept):], db)
        review = [] if not args.auto else suggest_merges(project.traces3d(), tolerance=args.tolerance, sight=sight,
                                                         review=True)
    say(f"merged {len(removed)} 3D traces into {len(added)}; {len(traces) - len(removed) + len(added)} traces now")
    doubtful = sum(s.kind == "candidate" for s in review)
    if doubtful:
        say(f"{doubtful} pairs of pieces may continue each other across a gap no photo shows, but the rules "
            f"leave them apart: judge them in the 3D viewer (Merge → Suggest merges…) or see `merge --list`")
    conflicts = [s for s in review if s.kind == "kinds"]
    if conflicts:
        say(f"{len(conflicts)} pairs of traces of two kinds lie along each other as one trace would (e.g. "
            f"{conflicts[0].a_id} and {conflicts[0].b_id}): give each pair one kind (`tracemap kind`) and merge "
            "again; `merge --list` lists them")


def _merge_pairs(traces: dict[int, Trace3D], pairs, *, tolerance: float,
                 sight: Sight | None) -> tuple[list[int], list[Trace3D]]:
    """The ids the --pair merges replace and the traces they make. Pairs are merged in the order given, and a
    trace already merged stands for its merger, so `--pair 1 2 --pair 2 3` makes one trace of three."""
    from engine.merge import merge_pair

    into: dict[int, int] = {}  # original id → key of the merged trace that now holds it
    made: dict[int, Trace3D] = {}  # negative keys: the traces merged so far
    for a, b in pairs:
        ka, kb = into.get(a, a), into.get(b, b)
        if ka == kb:
            raise TracemapError(f"--pair {a} {b}: the two traces are already merged by an earlier --pair")
        merged = merge_pair(made.get(ka, traces.get(ka)), made.get(kb, traces.get(kb)), tolerance=tolerance,
                            sight=sight)
        key = -1 - len(made)
        made[key] = merged
        for original, holder in [*into.items(), (a, ka), (b, kb)]:
            if holder in (ka, kb):
                into[original] = key
        for k in (ka, kb):
            made.pop(k, None)
    return sorted(into), list(made.values())


def _survey(project: Project) -> Sight | None:
    """The project's survey for pieces across a gap no photo shows, or None (with a warning) without the mesh:
    merging duplicates needs no mesh."""
    from engine.raytrace import RayTracer
    from engine.sight import Sight

    try:
        mesh = project.load_mesh()
        return Sight(mesh, project.cameras(), RayTracer(mesh.vertices, mesh.faces))
    except TracemapError as exc:
        say(f"warning: {exc}; pieces across gaps no photo shows are not bridged")
        return None


def _list_suggestions(suggestions: list[MergeSuggestion]) -> None:
    """One line per merge suggestion, best first; pairs left to the user's judgement marked ?."""
    from engine.merge import FOR_REVIEW

    if not suggestions:
        say("no merge suggestions")
        return
    say(f"{'':2s}{'A':>6s} {'B':>6s} {'kind':9s} {'score':>5s}  reason")
    for s in suggestions:
        say(f"{'?' if s.kind in FOR_REVIEW else '':2s}{s.a_id:6d} {s.b_id:6d} {s.kind:9s} {s.score:5.2f}  {s.reason}")
    sure = sum(s.kind not in FOR_REVIEW for s in suggestions)
    say(f"{sure} suggestions the rules are sure of (`merge --auto` takes them), {len(suggestions) - sure} "
        f"marked ? for your judgement (accept one with `merge --pair A B`)")


def cmd_orient(args: argparse.Namespace) -> None:
    from engine.analysis import orient_and_classify
    from engine.orientation import normal_to_dip_dipdir, upward
    from engine.project import Project
    from engine.register import rotate_directions

    with Project.open(args.project) as project:
        traces = project.traces3d()
        if not traces:
            raise TracemapError(f"{project.path}: no 3D traces to orient; run `tracemap extract` first")
        run = orient_and_classify(traces, project.load_mesh(), facets=project.facets(), n_sets=args.sets,
                                  k_threshold=args.k_threshold, progress=ProgressBar())
        with project.transaction() as db:
            project.update_traces3d(run.traces, db)
            for name, value in run.results.items():
                project.set_result(name, value, db)
            project.record_basis(list(run.results), project.traces3d(), db)
        sim = _similarity(project)
    model = run.model
    say(run.summary)
    for s in model.sets:
        dip, dip_direction = normal_to_dip_dipdir(upward(rotate_directions(s.normal, sim)))
        say(f"  set {s.id}: {s.n} traces, dip {float(dip):.0f}° / {float(dip_direction):03.0f}°, κ {s.kappa:.1f}, "
            f"α95 {s.alpha95:.1f}°" + ("" if sim is None else " (GCPs' frame)"))
    if model.peaks:
        peaks = (normal_to_dip_dipdir(upward(rotate_directions(p.normal, sim))) for p in model.peaks)
        say("  pole density peaks: " + ", ".join(f"{float(d):.0f}° / {float(a):03.0f}° ({p.density:.1f}× uniform)"
                                                for (d, a), p in zip(peaks, model.peaks)))


def _similarity(project: Project) -> Similarity | None:
    """The project's registration, which exports, plots and printed results report in; None without one."""
    registration = project.registration()
    return None if registration is None else registration.similarity


def cmd_analyse(args: argparse.Namespace) -> None:
    import numpy as np

    from engine.analysis import analyse_project, describe_topology
    from engine.errors import InputError
    from engine.project import Project
    from engine.register import length_scale

    with Project.open(args.project) as project:
        sim = _similarity(project)
        scale = length_scale(sim)  # --radius is in metres of the GCPs' frame, like everything the user reads
        radius = None if args.radius is None else args.radius / scale
        try:
            result = analyse_project(project, radius=radius, n_bootstrap=args.bootstrap, progress=ProgressBar())
        except InputError as exc:
            if sim is None or radius is None:
                raise
            raise InputError(None, f"--radius {args.radius:g} m in the GCPs' frame is {radius:.4g} m on the mesh "
                                   f"(scale {scale:.4f}): {exc}") from None
    frame = "" if sim is None else " (GCPs' frame)"
    say(describe_topology(result.topology))
    for line in result.relations.describe() if result.relations.sets else ():
        say(line)
    for label, a in result.lengths.items():
        km = a.kaplan_meier
        name = "all traces" if label == "all" else "non-systematic" if label == "-1" else f"set {label}"
        median = ("not reached (too many censored)" if km is not None and not np.isfinite(km.median)
                  else f"{km.median * length_scale(sim):.2f} m{frame}" if km is not None else "")
        say(f"lengths, {name}: {a.n} traces ({a.n_censored} censored)"
            + (f", Kaplan–Meier median {median}" if km is not None else f"; {a.message}"))
    if result.maps:
        say(f"intensity maps: {', '.join(sorted(result.maps))} (radius {args.radius:g} m{frame})")


def cmd_analyse_map(args: argparse.Namespace) -> None:
    from engine.maps2d import analyse_map, report_lines

    if args.grid_radius is not None and args.grid is None:
        raise InputError(None, "--grid-radius sets the radius of the P21 map's discs: give the map's cell with --grid")
    circles = [((x, y), r) for x, y, r in args.scan_circle or ()]
    result = analyse_map(args.traces, args.area, args.output, snap=args.snap, layer=args.layer,
                         area_layer=args.area_layer, set_column=args.set_column, n_bootstrap=args.bootstrap,
                         scan_circles=circles, grid=args.grid, grid_radius=args.grid_radius,
                         scan_circle_grid=args.scan_circle_grid, progress=ProgressBar())
    say(f"{args.traces} -> {args.output}")
    for line in report_lines(result.analysis):
        say(line)


def cmd_register(args: argparse.Namespace) -> None:
    import numpy as np

    from engine.errors import InputError
    from engine.project import Project
    from engine.raytrace import RayTracer
    from engine.register import read_gcps_csv, register_gcps

    with Project.open(args.project) as project:
        gcps = read_gcps_csv(args.gcps, project.cameras(local=False)) if args.gcps else project.gcps()
        if not gcps:
            raise TracemapError(f"{project.path}: no GCPs stored; give a CSV (columns name,x,y,z,image,u,v) or pick "
                                "them with the GCP tool of the image editor")
        mesh = project.load_mesh()
        try:
            registration = register_gcps(gcps, project.cameras(), RayTracer(mesh.vertices, mesh.faces),
                                         project.origin)
        except InputError as exc:  # a ray that misses, GCPs on a line in the model: say which file they came from
            raise InputError(args.gcps or project.path, str(exc)) from None
        with project.transaction() as db:
            if args.gcps:  # the CSV is the whole list: it replaces the stored GCPs
                for name in project.gcps():
                    project.remove_gcp(name, db)
                for name, gcp in gcps.items():
                    project.set_gcp(name, gcp["world"], gcp["observations"], db)
            project.set_registration(registration, db)
    sim = registration.similarity
    angle = np.degrees(np.arccos(np.clip((np.trace(sim.R) - 1) / 2, -1.0, 1.0)))
    say(f"registered with {len(registration.names)} GCPs: scale {sim.scale:.6f}, rotation {angle:.3f}°, "
        f"RMS error {sim.rmse:.4f} m; exports are now in the GCPs' frame")
    say(f"{'GCP':<12} {'photos':>6} {'spread m':>9} {'dx m':>9} {'dy m':>9} {'dz m':>9} {'error m':>9}")
    for name, images, spread, (dx, dy, dz), error in zip(registration.names, registration.images,
                                                         registration.spread, sim.residuals, sim.errors):
        say(f"{name:<12} {len(images):>6} {spread:>9.4f} {dx:>9.4f} {dy:>9.4f} {dz:>9.4f} {error:>9.4f}")
    if abs(sim.scale - 1) > FRAME_SCALE_NOTE or angle > FRAME_ANGLE_NOTE:
        say(f"note: the GCPs' frame is not the mesh's (scale {sim.scale:.4f}, rotation {angle:.2f}°): exports, "
            "plots, renders, `analyse --radius`, what `orient` and `analyse` print and the 3D viewer's readouts and "
            "tools are in the GCPs' frame; the analysis runs in the mesh's")


def cmd_facet(args: argparse.Namespace) -> None:
    import numpy as np

    from engine.project import Project
    from engine.sets import fit_mesh_facet, mesh_patch

    with Project.open(args.project) as project:
        mesh = project.load_mesh()
        point = np.array(args.point) - project.origin
        facet = fit_mesh_facet(mesh, mesh_patch(mesh, point, args.radius))
        where = f"the patch within {args.radius:g} m of ({', '.join(f'{x:g}' for x in args.point)})"
        if not facet.accepted:
            raise TracemapError(f"{project.path}: {where} was not stored: {facet.rejected_reason}")
        facet_id = project.add_facet(facet)
    dip, dip_direction = facet.dip_dipdir
    say(f"facet {facet_id}: dip {dip:.1f}° / dip direction {dip_direction:05.1f}°, planarity {facet.planarity:.3f}, "
        f"rms {facet.rms * 1000:.1f} mm over {facet.n_points} vertices of {where}; stored as a seed of the sets")


def cmd_scanline(args: argparse.Namespace) -> None:
    from engine.analysis import measure_scanlines
    from engine.project import Project
    from engine.scanline import describe_pooled, describe_scanline, pooled, scanline_report

    laying = args.start is not None or args.end is not None
    if laying and (args.start is None or args.end is None):
        raise TracemapError("scanline: give both ends, --from X Y Z and --to X Y Z")
    if sum((laying, args.levels is not None, args.remove is not None)) > 1:
        raise TracemapError("scanline: give one of --from/--to, --levels or --remove")
    with Project.open(args.project) as project:
        sim = _similarity(project)
        if args.remove is not None:
            _remove(project, args.remove, project.scanlines(), project.remove_scanline, "scanline")
            return
        if laying or args.levels is not None:
            measures = _lay_scanlines(project, args, sim)
        else:
            measures = measure_scanlines(project)
        reports = [scanline_report(m, project.origin, sim) for m in measures]
    if not reports:
        say("no scanlines yet: lay one with --from X Y Z --to X Y Z, or a survey of them with --levels N")
    frame = "" if sim is None else " (GCPs' frame)"
    for r in reports:
        say(describe_scanline(r) + frame)
    if len(measures) > 1:
        say(describe_pooled(pooled(measures, sim), len(measures)) + frame)


def _remove(project: Project, item_id: int, items: list, remove, noun: str) -> None:
    """Remove the stored scanline or scan circle `item_id` (`remove(id)`), or say there is none."""
    if item_id not in {item.id for item in items}:
        raise TracemapError(f"{project.path}: no {noun} with id {item_id} (`tracemap {noun.replace(' ', '-')} "
                            f"{project.path}` lists them)")
    remove(item_id)
    say(f"removed {noun} {item_id}")


def _lay_scanlines(project: Project, args: argparse.Namespace, sim: Similarity | None) -> list:
    """The scanlines `scanline --from/--to` or `--levels` lays, measured (refused, unstored, if any is off
    the rock) and then stored in one edit, with their ids."""
    from dataclasses import replace

    import numpy as np

    from engine.analysis import measure_scanlines
    from engine.register import length_scale
    from engine.scanline import Scanline, level_scanlines

    scale = length_scale(sim)
    reach = None if args.reach is None else args.reach / scale
    if args.levels is not None:
        up = np.array([0.0, 0.0, 1.0]) if sim is None else sim.R.T @ np.array([0.0, 0.0, 1.0])
        lines = level_scanlines(project.load_mesh(), args.levels, margin=args.margin / scale, up=up, reach=reach)
        if args.name:
            lines = [replace(line, name=f"{args.name} {k + 1}") for k, line in enumerate(lines)]
    else:
        lines = [Scanline(np.array(args.start) - project.origin, np.array(args.end) - project.origin, reach=reach,
                          name=args.name)]
    measures = measure_scanlines(project, lines=lines)
    with project.transaction() as db:
        return [replace(m, line=replace(m.line, id=project.add_scanline(m.line, db))) for m in measures]


def cmd_scan_circle(args: argparse.Namespace) -> None:
    from engine.analysis import measure_scan_circles
    from engine.project import Project
    from engine.register import length_scale
    from engine.scan_circle import (counts_report, describe_pooled_windows, describe_window, pooled_windows,
                                    window_report)

    if (args.at or args.grid) and args.radius is None:
        raise TracemapError("scan-circle: give the windows' radius, --radius R")
    if args.spacing is not None and not args.grid:
        raise TracemapError("scan-circle: --spacing is the grid's; give it with --grid")
    if sum((bool(args.at), args.grid, args.remove is not None)) > 1:
        raise TracemapError("scan-circle: give one of --at, --grid or --remove")
    with Project.open(args.project) as project:
        sim = _similarity(project)
        if args.remove is not None:
            _remove(project, args.remove, project.scan_circles(), project.remove_scan_circle, "scan circle")
            return
        measures = _lay_scan_circles(project, args, sim) if args.at or args.grid else measure_scan_circles(project)
        reports = [window_report(m, project.origin, sim) for m in measures]
    if not reports:
        say("no scan circles yet: lay one with --at X Y Z --radius R, or a grid of them with --grid --radius R")
    frame = "" if sim is None else " (GCPs' frame)"
    for r in reports:
        say(describe_window(r, frame))
    if len(measures) > 1:
        say(describe_pooled_windows(counts_report(pooled_windows(measures), length_scale(sim)), len(measures))
            + frame)


def _lay_scan_circles(project: Project, args: argparse.Namespace, sim: Similarity | None) -> list:
    """The scan circles `scan-circle --at` or `--grid` lays, measured (refused, unstored, if any is off the
    rock) and then stored in one edit, with their ids."""
    from dataclasses import replace

    import numpy as np

    from engine.analysis import project_sight
    from engine.errors import InputError
    from engine.register import length_scale
    from engine.scan_circle import ScanCircle, grid_scan_circles, measure_scan_circle

    scale = length_scale(sim)
    radius = args.radius / scale
    mesh = project.load_mesh()
    if args.grid:
        up = np.array([0.0, 0.0, 1.0]) if sim is None else sim.R.T @ np.array([0.0, 0.0, 1.0])
        spacing = None if args.spacing is None else args.spacing / scale
        circles = grid_scan_circles(mesh, radius, spacing=spacing, up=up)
        if args.name:
            circles = [replace(c, name=f"{args.name} {k + 1}") for k, c in enumerate(circles)]
    else:
        circles = [ScanCircle(np.array(at) - project.origin, radius,
                              args.name if len(args.at) == 1 or not args.name else f"{args.name} {k + 1}")
                   for k, at in enumerate(args.at)]
    sight, traces, measures = project_sight(project, mesh), project.traces3d(), []
    for circle in circles:
        try:
            measures.append(measure_scan_circle(mesh, traces, circle, sight=sight))
        except InputError as exc:  # only a centre the user gave can be off the rock
            at = " ".join(f"{x:.10g}" for x in circle.centre + project.origin)
            raise InputError(project.path, f"--at {at}: {exc}") from None
    with project.transaction() as db:
        return [replace(m, circle=replace(m.circle, id=project.add_scan_circle(m.circle, db))) for m in measures]


def cmd_render(args: argparse.Namespace) -> None:
    import numpy as np

    from engine.analysis import measure_samples
    from engine.project import Project
    from engine.register import length_scale
    from engine.render import SceneStyle, photo_size, render_to_file
    from engine.scale_bar import registered_scale_bar

    if args.map and args.color_by not in ("p21", "p32"):
        raise TracemapError(f"--map {args.map} colours the mesh by a map: use it with --color-by p21 or p32, "
                            f"not {args.color_by}")
    if args.output.suffix.lower() not in (".png", ".jpg", ".jpeg", ".tif", ".tiff"):
        raise TracemapError(f"{args.output}: the screenshot must end in .png, .jpg or .tif")
    with Project.open(args.project) as project:
        cameras = project.cameras()
        for option, name in (("--view", args.view), ("--drape", args.drape)):
            if name is not None and name not in cameras:
                raise TracemapError(f"{args.project}: {option} {name!r}: no photo of that name; the photos are "
                                    f"{', '.join(sorted(cameras))}")
        view = cameras.get(args.view)
        style = SceneStyle(color_by=args.color_by, size=tuple(args.size or (photo_size(view) if view else (1600, 1000))),
                           legend=not args.no_legend)
        mesh = project.load_mesh()
        vertex_map = project.vertex_map(args.map or args.color_by)[0] if args.color_by in ("p21", "p32") else None
        if vertex_map is not None:  # per metre of the GCPs' frame, as the exports and the viewer
            vertex_map = vertex_map / length_scale(_similarity(project))
        drape = None if args.drape is None else _drape(project, mesh, cameras[args.drape])
        centres = np.array([c.centre for c in cameras.values()])
        seen_from = centres.mean(axis=0) if view is None else view.centre
        bar = registered_scale_bar(mesh, seen_from, _similarity(project)) if args.scale_bar else None
        samples = measure_samples(project, mesh=mesh) if args.scanlines or args.scan_circles else ([], [])
        scanlines, windows = samples[0] if args.scanlines else [], samples[1] if args.scan_circles else []
        if args.scanlines and not scanlines:
            raise TracemapError(f"{args.project}: --scanlines: the project has no scanlines (lay one with "
                                f"`tracemap scanline`)")
        if args.scan_circles and not windows:
            raise TracemapError(f"{args.project}: --scan-circles: the project has no scan circles (lay one with "
                                f"`tracemap scan-circle`)")
        render_to_file(args.output, mesh, project.traces3d(), style, camera_centres=centres,
                       vertex_map=vertex_map, view=view, drape=drape, bar=bar, scanlines=scanlines, windows=windows)
    seen = f", seen from {args.view}" if view is not None else ""
    draped = f", {args.drape} draped" if drape is not None else ""
    say(f"wrote {args.output} ({style.size[0]}×{style.size[1]}, coloured by {style.color_by}{seen}{draped})")


def _drape(project, mesh, camera):
    """The photo of `camera` draped on `mesh` as the 3D viewer drapes it."""
    from engine.delineate import read_photo
    from engine.drape import drape_photo
    from engine.raytrace import RayTracer
    from engine.render import offscreen_texture_size

    path = project.image_path(camera.name)
    if path is None:
        raise TracemapError(f"{project.path}: --drape {camera.name!r}: the project has no photo file for it")
    return drape_photo(mesh, camera, read_photo(path, camera), RayTracer(mesh.vertices, mesh.faces),
                       max_size=offscreen_texture_size())


def cmd_plot(args: argparse.Namespace) -> None:
    from engine.analysis import project_figures
    from engine.plots import write_plots
    from engine.project import Project

    with Project.open(args.project) as project:
        plots = project_figures(project)
        stale = project.stale_results()
    written = write_plots(plots, args.outdir, tuple(f.strip() for f in args.format.split(",")))
    say(f"wrote {', '.join(p.name for p in written)} to {args.outdir}")
    for plot in plots.values():
        if plot.figure is None:
            say(f"  skipped {plot.name}: {plot.reason}")
    if stale:
        _warn_out_of_date("the plotted " + ", ".join(stale), stale)


def cmd_demo(args: argparse.Namespace) -> None:
    from engine.demo import DEMO_OUTCROP, run_demo
    from engine.synthetic import QUICK

    settings = {**DEMO_OUTCROP, **QUICK} if args.quick else DEMO_OUTCROP
    run_demo(Path(args.out), seed=args.seed, outcrop_settings=settings, progress=ProgressBar(), say=say)
    if not args.headless:
        from tracemap_gui.app import check_display, main as gui_main  # here: the engine never imports Qt

        try:
            check_display()
        except TracemapError as exc:
            say(f"not opening the windows: {exc}")
            return
        say("opening the project in the image editor and the 3D viewer (use --headless to skip)")
        if status := gui_main(str(Path(args.out) / "demo.tracemap")):
            raise SystemExit(status)


def cmd_gui(args: argparse.Namespace) -> None:
    from tracemap_gui.app import main as gui_main  # here, so that the engine never imports Qt on its own

    status = gui_main(None if args.project is None else str(args.project))
    if status:
        raise SystemExit(status)


# -- parser ------------------------------------------------------------------------------------------

def _number(kind: type, low: float | None = None, *, above: bool = False,
            high: float | None = None) -> Callable[[str], float]:
    """An argparse type: a finite `kind` not below `low` (above it if `above`) nor over `high`, so a bad
    option is refused before any work starts, with the range it must lie in."""
    what = "an integer" if kind is int else "a number"
    if low is not None:
        what += f" {'>' if above else '≥'} {low:g}"
    if high is not None:
        what += f"{' and' if low is not None else ''} ≤ {high:g}"

    def parse(text: str) -> float:
        try:
            value = kind(text)
            finite = math.isfinite(value)
        except (ValueError, OverflowError):  # OverflowError: an integer too large for a float (10**400)
            finite = False
        if not (finite and (low is None or value > low or value == low and not above)
                and (high is None or value <= high)):
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
        return value

    return parse


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="tracemap", description="3D fracture trace maps from calibrated "
                                     "outcrop photographs and a photogrammetric mesh.")
    parser.add_argument("--version", action="version", version=f"tracemap {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def command(name: str, func: Callable, help: str) -> argparse.ArgumentParser:
        p = sub.add_parser(name, help=help, description=help)
        p.set_defaults(func=func)
        return p

    p = command("new", cmd_new, "create a project from a mesh and a camera file")
    p.add_argument("project", type=Path, help="the project file to create (*.tracemap)")
    p.add_argument("--mesh", type=Path, required=True, help="mesh file: PLY, OBJ, STL, OFF, GLB, VTK or VTP")
    p.add_argument("--cameras", type=Path, required=True, help="COLMAP folder/file, Metashape XML, Bundler "
                   ".out, VisualSFM .nvm, OpenMVG sfm_data.json, OpenMVS .mvs or tracemap JSON")
    p.add_argument("--images", type=Path, help="folder holding the photos (checked against the cameras)")
    p.add_argument("--image-list", type=Path, help="Bundler: the image list the bundle was made from "
                   "(default: list.txt or <name>.list.txt beside the .out file)")
    p.add_argument("--image-size", type=_number(int, 0, above=True), nargs=2, metavar=("W", "H"), help="Bundler, NVM, OpenMVS: the photos' "
                   "size in pixels, when the photos are not at hand to read it from")

    p = command("info", cmd_info, "what a project holds, what is missing or out of date, and the next step")
    p.add_argument("project", type=Path)
    p.add_argument("--json", action="store_true", help="the report as JSON on standard output")

    p = command("import-traces", cmd_import_traces, "add 2D traces from a CSV (columns image,trace,u,v)")
    p.add_argument("project", type=Path)
    p.add_argument("traces", type=Path, help="CSV: one row per vertex; pixel (0, 0) = centre of top-left pixel")

    p = command("kind", cmd_kind, "say what traces are: fracture, vein, fault or bedding (bedding bounds the "
                "fractures but is left out of their sets, lengths, topology and intensities)")
    p.add_argument("project", type=Path)
    p.add_argument("kind", choices=KINDS)
    p.add_argument("--trace", type=int, action="append", metavar="ID",
                   help="a 3D trace (repeatable); the 2D traces it was made from take the kind too")
    p.add_argument("--trace2d", type=int, action="append", metavar="ID",
                   help="a 2D trace (repeatable); the 3D traces made from it take the kind too")
    p.add_argument("--set", type=int, action="append", metavar="ID",
                   help="every 3D trace of this set (repeatable), e.g. a set `orient` found that is bedding")

    p = command("autotrace", cmd_autotrace, "propose fracture traces on the photos (stored with source auto)")
    p.add_argument("project", type=Path)
    p.add_argument("--image", action="append", metavar="NAME", help="only this image (repeatable)")
    p.add_argument("--params", type=Path, metavar="FILE",
                   help="JSON file of delineation parameters (as the editor's Auto-trace → Save writes); the "
                        "options below override it")
    _delineation_arguments(p)

    p = command("extract", cmd_extract, "ray-trace the 2D traces onto the mesh (2D → 3D)")
    p.add_argument("project", type=Path)
    p.add_argument("--image", action="append", metavar="NAME", help="only this image (repeatable)")
    p.add_argument("--spacing", type=_number(float, 0, above=True), default=1.0, help="ray spacing along traces, pixels (default 1)")
    # 3 is engine.extract.MIN_VERTICES, not imported here so that parsing stays free of the ray tracer
    p.add_argument("--min-run", type=_number(int, 3), default=25,
                   help="drop pieces of a split trace with fewer rays than this (default 25, at least 3)")
    p.add_argument("--edge-px", type=_number(float, 0), default=None,
                   help="side rays this many pixels across a trace find occluding edges, whose pixels are dropped "
                        "(default: 0.4 mesh spacings at each pixel's footprint, 2–20 px; 0 keeps them); each 3D "
                        "trace keeps it, and merge judges by it what a photo would show across a gap")

    p = command("export", cmd_export, "write the traces as files other tools open")
    p.add_argument("project", type=Path)
    p.add_argument("outdir", type=Path)
    p.add_argument("--format", default="csv,ply", help="comma-separated from csv, ply, gpkg, vtp (default csv,ply)")

    p = command("merge", cmd_merge, "merge 3D traces of one fracture seen in several photos")
    p.add_argument("project", type=Path)
    p.add_argument("--auto", action="store_true",
                   help="merge every pair that passes the duplicate guard, and pieces cut by an occlusion")
    p.add_argument("--pair", type=int, nargs=2, action="append", metavar=("A", "B"), help="merge these two")
    p.add_argument("--list", action="store_true",
                   help="print the merge suggestions, with the pairs left to your judgement marked ?; merge nothing")
    p.add_argument("--tolerance", type=_number(float, 0, above=True), default=0.03,
                   help="overlap distance in metres, 2–3 × the ray-casting error (default 0.03)")

    p = command("orient", cmd_orient, "orient the 3D traces (eigen + probabilistic solver) and fit sets")
    p.add_argument("project", type=Path)
    p.add_argument("--sets", type=_number(int, 1), help="number of sets (default: chosen by BIC, see engine.sets)")
    p.add_argument("--k-threshold", type=_number(float, 0), default=0.8,
                   help="collinearity K above which the probabilistic solver is used (default 0.8)")

    p = command("analyse", cmd_analyse, "terminations, connectivity, censored lengths and P21/P32 maps")
    p.add_argument("project", type=Path)
    p.add_argument("--radius", type=_number(float, 0, above=True),
                   help="P21/P32 sphere radius in metres (of the GCPs' frame once registered; default: no maps)")
    p.add_argument("--bootstrap", type=_number(int, 0), default=199, help="samples of the AD p-values (default 199)")

    p = command("analyse-map", cmd_analyse_map, "terminations, topology and censored lengths of a 2D trace map")
    p.add_argument("traces", type=Path, help="GeoJSON, GeoPackage or Shapefile of trace LineStrings")
    p.add_argument("area", type=Path, nargs="?", help="the sampling-area polygon (same formats)")
    p.add_argument("-o", "--output", type=Path, required=True, help="folder for summary.json and the tables")
    p.add_argument("--snap", type=_number(float, 0, above=True), default=0.001, help="node tolerance in map units (default 0.001)")
    p.add_argument("--layer", help="GeoPackage layer of the traces")
    p.add_argument("--area-layer", help="GeoPackage layer of the area")
    p.add_argument("--set-column", help="attribute holding each trace's set")
    p.add_argument("--bootstrap", type=_number(int, 0), default=499, help="samples of the AD p-values (default 499)")
    p.add_argument("--scan-circle", type=_number(float), nargs=3, action="append", metavar=("X", "Y", "R"),
                   help="a circle inside the area for Mauldon's estimators of P21, P20 and mean trace length "
                        "(map units; repeat for more); a circular area gets them without it")
    p.add_argument("--scan-circle-grid", type=_number(float, 0, above=True), metavar="R",
                   help="a circle inventory: scan circles of radius R (map units) 2R apart, those wholly inside "
                        "the area, each measured and all pooled (summary.json scan_circle_grid)")
    p.add_argument("--grid", type=_number(float, 0, above=True), metavar="CELL",
                   help="a P21/P20 map on a grid of this cell (map units): a disc about each cell's centre, "
                        "its part inside the area (p21_grid.png, .csv, .gpkg)")
    p.add_argument("--grid-radius", type=_number(float, 0, above=True), metavar="R",
                   help="radius of the grid's discs (map units; default 1.5 cells, as fractopo's contour grid)")

    p = command("register", cmd_register, "fit the model → world similarity to ground-control points (Horn)")
    p.add_argument("project", type=Path)
    p.add_argument("gcps", type=Path, nargs="?", help="CSV with columns name,x,y,z,image,u,v (one row per photo a "
                   "GCP is picked on; it replaces the stored GCPs); default: the GCPs picked in the GUI")

    p = command("facet", cmd_facet, "fit a fracture plane to the mesh around a point and store it as a set seed")
    p.add_argument("project", type=Path)
    p.add_argument("--point", type=_number(float), nargs=3, required=True, metavar=("X", "Y", "Z"),
                   help="a point on the exposed fracture face, in the mesh file's coordinates")
    p.add_argument("--radius", type=_number(float, 0, above=True), required=True, help="patch radius in metres")

    p = command("scanline", cmd_scanline, "lay a virtual scanline on the outcrop (P10, spacing per set), or list "
                "the stored ones measured on the current traces")
    p.add_argument("project", type=Path)
    p.add_argument("--from", dest="start", type=_number(float), nargs=3, metavar=("X", "Y", "Z"),
                   help="one end, on the rock, in the mesh file's coordinates")
    p.add_argument("--to", dest="end", type=_number(float), nargs=3, metavar=("X", "Y", "Z"), help="the other end")
    p.add_argument("--reach", type=_number(float, 0, above=True),
                   help="how far from the line (m, of the GCPs' frame once registered) the rock under it may lie "
                        "(default a tenth of the line's length, at least 0.5 m)")
    p.add_argument("--levels", type=_number(int, 1), metavar="N",
                   help="lay N level scanlines along the outcrop, evenly spaced in height (a scanline survey)")
    p.add_argument("--margin", type=_number(float, 0), default=1.0,
                   help="with --levels: metres kept clear of the outcrop's foot, top and ends (default 1)")
    p.add_argument("--name", default="", help="a name for the new scanline (with --levels, numbered)")
    p.add_argument("--remove", type=int, metavar="ID", help="remove the stored scanline ID")

    p = command("scan-circle", cmd_scan_circle, "lay circular scan windows on the outcrop (Mauldon's P21, P20 and mean "
                "trace length, free of censoring and length bias), or list the stored ones measured on the "
                "current traces")
    p.add_argument("project", type=Path)
    p.add_argument("--at", type=_number(float), nargs=3, action="append", metavar=("X", "Y", "Z"),
                   help="a window's centre on the rock, in the mesh file's coordinates (repeat for more)")
    p.add_argument("--grid", action="store_true",
                   help="lay windows on a square grid over the outcrop's face, each whole on the rock")
    p.add_argument("--spacing", type=_number(float, 0, above=True),
                   help="with --grid: metres between window centres (default twice the radius: touching circles)")
    p.add_argument("--radius", type=_number(float, 0, above=True),
                   help="window radius in metres (of the GCPs' frame once registered)")
    p.add_argument("--name", default="", help="a name for the new windows (numbered when there are several)")
    p.add_argument("--remove", type=int, metavar="ID", help="remove the stored scan circle ID")

    p = command("render", cmd_render, "write a screenshot of the 3D scene (no display needed)")
    p.add_argument("project", type=Path)
    p.add_argument("-o", "--output", type=Path, required=True, help="image file: .png, .jpg or .tif")
    p.add_argument("--color-by", default="set", choices=COLOR_BY, help="trace or mesh colouring (default set)")
    p.add_argument("--map", help="with p21/p32: the map name, e.g. p21:set0 (default: all sets)")
    p.add_argument("--scale-bar", action="store_true",
                   help="add a scale bar at the outcrop's foot and a north arrow (of the registered frame, if any)")
    p.add_argument("--scanlines", action="store_true",
                   help="draw the project's scanlines (`tracemap scanline`), with a mark at each crossing")
    p.add_argument("--scan-circles", action="store_true",
                   help="draw the project's scan circles (`tracemap scan-circle`): each window's edge on the rock, "
                        "a mark where a trace crosses it and at each trace end inside")
    p.add_argument("--no-legend", action="store_true",
                   help="leave out the key of the set, termination or method colours (upper right)")
    p.add_argument("--view", metavar="PHOTO", help="look from this photo: its position, axis, roll, field of view "
                   "and lens distortion, so that the picture lies over the photo")
    p.add_argument("--drape", metavar="PHOTO", help="drape this photo on the faces it saw (the other faces keep the "
                   "mesh colours); with --view of the same photo, the render is the photo with the traces on it")
    p.add_argument("--size", type=_number(int, MIN_RENDER, high=MAX_RENDER), nargs=2, metavar=("W", "H"),
                   help="image size in pixels (default 1600 1000; with --view the photo's frame, at most 1600 a "
                        "side, and a size given must keep its aspect)")

    p = command("plot", cmd_plot, "write the analysis plots (stereonet, lengths, Kaplan–Meier, terminations, "
                "summary, each scanline's cumulative crossings and the scan circles on the face) and their data as CSV")
    p.add_argument("project", type=Path)
    p.add_argument("-o", "--outdir", type=Path, required=True, help="folder for the images and CSV tables")
    p.add_argument("--format", default="png", help="comma-separated image formats from png, svg (default png)")

    p = command("demo", cmd_demo, "build the synthetic outcrop and run the whole pipeline on it")
    p.add_argument("--headless", action="store_true", help="no windows: write files and print results")
    p.add_argument("--out", default="tracemap-demo", help="output folder (default ./tracemap-demo)")
    p.add_argument("--seed", type=int, default=1, help="random seed of the synthetic outcrop (default 1)")
    p.add_argument("--quick", action="store_true", help="a small outcrop (3 photos of 640×480) for a fast look")

    p = command("gui", cmd_gui, "open the image editor and the 3D viewer")
    p.add_argument("project", type=Path, nargs="?", help="the project to open (default: none, use File → Open)")
    return parser


def _delineation_arguments(parser: argparse.ArgumentParser) -> None:
    """One option per DelineationParams field (--nlm-h, --low, …), with its unit, range and default. An option
    not given is None, so that it does not override a parameter file."""
    from engine.delineate.params import SECTIONS, DelineationParams

    for name, default, unit, allowed, doc in DelineationParams.describe():
        if name in SECTIONS:
            group = parser.add_argument_group(f"delineation: {SECTIONS[name]}")
        flag = "--" + name.replace("_", "-")
        doc = doc.replace("%", "%%")  # argparse formats help with %
        if isinstance(default, bool):
            group.add_argument(f"--no-{name.replace('_', '-')}", dest=name, action="store_false", default=None,
                               help=f"turn off (default on): {doc}")
        else:
            group.add_argument(flag, dest=name, type=type(default), default=None, metavar="X",
                               help=f"{doc}; {allowed}{f' {unit}' if unit else ''} (default {default})")


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    _Report.lost = None
    try:
        args.func(args)
    except TracemapError as exc:
        where = getattr(args, "project", None)
        unplaced = isinstance(exc, InputError) and exc.source is None and where is not None \
            and not str(exc).startswith("--")  # an option's error is the option's, not the project's
        print(f"tracemap {args.command}: error: {f'{where}: ' if unplaced else ''}{exc}", file=sys.stderr)
        return EXIT_ERROR
    except (KeyboardInterrupt, Cancelled):
        print(f"tracemap {args.command}: interrupted; nothing was changed", file=sys.stderr)
        return EXIT_INTERRUPTED
    except MemoryError:
        print(f"tracemap {args.command}: error: out of memory; nothing was changed", file=sys.stderr)
        return EXIT_ERROR
    except sqlite3.DatabaseError as exc:  # a page of the project (or a GeoPackage) that SQLite cannot read
        print(f"tracemap {args.command}: error: a database file is damaged (SQLite: {exc}); nothing was changed",
              file=sys.stderr)
        return EXIT_ERROR
    except OSError as exc:
        print(f"tracemap {args.command}: error: {exc.strerror or exc} "
              f"({exc.filename or 'file system'}); nothing was changed", file=sys.stderr)
        return EXIT_ERROR
    except Exception:  # a bug: keep the traceback for the report, show the user one line
        log = Path(tempfile.gettempdir()) / "tracemap-error.log"
        log.write_text(traceback.format_exc(), encoding="utf-8")
        print(f"tracemap {args.command}: internal error: {sys.exc_info()[1]!r}; the project is unchanged. "
              f"Please report it with {log}", file=sys.stderr)
        return EXIT_ERROR
    return _report_lost(args.command)


def _report_lost(command: str) -> int:
    """The exit status of a command that completed: 0, unless its report could not be written. A reader that
    stopped reading (`| head`) wanted no more; any other failure is an error the user must hear of."""
    lost = _Report.lost
    if lost is None or isinstance(lost, BrokenPipeError):
        return 0
    print(f"tracemap {command}: the command completed (its changes are saved), but its report could not be "
          f"written to standard output: {lost.strerror or lost}", file=sys.stderr)
    return EXIT_ERROR


if __name__ == "__main__":
    sys.exit(main())
