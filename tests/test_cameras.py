"""Camera readers: real files from other tools (reprojection of their own tie points), hand-written files
from a known set of cameras (each format's spec followed byte by byte), and bad input.

Oracles: the tie-point observations stored in the Bundler and NVM files; OpenCV's cv2.projectPoints for
the COLMAP models; each tool's documented projection formula, written out here, for the others.
"""

from __future__ import annotations

import json
import shutil
import struct
import tracemalloc
import xml.etree.ElementTree as ET
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from engine.cameras import Camera, check_images, read_cameras, write_cameras_json
from engine.errors import InputError


@pytest.fixture(scope="module")
def cams_dir(fixtures_dir: Path) -> Path:
    return fixtures_dir / "cameras"


def rotation(seed: int) -> np.ndarray:
    q = np.random.default_rng(seed).normal(size=4)
    return quaternion_matrix(q / np.linalg.norm(q))


def quaternion_matrix(q) -> np.ndarray:
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def matrix_quaternion(R: np.ndarray) -> np.ndarray:
    w = np.sqrt(max(1 + np.trace(R), 1e-12)) / 2
    return np.array([w, (R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w), (R[1, 0] - R[0, 1]) / (4 * w)])


def point_in_view(R: np.ndarray, t: np.ndarray, xn=(0.21, -0.13), depth=7.0) -> np.ndarray:
    """A world point seen at normalised camera coordinates `xn` at `depth`."""
    return R.T @ (np.array([xn[0], xn[1], 1.0]) * depth - t)


def numbers(values) -> str:
    """Space-separated full-precision numbers, as the tools print them."""
    return " ".join(repr(float(v)) for v in np.ravel(values))


def write_jpeg(path: Path, width: int, height: int) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.new("L", (width, height)).save(path)


# --- real files ---------------------------------------------------------------------------------------------

def bundler_observations(path: Path):
    """(camera index, point, key point x, y) of every observation in a Bundler v0.3 file."""
    lines = [line for line in path.read_text().splitlines() if line.strip()]
    n_cameras, n_points = map(int, lines[1].split())
    first = 2 + 5 * n_cameras
    for i in range(n_points):
        X = np.array(lines[first + 3 * i].split(), dtype=float)
        views = lines[first + 3 * i + 2].split()
        for j in range(int(views[0])):
            camera, _, x, y = views[1 + 4 * j: 5 + 4 * j]
            yield int(camera), X, float(x), float(y)


def test_bundler_kermit_reprojects_its_key_points(cams_dir):
    cameras = read_cameras(cams_dir / "bundler_kermit.out", image_sizes=(640, 480))
    assert len(cameras) == 9  # 11 images, 2 not reconstructed (f = 0)
    assert "image004" not in cameras and "image006" not in cameras
    errors = []
    for index, X, x, y in bundler_observations(cams_dir / "bundler_kermit.out"):
        camera = cameras[f"image{index:03d}"]
        observed = np.array([x + 640 / 2 - 0.5, 480 / 2 - 0.5 - y])  # centre origin, y up → ours
        errors.append(np.linalg.norm(camera.project(X[None])[0] - observed))
    assert len(errors) > 1500
    assert np.median(errors) < 0.3  # measured 0.20 px


def test_bundler_names_and_sizes_come_from_list_and_photos(cams_dir, tmp_path):
    (tmp_path / "bundle").mkdir()
    shutil.copy(cams_dir / "bundler_kermit.out", tmp_path / "bundle" / "bundle.out")
    names = [f"kermit{i:03d}.jpg" for i in range(11)]
    (tmp_path / "list.txt").write_text("".join(f"./images/{n} 0 688.4\n" for n in names))
    for n in names:
        write_jpeg(tmp_path / "images" / n, 640, 480)
    cameras = read_cameras(tmp_path / "bundle" / "bundle.out")  # list one folder up, as Bundler lays it out
    assert sorted(cameras) == sorted(set(names) - {"kermit004.jpg", "kermit006.jpg"})
    assert all((c.width, c.height) == (640, 480) for c in cameras.values())
    assert cameras["kermit000.jpg"].image_path == str(tmp_path / "images" / "kermit000.jpg")
    np.testing.assert_allclose(cameras["kermit000.jpg"].K[:2, 2], [319.5, 239.5])


def nvm_observations(path: Path):
    lines = [line for line in path.read_text().splitlines() if line.strip()]
    n_cameras = int(lines[1])
    names = [lines[2 + i].split()[0] for i in range(n_cameras)]
    n_points = int(lines[2 + n_cameras])
    for line in lines[3 + n_cameras: 3 + n_cameras + n_points]:
        tokens = line.split()
        X = np.array(tokens[:3], dtype=float)
        for j in range(int(tokens[6])):
            image, _, x, y = tokens[7 + 4 * j: 11 + 4 * j]
            yield names[int(image)], X, float(x), float(y)


def test_nvm_reprojects_its_measurements(cams_dir):
    path = cams_dir / "visualsfm_model.nvm"
    cameras = read_cameras(path, image_sizes=(1920, 1080))
    assert len(cameras) == 22
    errors, undistorted_errors = [], []
    for name, X, x, y in nvm_observations(path):
        camera = cameras[name]
        observed = np.array([x + 1920 / 2 - 0.5, y + 1080 / 2 - 0.5])  # centre origin, y down → ours
        errors.append(np.linalg.norm(camera.project(X[None])[0] - observed))
        plain = Camera(name, camera.width, camera.height, camera.K, [], camera.R, camera.t)
        undistorted_errors.append(np.linalg.norm(plain.project(X[None])[0] - observed))
    assert np.median(errors) < 1.0  # measured 0.76 px
    assert np.median(undistorted_errors) > 1.5  # 2.1 px: the radial model matters and is applied right


def test_nvm_radial_model_is_inverted_within_005_px(cams_dir):
    path = cams_dir / "visualsfm_model.nvm"
    cameras = read_cameras(path, image_sizes=(1920, 1080))
    values = {line.split()[0]: np.array(line.split()[1:], dtype=float)
              for line in path.read_text().splitlines()[3:25]}
    u, v = np.meshgrid(np.linspace(-0.5, 1919.5, 41), np.linspace(-0.5, 1079.5, 31))
    uv = np.column_stack([u.ravel(), v.ravel()])
    for name, camera in cameras.items():
        f, r = values[name][0], values[name][8]
        measured = (uv - camera.K[:2, 2]) / f
        nvm = measured * (1 + r * np.sum(measured**2, axis=1, keepdims=True))  # VisualSFM's undistortion
        ours = camera.undistort_normalised(uv)
        assert f * np.abs(ours - nvm).max() < 0.05


def metashape_sensor(path: Path, sensor_id: str) -> dict[str, float]:
    sensor = ET.parse(path).getroot().find(f"chunk/sensors/sensor[@id='{sensor_id}']")
    calibration = sensor.find("calibration")
    values = {e.tag: float(e.text) for e in calibration if e.tag != "resolution"}
    values["w"], values["h"] = (float(calibration.find("resolution").get(k)) for k in ("width", "height"))
    return values


