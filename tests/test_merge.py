"""Merging duplicate 3D traces: overlap, centroid averaging, spline bridges, trimming, automatic merging."""

import functools
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial import cKDTree

from engine.errors import InputError
from engine.extract import EDGE_PX_KEY
from engine.merge import (
    auto_merge,
    joint,
    merge_pair,
    overlap,
    relabel_components,
    suggest_merges,
    trim,
)
from engine.mesh import Mesh
from engine.raytrace import RayTracer
from engine.sight import Sight
from engine.synthetic import QUICK, distance_to_true_traces, make_outcrop
from engine.traces import Trace3D
from outcrops import extract_every_photo, merge_noisy_outcrop, mixed_groups, seen_traces
from scenes import FOLD, folded, plane_on_wavy_wall, wavy_wall_with_post

TOL = 0.02


def curve(s):
    """A gently curved fracture trace on a wall, parametrised by s (m)."""
    s = np.asarray(s, dtype=float)
    return np.column_stack([s, 0.05 * np.sin(2.0 * s), 0.3 * s + 0.1 * np.cos(1.5 * s)])


def make(id_, s, *, image="photo_1", noise=0.0, seed=0, parents=None, ends=("", ""), set_id=-1):
    """A trace along `curve` at parameters s, with pixel provenance and optional noise (m)."""
    points = curve(s) + np.random.default_rng(seed).normal(0, noise, (len(s), 3))
    n = len(points)
    return Trace3D(id_, points, np.column_stack([np.arange(n), np.full(n, 7.0)]), np.arange(n) + 1000 * id_,
                   np.zeros(n), (image,), parents=(id_ * 10,) if parents is None else parents,
                   term_start=ends[0], term_end=ends[1], set_id=set_id)


def distance_to_curve(points):
    s = np.linspace(-1, 4, 50001)
    dense = curve(s)
    return cKDTree(dense).query(points)[0]


# --- overlap -----------------------------------------------------------------------------------------------

def test_overlap_fractions_of_two_overlapping_copies():
    a = make(1, np.arange(0.0, 1.5, 0.01))
    b = make(2, np.arange(0.5, 2.0, 0.013), image="photo_2")
    ov = overlap(a, b, tolerance=TOL)
    shared = 1.0 * np.linalg.norm(curve([1.5])[0] - curve([0.5])[0])  # chord ≈ arc here
    assert ov.fraction_ab == pytest.approx(shared / a.surface_length, abs=0.03)
    assert ov.fraction_ba == pytest.approx(shared / b.surface_length, abs=0.03)
    assert ov.same_direction and ov.separation < 1e-3 and ov.angle < 1.0 and ov.divergence < 0.02
    assert ov.a_range[0] == pytest.approx(50, abs=3) and ov.b_range[1] == pytest.approx(77, abs=3)
    reverse = overlap(a, make(3, np.arange(0.5, 2.0, 0.013)[::-1], image="photo_2"), tolerance=TOL)
    assert not reverse.same_direction and reverse.fraction_ab == pytest.approx(ov.fraction_ab, abs=0.01)


def test_nearest_points_on_a_polyline_are_exact_within_the_reach_of_the_rules():
    """The projection behind every overlap rule against brute force, on zigzag pixel-density polylines with
    long steps (pixels dropped on occluding edges, bridges) where the nearest midpoints mislead."""
    from engine.merge import DIVERGENCE_REACH, _project

    rng = np.random.default_rng(5)
    for trial in range(20):
        steps = rng.normal(0, 0.01, (400, 3)) + [0.01, 0, 0]
        steps[rng.integers(0, 400, 6)] *= rng.uniform(10, 60, (6, 1))  # a few steps 10–60 cm long
        polyline = np.cumsum(steps, axis=0)
        points = polyline[rng.integers(0, 400, 300)] + rng.normal(0, 0.08, (300, 3))
        a, d = polyline[:-1], np.diff(polyline, axis=0)
        t = np.clip(np.einsum("nmk,mk->nm", points[:, None] - a, d) / np.einsum("mk,mk->m", d, d), 0, 1)
        brute = np.linalg.norm(points[:, None] - (a + t[..., None] * d), axis=2).min(axis=1)
        found = _project(points, polyline, TOL).distance
        within = brute <= DIVERGENCE_REACH * TOL
        np.testing.assert_allclose(found[within], brute[within], rtol=0, atol=1e-12)
        assert np.all(found >= brute - 1e-12)  # beyond the reach, an upper bound


def test_end_touching_traces_do_not_overlap():
    a = make(1, np.arange(0.0, 1.0, 0.01))
    b = make(2, np.arange(1.0, 2.0, 0.01) + 0.005, image="photo_2")
    ov = overlap(a, b, tolerance=TOL)
    assert ov.fraction_ab == 0 and ov.fraction_ba == 0 and not ov.overlaps


def test_crossing_traces_overlap_only_near_the_crossing():
    a = make(1, np.arange(0.0, 2.0, 0.01))
    mid = curve([1.0])[0]
    t = np.linspace(-1, 1, 200)[:, None]
    b = Trace3D(2, mid + t * np.array([0.0, 0.0, 1.0]), np.zeros((200, 2)), np.zeros(200), np.zeros(200), ("p",))
    ov = overlap(a, b, tolerance=TOL)
    assert 0 < ov.fraction_ab < 0.05 and 0 < ov.fraction_ba < 0.05 and ov.angle > 60


# --- merging a pair ----------------------------------------------------------------------------------------

def test_two_noisy_copies_merge_to_within_noise_of_the_truth():
    sigma = 0.002
    a = make(1, np.arange(0.0, 1.5, 0.008), noise=sigma, seed=1, ends=("C", "B"))
    b = make(2, np.arange(0.5, 2.0, 0.011), image="photo_2", noise=sigma, seed=2, ends=("B", "C"))
    merged = merge_pair(a, b, tolerance=TOL)
    s_ends = [merged.points[0, 0], merged.points[-1, 0]]
    assert s_ends[0] == pytest.approx(0.0, abs=0.01) and s_ends[1] == pytest.approx(2.0, abs=0.02)
    error = distance_to_curve(merged.points)
    both = (merged.points[:, 0] > 0.55) & (merged.points[:, 0] < 1.45)
    rms_both, rms_one = np.sqrt(np.mean(error[both] ** 2)), np.sqrt(np.mean(error[~both] ** 2))
    # perpendicular noise of one copy is σ√2 (two of three axes); averaging two copies divides it by √2
    assert rms_one == pytest.approx(sigma * np.sqrt(2), rel=0.25)
    assert rms_both < 0.8 * rms_one
    steps = np.linalg.norm(np.diff(merged.points, axis=0), axis=1)
    assert steps.min() > 0 and steps.max() < 0.03  # ordered along the trace: no jumps back and forth
    assert merged.id == 0 and merged.images == ("photo_1", "photo_2") and merged.parents == (10, 20)
    assert merged.extra["merged_from"] == [1, 2]
    assert merged.term_start == "C" and merged.term_end == "C"  # each end covered by one source only
    # every vertex comes from an original vertex and keeps its pixel, face and photo
    assert np.all(merged.image_index >= 0) and not np.isnan(merged.uv).any()
    from_b = merged.image_index == 1
    assert np.all(merged.face[from_b] >= 2000) and np.all(merged.face[~from_b] < 2000)


