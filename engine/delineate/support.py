"""Support from other photos: a chain one photo turned down is kept where the other photos of the rock show it,
and the other photos' traces are carried into a photo whose edges lie along them.

A fracture trace is a feature of the rock, so the photos that see it show it, but one photo may show it too
faintly for its own judge (in shade, on mottled rock, at a grazing angle). Each chain of the wanted polarity
that a photo's brightness profile turned down (`Segments.rejected`) is ray-traced onto the mesh, one ray per
pixel, and its points are projected into every other photo that sees at least half of it (in frame and not
occluded). Such a photo votes for the chain when at least `share` of what it sees lies within `tolerance` px
of its accepted traces; the chain is kept on a majority of the votes. One photo's support is not enough
where another sees the chain whole and shows nothing there: a mesh crease or a shadow can be traced falsely
in one photo and be a dark line in the next. Chains already half within `tolerance` of the photo's own
traces add nothing and are left out.

Measured on the synthetic outcrop (1024×768, three photos, seeds 1–3, both looks; held out seeds 4–5 in
brackets), recall and precision of trace pixels within 2 px: alt look +1.8 (+1.6) and −0.4 (−0.55) points in
the mean, precision −1.4 (−1.3) at worst; default look +1.2 (+1.1) and −0.2 (−0.2), −0.3 (−0.9) at worst.
Kept on the best photo's support alone, alt precision fell by up to 6.3 points (a long false chain along a
dark line another photo had traced falsely).

Second, traces are carried between photos (`carried_traces`): a trace one photo has (found, supported or
drawn by hand) is ray-traced onto the mesh and projected into each other photo that sees half of it and
has not traced it; the pieces off that photo's own traces are added if at least `evidence` of the trace
lies within `tolerance` of the photo's skeleton (its edges before judging: the photo shows something
there, too faintly for its judge, or broken into chains too short to judge) and every third traced photo
that sees half of it shows it too. Pieces shorter than `min_length` px in the photo go (measured: at
10 px, stubs of creases and of the wall foot cost up to 2.3 points of precision). Seed 1 (session 16), alt
look: recall +0.5, +0, +5.1 points, precision +0, +0, +0.5; default +0 to +1.3 and −1.6 to +0.1. Held out,
seeds 2–5: alt recall +0 to +2.2, precision −0.5 to +0.2; default +0 to +2.4 and −0.4 to +0.1. Without the
third photo's veto, false traces of one photo were carried (alt seed 3 photo 1 precision 0.942 → 0.877).

Third, a proposal takes the kind other photos' traces of it have (`kinds_traced_elsewhere`): a line traced
as bedding (or a vein, a fault) in one photo is proposed as bedding where another photo's auto-trace finds
it, by the same vote, so that it neither counts as a fracture nor stays beside the bedding trace as a
duplicate the merge cannot join (merging never joins two kinds).

This goes beyond Seers & Hodgetts (2016), who traced each photo on its own; it needs the mesh and the
cameras, so `tracemap autotrace` runs it over all the photos of the project.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np
from scipy.spatial import cKDTree

from engine.cameras import Camera
from engine.delineate.params import check
from engine.delineate.segments import simplify_polyline
from engine.errors import Progress, report
from engine.raytrace import RayTracer
from engine.traces import NETWORK_KINDS, Trace2D, polyline_length, resample_polyline


@dataclass(frozen=True, eq=False)
class TracedPhoto:
    """A photo's camera (in the tracer's frame) and its accepted traces as points every pixel, in a k-d tree:
    what the other photos' chains are checked against."""

    camera: Camera
    tree: cKDTree

    @classmethod
    def of(cls, camera: Camera, polylines: Sequence[np.ndarray]) -> TracedPhoto:
        samples = [_samples(p) for p in polylines if len(p) >= 2]
        return cls(camera, cKDTree(np.vstack(samples) if samples else np.zeros((0, 2))))

    def on_traces(self, uv: np.ndarray, tolerance: float) -> np.ndarray:
        """(n,) whether each pixel position lies within `tolerance` px of the photo's traces."""
        if self.tree.n == 0:
            return np.zeros(len(uv), bool)
        return np.isfinite(self.tree.query(uv, distance_upper_bound=tolerance)[0])