def metashape_project(s: dict[str, float], X: np.ndarray) -> np.ndarray:
    """Metashape manual 1.5, appendix C (frame camera), in Metashape's pixels (top-left centre at 0.5)."""
    g = lambda key: s.get(key, 0.0)  # noqa: E731 (absent coefficients are 0)
    x, y = X[..., 0] / X[..., 2], X[..., 1] / X[..., 2]
    r2 = x * x + y * y
    radial = 1 + r2 * (g("k1") + r2 * (g("k2") + r2 * (g("k3") + r2 * g("k4"))))
    xp = x * radial + g("p1") * (r2 + 2 * x * x) + 2 * g("p2") * x * y
    yp = y * radial + g("p2") * (r2 + 2 * y * y) + 2 * g("p1") * x * y
    u = s["w"] * 0.5 + g("cx") + xp * s["f"] + xp * g("b1") + yp * g("b2")
    v = s["h"] * 0.5 + g("cy") + yp * s["f"]
    return np.stack([u, v], axis=-1)


def test_metashape_dji_flight(cams_dir):
    path = cams_dir / "metashape_dji25.xml"
    cameras = read_cameras(path)
    assert len(cameras) == 25
    centres = np.array([c.centre for c in cameras.values()])
    centred = centres - centres.mean(axis=0)
    axis = np.linalg.svd(centred)[2][0]
    across = centred - np.outer(centred @ axis, axis)
    spread = np.ptp(centred @ axis)
    assert spread > 20.0 and np.linalg.norm(across, axis=1).max() < 0.05 * spread  # 0.75 m over 28.6 m
    view_z = np.array([c.R[2] for c in cameras.values()])  # camera z axis in the world frame
    assert np.all(view_z[:, 2] < -0.99)  # all looking down


def test_metashape_intrinsics_follow_the_manual(cams_dir):
    path = cams_dir / "metashape_dji25.xml"
    camera = read_cameras(path)["DJI_0002"]  # sensor 0
    s = metashape_sensor(path, "0")
    np.testing.assert_allclose(camera.K, [[s["f"], 0, 2640 + s["cx"] - 0.5], [0, s["f"], 1978 + s["cy"] - 0.5],
                                          [0, 0, 1]], rtol=0, atol=1e-9)
    np.testing.assert_allclose(camera.distortion[:5], [s["k1"], s["k2"], s["p2"], s["p1"], s["k3"]], atol=0)
    X_cam = np.array([[0.31, -0.22, 1.0], [-0.6, 0.45, 1.0], [0.0, 0.0, 1.0]]) * 40.0
    X = (X_cam - camera.t) @ camera.R  # world points at those camera-frame positions
    np.testing.assert_allclose(camera.project(X), metashape_project(s, X_cam) - 0.5, atol=1e-6)


M3M = {"w": 5280, "h": 3956, "f": 3705.4728792737214, "cx": 11.6738523909, "cy": -27.7497969199,
       "b1": 0.5262024073, "b2": -0.3058334293, "k1": -0.0919367147, "k2": -0.0762807468, "k3": 0.1162639394,
       "k4": -0.0761413904, "p1": -0.0003134847, "p2": 0.0001164035}


def write_metashape(path: Path, sensor: dict[str, float], cameras: list[tuple[str, np.ndarray | None]],
                    chunk: str = "", components: str = "") -> Path:
    tags = "".join(f"<{k}>{v!r}</{k}>" for k, v in sensor.items() if k not in ("w", "h"))
    cams = "".join(f'<camera id="{i}" sensor_id="0" component_id="0" label="{label}">'
                   + ("" if T is None else f"<transform>{numbers(T.ravel())}</transform>") + "</camera>"
                   for i, (label, T) in enumerate(cameras))
    path.write_text(f'<?xml version="1.0"?><document version="2.0.0"><chunk><sensors>'
                    f'<sensor id="0" type="frame"><resolution width="{sensor["w"]}" height="{sensor["h"]}"/>'
                    f'<calibration type="frame" class="adjusted"><resolution width="{sensor["w"]}" '
                    f'height="{sensor["h"]}"/>{tags}</calibration></sensor></sensors>'
                    f'<components>{components}</components><cameras>{cams}</cameras>{chunk}</chunk></document>')
    return path


def test_metashape_k4_affinity_and_transforms(tmp_path):
    R_c, C_c = rotation(1), np.array([1.0, 2.0, 3.0])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R_c, C_c  # camera → component
    R_k, t_k, s_k = rotation(2), np.array([0.5, -1.0, 2.0]), 0.8  # component → chunk
    R_w, t_w, s_w = rotation(3), np.array([5e5, 4e6, 100.0]), 2.5  # chunk → world
    component = (f'<component id="0"><transform><rotation>{numbers(R_k.ravel())}</rotation>'
                 f'<translation>{numbers(t_k)}</translation><scale>{s_k!r}</scale></transform>'
                 '</component>')
    chunk = (f'<transform><rotation>{numbers(R_w.ravel())}</rotation>'
             f'<translation>{numbers(t_w)}</translation><scale>{s_w!r}</scale></transform>')
    path = write_metashape(tmp_path / "cameras.xml", M3M, [("aligned", T), ("not_aligned", None)], chunk, component)
    cameras = read_cameras(path)
    assert list(cameras) == ["aligned"]
    camera = cameras["aligned"]
    # camera-frame points covering the whole photo, as Metashape sees them
    corners = camera.undistort_normalised(np.array([[-0.5, -0.5], [5279.5, 3955.5], [-0.5, 3955.5], [5279.5, -0.5]]))
    x_max, y_max = 1.03 * np.abs(corners).max(axis=0)
    x, y = np.meshgrid(np.linspace(-x_max, x_max, 81), np.linspace(-y_max, y_max, 61))
    X_cam = np.column_stack([x.ravel(), y.ravel(), np.ones(x.size)]) * 3.0
    uv_metashape = metashape_project(M3M, X_cam) - 0.5
    inside = np.all((uv_metashape > -0.5) & (uv_metashape < [M3M["w"] - 0.5, M3M["h"] - 0.5]), axis=1)
    assert inside.sum() > 3000 and inside[[0, 80, -81, -1]].sum() == 0  # grid overshoots every corner
    X_chunk = s_k * (X_cam @ R_c.T + C_c) @ R_k.T + t_k
    X_world = s_w * X_chunk @ R_w.T + t_w
    error = np.linalg.norm(camera.project(X_world[inside]) - uv_metashape[inside], axis=1)
    assert error.max() < 0.05  # K4 fitted into OpenCV's rational model
    np.testing.assert_allclose(camera.centre, s_w * R_w @ (s_k * R_k @ C_c + t_k) + t_w, rtol=0, atol=1e-6)
    # the fit may rescale the focal length (only f·d(r²) is observable) but keeps B1, B2 relative to f
    assert camera.K[1, 1] == pytest.approx(M3M["f"], rel=1e-3)
    assert camera.K[0, 0] / camera.K[1, 1] == pytest.approx((M3M["f"] + M3M["b1"]) / M3M["f"], rel=1e-12)
    assert camera.K[0, 1] / camera.K[1, 1] == pytest.approx(M3M["b2"] / M3M["f"], rel=1e-12)