def test_a_merged_end_is_censored_only_if_censored_in_every_source_covering_it():
    a = make(1, np.arange(0.0, 1.0, 0.01), ends=("C", "C"))
    b = make(2, np.arange(0.0, 1.5, 0.01) + 0.003, image="photo_2", ends=("B", "C"))
    merged = merge_pair(a, b, tolerance=TOL)
    assert merged.term_start == ""  # a says censored, b says blind: unclassified, topology decides
    assert merged.term_end == "C"  # only b reaches it
    c = make(3, np.arange(0.0, 1.5, 0.01) + 0.004, image="photo_3", ends=("C", "B"))
    assert merge_pair(a, c, tolerance=TOL).term_start == "C"


def test_non_overlapping_pieces_are_bridged_by_a_smoothing_spline():
    sigma = 0.001
    a = make(1, np.arange(0.0, 1.0, 0.01), noise=sigma, seed=3)
    b = make(2, np.arange(1.3, 2.2, 0.01)[::-1], image="photo_2", noise=sigma, seed=4)  # reversed
    b.points[5] = b.points[4]  # a repeated vertex: splprep fails on it unless de-duplicated
    merged = merge_pair(a, b, tolerance=TOL, smoothing_sigma=sigma)
    new = merged.image_index == -1
    assert 20 <= new.sum() <= 40  # the 0.3 m gap filled at the traces' spacing
    assert np.isnan(merged.uv[new]).all() and np.all(merged.face[new] == -1)
    assert distance_to_curve(merged.points[new]).max() < 0.01
    steps = np.linalg.norm(np.diff(merged.points, axis=0), axis=1)
    assert steps.max() < 0.03  # continuous, and b was turned round to follow a
    np.testing.assert_array_equal(merged.points[[0, -1]], [a.points[0], b.points[0]])


def test_merging_a_merge_carries_the_ids_it_replaces():
    a, b, c = (make(k, np.arange(0.2 * k, 1.0 + 0.2 * k, 0.01), image=f"photo_{k}") for k in (1, 2, 3))
    ab = merge_pair(a, b, tolerance=TOL)
    assert ab.extra["merged_from"] == [1, 2]
    abc = merge_pair(ab, c, tolerance=TOL)
    assert abc.extra["merged_from"] == [1, 2, 3] and abc.images == ("photo_1", "photo_2", "photo_3")
    stored = replace(ab, id=17)  # once stored, the merge is replaced as a whole
    assert merge_pair(stored, c, tolerance=TOL).extra["merged_from"] == [3, 17]


def test_trim_keeps_provenance_and_clears_cut_ends():
    t = make(4, np.arange(0.0, 1.0, 0.01), ends=("C", "B"))
    cut = trim(t, 10, -5)
    assert len(cut.points) == 85 and cut.id == 4
    np.testing.assert_array_equal(cut.uv, t.uv[10:-5])
    assert (cut.term_start, cut.term_end) == ("", "")
    assert trim(t, 0, 50).term_start == "C" and trim(t, 50, 100).term_end == "B"
    t.normal, t.method, t.K, t.extra = np.array([0.0, 0.0, 1.0]), "eigen", 3.0, {"eigen_normal": [0, 0, 1]}
    cut = trim(t, 10, -5)  # the pole was fitted to the whole trace
    assert cut.normal is None and cut.method == "" and np.isnan(cut.K) and "eigen_normal" not in cut.extra
    assert t.method == "eigen" and t.extra == {"eigen_normal": [0, 0, 1]}
    with pytest.raises(InputError, match="trace 4: trimming to vertices \\[5, 6\\) of 100 leaves 1"):
        trim(t, 5, 6)


# --- automatic merging -------------------------------------------------------------------------------------

def test_auto_merge_joins_a_chain_of_duplicates_into_one_trace():
    a = make(1, np.arange(0.0, 1.0, 0.01), image="photo_1")
    b = make(2, np.arange(0.3, 1.5, 0.009), image="photo_2")
    c = make(3, np.arange(0.8, 2.0, 0.011), image="photo_3")
    other = make(4, np.arange(0.0, 1.0, 0.01), image="photo_1")
    other.points[:, 2] += 0.5  # a parallel fracture half a metre away
    result = auto_merge([a, b, c, other], tolerance=TOL)
    assert result.merged_groups == [(1, 2, 3)] and result.skipped == []
    assert len(result.traces) == 2 and result.traces[0].id == 0 and result.traces[1].id == 4
    assert result.traces[0].points[:, 0].min() < 0.01 and result.traces[0].points[:, 0].max() > 1.98
    assert sorted(t.component for t in result.traces) == [0, 1]


def test_suggestions_refuse_near_misses_that_are_not_one_fracture():
    base = make(1, np.arange(0.0, 1.0, 0.01), image="photo_1")
    twin = make(2, np.arange(0.1, 1.1, 0.01) + 0.002, image="photo_2")
    parallel = make(3, np.arange(0.0, 1.0, 0.01), image="photo_2")
    parallel.points[:, 1] += 0.8 * TOL  # within tolerance all along, but never coinciding
    same_photo = make(4, np.arange(0.1, 1.1, 0.01) + 0.002, image="photo_1")
    s = np.arange(-0.2, 0.2, 0.005)  # a short trace crossing the base at 12°
    direction = (curve([0.6])[0] - curve([0.4])[0])
    direction /= np.linalg.norm(direction)
    turn = np.cross(direction, [0.0, 1.0, 0.0])
    crossing_dir = np.cos(np.radians(12)) * direction + np.sin(np.radians(12)) * turn
    crossing = Trace3D(5, curve([0.5])[0] + s[:, None] * crossing_dir, np.zeros((len(s), 2)), np.zeros(len(s)),
                       np.zeros(len(s)), ("photo_3",))
    suggestions = suggest_merges([base, twin, parallel, same_photo, crossing], tolerance=TOL)
    pairs = {(s.a_id, s.b_id) for s in suggestions}
    assert (1, 2) in pairs and (2, 4) in pairs  # photo_1's two traces each match photo_2's twin ...
    assert not pairs & {(1, 3), (2, 3), (3, 4), (1, 4), (1, 5), (2, 5), (4, 5)}  # ... and nothing else
    best = next(s for s in suggestions if (s.a_id, s.b_id) == (1, 2))
    assert 0.8 < best.score <= 1 and "within 0.02 m along trace" in best.reason
    # the chain 1 – 2 – 4 links two traces of photo_1: only one of them joins photo_2's trace
    result = auto_merge([base, twin, same_photo], tolerance=TOL)
    assert len(result.merged_groups) == 1 and len(result.traces) == 2


