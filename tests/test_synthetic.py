"""The synthetic outcrop is the oracle of every other test, so its own truth is checked against geometry."""

import csv
import json

import cv2
import numpy as np
import pytest
from scipy.stats import mannwhitneyu

from engine.cameras import Camera
from engine.errors import InputError
from engine.mesh import read_mesh
from engine.orientation import dip_dipdir_to_normal, normal_to_dip_dipdir
from engine.raytrace import RayTracer
from engine.synthetic import (DEFAULT_SETS, QUICK, distance_to_true_traces, make_outcrop, sample_fractures,
                              write_outcrop)

OFFSET = (500000.0, 4200000.0, 100.0)
DISTORTION = (-0.08, 0.03, 2e-4, -1e-4)


@pytest.fixture(scope="module")
def planar():
    return make_outcrop(1, **QUICK)


@pytest.fixture(scope="module")
def undulating():
    """Everything that can go wrong at once: UTM offset, lens distortion, undulating fractures, alt look."""
    return make_outcrop(2, **QUICK, fracture_model="undulating", world_offset=OFFSET, distortion=DISTORTION,
                        style="alt")


@pytest.fixture(params=["planar", "undulating"])
def outcrop(request):
    return request.getfixturevalue(request.param)


def _arclength(p, polyline):
    """Arc-length positions of points p (N, 3) that lie on polyline (M, 3)."""
    a, b = polyline[:-1], polyline[1:]
    length = np.linalg.norm(b - a, axis=1)
    s = np.clip(np.einsum("nkj,kj->nk", p[:, None] - a, b - a) / np.maximum(length**2, 1e-300), 0, 1)
    k = np.linalg.norm(p[:, None] - (a + s[..., None] * (b - a)), axis=2).argmin(axis=1)
    return np.r_[0, np.cumsum(length)][k] + s[np.arange(len(p)), k] * length[k]


def _barycentric(p, tri):
    """Barycentric coordinates (N, 3) of points p (N, 3) in triangles tri (N, 3, 3), by least squares."""
    e = np.stack([tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]], axis=2)
    gram = np.einsum("nij,nik->njk", e, e)
    b = np.linalg.solve(gram, np.einsum("nij,ni->nj", e, p - tri[:, 0])[..., None])[..., 0]
    return np.column_stack([1 - b.sum(axis=1), b])


# --- orientation helpers -----------------------------------------------------------------------------------

def test_dip_dipdir_normal_round_trip():
    np.testing.assert_allclose(dip_dipdir_to_normal(0, 123), [0, 0, 1], atol=1e-15)
    np.testing.assert_allclose(dip_dipdir_to_normal(90, 90), [1, 0, 0], atol=1e-15)
    np.testing.assert_allclose(dip_dipdir_to_normal(45, 180), [0, -np.sqrt(0.5), np.sqrt(0.5)], atol=1e-15)
    rng = np.random.default_rng(0)
    dip, dipdir = rng.uniform(0, 89.9, 1000), rng.uniform(0, 360, 1000)
    n = dip_dipdir_to_normal(dip, dipdir)
    assert n.shape == (1000, 3)
    for sign in (1, -1):  # poles are axial: a downward normal gives the same plane
        d2, a2 = normal_to_dip_dipdir(sign * 3.0 * n)
        np.testing.assert_allclose(d2, dip, atol=1e-9)
        np.testing.assert_allclose(a2, dipdir, atol=1e-9)
    assert float(normal_to_dip_dipdir([-1e-17, 1.0, 1.0])[1]) == 0.0  # never 360


# --- determinism and independence of the parts ------------------------------------------------------------

def test_same_seed_same_outcrop_and_noise_only_changes_the_noisy_mesh():
    small = dict(mesh_spacing=0.2, n_cameras=2, image_size=(160, 120), trace_width=0.08)
    a, b = make_outcrop(7, **small), make_outcrop(7, **small)
    c = make_outcrop(7, **small, mesh_noise=0.01)
    d = make_outcrop(8, **small)
    for other in (b, c):
        np.testing.assert_array_equal(a.mesh.vertices, other.mesh.vertices)
        assert len(a.traces3d) == len(other.traces3d) > 0
        for s, t in zip(a.traces3d, other.traces3d):
            np.testing.assert_array_equal(s.points, t.points)
        for name in a.images:
            np.testing.assert_array_equal(a.images[name], other.images[name])
            np.testing.assert_array_equal(a.cameras[name].t, other.cameras[name].t)
    np.testing.assert_array_equal(a.noisy_mesh.vertices, b.noisy_mesh.vertices)
    noise = c.noisy_mesh.vertices - c.mesh.vertices
    assert abs(noise.std() / 0.01 - 1) < 0.05 and abs(noise.mean()) < 1e-3
    assert not np.array_equal(a.mesh.vertices, d.mesh.vertices)