def test_metashape_k4_beyond_opencv_is_refused(tmp_path):
    wild = dict(M3M, k4=-1.0)  # r·d(r²) turns back inside the photo
    path = write_metashape(tmp_path / "wild.xml", wild, [("a", np.eye(4))])
    with pytest.raises(InputError, match=r"wild\.xml.*folds back before the image corners"):
        read_cameras(path)


# --- hand-written files from known cameras -------------------------------------------------------------------

COLMAP_CAMERAS = [  # name, model, width, height, params (COLMAP's pixel convention)
    ("a.jpg", "SIMPLE_PINHOLE", 640, 480, [500.0, 320.0, 240.0]),
    ("b.jpg", "PINHOLE", 800, 600, [700.0, 710.0, 401.5, 299.5]),
    ("c.jpg", "SIMPLE_RADIAL", 1024, 768, [900.0, 512.0, 384.0, -0.05]),
    ("d.jpg", "RADIAL", 1024, 768, [900.0, 510.0, 380.0, -0.05, 0.01]),
    ("sub/e.jpg", "OPENCV", 1600, 1200, [1200.0, 1190.0, 800.0, 600.0, -0.1, 0.02, 0.001, -0.002]),
    ("f.jpg", "FULL_OPENCV", 1600, 1200,
     [1200.0, 1190.0, 800.0, 600.0, -0.1, 0.02, 0.001, -0.002, 0.003, 0.01, 0.002, 0.0005]),
]
MODEL_IDS = {"SIMPLE_PINHOLE": 0, "PINHOLE": 1, "SIMPLE_RADIAL": 2, "RADIAL": 3, "OPENCV": 4, "FULL_OPENCV": 6}


def colmap_opencv(model: str, p: list[float]) -> tuple[np.ndarray, np.ndarray]:
    """K and distortion of a COLMAP camera for cv2, in COLMAP's own pixel convention."""
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        K, dist = [[p[0], 0, p[1]], [0, p[0], p[2]], [0, 0, 1]], p[3:] + [0.0] * (4 - len(p[3:]))
    else:
        K, dist = [[p[0], 0, p[2]], [0, p[1], p[3]], [0, 0, 1]], p[4:] or [0.0] * 4
    return np.array(K), np.array(dist)


def colmap_poses():
    for i, (name, *_rest) in enumerate(COLMAP_CAMERAS):
        R = rotation(10 + i)
        yield i + 1, name, matrix_quaternion(R), np.array([0.3 * i, -1.0, 2.0 + i]), R


def write_colmap_text(folder: Path) -> None:
    folder.mkdir()
    with open(folder / "cameras.txt", "w") as f:
        f.write("# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n")
        for i, (_, model, w, h, params) in enumerate(COLMAP_CAMERAS):
            f.write(f"{i + 1} {model} {w} {h} {numbers(params)}\n")
    with open(folder / "images.txt", "w") as f:
        f.write("# Image list with two lines of data per image:\n")
        for image_id, name, q, t, _ in colmap_poses():
            f.write(f"{image_id} {numbers([*q, *t])} {image_id} {name}\n")
            f.write("\n" if image_id % 2 else "10.5 20.25 -1 30.0 40.0 7\n")  # empty POINTS2D lines too


def write_colmap_binary(folder: Path) -> None:
    folder.mkdir()
    data = struct.pack("<Q", len(COLMAP_CAMERAS))
    for i, (_, model, w, h, params) in enumerate(COLMAP_CAMERAS):
        data += struct.pack("<iiQQ", i + 1, MODEL_IDS[model], w, h) + struct.pack(f"<{len(params)}d", *params)
    (folder / "cameras.bin").write_bytes(data)
    data = struct.pack("<Q", len(COLMAP_CAMERAS))
    for image_id, name, q, t, _ in colmap_poses():
        data += struct.pack("<i4d3di", image_id, *q, *t, image_id) + name.encode() + b"\0"
        points = [(10.5, 20.25, -1), (30.0, 40.0, 7)][: image_id % 3]
        data += struct.pack("<Q", len(points)) + b"".join(struct.pack("<ddq", *p) for p in points)
    (folder / "images.bin").write_bytes(data)


@pytest.mark.parametrize("writer", [write_colmap_text, write_colmap_binary])
def test_colmap_models_and_half_pixel_origin(tmp_path, writer):
    writer(tmp_path / "sparse")
    cameras = read_cameras(tmp_path / "sparse")
    assert list(cameras) == [c[0] for c in COLMAP_CAMERAS]
    for (name, model, w, h, params), (_, _, q, t, R) in zip(COLMAP_CAMERAS, colmap_poses()):
        camera = cameras[name]
        K_colmap, dist = colmap_opencv(model, params)
        assert (camera.width, camera.height) == (w, h)
        np.testing.assert_allclose(camera.K, K_colmap - [[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]], atol=1e-12)
        np.testing.assert_allclose(camera.distortion[: len(dist)], dist, atol=1e-15)
        np.testing.assert_allclose(camera.R, R, atol=1e-12)
        np.testing.assert_allclose(camera.t, t, atol=1e-15)
        X = point_in_view(R, t)
        expected, _ = cv2.projectPoints(X[None], cv2.Rodrigues(R)[0], t, K_colmap, dist)
        # COLMAP's pixel of X is OpenCV's with COLMAP's K; ours is half a pixel less on both axes
        np.testing.assert_allclose(camera.project(X[None])[0], expected.ravel() - 0.5, atol=1e-9)


def test_colmap_file_path_finds_its_sibling(tmp_path):
    write_colmap_text(tmp_path / "model")
    assert len(read_cameras(tmp_path / "model" / "images.txt")) == len(COLMAP_CAMERAS)


OPENMVG_INTRINSICS = [  # key, model, data
    (0, "pinhole_brown_t2", {"width": 1600, "height": 1200, "focal_length": 1250.0,
                             "principal_point": [801.2, 598.7], "disto_t2": [-0.12, 0.03, 0.004, 0.0015, -0.0021]}),
    (1, "pinhole_radial_k3", {"width": 1024, "height": 768, "focal_length": 900.0,
                              "principal_point": [512.5, 383.0], "disto_k3": [-0.05, 0.01, -0.002]}),
    (2, "pinhole_brown_t2", {"width": 1600, "height": 1200, "focal_length": 1300.0,
                             "principal_point": [799.0, 601.0], "disto_t2": [0.02, -0.01, 0.0, -0.001, 0.002]}),
    (3, "pinhole", {"width": 640, "height": 480, "focal_length": 500.0, "principal_point": [319.5, 239.5]}),
]
UNDEFINED = 4294967295


