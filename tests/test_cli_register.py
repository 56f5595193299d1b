"""`tracemap register`: GCPs picked in the quick demo's photos, a known similarity to recover, residuals,
refusals naming the CSV row, and exports in the registered frame."""

import csv
import json
import re
import shutil

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from engine.cli import main
from engine.orientation import normal_to_dip_dipdir, upward
from engine.plots import plot_data
from engine.project import Project
from engine.raytrace import RayTracer
from engine.register import Similarity, apply_similarity, gcp_from_pixels, horn_similarity

SCALE = 1.37
ROTATION = Rotation.from_euler("zyx", [33.0, 4.0, -7.0], degrees=True).as_matrix()
SHIFT = np.array([431_000.0, 6_512_000.0, 240.0])  # UTM-sized: millimetres must survive
KNOWN = Similarity(SCALE, ROTATION, SHIFT, np.zeros((0, 3)), np.zeros(0), 0.0)
HEADER = ("name", "x", "y", "z", "image", "u", "v")


@pytest.fixture
def demo(quick_demo, tmp_path):
    shutil.copytree(quick_demo, tmp_path / "demo")
    return tmp_path / "demo" / "demo.tracemap"


@pytest.fixture
def picks(demo):
    """Five GCPs spread over the wall: name → (observations {photo: (u, v)}, model point (local + origin)).
    Each is a mesh vertex projected into the photos that see it; the model point is the engine's ray hit."""
    with Project.open(demo) as p:
        mesh, cameras, origin = p.load_mesh(), p.cameras(), p.origin
    tracer = RayTracer(mesh.vertices, mesh.faces)
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    found = {}
    for k, (fx, fz) in enumerate([(0.3, 0.3), (0.7, 0.3), (0.5, 0.6), (0.35, 0.75), (0.65, 0.7)]):
        aim = np.array([lo[0] + fx * (hi[0] - lo[0]), 0.0, lo[2] + fz * (hi[2] - lo[2])])
        vertex = mesh.vertices[np.argmin(np.linalg.norm((mesh.vertices - aim)[:, [0, 2]], axis=1))]
        seen = {}
        for name, cam in cameras.items():
            uv = cam.project(vertex[None])[0]
            inside = np.all(np.isfinite(uv)) and 0 <= uv[0] <= cam.width - 1 and 0 <= uv[1] <= cam.height - 1
            if inside and np.linalg.norm(gcp_from_pixels({name: uv}, cameras, tracer).point - vertex) < 0.01:
                seen[name] = tuple(uv)
        assert seen, f"GCP {k} is seen by no photo"
        found[f"G{k}"] = (seen, gcp_from_pixels(seen, cameras, tracer).point + origin)
    return found


def write_gcps(path, picks, world):
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(HEADER)
        for name, (observations, _) in picks.items():
            for image, (u, v) in observations.items():
                writer.writerow([name, *(f"{x:.6f}" for x in world[name]), image, f"{u:.9f}", f"{v:.9f}"])
    return path