# --- bridges: pieces of one fracture end to end ----------------------------------------------------------

ALONG, ACROSS = np.array([1.0, 0.0, 0.3]) / np.hypot(1, 0.3), np.array([0.0, 1.0, 0.0])
NORMAL = np.cross(ALONG, ACROSS)


def planar(id_, s, *, image="photo_1", noise=0.0, seed=0, tilt=0.0, parents=None):
    """A trace of the planar fracture through the origin spanned by ALONG and ACROSS (turned `tilt` degrees
    about ALONG), wiggling 5 cm within the plane as a rough wall makes it, parametrised by s (m)."""
    s = np.asarray(s, dtype=float)
    across = np.cos(np.radians(tilt)) * ACROSS + np.sin(np.radians(tilt)) * NORMAL
    points = s[:, None] * ALONG + 0.05 * np.sin(3 * s)[:, None] * across
    points += np.random.default_rng(seed).normal(0, noise, points.shape)
    n = len(points)
    return Trace3D(id_, points, np.column_stack([np.arange(n), np.zeros(n)]), np.arange(n), np.zeros(n), (image,),
                   parents=(id_ * 10,) if parents is None else parents)


def kinds(suggestions):
    return {(s.a_id, s.b_id): s.kind for s in suggestions}


def test_pieces_seen_end_to_end_are_bridged():
    a = planar(1, np.arange(0.0, 1.0, 0.005), noise=0.001, seed=1)
    b = planar(2, np.arange(1.05, 2.0, 0.005)[::-1], image="photo_2", noise=0.001, seed=2)  # runs the other way
    (s,) = suggest_merges([a, b], tolerance=TOL)
    assert (s.a_id, s.b_id, s.kind) == (1, 2, "bridge") and 0.5 < s.score <= 1
    assert "trace 2 continues trace 1 end to end across a 5" in s.reason
    jt = joint(a, b, tolerance=TOL)
    assert (jt.a_end, jt.b_end) == (-1, -1) and jt.gap == pytest.approx(0.05, abs=0.005)
    assert jt.angle < 3 and jt.offset < 0.005 and jt.back == 0 and abs(jt.plane_excess) < 0.001
    result = auto_merge([a, b], tolerance=TOL)
    (merged,) = result.traces
    assert result.merged_groups == [(1, 2)]
    ends = planar(0, [0.0, 1.995]).points
    assert np.linalg.norm(np.sort(merged.points[[0, -1]], axis=0) - np.sort(ends, axis=0)) < 0.01
    truth = planar(0, np.linspace(0.0, 2.0, 20001)).points
    assert cKDTree(truth).query(merged.points[merged.image_index == -1])[0].max() < 0.004  # the spline bridge


@pytest.mark.parametrize("case", ["wide gap", "kink", "side step", "other plane", "crossed", "loop"])
def test_bridges_refuse_pieces_that_need_not_be_one_fracture(case):
    """Each case breaks one bridge rule (B1–B5) of a pair that is otherwise bridged."""
    a = planar(1, np.arange(0.0, 1.0, 0.005), noise=0.001, seed=1)
    b = planar(2, np.arange(1.05, 2.0, 0.005), image="photo_2", noise=0.001, seed=2)
    traces = [a, b]
    joint_point = planar(0, [1.025]).points[0]
    if case == "wide gap":  # B1: 4 tolerances at most
        b = planar(2, np.arange(1.1, 2.0, 0.005), image="photo_2", noise=0.001, seed=2)
    elif case == "kink":  # B2: 20° off straight
        turn = np.radians(20)
        rot = np.cos(turn) * np.eye(3) + np.sin(turn) * np.array([[0, -1, 0], [1, 0, 0], [0, 0, 0]]) \
            + (1 - np.cos(turn)) * np.diag([0, 0, 1.0])
        b = replace(b, points=(b.points - joint_point) @ rot.T + joint_point)
    elif case == "side step":  # B3: a parallel fracture 3 cm aside
        b = replace(b, points=b.points + 0.03 * NORMAL)
    elif case == "other plane":  # B4: the same end line, a plane turned 45° about it
        b = planar(2, np.arange(1.05, 2.0, 0.005), image="photo_2", noise=0.001, seed=2, tilt=45)
    elif case == "crossed":  # B5: a third fracture runs through the gap
        t = np.linspace(-0.2, 0.2, 81)[:, None]
        traces.append(Trace3D(3, joint_point + t * NORMAL, np.zeros((81, 2)), np.zeros(81), np.zeros(81), ("photo_3",)))
    elif case == "loop":  # a loop has no end: b and back 30 cm aside, closed where b begins by the gap
        points = np.vstack([b.points, b.points[::-1] + 0.3 * ACROSS, b.points[:1]])
        b = Trace3D(2, points, np.zeros((len(points), 2)), np.zeros(len(points)), np.zeros(len(points)), ("photo_2",))
        with pytest.raises(InputError, match="trace 2 is a closed loop: it has no end to continue"):
            joint(a, b, tolerance=TOL)
    traces[1] = b
    assert "bridge" not in kinds(suggest_merges(traces, tolerance=TOL)).values()
    assert len(auto_merge(traces, tolerance=TOL).traces) == len(traces)
    assert kinds(suggest_merges([a, planar(2, np.arange(1.05, 2.0, 0.005), image="photo_2", noise=0.001, seed=2)],
                                tolerance=TOL)) == {(1, 2): "bridge"}  # the pair itself is bridged