def openmvg_project(model: str, data: dict, X_cam: np.ndarray) -> np.ndarray:
    """openMVG cam2ima(add_disto(x)) from Camera_Pinhole_Radial.hpp / Camera_Pinhole_Brown.hpp."""
    x, y = X_cam[0] / X_cam[2], X_cam[1] / X_cam[2]
    r2 = x * x + y * y
    if model == "pinhole_brown_t2":
        k1, k2, k3, t1, t2 = data["disto_t2"]
        k_diff = k1 * r2 + k2 * r2**2 + k3 * r2**3
        xd = x + x * k_diff + t2 * (r2 + 2 * x * x) + 2 * t1 * x * y
        yd = y + y * k_diff + t1 * (r2 + 2 * y * y) + 2 * t2 * x * y
    else:
        k = data.get("disto_k3", [0.0, 0.0, 0.0])
        factor = 1 + k[0] * r2 + k[1] * r2**2 + k[2] * r2**3
        xd, yd = x * factor, y * factor
    return data["focal_length"] * np.array([xd, yd]) + data["principal_point"]


def write_openmvg(path: Path) -> dict[str, tuple[int, int]]:
    """An sfm_data.json written as cereal does; returns reconstructed view → (intrinsic, pose)."""
    type_ids, intrinsics = {}, []
    for key, model, data in OPENMVG_INTRINSICS:
        value = {"polymorphic_id": type_ids.get(model, 0)}
        if model not in type_ids:  # first occurrence: name and top bit; later ones repeat the bare id
            type_ids[model] = len(type_ids) + 1
            value = {"polymorphic_id": 2147483648 + type_ids[model], "polymorphic_name": model}
        value["ptr_wrapper"] = {"id": 2147483700 + key, "data": data}
        intrinsics.append({"key": key, "value": value})
    views, expected = [], {}
    for i, (intrinsic, pose) in enumerate([(0, 0), (1, 1), (2, 2), (3, 3), (0, 9), (UNDEFINED, 0)]):
        name = f"view{i}.jpg"
        views.append({"key": i, "value": {"polymorphic_id": 1073741824, "ptr_wrapper": {
            "id": 2147483649 + i, "data": {"local_path": "", "filename": name, "width": 0, "height": 0,
                                           "id_view": i, "id_intrinsic": intrinsic, "id_pose": pose}}}})
        if intrinsic != UNDEFINED and pose < 4:
            expected[name] = (intrinsic, pose)
    extrinsics = [{"key": p, "value": {"rotation": rotation(20 + p).tolist(), "center": [p, 2.0 * p, -1.0]}}
                  for p in range(4)]
    path.write_text(json.dumps({"sfm_data_version": "0.3", "root_path": "/photos", "views": views,
                                "intrinsics": intrinsics, "extrinsics": extrinsics, "structure": [],
                                "control_points": []}, indent=4))
    return expected


def test_openmvg_models_tangential_order_and_pixel_origin(tmp_path):
    expected = write_openmvg(tmp_path / "sfm_data.json")
    cameras = read_cameras(tmp_path / "sfm_data.json")
    assert sorted(cameras) == sorted(expected)  # views without pose or intrinsic are left out
    for name, (key, pose) in expected.items():
        _, model, data = OPENMVG_INTRINSICS[key]
        camera, R, C = cameras[name], rotation(20 + pose), np.array([pose, 2.0 * pose, -1.0])
        assert (camera.width, camera.height) == (data["width"], data["height"])
        assert camera.image_path == f"/photos/{name}"
        f, (cx, cy) = data["focal_length"], data["principal_point"]
        np.testing.assert_array_equal(camera.K, [[f, 0, cx], [0, f, cy], [0, 0, 1]])  # no pixel shift
        k = data.get("disto_t2", data.get("disto_k3", [0.0] * 3))
        expected_dist = [k[0], k[1], k[3], k[4], k[2]] if model == "pinhole_brown_t2" else [k[0], k[1], 0, 0, k[2]]
        np.testing.assert_array_equal(camera.distortion, expected_dist + [0.0] * 3)  # t1 → p1, t2 → p2
        np.testing.assert_allclose(camera.R, R, atol=1e-12)
        np.testing.assert_allclose(camera.t, -R @ C, atol=1e-12)
        X = C + R.T @ np.array([0.3, -0.25, 1.0]) * 5.0
        np.testing.assert_allclose(camera.project(X[None])[0], openmvg_project(model, data, R @ (X - C)),
                                   atol=1e-9)


def write_openmvs(path: Path, version: int, normalised: bool = False) -> None:
    """An OpenMVS interface stream (Interface.h ArchiveSave): 2 platforms, the first a two-camera rig."""
    def string(s: str) -> bytes:
        return struct.pack("<Q", len(s)) + s.encode()
    data = b"" if version == 0 else b"MVSI" + struct.pack("<II", version, 0)
    data += struct.pack("<Q", len(OPENMVS_PLATFORMS))
    for name, cameras, poses in OPENMVS_PLATFORMS:
        data += string(name) + struct.pack("<Q", len(cameras))
        for cam_name, w, h, K, R, C in cameras:
            data += string(cam_name) + (string("RGB") if version > 3 else b"")
            data += struct.pack("<II", 0 if normalised else w, 0 if normalised else h) if version > 0 else b""
            K = np.vstack([K[:2] / max(w, h), K[2:]]) if normalised else K  # Scene::LoadInterface's scaling
            data += struct.pack("<9d", *K.ravel()) + struct.pack("<9d", *R.ravel()) + struct.pack("<3d", *C)
        data += struct.pack("<Q", len(poses)) + b"".join(struct.pack("<9d", *R.ravel()) + struct.pack("<3d", *C)
                                                          for R, C in poses)
    data += struct.pack("<Q", len(OPENMVS_IMAGES))
    for i, (name, platform, camera, pose) in enumerate(OPENMVS_IMAGES):
        data += string(name) + (string("") if version > 4 else b"") + struct.pack("<3I", platform, camera, pose)
        data += struct.pack("<I", i) if version > 2 else b""
    data += struct.pack("<QQQ", 0, 0, 0)  # vertices, normals, colours (not read)
    path.write_bytes(data)


OPENMVS_PLATFORMS = [
    ("rig", [("left", 1600, 1200, np.array([[1250.0, 0.2, 799.5], [0, 1251.0, 600.5], [0, 0, 1]]), np.eye(3),
              np.zeros(3)),
             ("right", 1600, 1200, np.array([[1240.0, 0, 801.0], [0, 1240.0, 598.0], [0, 0, 1]]), rotation(30),
              np.array([0.5, 0.0, 0.0]))],
     [(rotation(31), np.array([1.0, 2.0, 3.0])), (rotation(32), np.array([2.0, 2.0, 3.5]))]),
    ("single", [("cam", 1000, 750, np.array([[900.0, 0, 499.5], [0, 900.0, 374.5], [0, 0, 1]]), np.eye(3),
                 np.zeros(3))],
     [(rotation(33), np.array([-1.0, 0.0, 2.0]))]),
]
OPENMVS_IMAGES = [("images/l0.jpg", 0, 0, 0), ("images/r0.jpg", 0, 1, 0), ("images/l1.jpg", 0, 0, 1),
                  ("/abs/s0.jpg", 1, 0, 0), ("images/unposed.jpg", 1, 0, 0xFFFFFFFF)]