def test_register_recovers_a_known_similarity_and_exports_in_its_frame(demo, picks, tmp_path, capsys):
    world = {n: apply_similarity(m, KNOWN) for n, (_, m) in picks.items()}
    assert sum(len(o) for o, _ in picks.values()) > len(picks)  # some GCPs are picked on two photos
    csv_path = write_gcps(tmp_path / "gcps.csv", picks, world)
    assert main(["register", str(demo), str(csv_path)]) == 0
    out = capsys.readouterr().out
    assert "registered with 5 GCPs: scale 1.370000" in out
    assert "note: the GCPs' frame is not the mesh's (scale 1.3700" in out  # what reports stay in the mesh's
    rows = {line.split()[0]: line.split() for line in out.splitlines()[2:2 + len(picks)]}
    assert set(rows) == set(picks) and all(float(r[-1]) < 1e-4 for r in rows.values())
    with Project.open(demo) as p:
        reg = p.registration()
        assert set(p.gcps()) == set(picks)
        traces = p.traces3d()
        origin = p.origin
    sim = reg.similarity
    assert sim.scale == pytest.approx(SCALE, abs=1e-6)
    np.testing.assert_allclose(sim.R, ROTATION, atol=1e-6)
    np.testing.assert_allclose(sim.t, SHIFT, atol=1e-6 * np.linalg.norm(SHIFT))
    np.testing.assert_allclose(apply_similarity(reg.model, sim), reg.world, atol=1e-5)  # world in µm (CSV)
    assert sim.rmse < 1e-5 and reg.names == tuple(picks)

    assert main(["export", str(demo), str(tmp_path / "out"), "--format", "csv"]) == 0
    with open(tmp_path / "out" / "trace_vertices.csv", newline="") as f:
        first = next(r for r in csv.DictReader(f) if r["trace"] == str(traces[0].id) and r["vertex"] == "0")
    expected = apply_similarity(traces[0].points[0] + origin, KNOWN)
    np.testing.assert_allclose([float(first[c]) for c in "xyz"], expected, atol=1e-3)
    oriented = next(t for t in traces if t.normal is not None)
    with open(tmp_path / "out" / "traces.csv", newline="") as f:
        row = next(r for r in csv.DictReader(f) if r["id"] == str(oriented.id))
    dip, dipdir = normal_to_dip_dipdir(ROTATION @ oriented.normal)
    assert (float(row["dip"]), float(row["dip_direction"])) == pytest.approx((float(dip), float(dipdir)), abs=0.006)
    eigen = normal_to_dip_dipdir(ROTATION @ np.asarray(oriented.extra["eigen_normal"]))  # beside the final one
    assert (float(row["eigen_dip"]), float(row["eigen_dip_direction"])) == pytest.approx(tuple(map(float, eigen)),
                                                                                       abs=0.006)
    # lengths are in the registered frame too, as the coordinates are
    assert float(row["surface_length"]) == pytest.approx(SCALE * oriented.surface_length, rel=1e-5)
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["traces3d"]["total_surface_length_m"] == pytest.approx(
        SCALE * sum(t.surface_length for t in traces), rel=1e-6)  # the scale recovered to 1e-6
    with Project.open(demo) as p:  # the plots report in the registered frame, as the exports
        data, sets, fits = plot_data(p), p.result("sets"), p.result("lengths")["all"]["fits"]
    normals = np.array([t.normal for t in traces if t.normal is not None])
    np.testing.assert_allclose(data.poles, upward(normals @ ROTATION.T), atol=1e-5)
    lengths = {t.id: t.surface_length for t in traces}
    np.testing.assert_allclose(data.lengths.surface, [SCALE * lengths[i] for i in data.lengths.id], rtol=1e-5)
    turned = normal_to_dip_dipdir(upward(ROTATION @ np.asarray(sets[0]["normal"])))
    assert (data.sets[0]["dip"], data.sets[0]["dip_direction"]) == pytest.approx(tuple(map(float, turned)), abs=1e-3)
    for stored, shown in zip(fits, data.fits["all"]):  # the fitted curves follow the lengths
        for name, value in stored["params"].items():
            assert shown["params"][name] == pytest.approx(value * (SCALE if name in ("scale", "x_min") else 1))
    assert any(f["params"] for f in fits)


def test_orient_and_analyse_print_in_the_registered_frame(demo, picks, tmp_path, capsys, monkeypatch):
    world = {n: apply_similarity(m, KNOWN) for n, (_, m) in picks.items()}
    assert main(["register", str(demo), str(write_gcps(tmp_path / "gcps.csv", picks, world))]) == 0
    assert main(["orient", str(demo)]) == 0
    out = capsys.readouterr().out
    with Project.open(demo) as p:
        sets = p.result("sets")
    for s in sets:
        dip, dipdir = normal_to_dip_dipdir(upward(ROTATION @ np.asarray(s["normal"])))
        assert f"set {s['id']}: {s['n']} traces, dip {float(dip):.0f}° / {float(dipdir):03.0f}°" in out
    assert "(GCPs' frame)" in out
    assert main(["analyse", str(demo), "--radius", "0.5", "--bootstrap", "0"]) == 0
    out = capsys.readouterr().out
    with Project.open(demo) as p:
        median = p.result("lengths")["all"]["kaplan_meier"]["median"]
    assert f"Kaplan–Meier median {median * SCALE:.2f} m (GCPs' frame)" in out
    assert "(radius 0.5 m (GCPs' frame))" in out
    with Project.open(demo) as p:  # given in the GCPs' frame: the maps were made 0.5 / 1.37 m wide on the mesh
        assert p.vertex_map("p21")[1]["radius"] == pytest.approx(0.5 / SCALE, rel=1e-6)
    assert main(["analyse", str(demo), "--radius", "0.05", "--bootstrap", "0"]) == 2
    err = capsys.readouterr().err
    assert "--radius 0.05 m in the GCPs' frame is 0.0365 m on the mesh (scale 1.3700)" in err
    assert "below the mesh spacing" in err
    seen = {}
    monkeypatch.setattr("engine.render.render_to_file", lambda *a, vertex_map=None, **k: seen.update(map=vertex_map))
    assert main(["render", str(demo), "-o", str(tmp_path / "p21.png"), "--color-by", "p21"]) == 0
    with Project.open(demo) as p:  # a render colours by P21 per metre of the GCPs' frame
        np.testing.assert_allclose(seen["map"], p.vertex_map("p21")[0] / SCALE, rtol=1e-5)