def test_duplicates_at_the_joint_do_not_block_the_bridge():
    """Two photos saw piece a, one saw piece b: the duplicates overlap, each bridges to b, all merge."""
    a = planar(1, np.arange(0.0, 1.0, 0.005), noise=0.001, seed=1)
    again = planar(2, np.arange(0.3, 1.01, 0.006), image="photo_2", noise=0.001, seed=3)
    b = planar(3, np.arange(1.06, 2.0, 0.005), image="photo_3", noise=0.001, seed=2)
    assert kinds(suggest_merges([a, again, b], tolerance=TOL)) == {(1, 2): "overlap", (1, 3): "bridge",
                                                                   (2, 3): "bridge"}
    result = auto_merge([a, again, b], tolerance=TOL)
    (merged,) = result.traces
    assert result.merged_groups == [(1, 2, 3)] and sorted(merged.images) == ["photo_1", "photo_2", "photo_3"]
    ends = planar(0, [0.0, 1.995]).points
    assert np.linalg.norm(np.sort(merged.points[[0, -1]], axis=0) - np.sort(ends, axis=0)) < 0.01


def test_short_duplicates_overlap_despite_their_end_zones():
    """A 5 cm fracture tip seen in three photos: shorter than two tolerances, yet three copies of one trace."""
    tips = [planar(k, np.arange(0.0, 0.05, 0.004), image=f"photo_{k}", noise=0.001, seed=k) for k in (1, 2, 3)]
    assert set(kinds(suggest_merges(tips, tolerance=TOL)).values()) == {"overlap"}
    assert auto_merge(tips, tolerance=TOL).merged_groups == [(1, 2, 3)]


def test_a_short_duplicate_of_an_end_overlaps_though_it_lies_in_the_end_zone():
    """A 5 cm piece seen in one photo on the first 5 cm of a 60 cm trace seen in another: most of it lies in
    the long trace's end zone (rule 1's stabilising zone counted 42% on the synthetic outcrop), but all of
    it lies within tolerance of the long trace."""
    long = planar(1, np.arange(0.0, 0.6, 0.004), image="photo_1", noise=0.001, seed=1)
    short = planar(2, np.arange(0.0, 0.05, 0.004), image="photo_2", noise=0.001, seed=2)
    assert overlap(short, long, tolerance=0.03).fraction_ab == 1.0
    assert kinds(suggest_merges([long, short], tolerance=0.03)) == {(1, 2): "overlap"}
    assert auto_merge([long, short], tolerance=0.03).merged_groups == [(1, 2)]


def test_pieces_overlapping_end_to_end_are_duplicates():
    """Two photos each showing part of a long trace, overlapping 20 cm at their ends: under half of either
    (rule 1's fraction), but each leaves the other only past its end (planar outcrop 7: 13 cm of 31 cm)."""
    a = planar(1, np.arange(0.0, 1.0, 0.004), image="photo_1", noise=0.001, seed=1)
    b = planar(2, np.arange(0.8, 2.0, 0.004), image="photo_2", noise=0.001, seed=2)
    ov = overlap(a, b, tolerance=0.03)
    assert ov.end_to_end and max(ov.fraction_ab, ov.fraction_ba) < 0.25
    (s,) = suggest_merges([a, b], tolerance=0.03)
    assert s.kind == "overlap" and "overlap end to end for" in s.reason
    result = auto_merge([a, b], tolerance=0.03)
    assert result.merged_groups == [(1, 2)]
    assert np.ptp(result.traces[0].points[:, 0]) == pytest.approx(np.ptp(planar(0, [0.0, 1.996]).points[:, 0]),
                                                                  abs=0.01)


def test_a_trace_leaving_another_beside_it_does_not_overlap_end_to_end():
    """A trace running 30 cm along another's middle, then leaving it at 10° (a fracture abutting another at
    a small angle): it leaves the overlap beside the other's interior, not past its end."""
    a = planar(1, np.arange(0.0, 2.0, 0.004), image="photo_1")
    s = np.arange(0.0, 1.0, 0.004)
    leave = np.where(s > 0.3, (s - 0.3) * np.tan(np.radians(10)), 0.0)
    points = planar(0, 0.7 + s).points + leave[:, None] * NORMAL
    b = replace(planar(2, 0.7 + s, image="photo_2"), points=points)
    assert not overlap(a, b, tolerance=0.03).end_to_end
    assert suggest_merges([a, b], tolerance=0.03) == []


def test_two_fractures_taking_over_from_each_other_stay_apart_where_a_photo_shows_both():
    """Two fractures whose traces run 5 mm apart for 25 cm where one ends and the other begins, each seen in
    two photos, the first one's end in the second photo as a 10 cm piece of its own (planar outcrop 8). In
    3D the second fracture continues the first one's merged copies end to end, and it comes before the
    small piece in the merge; but each photo shows two traces along the overlap (rule 5 along it)."""
    def seen(id_, s, image, shift=0.0):
        t = planar(id_, s, image=image, noise=0.0005, seed=id_)
        return replace(t, points=t.points + shift * NORMAL)

    first = [seen(1, np.arange(0.0, 2.0, 0.004), "photo_1"), seen(2, np.arange(0.0, 1.6, 0.004), "photo_2"),
             seen(3, np.arange(1.9, 2.0, 0.004), "photo_2")]
    second = [seen(k, np.arange(1.75, 2.5, 0.004), f"photo_{k - 3}", 0.005) for k in (4, 5)]
    groups = auto_merge(first + second, tolerance=0.03).merged_groups
    assert all(set(g) <= {1, 2, 3} or set(g) <= {4, 5} for g in groups) and (4, 5) in groups
    # with one photo's view of each, nothing tells them from two photos' parts of one trace
    assert auto_merge([first[0], second[1]], tolerance=0.03).merged_groups == [(1, 5)]


def test_a_trace_round_a_rib_merges_though_it_runs_back_beside_itself():
    """A trace up one side of a thin rib of rock and back down the other, 10 cm apart, seen in two photos:
    one sees the first side and the turn, the other the turn and the second side. Past the other's end
    each runs back beside the other's interior, which says nothing about the overlap (rule 4; planar
    outcrop 0: traces of 3.3 and 2.5 m)."""
    t = np.arange(0.0, 1.0 + np.pi * 0.05 + 1.0, 0.004)
    arm = np.clip(t, 0, 1.0)
    angle = np.clip(t - 1.0, 0, np.pi * 0.05) / 0.05
    back = np.clip(t - 1.0 - np.pi * 0.05, 0, None)
    x = arm + 0.05 * np.sin(angle) - back
    y = 0.05 - 0.05 * np.cos(angle)
    hairpin = np.column_stack([x, y, np.zeros_like(x)])
    n = len(hairpin)
    one, two = t < 1.0 + np.pi * 0.05, t > 1.0 - 0.3
    a, b = (Trace3D(k, hairpin[m], np.zeros((m.sum(), 2)), np.zeros(m.sum()), np.zeros(m.sum()), (f"photo_{k}",),
                    parents=(k,)) for k, m in ((1, one), (2, two)))
    assert n > 500 and overlap(a, b, tolerance=0.03).end_to_end
    assert auto_merge([a, b], tolerance=0.03).merged_groups == [(1, 2)]


