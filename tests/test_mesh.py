import locale
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
import trimesh

from engine.errors import InputError
from engine.mesh import Mesh, first_hit, read_mesh
from engine.raytrace import RayTracer
from tests.scenes import grid_wall, wavy, wavy_wall_with_post

UTM = np.array([512_345.678, 6_123_456.789, 812.345])


@pytest.fixture
def wall_mesh():
    v, f = grid_wall(width=4.0, height=2.0, step=0.5, offset=UTM)
    colors = (np.arange(len(v) * 3).reshape(-1, 3) % 256).astype(np.uint8)
    return trimesh.Trimesh(v, f, vertex_colors=colors, process=False)


def write_double_ply(path, vertices, faces):
    lines = ["ply", "format ascii 1.0", f"element vertex {len(vertices)}", "property double x",
             "property double y", "property double z", f"element face {len(faces)}",
             "property list uchar int vertex_indices", "end_header"]
    lines += [" ".join(repr(float(c)) for c in p) for p in vertices] + [f"3 {a} {b} {c}" for a, b, c in faces]
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("suffix", [".ply", ".obj", ".off"])
def test_utm_coordinates_round_trip_to_the_millimetre(tmp_path, wall_mesh, suffix):
    path = tmp_path / f"wall{suffix}"
    if suffix == ".ply":  # trimesh writes float32 PLY; surveys at UTM scale need doubles
        write_double_ply(path, wall_mesh.vertices, wall_mesh.faces)
    else:
        wall_mesh.export(path)
    mesh = read_mesh(path)
    assert len(mesh.faces) == len(wall_mesh.faces)
    np.testing.assert_allclose(mesh.origin, np.round(UTM + [2.0, 0.0, 1.0]))
    assert np.abs(mesh.vertices).max() < 5  # the local frame is small ...
    assert np.abs(mesh.world_vertices - wall_mesh.vertices).max() < 1e-3  # ... and world comes back
    assert mesh.face_areas.sum() == pytest.approx(8.0, rel=1e-6)


@pytest.mark.parametrize("suffix", [".ply", ".stl", ".glb"])
def test_binary_float32_formats(tmp_path, suffix):
    v, f = grid_wall(width=4.0, height=2.0, step=0.5)
    trimesh.Trimesh(v, f, process=False).export(tmp_path / f"wall{suffix}")
    mesh = read_mesh(tmp_path / f"wall{suffix}")
    assert len(mesh.faces) == len(f)
    assert mesh.face_areas.sum() == pytest.approx(8.0, rel=1e-6)


def test_ply_keeps_vertex_colours(tmp_path, wall_mesh):
    path = tmp_path / "wall.ply"
    wall_mesh.export(path)
    mesh = read_mesh(path)
    np.testing.assert_array_equal(mesh.vertex_colors, wall_mesh.visual.vertex_colors[:, :3])


def test_vtk_polydata_with_quads_is_triangulated(tmp_path):
    import pyvista as pv

    plane = pv.Plane(i_resolution=4, j_resolution=3)  # quads
    path = tmp_path / "plane.vtp"
    plane.save(path)
    mesh = read_mesh(path)
    assert mesh.faces.shape == (24, 3)
    assert mesh.face_areas.sum() == pytest.approx(1.0)


def test_obj_quads_are_triangulated(tmp_path):
    path = tmp_path / "quad.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n")
    mesh = read_mesh(path)
    assert mesh.faces.shape == (2, 3) and mesh.face_areas.sum() == pytest.approx(1.0)


def test_geometry_helpers():
    v, f = grid_wall(width=2.0, height=1.0, step=0.5)
    mesh = Mesh(v, f)
    assert mesh.vertex_areas.sum() == pytest.approx(2.0)
    np.testing.assert_allclose(mesh.face_normals, np.tile([0.0, -1.0, 0.0], (len(f), 1)), atol=1e-12)
    # a 4 × 2 grid of squares has a rim of 2·(4 + 2) edges
    assert len(mesh.boundary_edges) == 12


def test_face_tree_is_built_once_and_shared_by_threads():
    v, f = grid_wall(width=2.0, height=1.0, step=0.1)
    mesh = Mesh(v, f)
    with ThreadPoolExecutor(4) as pool:
        trees = list(pool.map(lambda _: mesh.face_tree, range(8)))
    assert all(tree is mesh.face_tree for tree in trees)
    np.testing.assert_array_equal(mesh.face_tree.data, mesh.face_centroids)


def test_first_hit_finds_what_the_ray_tracer_finds():
    # a rough wall of 2 cm faces with a post of 0.5–6 m faces in front of it (faces far larger than the step)
    v, f, camera = wavy_wall_with_post(spacing=0.02)
    mesh = Mesh(v, f)
    rng = np.random.default_rng(0)
    uv = rng.uniform([0, 0], [camera.width, camera.height], (300, 2))
    directions = camera.pixel_rays(uv)
    expected = RayTracer(v, f).intersect(camera.centre, directions)
    assert 0 < expected.hit.sum() < len(uv)  # the rays hit the wall, the post, and miss beside them
    for d, hit, point in zip(directions, expected.hit, expected.points):
        found = first_hit(mesh, camera.centre, d)
        if hit:
            np.testing.assert_allclose(found, point, atol=1e-5)  # Embree traces in float32
        else:
            assert found is None
    assert first_hit(mesh, camera.centre, -directions[0]) is None  # the wall is behind this ray
    assert first_hit(mesh, [10.0, -8.0, 2.0], [0.0, 1.0, 0.0]) is None  # beside the wall's box
    np.testing.assert_allclose(first_hit(mesh, [2.0, -8.0, 2.0], [0.0, 1.0, 0.0]), [2.0, wavy(2.0, 2.0), 2.0])


