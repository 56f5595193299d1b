import numpy as np
import pytest

from engine import topology as tp
from engine.errors import InputError
from engine.extract import extract_traces
from engine.mesh import Mesh
from engine.raytrace import RayTracer
from engine.synthetic import QUICK, distance_to_true_traces, make_outcrop
from engine.traces import Trace2D, Trace3D
from tests.scenes import facing_camera, grid_wall


def _extract(polylines, cam, tracer):
    traces = extract_traces([Trace2D(i, cam.name, p) for i, p in enumerate(polylines)], {cam.name: cam},
                            tracer).traces
    for i, t in enumerate(traces):
        t.id = i
    return traces


def _wall_uv(cam, *xz, y=0.0):
    return cam.project(np.array([[x, y, z] for x, z in xz]))


@pytest.fixture(scope="module")
def wall_scene():
    """A 10 m × 6 m wall (y = 0) with a hole, one photo, and traces with known codes (MATHS §6)."""
    v, f = grid_wall(step=0.5, hole=(8.5, 9.5, 4.0, 5.0))
    cam = facing_camera()  # sees x ∈ [0.43, 9.57] and the whole height: top and bottom mesh edges in view
    tracer = RayTracer(v, f)
    border = _wall_uv(cam, (8, 1))[0]
    polylines = {
        "A": _wall_uv(cam, (2, 3), (8, 3)),  # B, B; crossed by C
        "T": _wall_uv(cam, (4, 1), (4, 3)),  # B, then T on A's interior
        "C": _wall_uv(cam, (6, 2), (6, 4)),  # B, B; X with A at (6, 0, 3)
        "mesh": _wall_uv(cam, (7, 4.5), (7, 5.995)),  # reaches the top of the mesh: C
        "photo": np.array([border, [cam.width - 1.0, border[1]]]),  # runs out of the photo: C
        "free": _wall_uv(cam, (2, 5), (3, 5.5)),  # B, B
        "hole": _wall_uv(cam, (8, 4.5), (8.49, 4.5)),  # stops at the rim of the hole: C
    }
    traces = _extract(list(polylines.values()), cam, tracer)
    return Mesh(v, f), cam, tracer, traces, list(polylines)


EXPECTED = {"A": ("B", "B"), "T": ("B", "T"), "C": ("B", "B"), "mesh": ("B", "C"), "photo": ("B", "C"),
            "free": ("B", "B"), "hole": ("B", "C")}


def test_hand_made_scene_terminations_crossing_and_counts(wall_scene):
    mesh, cam, tracer, traces, names = wall_scene
    gsd = tp.ground_sampling_distance(traces, {"cam": cam})
    assert gsd == pytest.approx(8.0 / 700, rel=0.05)  # distance / focal length
    codes = tp.classify_terminations(traces, mesh=mesh, gsd=gsd, cameras={"cam": cam}, tracer=tracer)
    assert dict(zip(names, codes)) == EXPECTED
    assert all(t.term_start == "" for t in traces)  # classification does not change the traces
    tolerance = tp.TOLERANCE_SCALE * gsd
    crossings = tp.find_crossings(traces, tolerance)
    assert crossings.traces.tolist() == [[names.index("A"), names.index("C")]]
    np.testing.assert_allclose(crossings.points[0], [6.0, 0.0, 3.0], atol=1e-4)
    counts = tp.node_counts(codes, crossings)
    assert (counts.B, counts.T, counts.X, counts.C) == (10, 1, 1, 3)
    assert (counts.N_I, counts.N_Y, counts.N_X, counts.N_E) == (10, 1, 1, 3)
    assert counts.N_L == (10 + 1) / 2 and counts.N_B == (10 + 3 * 1 + 4 * 1) / 2
    assert counts.C_L == pytest.approx(2 * (1 + 1) / 5.5) and counts.C_B == pytest.approx((3 + 4) / 8.5)
    assert counts.censored_fraction == pytest.approx(3 / 14)
    assert sum(counts.proportions.values()) == pytest.approx(1.0)
    groups = tp.connectivity(traces, tolerance)
    joined = {names.index(n) for n in ("A", "T", "C")}
    assert set(np.flatnonzero(groups.labels == 0)) == joined and groups.n_components == 5
    vertices = np.array([len(t.points) for t in traces])
    assert groups.largest_vertex_fraction == pytest.approx(vertices[list(joined)].sum() / vertices.sum())


