import numpy as np
import pytest
from PIL import Image

from engine.cli import main
from engine.project import Project
from engine.render import PALETTE, SceneStyle


def colour_fraction(path, rgb, tol=30):
    image = np.asarray(Image.open(path).convert("RGB")).astype(int)
    return np.mean(np.all(np.abs(image - np.asarray(rgb)) <= tol, axis=-1))


def test_render_shows_mesh_and_traces(quick_demo, tmp_path):
    shot = tmp_path / "set.png"
    # colour by component: give the traces components so the palette must appear
    with Project.open(quick_demo / "demo.tracemap") as p:
        traces = p.traces3d()
    assert main(["render", str(quick_demo / "demo.tracemap"), "-o", str(shot), "--size", "640", "400",
                 "--color-by", "termination"]) == 0
    image = np.asarray(Image.open(shot).convert("RGB"))
    assert image.shape == (400, 640, 3)
    background = np.all(image == 255, axis=-1).mean()
    assert 0.05 < background < 0.95  # the mesh fills part of the frame
    rock = np.mean((image[..., 0] > image[..., 2] + 20))  # the synthetic rock is orange-brown
    assert rock > 0.05
    assert colour_fraction(shot, (40, 40, 40), tol=25) > 0.001  # dark trace lines
    assert len(traces) > 0


def test_render_by_map_needs_the_map(quick_demo, tmp_path, capsys):
    assert main(["render", str(quick_demo / "demo.tracemap"), "-o", str(tmp_path / "p21.png"),
                 "--color-by", "p21", "--map", "p21:set99"]) == 2
    err = capsys.readouterr().err
    assert "no map named 'p21:set99'" in err and "available: p21" in err
    assert not (tmp_path / "p21.png").exists()


def test_render_with_a_vertex_map(quick_demo, tmp_path):
    from engine.render import render_to_file

    with Project.open(quick_demo / "demo.tracemap") as p:
        mesh = p.load_mesh()
        values = mesh.vertices[:, 0] - mesh.vertices[:, 0].min()
        render_to_file(tmp_path / "map.png", mesh, p.traces3d(), SceneStyle(color_by="p21", size=(320, 200)),
                       vertex_map=values)
    image = np.asarray(Image.open(tmp_path / "map.png").convert("RGB")).astype(int)
    # viridis runs from purple to yellow
    assert np.mean((image[..., 2] > 100) & (image[..., 1] < 80)) > 0.005
    assert np.mean((image[..., 0] > 180) & (image[..., 1] > 180) & (image[..., 2] < 100)) > 0.005


def test_bad_style_is_refused():
    from engine.errors import InputError

    with pytest.raises(InputError, match="expected one of set"):
        SceneStyle(color_by="rainbow")
    with pytest.raises(InputError, match="16..16384"):
        SceneStyle(size=(4, 4))
    assert len(PALETTE) >= 8