def test_a_shred_shorter_than_the_tolerance_merges_whatever_its_direction():
    """A 1 cm, 3-vertex piece that a photo saw of a trace's tip (rays beside it given up), its noise turning
    it 40° off the trace: it has no direction at the 3 cm scale of rule 2 (planar outcrop 4)."""
    long = planar(1, np.arange(0.0, 0.6, 0.004), image="photo_1")
    tip = planar(0, [0.0, 0.005, 0.01]).points + np.outer([0.0, 0.0042, 0.0084], ACROSS)  # atan(0.84) = 40°
    shred = Trace3D(2, tip, np.zeros((3, 2)), np.zeros(3), np.zeros(3), ("photo_2",), parents=(2,))
    ov = overlap(shred, long, tolerance=0.03)
    assert ov.fraction_ab == 1.0 and np.isnan(ov.angle)
    assert auto_merge([long, shred], tolerance=0.03).merged_groups == [(1, 2)]
    # a shred farther off than half the tolerance is not one (rule 3)
    off = replace(shred, points=shred.points + 0.02 * NORMAL)
    assert auto_merge([long, off], tolerance=0.03).merged_groups == []


def bend(id_, up, right, *, image, step, seed):
    """A trace turning a right angle: `up` m down a vertical arm, then `right` m along the x axis, 1 mm noise."""
    down = np.column_stack([np.zeros(round(up / step)), np.zeros(round(up / step)),
                            np.linspace(up, 0, round(up / step), endpoint=False)])
    along = np.column_stack([np.linspace(0, right, round(right / step) + 1), np.zeros((round(right / step) + 1, 2))])
    points = np.vstack([down, along]) + np.random.default_rng(seed).normal(0, 0.001, (len(down) + len(along), 3))
    n = len(points)
    return Trace3D(id_, points, np.zeros((n, 2)), np.zeros(n, int), np.zeros(n, int), (image,), parents=(id_,))


def test_copies_of_a_bend_run_along_each_other():
    """Two photos' copies of a trace turning 90°, each seeing 6 cm more of a different arm: the overlapping
    parts are L-shaped with arms 12 and 15 cm, whose principal axes lie 23–25° apart (rule 2 before session
    6 refused them), while the traces run the same way at every matched point."""
    a = bend(1, 0.21, 0.15, image="photo_1", step=0.004, seed=1)
    b = bend(2, 0.15, 0.21, image="photo_2", step=0.005, seed=2)
    ov = overlap(a, b, tolerance=0.03)
    assert ov.separation < 0.002 and ov.angle < 6.0
    first, last = ov.a_range
    parts = [a.points[first:last + 1], b.points[ov.b_range[0]:ov.b_range[1] + 1]]
    axes = [np.linalg.svd(p - p.mean(axis=0))[2][0] for p in parts]
    assert np.degrees(np.arccos(abs(axes[0] @ axes[1]))) > 15.0
    assert auto_merge([a, b], tolerance=0.03).merged_groups == [(1, 2)]


def test_relabel_components_groups_touching_traces():
    a = make(1, np.arange(0.0, 1.0, 0.01))
    mid = curve([0.5])[0]
    b = Trace3D(2, mid + np.linspace(0, 1, 50)[:, None] * [0, 0, 1.0], np.zeros((50, 2)), np.zeros(50), np.zeros(50),
                ("p",))
    c = make(3, np.arange(0.0, 1.0, 0.01))
    c.points[:, 2] += 3.0
    labels = [t.component for t in relabel_components([a, b, c], TOL)]
    assert labels == [0, 0, 1]


def test_bad_input_names_the_trace_and_the_expected_range():
    good = make(1, np.arange(0.0, 1.0, 0.01))
    short = make(2, np.array([0.0, 0.1]))
    loop = circle(3, 0.0, centre=(5.0, 0.0, 0.0))
    nan = make(4, np.arange(0.0, 1.0, 0.01))
    nan.points[3, 1] = np.nan
    with pytest.raises(InputError, match="trace 2: 2 vertices; merging needs at least 3"):
        merge_pair(good, short, tolerance=TOL)
    with pytest.raises(InputError, match="trace 3 is a closed loop and the other trace does not overlap it"):
        merge_pair(loop, good, tolerance=TOL)
    with pytest.raises(InputError, match="trace 1 cannot be merged with itself"):
        merge_pair(good, good, tolerance=TOL)
    with pytest.raises(InputError, match="trace 4: 1 of its 100 vertices are NaN"):
        auto_merge([good, nan], tolerance=TOL)
    with pytest.raises(InputError, match="tolerance=0: expected a positive distance in metres"):
        overlap(good, good, tolerance=0)
    with pytest.raises(InputError, match="smoothing_sigma=-1"):
        merge_pair(good, make(5, np.arange(1.0, 2.0, 0.01)), tolerance=TOL, smoothing_sigma=-1)
    with pytest.raises(InputError, match="min_fraction=0: expected a share in \\(0, 1\\]"):
        suggest_merges([good], tolerance=TOL, min_fraction=0)
    with pytest.raises(InputError, match="ids must be unique"):
        suggest_merges([good, make(1, np.arange(1.0, 2.0, 0.01))], tolerance=TOL)
    result = auto_merge([good, short, loop], tolerance=TOL)  # unmergeable traces are kept and reported
    assert [t.id for t in result.traces] == [1, 2, 3] and [k for k, _ in result.skipped] == [2]


def circle(id_, seam, *, centre=(0.0, 0.0, 0.0), image="photo_1", noise=0.0, seed=0, arc=2 * np.pi):
    """A closed loop of radius 0.3 m (or an open arc of it) starting at angle `seam`, 1 vertex per ~5 mm."""
    angle = seam + np.linspace(0.0, arc, int(arc * 60) + 1)
    points = np.column_stack([0.3 * np.cos(angle), 0.1 * np.sin(angle), 0.3 * np.sin(angle)]) + centre
    points += np.random.default_rng(seed).normal(0, noise, points.shape)
    if arc == 2 * np.pi:
        points[-1] = points[0]
    n = len(points)
    return Trace3D(id_, points, np.column_stack([np.arange(n), np.zeros(n)]), np.arange(n), np.zeros(n), (image,),
                   parents=(id_ * 10,))