def test_analyse_topology_bundles_the_steps(wall_scene):
    mesh, cam, tracer, traces, names = wall_scene
    result = tp.analyse_topology(traces, mesh=mesh, cameras={"cam": cam}, tracer=tracer)
    assert dict(zip(names, result.terminations)) == EXPECTED
    assert result.tolerance == pytest.approx(tp.TOLERANCE_SCALE * tp.ground_sampling_distance(traces, {"cam": cam}))
    assert (result.nodes.N_X, result.connectivity.n_components) == (1, 5)
    with pytest.raises(InputError, match="give the ground sampling distance"):
        tp.analyse_topology(traces, mesh=mesh)


def test_without_cameras_only_the_mesh_boundary_censors(wall_scene):
    mesh, cam, tracer, traces, names = wall_scene
    codes = dict(zip(names, tp.classify_terminations(traces, mesh=mesh, gsd=0.0115)))
    assert codes["photo"] == ("B", "B") and codes["mesh"] == ("B", "C") and codes["hole"] == ("B", "C")


def test_photo_mask_censors_an_end_at_a_masked_region(wall_scene):
    mesh, cam, tracer, traces, names = wall_scene
    end = traces[names.index("free")].uv[-1]
    mask = np.ones((cam.height, cam.width), dtype=bool)
    u, v = np.rint(end).astype(int)
    mask[v - 10:v + 10, u + 2:u + 20] = False  # vegetation just past the end
    codes = tp.classify_terminations(traces, mesh=mesh, gsd=0.0115, cameras={"cam": cam}, tracer=tracer,
                                     masks={"cam": mask})
    assert codes[names.index("free")] == ("B", "C")
    with pytest.raises(InputError, match="mask of photo 'cam' is 10×10"):
        tp.classify_terminations(traces, mesh=mesh, gsd=0.0115, cameras={"cam": cam},
                                 masks={"cam": np.zeros((10, 10), bool)})


def test_end_hidden_behind_a_ledge_is_censored():
    # a near wall (y = -2, x < 5) hides the far wall left of x ≈ 4.667 from a camera at (6, -8, 3)
    v1, f1 = grid_wall(width=5.0, step=0.25, offset=(0.0, -2.0, 0.0))
    v2, f2 = grid_wall(step=0.25)
    v, f = np.vstack([v1, v2]), np.vstack([f1, f2 + len(v1)])
    tracer = RayTracer(v, f)
    cam = facing_camera(centre=(6.0, -8.0, 3.0))
    traces = _extract([_wall_uv(cam, (8, 3), (4.68, 3)),  # stops ~1 px from the occluding edge
                       _wall_uv(cam, (8, 4), (5.5, 4)),  # stops in the open
                       _wall_uv(cam, (4.8, 1), (3, 1), y=-2.0)], cam, tracer)  # on the near wall
    codes = tp.classify_terminations(traces, mesh=Mesh(v, f), gsd=8.0 / 700, cameras={"cam": cam}, tracer=tracer)
    assert codes == [("B", "C"), ("B", "B"), ("B", "B")]


def test_tolerance_rules_on_plain_polylines():
    d = 0.1  # δ
    lines = [np.array([[0.0, 0.0], [10.0, 0.0]]),  # L
             np.array([[5.0, 0.5 * d], [5.0, 5.0]]),  # abuts L within δ: T
             np.array([[7.0, 2 * d], [7.0, 5.0]]),  # 2δ from L: B
             np.array([[10.0 + 0.5 * d, 0.0], [12.0, 3.0]]),  # at L's end node: not T, but touching
             np.array([[2.0, -3.0], [2.0, 3.0]]),  # crosses L: X
             np.array([[8.5, -3.0], [8.5, 0.5 * d]])]  # overshoots L by δ/2: T, not X
    abut = tp.abutting_ends(lines, d)
    assert abut[:, 0].tolist() == [-1, 0, -1, -1, -1, -1] and abut[:, 1].tolist() == [-1, -1, -1, -1, -1, 0]
    crossings = tp.find_crossings(lines, d)
    assert crossings.traces.tolist() == [[0, 4]]
    np.testing.assert_allclose(crossings.points, [[2.0, 0.0]], atol=1e-12)
    groups = tp.connectivity(lines, d)
    assert (groups.labels == groups.labels[0]).tolist() == [True, True, False, True, True, True]