@pytest.mark.parametrize("content, message", [
    ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
     "end_header\n0 0 0\n1 0 0\n0 1 0\n", "no triangle faces"),
    ("v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n", "NaN"),
    ("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n", "degenerate"),
    ("", "no triangle faces"),
    ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nelement face 1\n"
     "property list uchar int vertex_indices\nend_header\n0 0\n1 0\n0 1\n3 0 1 2\n", "it has no 'z' field"),
])
def test_bad_meshes_name_the_file(tmp_path, content, message):
    suffix = ".ply" if content.startswith("ply") else ".obj"
    path = tmp_path / f"bad{suffix}"
    path.write_text(content)
    with pytest.raises(InputError, match=message) as err:
        read_mesh(path)
    assert str(path) in str(err.value)


def test_missing_and_unknown_files(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_mesh(tmp_path / "nope.ply")
    (tmp_path / "mesh.xyz").write_text("0 0 0\n")
    with pytest.raises(InputError, match="unknown mesh format"):
        read_mesh(tmp_path / "mesh.xyz")


@pytest.mark.parametrize("suffix", [".obj", ".glb"])
def test_texture_is_kept_for_display(tmp_path, suffix):
    from PIL import Image

    v, f = grid_wall(width=2.0, height=1.0, step=0.5)
    uv = np.column_stack([v[:, 0] / 2.0, v[:, 2] / 1.0])
    image = Image.fromarray(np.random.default_rng(0).integers(0, 255, (16, 32, 3), dtype=np.uint8))
    visual = trimesh.visual.TextureVisuals(uv=uv, image=image)
    trimesh.Trimesh(v, f, visual=visual, process=False).export(tmp_path / f"wall{suffix}")
    mesh = read_mesh(tmp_path / f"wall{suffix}")
    assert mesh.texture_image is not None and mesh.texture_image.shape == (16, 32, 3)
    assert mesh.texture_uv.shape == (len(mesh.vertices), 2)
    # each vertex keeps its own texture coordinate
    order = np.lexsort(np.round(mesh.vertices, 6).T)
    ref = np.lexsort(np.round(v - mesh.origin, 6).T)
    np.testing.assert_allclose(mesh.texture_uv[order], uv[ref], atol=1e-6)


def test_a_damaged_vtk_file_is_one_clear_error_without_vtk_noise(tmp_path, capfd):
    before = locale.setlocale(locale.LC_ALL)
    (tmp_path / "bad.vtp").write_bytes(b"garbage\x00\x01 not a vtp file")
    (tmp_path / "bad.vtk").write_text("# vtk DataFile Version 3.0\nbad\nASCII\nDATASET POLYDATA\nPOINTS 3 float\n0 0\n")
    with pytest.raises(InputError, match="VTK read no points from it: the file is empty or damaged"):
        read_mesh(tmp_path / "bad.vtp")
    with pytest.raises(InputError, match="VTK read no points|no triangle faces"):  # VTK 9.4 reads a point or two
        read_mesh(tmp_path / "bad.vtk")
    out, err = capfd.readouterr()
    assert "ERR|" not in out + err and "vtkXML" not in out + err
    assert locale.setlocale(locale.LC_ALL) == before  # VTK 9.4 left "C" behind: text files then read as ASCII


def test_contour_segments_cut_each_crossed_face_once():
    """Marching triangles: z − 0.5 on two faces of a unit square gives the segment at z = 0.5 on each; a
    contour along the top edge (z = 1) is counted once, by the face below it (the other face only touches it
    at a corner: a segment of no length)."""
    from engine.mesh import contour_segments

    vertices = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    corners = np.array([[0, 1, 2], [0, 2, 3]])
    segments = contour_segments(vertices, corners, vertices[corners][..., 2] - 0.5)
    assert segments.shape == (2, 2, 3)
    np.testing.assert_allclose(segments[..., 2], 0.5)
    np.testing.assert_allclose(sorted(np.abs(segments[:, 1, 0] - segments[:, 0, 0])), [0.5, 0.5])
    through = contour_segments(vertices, corners, vertices[corners][..., 2] - 1.0)
    assert np.linalg.norm(through[:, 1] - through[:, 0], axis=1).sum() == pytest.approx(1.0)
    diagonal = contour_segments(vertices, corners, (vertices[corners] @ [1.0, 0.0, -1.0]))  # x − z through 0 and 2
    np.testing.assert_allclose(np.abs(diagonal[..., 0] - diagonal[..., 2]).max(), 0.0, atol=1e-12)