def test_loops_seen_in_several_photos_merge_into_one_loop():
    """A fracture cutting a knob all round is a closed trace: it has no ends, so every vertex is interior."""
    a = circle(1, 0.0, image="photo_1", noise=0.001, seed=1)
    b = circle(2, 2.0, image="photo_2", noise=0.001, seed=2)  # its seam elsewhere, digitised the other way
    b = replace(b, points=b.points[::-1].copy())
    part = circle(3, 4.0, image="photo_3", noise=0.001, seed=3, arc=2.0)  # an open arc of the same loop
    assert overlap(a, b, tolerance=TOL).fraction_ab > 0.99 and not overlap(a, b, tolerance=TOL).same_direction
    result = auto_merge([a, b, part], tolerance=TOL)
    assert result.merged_groups == [(1, 2, 3)]
    (loop,) = result.traces
    p = loop.points
    assert np.linalg.norm(p[0] - p[-1]) < 0.01  # still closed
    radial = np.hypot(p[:, 0], p[:, 2] / 1.0)
    assert np.abs(radial - 0.3).max() < 0.004 and np.abs(p[:, 1] - 0.1 * p[:, 2] / 0.3).max() < 0.004
    steps = np.linalg.norm(np.diff(p, axis=0), axis=1)
    assert steps.max() < 0.02  # ordered round the loop, no jumps across it
    assert sorted(loop.images) == ["photo_1", "photo_2", "photo_3"]


# --- bridges across gaps that no photo shows -----------------------------------------------------------------

@pytest.fixture(scope="module")
def post_sight():
    vertices, faces, camera = wavy_wall_with_post()
    return Sight(Mesh(vertices, faces), {camera.name: camera}, RayTracer(vertices, faces))


def seen_pieces(sight, normal, x, *, first_id=1, noise=0.001, point=(3.0, 0.0, 2.0), surface=None):
    """The stretches of the plane's exact trace on the wavy wall (or `surface`) that the camera sees, as
    noisy 3D traces."""
    points = plane_on_wavy_wall(point, normal, x, surface)
    seen = sight.seen(points, 0.01)
    edges = np.flatnonzero(np.diff(np.r_[0, seen.astype(int), 0]))
    camera = next(iter(sight.cameras.values()))
    rng = np.random.default_rng(first_id)
    out = []
    for k, (lo, hi) in enumerate(zip(edges[::2], edges[1::2])):
        p = points[lo:hi] + rng.normal(0, noise, (hi - lo, 3))
        n = len(p)
        out.append(Trace3D(first_id + k, p, camera.project(p), np.zeros(n, int), np.zeros(n, int), (camera.name,),
                           parents=(first_id + k,)))
    return out


DIPPING = (0.55, -0.25, 0.8)  # a fracture dipping ~37° towards the south-east: its trace climbs across the post


def test_pieces_cut_by_an_occlusion_in_every_photo_are_bridged(post_sight):
    pieces = seen_pieces(post_sight, DIPPING, np.arange(0.8, 5.2, 0.004))
    assert len(pieces) == 2 and 0.4 < joint(*pieces, tolerance=0.03).gap < 0.9  # the post's shadow
    assert auto_merge(pieces, tolerance=0.03).merged_groups == []  # too wide for rules B1–B5
    (suggestion,) = suggest_merges(pieces, tolerance=0.03, sight=post_sight)
    assert suggestion.kind == "bridge" and "no photo shows" in suggestion.reason
    result = auto_merge(pieces, tolerance=0.03, sight=post_sight)
    (merged,) = result.traces
    truth = plane_on_wavy_wall((3.0, 0.0, 2.0), DIPPING, np.arange(0.7, 5.3, 0.001))
    bridge = merged.points[merged.image_index == -1]
    assert len(bridge) > 30 and np.linalg.norm(np.diff(bridge, axis=0), axis=1).max() < 0.03
    # on the rock where the plane cuts the mesh (measured 0.4 mm: the 2 cm mesh's chords of the curved wall);
    # the spline alone strays up to 7 cm from it across the wall's 8 cm relief
    assert cKDTree(truth).query(bridge)[0].max() < 0.002


def test_merging_asks_what_a_photo_shows_with_the_edge_px_its_traces_were_extracted_with(post_sight, monkeypatch):
    """Rule H3 asks `Sight.shows`, which depends on how extraction treated occluding edges: the pieces'
    recorded `edge_px` (engine.extract.EDGE_PX_KEY) is what it is asked with, and the merge keeps it."""
    (name,) = post_sight.cameras
    pieces = [replace(t, extra={EDGE_PX_KEY: {name: 0}}) for t in seen_pieces(post_sight, DIPPING, np.arange(0.8, 5.2, 0.004))]
    asked, shows = [], Sight.shows
    monkeypatch.setattr(Sight, "shows", lambda self, path, tolerance: asked.append(dict(self.edge_px))
                        or shows(self, path, tolerance))
    (merged,) = auto_merge(pieces, tolerance=0.03, sight=post_sight).traces
    assert asked and all(a == {name: 0} for a in asked) and post_sight.edge_px == {}
    assert merged.extra[EDGE_PX_KEY] == {name: 0}


def test_a_gap_the_photo_shows_is_not_bridged(post_sight):
    """The same fracture with a stretch missing where the camera sees the wall: the trace may end there (two
    fractures in one plane) or the detector may have missed it; either way there is no evidence to join."""
    x = np.arange(0.8, 2.6, 0.004)
    points = plane_on_wavy_wall((3.0, 0.0, 2.0), DIPPING, x)
    assert post_sight.seen(points, 0.01).all()
    left, right = seen_pieces(post_sight, DIPPING, x[x < 1.5]), seen_pieces(post_sight, DIPPING, x[x > 2.0], first_id=5)
    assert suggest_merges(left + right, tolerance=0.03, sight=post_sight) == []
    assert suggest_merges(left + right, tolerance=0.03, sight=post_sight, review=True) == []  # not for review