@pytest.mark.parametrize("version,normalised", [(5, False), (3, False), (1, False), (0, True), (2, True)])
def test_openmvs_rig_poses_and_intrinsics(tmp_path, version, normalised):
    write_openmvs(tmp_path / "scene.mvs", version, normalised)
    sizes = {"l0.jpg": (1600, 1200), "r0.jpg": (1600, 1200), "l1.jpg": (1600, 1200), "s0.jpg": (1000, 750)}
    cameras = read_cameras(tmp_path / "scene.mvs", image_sizes=sizes if normalised else None)
    assert sorted(cameras) == sorted(sizes)
    for name, platform, camera_index, pose in OPENMVS_IMAGES[:4]:
        _, cams, poses = OPENMVS_PLATFORMS[platform]
        _, w, h, K, R_cam, C_cam = cams[camera_index]
        R_pose, C_pose = poses[pose]
        R, C = R_cam @ R_pose, R_pose.T @ C_cam + C_pose  # Interface::Platform::GetPose
        camera = cameras[Path(name).name]
        assert (camera.width, camera.height) == (w, h)
        np.testing.assert_allclose(camera.K, K, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(camera.R, R, atol=1e-12)
        np.testing.assert_allclose(camera.t, -R @ C, atol=1e-12)
        assert not camera.distortion.any()
        X = C + R.T @ np.array([-0.2, 0.3, 1.0]) * 4.0
        x = K @ (R @ (X - C))
        np.testing.assert_allclose(camera.project(X[None])[0], x[:2] / x[2], atol=1e-9)


def test_native_json_round_trip_is_exact(tmp_path):
    write_colmap_text(tmp_path / "model")
    cameras = read_cameras(tmp_path / "model")
    write_cameras_json(cameras, tmp_path / "cameras.json")
    again = read_cameras(tmp_path / "cameras.json")
    assert list(again) == list(cameras)
    for name, camera in cameras.items():
        assert again[name].to_dict() == camera.to_dict()


@pytest.mark.parametrize("k1", [-0.3, -0.1, 0.1, 0.3])
def test_undistortion_round_trip_to_the_corners(k1):
    R, t = rotation(40), np.array([0.2, -0.1, 3.0])
    camera = Camera("c", 1000, 750, [[1000.0, 0, 501.3], [0, 1002.0, 372.9], [0, 0, 1]],
                    [k1, 0.05, 0.0012, -0.0009], R, t)
    u, v = np.meshgrid(np.linspace(-0.5, 999.5, 51), np.linspace(-0.5, 749.5, 39))
    uv = np.column_stack([u.ravel(), v.ravel()])  # includes the four image corners
    points = camera.centre + 6.0 * camera.pixel_rays(uv)
    assert np.abs(camera.project(points) - uv).max() < 0.01
    again = camera.project(camera.centre + 2.0 * camera.pixel_rays(camera.project(points)))
    assert np.abs(again - uv).max() < 0.01


def camera_4000x3000(f: float, distortion) -> Camera:
    return Camera("IMG_1", 4000, 3000, [[f, 0, 1999.5], [0, f, 1499.5], [0, 0, 1]], distortion, rotation(41),
                  [0.1, 0.2, 5.0])


@pytest.mark.parametrize("f, distortion, fault", [
    (3200.0, [-0.3], "comes back"),  # r(1 − 0.3r²) peaks at 0.70, the corners are at 0.78: no direction there
    (2000.0, [-0.2], "comes back"),  # peaks at 0.86, the corners at 1.25
    (1000.0, [-0.5, 0.1], "reached twice"),  # folds and unfolds: Newton lands on the far branch
])
def test_distortion_that_folds_before_the_border_is_refused(tmp_path, f, distortion, fault):
    write_cameras_json([camera_4000x3000(f, distortion)], tmp_path / "cameras.json")
    with pytest.raises(InputError) as error:
        read_cameras(tmp_path / "cameras.json")
    message = str(error.value)
    assert message.startswith(f"{tmp_path / 'cameras.json'}: camera 'IMG_1' (OpenCV model, f = {f:g} px, "
                              f"k1 = {distortion[0]:g}")
    assert "does not invert over the 4000×3000 image" in message and fault in message


@pytest.mark.parametrize("f, distortion", [(3200.0, [-0.1]), (3200.0, [0.3]), (4000.0, [-0.3]),
                                           (3000.0, [-0.3, 0.05, 0.001, -0.002]), (2000.0, [0.2, -0.05])])
def test_distortion_that_inverts_over_the_image_loads(tmp_path, f, distortion):
    write_cameras_json([camera_4000x3000(f, distortion)], tmp_path / "cameras.json")
    camera = read_cameras(tmp_path / "cameras.json")["IMG_1"]
    uv = np.array([[-0.5, -0.5], [3999.5, 2999.5], [2000.0, -0.5], [-0.5, 1500.0]])
    assert np.abs(camera.project(camera.centre + camera.pixel_rays(uv)) - uv).max() < 0.01


def test_check_images_finds_photos_and_checks_sizes(tmp_path):
    def camera(name, w, h):
        return Camera(name, w, h, [[50.0, 0, w / 2], [0, 50.0, h / 2], [0, 0, 1]], [], np.eye(3), np.zeros(3))
    write_jpeg(tmp_path / "photos" / "a.jpg", 64, 48)
    write_jpeg(tmp_path / "photos" / "deep" / "DJI_0001.JPG", 32, 24)
    cameras = {"a.jpg": camera("a.jpg", 64, 48), "DJI_0001": camera("DJI_0001", 32, 24)}
    found = check_images(cameras, tmp_path / "photos")
    assert found == {"a.jpg": tmp_path / "photos" / "a.jpg",
                     "DJI_0001": tmp_path / "photos" / "deep" / "DJI_0001.JPG"}
    wrong = dict(cameras, **{"a.jpg": camera("a.jpg", 640, 480)})
    with pytest.raises(InputError, match=r"a\.jpg is 64×48 px but camera 'a\.jpg' is 640×480"):
        check_images(wrong, tmp_path / "photos")
    missing = dict(cameras, b=camera("b", 64, 48), c=camera("c.png", 64, 48))
    with pytest.raises(InputError, match=r"no photo found for 2 of 4 cameras: b, c"):
        check_images(missing, tmp_path / "photos")


# --- bad input ------------------------------------------------------------------------------------------------

def colmap_case(cameras_txt: str, images_txt: str = "1 1 0 0 0 0 0 0 1 a.jpg\n\n"):
    def write(folder: Path) -> Path:
        (folder / "cameras.txt").write_text(cameras_txt)
        (folder / "images.txt").write_text(images_txt)
        return folder / "cameras.txt"
    return write


def file_case(name: str, content: str | bytes):
    def write(folder: Path) -> Path:
        path = folder / name
        path.write_bytes(content if isinstance(content, bytes) else content.encode())
        return path
    return write


def colmap_binary_case(cut: int):
    def write(folder: Path) -> Path:
        write_colmap_binary(folder / "bin")
        data = (folder / "bin" / "cameras.bin").read_bytes()
        (folder / "bin" / "cameras.bin").write_bytes(data[:cut])
        return folder / "bin" / "cameras.bin"
    return write


def openmvs_case(version: int | None = None, cut: int | None = None):
    def write(folder: Path) -> Path:
        path = folder / "scene.mvs"
        write_openmvs(path, 5)
        data = path.read_bytes()
        if version is not None:
            data = data[:4] + struct.pack("<I", version) + data[8:]
        path.write_bytes(data[:cut])
        return path
    return write


def colmap_binary_edit(name: str, offset: int, data: bytes):
    def write(folder: Path) -> Path:
        write_colmap_binary(folder / "bin")
        old = (folder / "bin" / name).read_bytes()
        (folder / "bin" / name).write_bytes(old[:offset] + data + old[offset + len(data):])
        return folder / "bin" / name
    return write


def openmvs_resolution(width: int, height: int):
    """The OpenMVS stream with its first camera's stored width and height replaced."""
    def write(folder: Path) -> Path:
        path = folder / "scene.mvs"
        write_openmvs(path, 5)
        data = path.read_bytes()
        at = data.index(b"RGB") + 3  # the band name, then uint32 width, height
        path.write_bytes(data[:at] + struct.pack("<II", width, height) + data[at + 8:])
        return path
    return write


BUNDLE = "# Bundle file v0.3\n1 0\n500 0 0\n1 0 0\n0 1 0\n0 0 1\n0 0 0\n"
NVM_CAMERA = "a.jpg 1000 1 0 0 0 0 0 0 0.1 0\n"
SENSOR = ('<sensors><sensor id="0" type="{type}"><resolution width="100" height="80"/><calibration '
          'class="adjusted"><f>90</f></calibration></sensor></sensors>')
METASHAPE = '<document><chunk>{sensors}<cameras><camera id="0" sensor_id="{sid}" label="a">{tf}</camera></cameras>' \
            '</chunk></document>'
IDENTITY = "<transform>1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1</transform>"
OPENMVG_FISHEYE = {"sfm_data_version": "0.3", "views": [], "extrinsics": [], "intrinsics": [
    {"key": 0, "value": {"polymorphic_id": 2147483649, "polymorphic_name": "fisheye",
                         "ptr_wrapper": {"id": 2147483650, "data": {}}}}]}

BAD_INPUTS = {
    "colmap unknown model": (colmap_case("1 FISHEYE_X 640 480 1 2 3\n"), {}, "camera model 'FISHEYE_X'"),
    "colmap parameter count": (colmap_case("1 PINHOLE 640 480 500 500 320\n"), {}, "line 1: expected the PINHOLE"
                               r" parameters \(4 values\), found 3"),
    "colmap non-numeric": (colmap_case("# c\n1 PINHOLE 640 480 500 abc 320 240\n"), {}, "line 2.*'abc'"),
    "colmap unknown camera id": (colmap_case("1 PINHOLE 640 480 500 500 320 240\n", "1 1 0 0 0 0 0 0 2 a.jpg\n"),
                                 {}, "CAMERA_ID 2"),
    "colmap short image line": (colmap_case("1 PINHOLE 640 480 500 500 320 240\n", "1 1 0 0 0 0 0 1 a.jpg\n"),
                                {}, "found 9 values"),
    "colmap truncated binary": (colmap_binary_case(300), {}, "truncated at byte 256: expected 8 OPENCV parameters"),
    "colmap count beyond file": (colmap_binary_case(30), {}, "claims 6 cameras"),
    "bundler header": (file_case("x.out", "# Bundle file v0.4\n"), {}, "line 1: expected the header"),
    "bundler truncated": (file_case("x.out", BUNDLE[:-6]), {"image_sizes": (10, 10)}, "ends after line 6"),
    "bundler non-numeric": (file_case("x.out", BUNDLE.replace("0 1 0", "0 one 0")), {"image_sizes": (10, 10)},
                            "line 5.*'one'"),
    "bundler missing list": (file_case("x.out", BUNDLE), {"image_list": "/nonexistent/list.txt"},
                             "list.txt: image list of x.out not found"),
    "bundler no sizes": (file_case("x.out", BUNDLE), {}, "does not store image sizes"),
    "nvm fixed K": (file_case("m.nvm", "NVM_V3 FixedK 1 2 3 4 0\n1\n" + NVM_CAMERA), {}, "FixedK"),
    "nvm short camera": (file_case("m.nvm", "NVM_V3\n1\na.jpg 1000 1 0 0 0 0 0 0.1 0\n"), {}, "found 10 values"),
    "nvm missing camera": (file_case("m.nvm", "NVM_V3\n2\n" + NVM_CAMERA), {"image_sizes": (10, 10)},
                           "expected camera 2 of 2"),
    "nvm bad quaternion": (file_case("m.nvm", "NVM_V3\n1\n" + NVM_CAMERA.replace(" 1 0 0 0 ", " 2 0 0 0 ")),
                           {"image_sizes": (10, 10)}, "norm 2"),
    "metashape malformed": (file_case("c.xml", "<document><chunk>"), {}, "not well-formed XML"),
    "metashape transform": (file_case("c.xml", METASHAPE.format(sensors=SENSOR.format(type="frame"), sid=0,
                                                                tf="<transform>1 0 0</transform>")),
                            {}, "camera 'a' <transform>: expected 16 numbers, found 3"),
    "metashape sensor type": (file_case("c.xml", METASHAPE.format(sensors=SENSOR.format(type="fisheye"), sid=0,
                                                                  tf=IDENTITY)), {}, "sensor type 'fisheye'"),
    "metashape sensor id": (file_case("c.xml", METASHAPE.format(sensors=SENSOR.format(type="frame"), sid=7,
                                                                tf=IDENTITY)), {}, "sensor_id '7'"),
    "openmvg malformed": (file_case("sfm_data.json", '{"sfm_data_version": "0.3", "views": [}'), {},
                          "not valid JSON"),
    "openmvg fisheye": (file_case("sfm_data.json", json.dumps(OPENMVG_FISHEYE)), {}, "fisheye"),
    "openmvg missing field": (file_case("sfm_data.json", '{"sfm_data_version": "0.3", "views": []}'), {},
                              "'intrinsics' list"),
    "openmvs truncated": (openmvs_case(cut=-30), {}, "truncated at byte"),
    "openmvs count beyond file": (openmvs_case(cut=200), {}, "claims 2 cameras"),
    "openmvs version": (openmvs_case(version=9), {}, "stream version 9"),
    "openmvs boost": (file_case("scene.mvs", b"\x16\0\0\0\0\0\0\0serialization::archive\x11\0"), {},
                      "Boost archive"),
    "native version": (file_case("c.json", '{"format": "tracemap-cameras", "version": 7, "cameras": []}'), {},
                       "version"),
    "native field": (file_case("c.json", '{"format": "tracemap-cameras", "version": 1, "cameras": [{"name": "a"}]}'),
                     {}, r"cameras\[0\]: missing field\(s\) width"),
    "native shape": (file_case("c.json", json.dumps({"format": "tracemap-cameras", "version": 1, "cameras": [
        {"name": "a", "width": 10, "height": 10, "K": [1, 2], "distortion": [], "R": np.eye(3).tolist(),
         "t": [0, 0, 0]}]})), {}, r"cameras\[0\] \('a'\): field 'K' is \[1, 2\], expected 3 rows of 3 finite numbers"),
    "unknown file": (file_case("notes.txt", "hello\n"), {}, "unrecognised camera file"),
    "colmap duplicate camera id": (colmap_case("1 PINHOLE 640 480 500 500 320 240\n1 PINHOLE 800 600 500 500 400 300\n"),
                                   {}, "cameras.txt: line 2: CAMERA_ID 1 appears twice"),
    "colmap duplicate image id": (colmap_case("1 PINHOLE 640 480 500 500 320 240\n",
                                              "1 1 0 0 0 0 0 0 1 a.jpg\n\n1 1 0 0 0 0 0 0 1 b.jpg\n\n"),
                                  {}, "images.txt: line 3: IMAGE_ID 1 appears twice"),
    "colmap image id not an integer": (colmap_case("1 PINHOLE 640 480 500 500 320 240\n", "x 1 0 0 0 0 0 0 1 a.jpg\n"),
                                       {}, r"line 1: expected IMAGE_ID \(an integer\), found 'x'"),
    "colmap binary duplicate camera id": (colmap_binary_edit("cameras.bin", 8 + 24 + 3 * 8, struct.pack("<i", 1)), {},
                                          "cameras.bin: byte 56: CAMERA_ID 1 appears twice"),
    "colmap binary duplicate image id": (colmap_binary_edit("images.bin", 110, struct.pack("<i", 1)), {},  # image 2
                                         "images.bin: byte 110: IMAGE_ID 1 appears twice"),
    "colmap binary nan parameter": (colmap_binary_edit("cameras.bin", 8 + 24, struct.pack("<d", np.nan)), {},
                                    "byte 32: expected 3 SIMPLE_PINHOLE parameters as finite numbers, found .*nan"),
    "nvm huge radial": (file_case("m.nvm", "NVM_V3\n1\n" + NVM_CAMERA.replace(" 0.1 0", " 1e100 0")),
                        {"image_sizes": (1920, 1080)}, r"camera 'a\.jpg': radial distortion r = 1e\+100 is out of range "
                                                       r"for this 1920×1080 photo at f = 1000 px: expected -0\.2748 < r "
                                                       r"<= 7\.418"),
    "nvm radial beyond opencv": (file_case("m.nvm", "NVM_V3\n1\n" + NVM_CAMERA.replace(" 0.1 0", " 5 0")),
                                 {"image_sizes": (1920, 1080)}, "camera 'a.jpg' radial distortion r = 5: this radial "
                                                                "distortion cannot be converted to OpenCV's model"),
    "openmvs resolution half given": (openmvs_resolution(1600, 0), {}, "does not store image sizes"),
}


@pytest.mark.parametrize("case", list(BAD_INPUTS))
def test_bad_input_names_the_file(tmp_path, case):
    write, options, expected = BAD_INPUTS[case]
    path = write(tmp_path)
    with pytest.raises(InputError) as error:
        read_cameras(path, **options)
    message = str(error.value)
    assert path.name in message or str(path.parent) in message
    assert error.match(expected)


def test_bundler_camera_count_beyond_the_file_allocates_nothing(tmp_path):
    """A corrupt count (10^20 would exhaust the memory) fails at the end of the file, before names are made."""
    path = tmp_path / "x.out"
    path.write_text(BUNDLE.replace("\n1 0\n", "\n1000000 0\n"))
    tracemalloc.start()
    with pytest.raises(InputError, match=r"x\.out: the file ends after line 7; expected camera 1"):
        read_cameras(path, image_sizes=(10, 10))
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 10e6  # a million camera names take 70 MB


def test_folder_without_a_model_is_reported(tmp_path):
    with pytest.raises(InputError, match="no cameras.txt/images.txt"):
        read_cameras(tmp_path)


OPENMVG_FIELDS = {  # field → where it is in write_openmvg's file, and what the message calls its owner
    "view key": (lambda d: d["views"][0], "key", "view"),
    "id_view": (lambda d: d["views"][0]["value"]["ptr_wrapper"]["data"], "id_view", "view 'view0.jpg'"),
    "id_intrinsic": (lambda d: d["views"][0]["value"]["ptr_wrapper"]["data"], "id_intrinsic", "view 'view0.jpg'"),
    "id_pose": (lambda d: d["views"][0]["value"]["ptr_wrapper"]["data"], "id_pose", "view 'view0.jpg'"),
    "view pointer id": (lambda d: d["views"][0]["value"]["ptr_wrapper"], "id", "view 0"),
    "intrinsic key": (lambda d: d["intrinsics"][0], "key", "intrinsic"),
    "polymorphic_id": (lambda d: d["intrinsics"][0]["value"], "polymorphic_id", "intrinsic 0"),
    "intrinsic width": (lambda d: d["intrinsics"][0]["value"]["ptr_wrapper"]["data"], "width",
                        r"intrinsic 0 \(pinhole_brown_t2\)"),
    "extrinsic key": (lambda d: d["extrinsics"][0], "key", "extrinsic"),
}


@pytest.mark.parametrize("value", ["0", 0.5, 640.5, None, [0], True, -1, 2**32])
@pytest.mark.parametrize("field", list(OPENMVG_FIELDS))
def test_openmvg_ids_of_the_wrong_type_are_refused(tmp_path, field, value):
    path = tmp_path / "sfm_data.json"
    write_openmvg(path)
    data = json.loads(path.read_text())
    owner, key, where = OPENMVG_FIELDS[field]
    owner(data)[key] = value
    path.write_text(json.dumps(data))
    with pytest.raises(InputError, match=rf"sfm_data\.json: {where}: field '{key}' is .*, expected an integer "
                                         "from 0 to 4294967295"):
        read_cameras(path)


@pytest.mark.parametrize("edit, expected", [
    (lambda d: d["intrinsics"].append(d["intrinsics"][0]), "intrinsic key 0 appears twice"),
    (lambda d: d["extrinsics"].append(d["extrinsics"][0]), "extrinsic key 0 appears twice"),
    (lambda d: d["views"][0]["value"]["ptr_wrapper"]["data"].update(filename=None),
     "view 0: field 'filename' is None, expected a string"),
    (lambda d: d.update(root_path=7), "sfm_data: field 'root_path' is 7, expected a string"),
    (lambda d: d["intrinsics"][0]["value"]["ptr_wrapper"]["data"].update(focal_length=[1250.0]),
     r"focal_length: expected 1 finite numbers, found \[\[1250\.0\]\]"),
    (lambda d: d["intrinsics"][0]["value"]["ptr_wrapper"]["data"].update(principal_point=["801", 598.7]),
     "principal_point: expected 2 finite numbers"),
    (lambda d: d["extrinsics"][0]["value"].update(center=[1e300, 0.0, 0.0]),
     r"camera 'view0\.jpg': centre .* is beyond 1e\+09 from the origin"),
])
def test_openmvg_malformed_fields_are_refused(tmp_path, edit, expected):
    path = tmp_path / "sfm_data.json"
    write_openmvg(path)
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))
    with pytest.raises(InputError, match=r"sfm_data\.json: .*" + expected):
        read_cameras(path)