# --- fracture sampling ------------------------------------------------------------------------------------

def test_sampled_sets_match_the_generating_fisher_distributions():
    rng = np.random.default_rng(11)
    box = (np.zeros(3), np.array([10.0, 10.0, 6.0]))  # 600 m³ × density 1 → ~600 fractures, ~300 per set
    fractures, sets = sample_fractures(rng, box, density=1.0)
    assert 500 < len(fractures) < 700
    for k, (dip, dipdir, kappa, weight) in enumerate(DEFAULT_SETS):
        poles = np.array([f.normal for f in fractures if f.set_id == k])
        assert abs(len(poles) / len(fractures) - weight) < 0.08
        mu = dip_dipdir_to_normal(dip, dipdir)
        poles *= np.sign(poles @ mu)[:, None]  # axial data: flip toward the set
        resultant = poles.sum(axis=0)
        mean = resultant / np.linalg.norm(resultant)
        assert np.degrees(np.arccos(min(1.0, mean @ mu))) < 3.0
        n, r = len(poles), np.linalg.norm(resultant)
        assert abs((n - 1) / (n - r) / kappa - 1) < 0.25  # Fisher (1953) estimate
        np.testing.assert_allclose(sets[k].normal, mu)
    normals = np.array([f.normal for f in fractures])
    assert np.all(normals[:, 2] >= 0) and np.allclose(np.linalg.norm(normals, axis=1), 1)
    radii = np.array([f.radius for f in fractures])
    assert radii.min() >= 0.25 and radii.max() <= 6.0
    assert abs(np.median(radii) / 1.0 - 1) < 0.12  # lognormal median 1 m, hardly truncated
    np.testing.assert_allclose(sum(s.p32 for s in sets), np.pi * np.sum(radii**2) / 600.0)


def test_power_law_radii_follow_the_exponent():
    rng = np.random.default_rng(3)
    fractures, _ = sample_fractures(rng, (np.zeros(3), np.full(3, 10.0)), density=2.0,
                                    size_distribution="powerlaw", radius_min=0.5, radius_max=1e6,
                                    radius_exponent=2.5)
    r = np.array([f.radius for f in fractures])
    alpha = 1 + len(r) / np.sum(np.log(r / 0.5))  # MLE of a Pareto exponent
    assert r.min() >= 0.5 and abs(alpha - 2.5) < 0.1


# --- exact 3D traces ---------------------------------------------------------------------------------------

def test_true_trace_vertices_lie_on_the_fracture_and_on_the_mesh(outcrop):
    origin = outcrop.origin
    fractures = {f.id: f.shifted(origin) for f in outcrop.fractures}  # compare in the local frame
    v, faces = outcrop.mesh.vertices, outcrop.mesh.faces
    assert len(outcrop.traces3d) > 30
    for t in outcrop.traces3d:
        p = t.points - origin
        f = fractures[t.fracture_id]
        # planar: exact; undulating at a UTM offset: limited by one ulp of 4.2e6 m ≈ 1e-9 m
        assert np.abs(f.offset(p)).max() <= 1e-9 * f.radius + (1e-8 if np.any(origin) else 0)
        assert np.all(np.linalg.norm(f.plane_coords(p), axis=1) <= f.radius * (1 + 1e-9))
        tri = v[faces[t.face]]
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        assert np.abs(np.einsum("ij,ij->i", p - tri[:, 0], normal)).max() < 1e-8
        assert _barycentric(p, tri).min() > -1e-7
        assert t.closed == np.array_equal(t.points[0], t.points[-1])


def test_trace_ends_are_tips_or_the_mesh_border(outcrop):
    origin = outcrop.origin
    lo, hi = outcrop.mesh.vertices.min(axis=0), outcrop.mesh.vertices.max(axis=0)
    fractures = {f.id: f.shifted(origin) for f in outcrop.fractures}
    kinds = set()
    for t in outcrop.traces3d:
        for point, kind in zip(t.points[[0, -1]] - origin, t.ends):
            kinds.add(kind)
            f = fractures[t.fracture_id]
            if kind == "B":
                assert abs(np.linalg.norm(f.plane_coords(point)) / f.radius - 1) < 1e-9
            elif kind == "C":  # the wall is a grid over x and z: its border is x = ±width/2, z = 0 or height
                assert min(abs(point[0] - lo[0]), abs(point[0] - hi[0]), abs(point[2] - lo[2]),
                           abs(point[2] - hi[2])) < 1e-9
    assert {"B", "C"} <= kinds