def test_two_fractures_meeting_behind_the_post_are_not_bridged(post_sight):
    """Left of the post one fracture, right of it another 20° off, whose traces meet behind the post."""
    other = (0.35, -0.55, 0.75)
    left = [t for t in seen_pieces(post_sight, DIPPING, np.arange(0.8, 5.2, 0.004)) if t.points[:, 0].max() < 3]
    right = [t for t in seen_pieces(post_sight, other, np.arange(0.8, 5.2, 0.004), first_id=5)
             if t.points[:, 0].min() > 3]
    assert np.degrees(np.arccos(np.dot(DIPPING, other) / np.linalg.norm(DIPPING) / np.linalg.norm(other))) > 20
    assert joint(left[0], right[0], tolerance=0.03).gap < 0.9
    assert suggest_merges(left + right, tolerance=0.03, sight=post_sight) == []


@pytest.fixture(scope="module")
def fold_sight():
    vertices, faces, camera = wavy_wall_with_post(surface=folded)
    return Sight(Mesh(vertices, faces), {camera.name: camera}, RayTracer(vertices, faces))


ON_FOLD = (FOLD, 0.0, 2.0)
ANOTHER = (0.2, -0.5, 0.85)  # a second fracture's plane through the same point of the fold


def test_straight_pieces_bending_round_a_hidden_edge_are_bridged(fold_sight):
    """A fracture crossing the folded wall's edge behind the post: two straight pieces, each too straight to
    show a plane of its own (rule H2), meeting at 39° on the hidden edge. Together they show one, and
    nothing else could continue either (rule H5)."""
    pieces = seen_pieces(fold_sight, DIPPING, np.arange(0.8, 5.2, 0.004), point=ON_FOLD, surface=folded)
    assert len(pieces) == 2
    jt = joint(*pieces, tolerance=0.03)
    assert 0.4 < jt.gap < 0.9 and 30 < jt.angle < 50
    (suggestion,) = suggest_merges(pieces, tolerance=0.03, sight=fold_sight)
    assert suggestion.kind == "bridge" and "no photo shows" in suggestion.reason
    assert "nothing else continuing either piece" in suggestion.reason
    (merged,) = auto_merge(pieces, tolerance=0.03, sight=fold_sight).traces
    truth = plane_on_wavy_wall(ON_FOLD, DIPPING, np.arange(0.7, 5.3, 0.001), folded)
    bridge = merged.points[merged.image_index == -1]
    assert len(bridge) > 30 and cKDTree(truth).query(bridge)[0].max() < 0.005  # on the rock, round the edge


def test_straight_pieces_that_two_traces_could_continue_are_not_bridged(fold_sight):
    """As above, with a second fracture's trace leaving the same point of the hidden edge on the right face,
    35° off the first's. The left piece could continue in either: each pair alone is bridged, together
    neither is."""
    left, right = seen_pieces(fold_sight, DIPPING, np.arange(0.8, 5.2, 0.004), point=ON_FOLD, surface=folded)
    (other,) = seen_pieces(fold_sight, ANOTHER, np.arange(FOLD, 5.2, 0.004), first_id=5, point=ON_FOLD,
                           surface=folded)
    assert len(suggest_merges([left, right], tolerance=0.03, sight=fold_sight)) == 1
    assert len(suggest_merges([left, other], tolerance=0.03, sight=fold_sight)) == 1
    assert suggest_merges([left, right, other], tolerance=0.03, sight=fold_sight) == []
    assert auto_merge([left, right, other], tolerance=0.03, sight=fold_sight).merged_groups == []
    # for review, both continuations are listed, saying what is in doubt; either merge lies on the rock
    review = suggest_merges([left, right, other], tolerance=0.03, sight=fold_sight, review=True)
    assert {(s.a_id, s.b_id) for s in review} == {(left.id, right.id), (left.id, other.id)}
    assert all(s.kind == "candidate" and 0.05 <= s.score <= 0.1 and "no photo shows" in s.reason
               and "another piece could continue" in s.reason for s in review)
    for continuation in (right, other):
        merged = merge_pair(left, continuation, tolerance=0.03, sight=fold_sight)
        bridge = merged.points[merged.image_index == -1]
        assert len(bridge) > 30 and max(fold_sight.distance(p) for p in bridge) < 0.005


# --- acceptance: the synthetic outcrop ---------------------------------------------------------------------

def _visible_pieces(outcrop, gap):
    """Maximal stretches of each true trace seen by at least one photo (the most merging can recover)."""
    intervals = {}
    for runs in outcrop.traces2d.values():
        for run in runs:
            truth = outcrop.traces3d[run.trace_id].points
            a, d = truth[:-1], np.diff(truth, axis=0)
            length = np.linalg.norm(d, axis=1)
            ends = []
            for p in run.points[[0, -1]]:
                t = np.clip(((p - a) * d).sum(1) / length**2, 0, 1)
                k = np.linalg.norm(p - (a + t[:, None] * d), axis=1).argmin()
                ends.append(np.r_[0, np.cumsum(length)][k] + t[k] * length[k])
            intervals.setdefault(run.trace_id, []).append((min(ends), max(ends)))
    count = 0
    for spans in intervals.values():
        reach = -np.inf
        for lo, hi in sorted(spans):
            count += lo > reach + gap
            reach = max(reach, hi)
    return count


def _assert_on_the_true_traces(traces, outcrop):
    """No extracted vertex lies 3 cm or more off the true traces (before pixels on occluding edges were
    dropped in engine.extract, 114–371 did on these outcrops, up to 31 cm off)."""
    distance, _ = distance_to_true_traces(np.vstack([t.points for t in traces]), outcrop, local=True)
    assert distance.max() < 0.03, np.sort(distance)[-5:]


def _fracture(points, outcrop):
    """The fracture whose true trace is nearest most of the points, and that share of the points."""
    _, ids = distance_to_true_traces(points, outcrop, local=True)
    values, counts = np.unique(ids, return_counts=True)
    return values[counts.argmax()], counts.max() / len(ids)


def test_auto_merge_recovers_the_true_traces_of_the_synthetic_outcrop():
    """Every photo's true 2D traces extracted to 3D (duplicates where photos overlap), then merged."""
    outcrop = make_outcrop(1, **QUICK)
    traces = extract_every_photo(outcrop, outcrop.mesh)
    result = auto_merge(traces, tolerance=TOL)

    n_true, n_pieces = len(outcrop.traces3d), _visible_pieces(outcrop, 2 * TOL)
    assert len(traces) > 1.8 * n_true  # most fractures were seen twice or more
    assert abs(len(result.traces) - n_true) <= 0.05 * n_true
    assert abs(len(result.traces) - n_pieces) <= 0.05 * n_pieces

    by_id = {t.id: t for t in traces}
    for group in result.merged_groups:  # no merge mixes fractures
        assert len({_fracture(by_id[i].points, outcrop)[0] for i in group}) == 1, group
    for t in result.traces:
        assert _fracture(t.points, outcrop)[1] > 0.9