NATIVE_CAMERA = {"name": "a", "width": 640, "height": 480, "K": [[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]],
                 "distortion": [-0.1, 0.01], "R": np.eye(3).tolist(), "t": [0.0, 0.0, 5.0], "image_path": "a.jpg"}


@pytest.mark.parametrize("field, value, expected", [
    ("width", 640.5, "field 'width' is 640.5, expected a positive integer"),
    ("width", "640", "field 'width' is '640', expected a positive integer"),
    ("width", True, "field 'width' is True, expected a positive integer"),
    ("height", 0, "field 'height' is 0, expected a positive integer"),
    ("height", 10**7, "image height is 10000000, expected an integer from 1 to 1000000 px"),
    ("K", [[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, True]], "field 'K' is .*, expected 3 rows of 3 finite"),
    ("K", [[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 2]], r"K is .*, expected \[\[fx, s, cx\], \[0, fy, cy\], "
                                                            r"\[0, 0, 1\]\]"),
    ("K", [[1e300, 0, 319.5], [0, 1e300, 239.5], [0, 0, 1]], r"K = .* has a value beyond 1e\+09 px"),
    ("distortion", [[0.1]], "field 'distortion' is .*, expected at most 8 finite numbers"),
    ("distortion", [float("nan")], "field 'distortion' is .*, expected at most 8 finite numbers"),
    ("distortion", [0.0] * 9, "field 'distortion' is .*, expected at most 8 finite numbers"),
    ("R", [[1, 0, 0], [0, 1, 0]], "field 'R' is .*, expected 3 rows of 3 finite numbers"),
    ("t", [0, 0, "5"], "field 't' is .*, expected 3 finite numbers"),
    ("t", [1e300, 0, 0], r"centre .* is beyond 1e\+09 from the origin"),
    ("image_path", 5, "field 'image_path' is 5, expected a string or null"),
])
def test_native_fields_must_have_their_types(tmp_path, field, value, expected):
    path = tmp_path / "cameras.json"
    path.write_text(json.dumps({"format": "tracemap-cameras", "version": 1,
                                "cameras": [dict(NATIVE_CAMERA, **{field: value})]}))
    with pytest.raises(InputError, match=r"cameras\.json: (cameras\[0\] \('a'\)|camera 'a'): " + expected):
        read_cameras(path)