def test_planar_and_undulating_models_differ_as_designed(planar, undulating):
    def spread(o):
        worst = 0.0
        for t in o.traces3d:
            f = o.fractures[t.fracture_id].shifted(o.origin)
            worst = max(worst, np.abs((t.points - o.origin - f.centre) @ f.normal).max() / f.radius)
        return worst

    assert spread(planar) < 1e-12
    assert 0.005 < spread(undulating) < 0.2  # RMS 0.02 × radius


def test_distance_to_true_traces_is_exact(undulating):
    o = undulating
    t = max(o.traces3d, key=lambda t: t.length)
    on = 0.5 * (t.points[:-1] + t.points[1:])
    d, fid = distance_to_true_traces(on, o)
    assert d.max() < 1e-6 and np.all(fid == t.fracture_id)
    rng = np.random.default_rng(0)
    lo, hi = o.mesh.world_vertices.min(axis=0), o.mesh.world_vertices.max(axis=0)
    queries = rng.uniform(lo, hi, (200, 3))
    d, fid = distance_to_true_traces(queries, o)
    a = np.concatenate([s.points[:-1] for s in o.traces3d]) - o.origin
    b = np.concatenate([s.points[1:] for s in o.traces3d]) - o.origin
    owner = np.concatenate([np.full(len(s.points) - 1, s.fracture_id) for s in o.traces3d])
    q = queries - o.origin
    s = np.clip(np.einsum("nkj,kj->nk", q[:, None] - a, b - a) / np.einsum("kj,kj->k", b - a, b - a), 0, 1)
    brute = np.linalg.norm(q[:, None] - (a + s[..., None] * (b - a)), axis=2)  # every segment
    np.testing.assert_allclose(d, brute.min(axis=1), atol=1e-9)
    np.testing.assert_array_equal(fid, owner[brute.argmin(axis=1)])
    d_local, _ = distance_to_true_traces(q, o, local=True)
    np.testing.assert_allclose(d_local, d, atol=1e-9)


# --- photos and 2D truth -----------------------------------------------------------------------------------

def test_2d_truth_reprojects_the_3d_traces(outcrop):
    checked = 0
    for name, traces in outcrop.traces2d.items():
        camera = outcrop.cameras[name]
        assert len(traces) > 10
        for t in traces:
            assert t.image == name and outcrop.traces3d[t.trace_id].fracture_id == t.fracture_id
            # the polyline is the projection of its 3D points ...
            np.testing.assert_allclose(camera.project(t.points), t.polyline, atol=1e-6)
            assert np.all(t.polyline >= -0.5) and np.all(t.polyline <= [camera.width - 0.5, camera.height - 0.5])
            # ... and every vertex of the true 3D trace inside the run projects onto the polyline
            trace = outcrop.traces3d[t.trace_id]
            if trace.closed:  # runs of loops may start anywhere on them
                continue
            arc = np.r_[0, np.cumsum(np.linalg.norm(np.diff(trace.points, axis=0), axis=1))]
            first, last = _arclength(t.points[[0, -1]], trace.points)
            inside = (arc >= first) & (arc <= last)
            if not inside.any():
                continue
            uv = camera.project(trace.points[inside])
            a, b = t.polyline[:-1], t.polyline[1:]
            s = np.clip(np.einsum("nkj,kj->nk", uv[:, None] - a, b - a)
                        / np.maximum(np.einsum("kj,kj->k", b - a, b - a), 1e-300), 0, 1)
            gap = np.linalg.norm(uv[:, None] - (a + s[..., None] * (b - a)), axis=2).min(axis=1)
            assert gap.max() < 0.5
            checked += inside.sum()
    assert checked > 1000