_merge_noisy_outcrop = functools.cache(merge_noisy_outcrop)


# The seven outcrops the rules were developed on, and held-out ones (planar 5, undulating 0) where a looser
# rule H5 joined two fractures
NOISY = [("planar", 4), ("planar", 3), ("planar", 1), ("planar", 0), ("planar", 2), ("undulating", 4),
         ("undulating", 1), ("planar", 5), ("undulating", 0)]


@pytest.mark.parametrize("model, seed", NOISY)
def test_auto_merge_on_a_noisy_mesh_never_mixes_fractures(model, seed):
    """Issue 4 on 2 mm of mesh noise: a fracture comes out as duplicates, short tips and pieces end to end,
    and some fractures are cut in every photo by occlusions 0.3–1 m wide (bench edges, buttresses). No
    merge joins two fractures, by position or by the photos' truth of every 2D trace merged, and no
    extracted vertex lies 3 cm off the truth."""
    outcrop, traces, sight, result = _merge_noisy_outcrop(model, seed)
    _assert_on_the_true_traces(traces, outcrop)
    assert len(result.traces) < _visible_pieces(outcrop, 0.06)
    by_id = {t.id: t for t in traces}
    for group in result.merged_groups:
        assert len({_fracture(by_id[i].points, outcrop)[0] for i in group}) == 1, group
    assert mixed_groups(outcrop, traces, result) == []
    if (model, seed) == ("planar", 4):  # both kinds of bridge merge something
        suggestions = suggest_merges(traces, tolerance=0.03, sight=sight)
        for hidden in (False, True):
            bridges = {(s.a_id, s.b_id) for s in suggestions if s.kind == "bridge"
                       and ("no photo shows" in s.reason) == hidden}
            assert any({a, b} <= set(group) for a, b in bridges for group in result.merged_groups)
        # merging is repeated until nothing more merges (here a second round merged one more): again, nothing
        again = auto_merge([replace(t, id=k + 1) for k, t in enumerate(result.traces)], tolerance=0.03, sight=sight)
        assert again.merged_groups == []
        assert sorted(i for group in result.merged_groups for i in group) == sorted(
            i for t in result.traces if t.id == 0 for i in t.extra["merged_from"])  # each input in one group


def test_review_lists_the_pieces_the_rules_leave_apart_across_hidden_gaps():
    """After automatic merging of undulating outcrop 0 (101 traces for 91 seen: pieces of one trace left
    apart across hidden gaps), nothing sure is left to merge, and the pieces that may continue each other
    across a gap no photo shows are listed for the user: 29 candidates, 12 of them pieces of one trace
    (measured, session 18)."""
    outcrop, _, sight, result = _merge_noisy_outcrop("undulating", 0)
    traces = [replace(t, id=k + 1) for k, t in enumerate(result.traces)]
    review = suggest_merges(traces, tolerance=0.03, sight=sight, review=True)
    assert review and all(s.kind == "candidate" and "no photo shows" in s.reason for s in review)
    trace_of = {run.id: run.trace_id for runs in outcrop.traces2d.values() for run in runs}
    one = [s for s in review if len({trace_of[p] for i in (s.a_id, s.b_id) for p in traces[i - 1].parents}) == 1]
    assert len(one) >= 10 and len(review) <= 40


def _unmet(model, seed, reason):
    return pytest.param(model, seed, marks=pytest.mark.xfail(strict=True, reason=reason))


@pytest.mark.parametrize("model, seed", [
    ("planar", 4), ("planar", 1), ("planar", 0), ("planar", 2), ("planar", 3), ("undulating", 1),
    _unmet("undulating", 4, "73 for 69 seen (+5.8%): pieces of undulating fractures across hidden gaps")])
def test_auto_merge_recovers_the_seen_traces_within_5_percent(model, seed):
    """Issue 4's target, against the true traces some photo shows (no merge can recover one that no photo
    shows: planar seed 4 has 4 of 89, seed 2 6 of 91). Measured (session 20), merged for seen (true):
    planar seed 4 85 for 85 (89), 1 91 for 93 (96), 0 87 for 86 (87), 2 84 for 85 (91), 3 70 for 67 (70);
    undulating seed 4 73 for 69 (69), 1 98 for 94 (95). Held out (not tested; README): planar seeds 5–11
    −4% to +3%, undulating seeds 0, 2, 3, 5, 6, 7 and Fig. 6 seeds 4–6 +1% to +12%. Planar seed 3 met it
    when extraction stopped making traces of two vertices (session 19): the one it made there was the only
    piece of a trace photo 2 shows (1 mm of it on the mesh), so that trace is lost."""
    outcrop, _, _, result = _merge_noisy_outcrop(model, seed)
    n_seen = seen_traces(outcrop)
    assert abs(len(result.traces) - n_seen) <= 0.05 * n_seen, (len(result.traces), n_seen)


def test_a_merged_trace_keeps_the_edge_px_of_every_photo():
    a = replace(make(1, np.arange(0.0, 1.0, 0.01), image="photo_1"), extra={EDGE_PX_KEY: {"photo_1": 0}})
    b = replace(make(2, np.arange(1.2, 2.0, 0.01), image="photo_2"), extra={EDGE_PX_KEY: {"photo_2": None}})
    assert merge_pair(a, b, tolerance=TOL).extra[EDGE_PX_KEY] == {"photo_1": 0, "photo_2": None}
    assert EDGE_PX_KEY not in merge_pair(make(1, np.arange(0.0, 1.0, 0.01)), make(2, np.arange(1.2, 2.0, 0.01)),
                                         tolerance=TOL).extra  # traces from before it was recorded


def test_bridge_vertices_keep_no_photo_through_later_merges():
    a = make(1, np.arange(0.0, 1.0, 0.01), image="photo_1")
    b = make(2, np.arange(1.2, 2.0, 0.01), image="photo_2")
    bridged = merge_pair(a, b, tolerance=TOL)
    c = make(3, np.arange(1.5, 2.5, 0.01), image="photo_3")
    again = merge_pair(bridged, c, tolerance=TOL)
    assert again.images == ("photo_1", "photo_2", "photo_3")
    assert (again.image_index == -1).sum() == (bridged.image_index == -1).sum() > 0
