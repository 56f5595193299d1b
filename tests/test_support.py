"""Support from other photos (engine.delineate.support): a chain one photo turned down is kept where the
other photos that see it show a trace along it, and a trace of one photo is carried into another that sees
it where that photo's skeleton lies along it."""

import numpy as np
import pytest

from engine.delineate import carried_traces, supported_traces
from engine.delineate.support import TracedPhoto, supported_chains
from engine.errors import InputError
from engine.raytrace import RayTracer
from tests.scenes import facing_camera, grid_wall

CAMERAS = {"a": facing_camera("a", centre=(4.0, -8.0, 3.0)), "b": facing_camera("b", centre=(6.0, -8.0, 3.0)),
           "c": facing_camera("c", centre=(5.0, -9.0, 2.5)),
           "away": facing_camera("away", centre=(60.0, -8.0, 3.0))}  # sees no part of the wall near the lines
ON_WALL = np.linspace([3.0, 0.0, 2.0], [5.0, 0.0, 4.0], 300)  # a line on the wall y = 0
ELSEWHERE = np.linspace([7.0, 0.0, 1.0], [9.0, 0.0, 1.5], 300)


@pytest.fixture(scope="module")
def tracer():
    return RayTracer(*grid_wall(step=0.25))


def seen(name, points):
    return CAMERAS[name].project(points)


def photos(traced: dict[str, list[np.ndarray]]) -> dict[str, TracedPhoto]:
    return {n: TracedPhoto.of(CAMERAS[n], traced.get(n, [])) for n in ("a", *traced)}


def test_a_chain_other_photos_trace_is_kept_on_a_majority_of_their_votes(tracer):
    chain = seen("a", ON_WALL)
    assert len(supported_chains([chain], "a", photos({"b": [seen("b", ON_WALL)]}), tracer)) == 1
    # c sees the chain whole and has traces, none along it: one vote for, one against is no majority
    against = photos({"b": [seen("b", ON_WALL)], "c": [seen("c", ELSEWHERE)]})
    assert supported_chains([chain], "a", against, tracer) == []
    both = photos({"b": [seen("b", ON_WALL)], "c": [seen("c", ELSEWHERE), seen("c", ON_WALL)]})
    assert len(supported_chains([chain], "a", both, tracer)) == 1
    # a photo that does not see the chain does not vote
    assert len(supported_chains([chain], "a", photos({"b": [seen("b", ON_WALL)], "away": [seen("away", ELSEWHERE)]}),
                                tracer)) == 1


def test_no_support_for_chains_elsewhere_short_traced_already_or_off_the_mesh(tracer):
    others = photos({"b": [seen("b", ON_WALL)], "c": [seen("c", ON_WALL)]})
    assert supported_chains([seen("a", ELSEWHERE)], "a", others, tracer) == []
    assert supported_chains([seen("a", ON_WALL[:3])], "a", others, tracer) == []  # under 5 px
    own = {**others, "a": TracedPhoto.of(CAMERAS["a"], [seen("a", ON_WALL)])}
    assert supported_chains([seen("a", ON_WALL)], "a", own, tracer) == []  # a trace of its own photo already
    sky = np.linspace([100.0, 20.0], [400.0, 30.0], 50)  # above the 6 m wall in photo a: misses the mesh
    assert CAMERAS["a"].pixel_rays(sky)[:, 2].max() > 0
    assert supported_chains([sky], "a", others, tracer) == []


def test_supported_traces_of_several_photos_simplified_and_only_traced_photos_vote(tracer):
    rejected = {"a": [seen("a", ON_WALL), seen("a", ELSEWHERE)], "b": [seen("b", ELSEWHERE)]}
    traces = {"a": [], "b": [seen("b", ON_WALL)], "c": [], "away": [seen("away", ELSEWHERE)]}
    out = supported_traces(rejected, traces, CAMERAS, tracer, simplify=1.0)
    assert [len(out["a"]), len(out["b"])] == [1, 0]
    (line,) = out["a"]
    assert len(line) == 2  # a straight chain simplified to its ends
    np.testing.assert_allclose(line, seen("a", ON_WALL)[[0, -1]], atol=1e-9)


def test_support_parameters_are_checked(tracer):
    with pytest.raises(InputError, match=r"support_share=0 is out of range: expected a number in \(0, 1\]"):
        supported_chains([], "a", photos({}), tracer, share=0)