def supported_traces(rejected: Mapping[str, Sequence[np.ndarray]], traces: Mapping[str, Sequence[np.ndarray]],
                     cameras: Mapping[str, Camera], tracer: RayTracer, *, min_length: float = 5.0,
                     tolerance: float = 2.0, share: float = 0.5, simplify: float = 1.0,
                     progress: Progress | None = None) -> dict[str, list[np.ndarray]]:
    """For each photo of `rejected` (its turned-down chains, `Segments.rejected`), the chains the other photos
    support, simplified to `simplify` px (Douglas–Peucker) as auto-trace's polylines.

    traces : the accepted trace polylines of each photo, by name. Only photos with traces vote: one nobody
    has traced yet says nothing against a chain. cameras : by photo name, in `tracer`'s frame.
    min_length, tolerance, share : as `supported_chains`.
    """
    photos = {name: TracedPhoto.of(cameras[name], lines) for name, lines in traces.items() if len(lines)}
    out = {}
    for k, (name, chains) in enumerate(rejected.items()):
        report(progress, k / max(len(rejected), 1), f"{name}: support from the other photos")
        voters = {**photos, name: photos.get(name, TracedPhoto.of(cameras[name], []))}
        out[name] = [simplify_polyline(c, simplify) for c in supported_chains(
            chains, name, voters, tracer, min_length=min_length, tolerance=tolerance, share=share)]
    report(progress, 1.0, "support from the other photos: done")
    return out


def supported_chains(chains: Sequence[np.ndarray], photo: str, photos: Mapping[str, TracedPhoto],
                     tracer: RayTracer, *, min_length: float = 5.0, tolerance: float = 2.0,
                     share: float = 0.5) -> list[np.ndarray]:
    """The chains (polylines (N, 2), px) of photo `photo` that the other photos of `photos` support.

    min_length : shorter chains (px) are not considered. tolerance : px from another photo's trace that
    counts as on it. share : fraction of what another photo sees of the chain that must lie on its traces
    for that photo to vote for the chain; a majority of the photos that see half of it must vote for it.
    """
    for name, value in (("support_min_length", min_length), ("support_tolerance", tolerance),
                        ("support_share", share)):
        check(name, value)
    own = photos[photo]
    samples = [_samples(c) for c in chains]
    candidates = [k for k, uv in enumerate(samples)
                  if len(uv) >= max(min_length, 2) and own.on_traces(uv, tolerance).mean() < 0.5]
    if not candidates:
        return []
    votes = _votes([samples[k] for k in candidates], own.camera,
                   [p for n, p in photos.items() if n != photo], tracer, tolerance, share)
    return [chains[k] for k, (yes, voters) in zip(candidates, votes) if yes > 0.5 * voters]


def _votes(samples: list[np.ndarray], camera: Camera, others: Sequence[TracedPhoto], tracer: RayTracer,
           tolerance: float, share: float) -> np.ndarray:
    """(n, 2): for each chain, the other photos that vote for it and those that see at least half of it.
    All chains are traced together, one ray query per photo, so a photo's thousands of chains cost a few
    queries and not thousands."""
    chain = np.repeat(np.arange(len(samples)), [len(uv) for uv in samples])
    size = np.bincount(chain, minlength=len(samples))
    hits = tracer.intersect(camera.centre, camera.pixel_rays(np.vstack(samples)))
    on_mesh = np.bincount(chain[hits.hit], minlength=len(samples)) >= 0.5 * size  # else nothing to project
    points, chain = hits.points[hits.hit], chain[hits.hit]
    votes = np.zeros((len(samples), 2), np.int64)
    for other in others:
        seen, projected = _seen_from(other.camera, points, tracer)
        n_seen = np.bincount(chain[seen], minlength=len(samples))
        n_on = np.bincount(chain[seen][other.on_traces(projected[seen], tolerance)], minlength=len(samples))
        voter = on_mesh & (n_seen >= 0.5 * size)
        votes[:, 1] += voter
        votes[:, 0] += voter & (n_on >= share * np.maximum(n_seen, 1))
    return votes


def traced_elsewhere(chains: Sequence[np.ndarray], photo: str, traces: Mapping[str, Sequence[np.ndarray]],
                     cameras: Mapping[str, Camera], tracer: RayTracer, *, tolerance: float = 2.0,
                     share: float = 0.5) -> np.ndarray:
    """(n,) whether each chain (polyline (N, 2), px) of photo `photo` lies along the `traces` (polylines by
    photo name) of the other photos: a majority of the photos with such traces that see half of the chain
    have `share` of what they see within `tolerance` px of them (`supported_chains`' vote)."""
    others = [TracedPhoto.of(cameras[name], lines) for name, lines in traces.items() if name != photo and len(lines)]
    samples = [_samples(c) for c in chains]
    usable = [k for k, uv in enumerate(samples) if len(uv) >= 2]
    out = np.zeros(len(chains), bool)
    if others and usable:
        votes = _votes([samples[k] for k in usable], cameras[photo], others, tracer, tolerance, share)
        out[usable] = votes[:, 0] > 0.5 * votes[:, 1]
    return out