def test_native_camera_name_and_huge_integers(tmp_path):
    path = tmp_path / "cameras.json"
    path.write_text(json.dumps({"format": "tracemap-cameras", "version": 1, "cameras": [dict(NATIVE_CAMERA, name=5)]}))
    with pytest.raises(InputError, match=r"cameras\[0\]: field 'name' is 5, expected a non-empty string"):
        read_cameras(path)
    text = json.dumps({"format": "tracemap-cameras", "version": 1, "cameras": [dict(NATIVE_CAMERA, t=[0, 0, 7])]})
    path.write_text(text.replace("[0, 0, 7]", "[0, 0, 1" + "0" * 400 + "]"))  # too large for a float
    with pytest.raises(InputError, match="field 't' is .*, expected 3 finite numbers"):
        read_cameras(path)


@pytest.mark.parametrize("sensor, chunk, translation, expected", [
    (M3M, "<transform><scale>1e300</scale></transform>", 0.0,
     r"chunk transform <scale>: 1e\+300, expected a number from 1e-09 to 1e\+09"),
    (M3M, "<transform><scale>1e-300</scale></transform>", 0.0, "chunk transform <scale>: 1e-300, expected"),
    (M3M, "<transform><translation>1e300 0 0</translation></transform>", 0.0,
     r"chunk transform <translation>: \[1e\+300, 0\.0, 0\.0\], expected coordinates within ±1e\+09"),
    (M3M, "", 1e300, r"camera 'a' <transform> translation: \[1e\+300, .*\], expected coordinates within ±1e\+09"),
    (M3M, "<transform><translation>9e8 0 0</translation><scale>1e3</scale></transform>", 1e6,
     r"camera 'a': centre .* is beyond 1e\+09 from the origin"),  # each value fine, their product is not
    (dict(M3M, k4=1e50), "", 0.0, r"sensor 0 \(K1\.\.K4 = .*, 1e\+50\): the radial distortion magnifies the image "
                                  "corner's distance from the centre more than 10 times"),
    (dict(M3M, k4=1e308), "", 0.0, ".*magnifies the image corner's distance from the centre more than 10 times"),
    (dict(M3M, k1=1e100), "", 0.0, ".*magnifies the image corner's distance from the centre more than 10 times"),
    (dict(M3M, f=-1.0), "", 0.0, r"sensor 0: K = .*, expected positive focal lengths and values within 1e\+09 px"),
    (dict(M3M, cx=1e300), "", 0.0, r"sensor 0: K = .*, expected positive focal lengths and values within 1e\+09 px"),
])
def test_metashape_values_beyond_any_survey_are_refused(tmp_path, sensor, chunk, translation, expected):
    T = np.eye(4)
    T[0, 3] = translation
    path = write_metashape(tmp_path / "cameras.xml", sensor, [("a", T)], chunk)
    with pytest.raises(InputError, match=r"cameras\.xml: " + expected):
        read_cameras(path)


def test_legitimate_foreign_distortion_still_loads(tmp_path):
    """The bounds leave real lenses alone: a strong K4 and VisualSFM's r near both ends of its range."""
    path = write_metashape(tmp_path / "cameras.xml", dict(M3M, k1=-0.3, k4=0.05), [("a", np.eye(4))])
    assert read_cameras(path)["a"].distortion[0] < 0
    for r in (-0.1, 0.3, 1.0):
        nvm = tmp_path / "m.nvm"
        nvm.write_text("NVM_V3\n1\n" + NVM_CAMERA.replace(" 0.1 0", f" {r} 0"))
        assert read_cameras(nvm, image_sizes=(1920, 1080))["a.jpg"].K[0, 0] > 0