def test_a_photo_whose_view_is_blocked_does_not_vote(tracer):
    """A plate 1 m in front of photo b hides the line from it (not from a): b's trace there is of something
    else, and b does not vote; at a twentieth of the scale (the plate 5 cm off) alike."""
    for scale in (1.0, 0.05):
        v, f = grid_wall(step=0.25)
        plate = np.array([[5.3, -7.0, 2.5], [6.7, -7.0, 2.5], [6.7, -7.0, 3.5], [5.3, -7.0, 3.5]])
        blocked = RayTracer(np.vstack([v, plate]) * scale, np.vstack([f, len(v) + np.array([[0, 1, 2], [0, 2, 3]])]))
        cameras = {n: facing_camera(n, centre=np.array(c) * scale, f=700.0)
                   for n, c in (("a", (4.0, -8.0, 3.0)), ("b", (6.0, -8.0, 3.0)))}
        line = ON_WALL * scale
        chain = cameras["a"].project(line)
        voters = {n: TracedPhoto.of(cameras[n], [cameras[n].project(line)] if n == "b" else []) for n in cameras}
        assert supported_chains([chain], "a", voters, blocked) == [], scale
        open_view = RayTracer(v * scale, f)
        assert len(supported_chains([chain], "a", voters, open_view)) == 1, scale


def skeleton(name, *lines, shape=(600, 800)):
    """Photo `name`'s skeleton: the pixels of `lines` (3D points) as it sees them."""
    mask = np.zeros(shape, bool)
    for line in lines:
        uv = np.rint(seen(name, line)).astype(int)
        ok = (uv[:, 0] >= 0) & (uv[:, 0] < shape[1]) & (uv[:, 1] >= 0) & (uv[:, 1] < shape[0])
        mask[uv[ok, 1], uv[ok, 0]] = True
    return mask


def test_a_trace_of_one_photo_is_carried_where_the_other_photo_shows_an_edge_along_it(tracer):
    traces = {"b": [seen("b", ON_WALL)]}
    (line,) = carried_traces(traces, CAMERAS, tracer, {"a": skeleton("a", ON_WALL)}, simplify=0.0)["a"]
    expected = seen("a", ON_WALL)
    assert abs(line[0] - expected[0]).max() < 1.0 and abs(line[-1] - expected[-1]).max() < 1.0
    assert np.abs(line - expected[np.abs(expected[:, None] - line[None]).sum(-1).argmin(0)]).max() < 1.0
    # a's skeleton elsewhere: no edge along the trace, nothing carried
    assert carried_traces(traces, CAMERAS, tracer, {"a": skeleton("a", ELSEWHERE)})["a"] == []
    # an edge along a third of it is enough (carry_evidence 0.3), along a fifth not
    third, fifth = ON_WALL[:100], ON_WALL[:60]
    assert len(carried_traces(traces, CAMERAS, tracer, {"a": skeleton("a", third)})["a"]) == 1
    assert carried_traces(traces, CAMERAS, tracer, {"a": skeleton("a", fifth)})["a"] == []


def test_only_what_the_photo_has_not_traced_is_carried_and_a_third_photo_can_veto(tracer):
    mask = {"a": skeleton("a", ON_WALL)}
    (line,) = carried_traces({"b": [seen("b", ON_WALL)], "a": [seen("a", ON_WALL[200:])]}, CAMERAS, tracer, mask,
                             simplify=0.0)["a"]
    assert np.linalg.norm(line[-1] - seen("a", ON_WALL[199])) < 3.0  # up to where a's own trace begins
    assert carried_traces({"b": [seen("b", ON_WALL)], "a": [seen("a", ON_WALL)]}, CAMERAS, tracer, mask)["a"] == []
    # c sees the line and traced something else: b's trace is not carried; c untraced says nothing
    assert carried_traces({"b": [seen("b", ON_WALL)], "c": [seen("c", ELSEWHERE)]}, CAMERAS, tracer, mask)["a"] == []
    assert len(carried_traces({"b": [seen("b", ON_WALL)], "c": []}, CAMERAS, tracer, mask)["a"]) == 1
    # short pieces (under carry_min_length px in a) are not carried
    assert carried_traces({"b": [seen("b", ON_WALL)]}, CAMERAS, tracer, mask, min_length=1e4)["a"] == []


def test_carry_parameters_are_checked(tracer):
    with pytest.raises(InputError, match=r"carry_evidence=2 is out of range"):
        carried_traces({}, CAMERAS, tracer, {}, evidence=2)