def test_2d_truth_is_what_the_pixel_rays_see(outcrop):
    """A ray through a truth vertex (pixel convention of Camera) first meets the mesh at its 3D point."""
    tracer = RayTracer(outcrop.mesh.vertices, outcrop.mesh.faces)
    cameras = outcrop.local_cameras()
    lo, hi = outcrop.mesh.vertices.min(axis=0), outcrop.mesh.vertices.max(axis=0)
    for name, traces in outcrop.traces2d.items():
        camera = cameras[name]
        uv = np.concatenate([t.polyline for t in traces])
        points = np.concatenate([t.points for t in traces]) - outcrop.origin
        hits = tracer.intersect(camera.centre, camera.pixel_rays(uv))
        # rays through points exactly on the mesh border may slip past it (float32 Embree); nothing else may
        border = np.minimum(np.abs(points - lo), np.abs(points - hi))[:, [0, 2]].min(axis=1) < 1e-9
        assert np.all(hits.hit | border) and hits.hit.mean() > 0.99
        miss = np.linalg.norm(hits.points[hits.hit] - points[hits.hit], axis=1)
        assert np.median(miss) < 1e-6 and np.quantile(miss, 0.99) < 0.01


def test_rendered_photos_are_darker_along_true_traces(outcrop):
    for name, image in outcrop.images.items():
        assert image.dtype == np.uint8 and image.shape == (480, 640, 3)
        grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY).astype(float)
        uv = np.concatenate([t.polyline for t in outcrop.traces2d[name]])
        on = grey[np.rint(uv[:, 1]).astype(int), np.rint(uv[:, 0]).astype(int)]
        # the same places shifted 6 px sideways: rock of the same kind, away from the trace
        shifted = np.rint(uv + [6, 0]).astype(int)
        ok = (shifted[:, 0] < grey.shape[1])
        off = grey[shifted[ok, 1], shifted[ok, 0]]
        assert np.median(on) < 0.9 * np.median(off)
        assert mannwhitneyu(on, off, alternative="less").pvalue < 1e-10


def test_styles_look_different(planar, undulating):
    warm = planar.mesh.vertex_colors.mean(axis=0)
    grey = undulating.mesh.vertex_colors.mean(axis=0)
    assert warm[0] - warm[2] > 40 > 20 > abs(grey[0] - grey[2])  # sandstone versus grey rock
    assert np.array_equal(planar.mesh.vertex_colors, planar.noisy_mesh.vertex_colors)


# --- frames and files --------------------------------------------------------------------------------------

def test_world_offset_round_trips_through_the_files(undulating, tmp_path):
    o = undulating
    np.testing.assert_array_equal(o.origin, OFFSET)
    np.testing.assert_allclose(o.mesh.world_vertices - np.asarray(OFFSET), o.mesh.vertices, atol=1e-3)
    paths = write_outcrop(o, tmp_path)
    mesh = read_mesh(paths["mesh"], origin=o.origin)
    np.testing.assert_allclose(mesh.vertices, o.noisy_mesh.vertices, atol=1e-3)
    np.testing.assert_array_equal(mesh.faces, o.noisy_mesh.faces)
    assert mesh.vertex_colors is not None and mesh.vertex_colors.shape == (len(mesh.vertices), 3)

    doc = json.loads(paths["cameras"].read_text())
    assert doc["format"] == "tracemap-cameras" and doc["version"] == 1
    for entry in doc["cameras"]:
        camera = Camera.from_dict(entry)
        local = o.local_cameras()[camera.name]
        np.testing.assert_allclose(camera.centre - o.origin, local.centre, atol=1e-3)
        photo = cv2.imread(str(paths["images"] / entry["image_path"]))
        np.testing.assert_array_equal(cv2.cvtColor(photo, cv2.COLOR_BGR2RGB), o.images[camera.name])

    with open(paths["traces2d"], newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == ["image", "trace", "u", "v"]
    assert len(rows) == sum(len(t.polyline) for ts in o.traces2d.values() for t in ts)
    assert len({r["trace"] for r in rows}) == sum(len(ts) for ts in o.traces2d.values())
    assert {r["image"] for r in rows} == set(o.cameras)

    truth = json.loads(paths["truth"].read_text())
    assert truth["frame"] == "world" and len(truth["fractures"]) == len(o.fractures)
    np.testing.assert_array_equal(np.array(truth["traces3d"][0]["points"]), o.traces3d[0].points)
    np.testing.assert_allclose(truth["fractures"][0]["centre"], o.fractures[0].centre)


def test_bad_parameters_name_the_parameter():
    with pytest.raises(InputError, match="style"):
        make_outcrop(style="watercolour")
    with pytest.raises(InputError, match="sets"):
        make_outcrop(sets=[(95.0, 10.0, 5.0, 1.0)])