def test_shallow_crossing_of_dense_3d_traces_is_one_node():
    s = np.linspace(-1, 1, 2001)[:, None]  # 1 mm vertex spacing, crossing at 3°
    a = s * np.array([1.0, 0.0, 0.0])
    angle = np.radians(3)
    b = s * np.array([np.cos(angle), np.sin(angle), 0.0]) + np.array([0.0, 0.0, 0.002])
    crossings = tp.find_crossings([a, b], 0.005)
    assert len(crossings) == 1
    np.testing.assert_allclose(crossings.points[0], [0.0, 0.0, 0.001], atol=2e-3)


def test_manual_edit_survives_and_extraction_cut_is_kept(wall_scene):
    mesh, cam, tracer, traces, names = wall_scene
    traces = [Trace3D(t.id, t.points, t.uv, t.face, t.image_index, t.images) for t in traces]
    free = traces[names.index("free")]
    tp.set_termination(free, "end", "T")
    traces[names.index("A")].term_start = "C"  # as extraction marks a cut end
    kw = dict(mesh=mesh, gsd=0.0115, cameras={"cam": cam}, tracer=tracer)
    codes = tp.classify_terminations(traces, **kw)
    assert codes[names.index("free")] == ("B", "T") and codes[names.index("A")] == ("C", "B")
    tp.apply_terminations(traces, codes)
    assert (free.term_start, free.term_end) == ("B", "T") and free.extra[tp.SOURCE_KEY]["end"] == "manual"
    assert tp.classify_terminations(traces, **kw) == codes  # stable: kept codes keep their source
    tp.set_termination(free, "end", "")  # clearing hands the end back to the rules
    assert tp.classify_terminations(traces, **kw)[names.index("free")] == ("B", "B")
    tp.set_termination(traces[0], "end", "C")
    tp.apply_terminations(traces, [("B", "B")] * len(traces))  # an automatic code may later be recomputed
    assert traces[0].extra[tp.SOURCE_KEY]["end"] == "auto"
    assert tp.classify_terminations(traces, **kw)[0] == ("B", "B")
    with pytest.raises(InputError, match="X is a crossing"):
        tp.set_termination(free, "start", "X")
    with pytest.raises(InputError, match="end 'middle' must be 'start' or 'end'"):
        tp.set_termination(free, "middle", "B")


def test_component_labels_written_to_traces(wall_scene):
    *_, traces, names = wall_scene
    traces = [Trace3D(t.id, t.points, t.uv, t.face, t.image_index, t.images) for t in traces]
    groups = tp.connectivity(traces, 0.03)
    tp.apply_components(traces, groups)
    assert [t.component for t in traces] == groups.labels.tolist()


def test_bad_input_is_refused_with_a_clear_message(wall_scene):
    mesh, *_ = wall_scene
    one = Trace3D(4, np.zeros((1, 3)), np.zeros((1, 2)), [0], [0], ("cam",))
    with pytest.raises(InputError, match="trace 4 has 1 vertex; a trace needs at least 2"):
        tp.classify_terminations([one], mesh=mesh, gsd=0.01)
    flat = Trace3D(5, np.ones((3, 3)), np.zeros((3, 2)), [0] * 3, [0] * 3, ("cam",))
    with pytest.raises(InputError, match="trace 5 has zero length"):
        tp.find_crossings([flat], 0.01)
    with pytest.raises(InputError, match="gsd must be a positive number"):
        tp.classify_terminations([], mesh=mesh, gsd=0.0)
    with pytest.raises(InputError, match=r"trace 0 \(end\) has no termination code"):
        tp.node_counts([("B", "")], 0)
    with pytest.raises(InputError, match="3 coordinates per vertex"):
        tp.connectivity([np.zeros((2, 2)) + [[0, 0], [1, 0]], np.array([[0.0, 0, 0], [1, 1, 1]])], 0.1)


def test_empty_network():
    counts = tp.node_counts([], tp.find_crossings([], 0.1))
    assert counts.N_L == 0 and counts.C_L == 0.0 and np.isnan(counts.censored_fraction)
    assert tp.connectivity([], 0.1).n_components == 0


# -- the synthetic outcrop: every end is B (fracture tip) or C (mesh border, photo border, occlusion) -----