def kinds_traced_elsewhere(proposals: Sequence[Trace2D], photo: str, traces: Sequence[Trace2D],
                           cameras: Mapping[str, Camera], tracer: RayTracer, *, tolerance: float = 2.0,
                           share: float = 0.5) -> list[Trace2D]:
    """The proposals of photo `photo`, each of the kind other photos' `traces` of it have where they show it
    (`traced_elsewhere`, one kind after another: bedding first), else as they are."""
    out = list(proposals)
    for kind in ("bedding", *(k for k in NETWORK_KINDS if k != "fracture")):
        lines: dict[str, list[np.ndarray]] = {}
        for t in traces:
            if t.kind == kind and t.image != photo:
                lines.setdefault(t.image, []).append(t.polyline)
        undecided = [k for k, t in enumerate(out) if t.kind == "fracture"]
        if not lines or not undecided:
            continue
        shown = traced_elsewhere([out[k].polyline for k in undecided], photo, lines, cameras, tracer,
                                 tolerance=tolerance, share=share)
        for k in np.asarray(undecided)[shown]:
            out[k] = replace(out[k], kind=kind)
    return out


def carried_traces(traces: Mapping[str, Sequence[np.ndarray]], cameras: Mapping[str, Camera], tracer: RayTracer,
                   skeletons: Mapping[str, np.ndarray], *, tolerance: float = 2.0, share: float = 0.5,
                   evidence: float = 0.3, min_length: float = 20.0, simplify: float = 1.0,
                   progress: Progress | None = None) -> dict[str, list[np.ndarray]]:
    """For each photo of `skeletons`, the other photos' traces it sees but has not traced, where its own edges
    lie along them: the pieces off its own traces, simplified to `simplify` px (module docstring, second part).

    traces : the trace polylines of each photo (px), by name; photos without traces neither give nor veto.
    skeletons : by photo name, its auto-trace skeleton (bool, photo-sized): every edge before judging.
    A trace of photo S is carried into photo T if T sees at least half of it (in frame, not occluded), less
    than half of it lies within `tolerance` of T's traces, at least `evidence` of it within `tolerance` of
    T's skeleton, and every other traced photo that sees half of it has at least `share` of it on its
    traces (one photo's false trace is not carried where a third photo sees the rock and shows nothing).
    min_length : shortest trace (px in S) and shortest carried piece (px in T).
    """
    for name, value in (("support_tolerance", tolerance), ("support_share", share), ("carry_evidence", evidence),
                        ("carry_min_length", min_length)):
        check(name, value)
    photos = {name: TracedPhoto.of(cameras[name], lines) for name, lines in traces.items() if len(lines)}
    near = {name: _Near.of(mask, tolerance) for name, mask in skeletons.items()}
    out: dict[str, list[np.ndarray]] = {name: [] for name in skeletons}
    for k, (source, photo) in enumerate(photos.items()):
        report(progress, k / len(photos), f"{source}: its traces carried into the other photos")
        samples = [_samples(p) for p in traces[source] if len(p) >= 2]
        samples = [uv for uv in samples if len(uv) >= max(min_length, 2)]
        if not samples:
            continue
        chain = np.repeat(np.arange(len(samples)), [len(uv) for uv in samples])
        hits = tracer.intersect(photo.camera.centre, photo.camera.pixel_rays(np.vstack(samples)))
        points, chain = hits.points[hits.hit], chain[hits.hit]
        views = {name: _seen_from(cameras[name], points, tracer) for name in {*photos, *skeletons} - {source}}
        for target in skeletons:
            if target != source:
                out[target] += _carried(chain, views, target, source, photos, near[target], tolerance, share,
                                        evidence, min_length)
    report(progress, 1.0, "traces carried between the photos")
    return {name: [simplify_polyline(line, simplify) for line in lines] for name, lines in out.items()}