def test_residuals_show_the_gcp_that_is_off(demo, picks, tmp_path, capsys):
    world = {n: apply_similarity(m, KNOWN) for n, (_, m) in picks.items()}
    world["G2"] = world["G2"] + [0.05, -0.02, 0.03]  # a surveying blunder of 6 cm
    assert main(["register", str(demo), str(write_gcps(tmp_path / "gcps.csv", picks, world))]) == 0
    rows = {line.split()[0]: line.split() for line in capsys.readouterr().out.splitlines()[2:2 + len(picks)]}
    with Project.open(demo) as p:
        reg = p.registration()
    expected = horn_similarity(np.array([m for _, m in picks.values()]), np.array(list(world.values())))
    np.testing.assert_allclose(reg.similarity.errors, expected.errors, atol=1e-6)
    assert reg.similarity.rmse == pytest.approx(expected.rmse, abs=1e-6) and expected.rmse > 0.01
    errors = {name: float(r[-1]) for name, r in rows.items()}
    assert max(errors, key=errors.get) == "G2"
    assert errors["G2"] == pytest.approx(expected.errors[2], abs=1e-4)


def test_registering_again_from_the_stored_gcps(demo, picks, tmp_path, capsys):
    world = {n: apply_similarity(m, KNOWN) for n, (_, m) in picks.items()}
    assert main(["register", str(demo), str(write_gcps(tmp_path / "gcps.csv", picks, world))]) == 0
    assert main(["register", str(demo)]) == 0
    assert "registered with 5 GCPs" in capsys.readouterr().out


@pytest.mark.parametrize("edit, message", [
    (lambda rows: rows[:2], r"2 GCPs: G0 \(line 2\), G1 \(line \d\); a registration needs at least 3"),
    (lambda rows: [r[:1] + [str(i * 1.0), str(i * 2.0 + 7), str(i * 3.0)] + r[4:] for i, r in enumerate(rows)],
     r"5 GCPs: G0 \(line 2\).*not on one line"),
    (lambda rows: rows[:1] + [rows[1][:4] + ["nope"] + rows[1][5:]] + rows[2:], r"line 3: image 'nope'"),
    (lambda rows: [rows[0][:5] + ["x"] + rows[0][6:]] + rows[1:], r"line 2: column u is 'x'"),
    (lambda rows: [rows[0][:5] + ["5000"] + rows[0][6:]] + rows[1:], r"line 2: pixel \(5000, .*outside"),
    (lambda rows: [rows[0][:5] + ["0", "0"]] + rows[1:],  # the sky in the top-left corner of every photo
     r"gcps.csv: GCP 'G0' on photo 'photo_0\d': the ray through pixel \(0.0, 0.0\) misses the mesh"),
])
def test_bad_gcps_are_refused_naming_the_file_and_row(demo, picks, tmp_path, capsys, edit, message):
    first = {n: (dict(list(o.items())[:1]), m) for n, (o, m) in picks.items()}  # one row per GCP
    world = {n: apply_similarity(m, KNOWN) for n, (_, m) in picks.items()}
    path = write_gcps(tmp_path / "gcps.csv", first, world)
    with open(path, newline="") as f:
        rows = list(csv.reader(f))[1:]
    with open(path, "w", newline="") as f:
        csv.writer(f).writerows([HEADER, *edit(rows)])
    assert main(["register", str(demo), str(path)]) == 2
    err = capsys.readouterr().err
    assert str(path) in err
    assert re.search(message, err), err
    with Project.open(demo) as p:
        assert p.registration() is None and p.gcps() == {}


def test_register_without_gcps_says_how_to_give_them(demo, capsys):
    assert main(["register", str(demo)]) == 2
    assert "no GCPs stored; give a CSV" in capsys.readouterr().err