@pytest.fixture(scope="module", params=["planar", "undulating"])
def outcrop_terminations(request):
    """Each photo's true visible traces extracted onto the mesh and classified, with the truth per end.

    Photos are classified one at a time: without merging (engine.merge) the same fracture seen in two
    photos would be two overlapping traces. 1280×960 photos: δ = 2.5 GSD ≈ 3 cm. Planar fractures on the
    exact mesh, and undulating ones on the mesh with 2 mm of noise that a user is given (issue 4's setting).
    """
    undulating = request.param == "undulating"
    outcrop = make_outcrop(0, **{**QUICK, "image_size": (1280, 960)}, fracture_model=request.param,
                           mesh_noise=0.002 if undulating else 0.0)
    cameras, mesh = outcrop.local_cameras(), outcrop.noisy_mesh if undulating else outcrop.mesh
    tracer = RayTracer(mesh.vertices, mesh.faces)
    edges = mesh.vertices[mesh.boundary_edges]
    true_ends = {}
    for t in outcrop.traces3d:
        if not t.closed:
            for k in (0, 1):
                true_ends.setdefault(t.fracture_id, []).append((t.points[(0, -1)[k]] - outcrop.origin, t.ends[k]))
    rows = []
    for name, visible in outcrop.traces2d.items():
        traces = extract_traces([Trace2D(t.id, name, t.polyline) for t in visible], cameras, tracer).traces
        for i, t in enumerate(traces):
            t.id = i
        gsd = tp.ground_sampling_distance(traces, cameras)
        tolerance = tp.TOLERANCE_SCALE * gsd
        codes = tp.classify_terminations(traces, mesh=mesh, gsd=gsd, cameras=cameras, tracer=tracer)
        runs = [(t.fracture_id, t.points - outcrop.origin) for t in visible]
        for t, pair in zip(traces, codes):
            if np.linalg.norm(t.points[0] - t.points[-1]) <= tolerance:
                continue  # a whole closed loop: it has no end nodes
            for k in (0, 1):
                point = t.points[(0, -1)[k]]
                _, fracture = distance_to_true_traces(point[None], outcrop, local=True)
                truth = _true_end(point, true_ends.get(int(fracture[0]), []), tolerance)
                at_tolerance = _at_tolerance(truth, point, t.uv[(0, -1)[k]], cameras[name], int(fracture[0]),
                                             runs, edges, tolerance)
                rows.append((truth, at_tolerance, pair[k]))
    return rows


def _true_end(point, ends, tolerance):
    """The code of the nearest true end within δ; an end elsewhere was cut by the photo border or occlusion."""
    if not ends:
        return "C"
    distance = [np.linalg.norm(q - point) for q, _ in ends]
    return ends[int(np.argmin(distance))][1] if min(distance) <= tolerance else "C"


def _at_tolerance(truth, point, uv, camera, fracture, runs, edges, tolerance):
    """The truth as the rules read it at tolerance δ on exact geometry: a fracture tip within δ of the mesh
    border or within 3 px of the photo border is censored; within δ of another fracture's visible trace
    (away from its ends) it abuts it. Brute-force distances, independent of engine.topology."""
    if truth != "B":
        return truth
    clearance = min(uv[0] + 0.5, uv[1] + 0.5, camera.width - 0.5 - uv[0], camera.height - 0.5 - uv[1])
    if _distance(point, edges[:, 0], edges[:, 1]) <= tolerance or clearance <= tp.BORDER_PX:
        return "C"
    for other, run in runs:
        if other != fracture and _distance(point, run[:-1], run[1:]) <= tolerance \
                and np.linalg.norm(run[[0, -1]] - point, axis=1).min() > tolerance:
            return "T"
    return "B"


def _distance(p, a, b):
    d = b - a
    s = np.clip(np.einsum("ij,ij->i", p - a, d) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-300), 0, 1)
    return np.linalg.norm(a + s[:, None] * d - p, axis=1).min()


def test_synthetic_outcrop_terminations_agree_with_the_truth(outcrop_terminations):
    rows = outcrop_terminations
    raw = np.mean([truth == got for truth, _, got in rows])
    at_tolerance = np.mean([truth == got for _, truth, got in rows])
    print(f"\n{len(rows)} end nodes: {raw:.2%} agree with TrueTrace.ends, {at_tolerance:.2%} with the truth at δ")
    assert len(rows) > 300
    # the fractures are independent discs, so true ends are B or C; the misses are tips that happen to lie
    # within δ of another trace (T at that tolerance) or at an occluding edge
    assert raw >= 0.95
    assert at_tolerance >= 0.97
    assert {got for *_, got in rows} <= {"B", "T", "C"}