def _carried(chain: np.ndarray, views: Mapping[str, tuple[np.ndarray, np.ndarray]], target: str, source: str,
             photos: Mapping[str, TracedPhoto], near: _Near, tolerance: float, share: float,
             evidence: float, min_length: float) -> list[np.ndarray]:
    """The pieces of photo `source`'s traces (mesh points of trace `chain`, seen from each photo: `views`) that
    `carried_traces` carries into photo `target` (`near`: within tolerance of its skeleton)."""
    seen, uv = views[target]
    own = photos[target].on_traces(np.where(seen[:, None], uv, 0.0), tolerance) & seen if target in photos \
        else np.zeros(len(seen), bool)
    edge = seen & near.at(np.where(seen[:, None], uv, 0.0))
    size = np.bincount(chain)
    n_seen, n_own, n_edge = (np.bincount(chain[m], minlength=len(size)) for m in (seen, own, edge))
    wanted = (n_seen >= 0.5 * size) & (n_own < 0.5 * np.maximum(n_seen, 1)) & (n_edge >= evidence * np.maximum(n_seen, 1))
    for other in set(photos) - {source, target}:
        seen_o, uv_o = views[other]
        on_o = photos[other].on_traces(np.where(seen_o[:, None], uv_o, 0.0), tolerance) & seen_o
        sees = np.bincount(chain[seen_o], minlength=len(size)) >= 0.5 * size
        shows = np.bincount(chain[on_o], minlength=len(size)) >= share * np.maximum(np.bincount(chain[seen_o], minlength=len(size)), 1)
        wanted &= ~sees | shows
    pieces = []
    for c in np.flatnonzero(wanted):
        index = np.flatnonzero((chain == c) & seen & ~own)
        steps = np.linalg.norm(np.diff(uv[index], axis=0), axis=1)
        # a piece ends where the trace goes behind something or off its photo's traces, or jumps in this photo
        breaks = np.flatnonzero((np.diff(index) > 1) | (steps > 2 * tolerance)) + 1
        pieces += [uv[run] for run in np.split(index, breaks)
                   if len(run) >= 2 and polyline_length(uv[run]) >= min_length]  # px in this photo
    return pieces


@dataclass(frozen=True, eq=False)
class _Near:
    """The pixels within a tolerance of a photo's skeleton, one bit each (a 24 MP photo's mask in 3 MB, so
    every photo's can be held at once)."""

    bits: np.ndarray
    shape: tuple[int, int]

    @classmethod
    def of(cls, skeleton: np.ndarray, tolerance: float) -> _Near:
        r = int(np.floor(tolerance))
        dy, dx = np.mgrid[-r:r + 1, -r:r + 1]
        disc = (dx * dx + dy * dy <= tolerance * tolerance).astype(np.uint8)  # exactly the pixels within it
        near = cv2.dilate(np.asarray(skeleton, bool).view(np.uint8), disc)
        return cls(np.packbits(near.astype(bool)), near.shape)

    def at(self, uv: np.ndarray) -> np.ndarray:
        """(n,) whether the pixels nearest positions uv (n, 2) are near the skeleton (False outside)."""
        h, w = self.shape
        pixel = np.rint(uv).astype(np.int64)
        inside = (pixel[:, 0] >= 0) & (pixel[:, 0] < w) & (pixel[:, 1] >= 0) & (pixel[:, 1] < h)
        index = np.where(inside, pixel[:, 1] * w + pixel[:, 0], 0)
        return inside & ((self.bits[index >> 3] >> (7 - (index & 7))) & 1).astype(bool)


def _seen_from(camera: Camera, points: np.ndarray, tracer: RayTracer) -> tuple[np.ndarray, np.ndarray]:
    """(n,) whether `camera` sees each mesh point (in frame, in front, not occluded) and its pixels (n, 2)."""
    uv = camera.project(points)
    seen = np.isfinite(uv).all(axis=1) & (uv[:, 0] >= 0) & (uv[:, 0] <= camera.width - 1) & \
        (uv[:, 1] >= 0) & (uv[:, 1] <= camera.height - 1)
    if seen.any():
        distance = np.linalg.norm(points[seen] - camera.centre, axis=1)
        sight = tracer.intersect(camera.centre, points[seen] - camera.centre)  # t: metres along the unit ray
        # a surface within 0.1% of the distance does not hide the point: the mesh's own roughness beside it
        seen[seen] = ~sight.hit | (sight.t >= (1.0 - 1e-3) * distance)
    return seen, uv


def _samples(polyline: np.ndarray) -> np.ndarray:
    """Points every pixel along a polyline."""
    return resample_polyline(np.asarray(polyline, float), 1.0)[0]
