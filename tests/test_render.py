import numpy as np
import pytest
from PIL import Image

from engine.cli import main
from engine.project import Project
from engine.errors import InputError
from engine.render import LEGEND_ROW_PX, PALETTE, SceneStyle, legend_entries
from engine.traces import Trace3D


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
    with pytest.raises(InputError, match="expected one of set"):
        SceneStyle(color_by="rainbow")
    with pytest.raises(InputError, match="16..16384"):
        SceneStyle(size=(4, 4))
    assert len(PALETTE) >= 8


def trace(id, set_id=-1, method="", ends=("", "")):
    points = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]])
    return Trace3D(id, points, np.zeros((3, 2)), np.zeros(3, int), np.zeros(3, int), ("a",), set_id=set_id,
                   method=method, term_start=ends[0], term_end=ends[1])


def test_legend_names_each_class_drawn_with_its_count():
    traces = [trace(1, 0, "eigen", ("B", "C")), trace(2, 2, "probabilistic", ("B", "T")),
              trace(3, -1, "eigen", ("C", "C")), trace(4, 2, "manual", ("X", ""))]
    assert legend_entries(traces, "set") == [("set 0 (1)", tuple(PALETTE[0])), ("set 2 (2)", tuple(PALETTE[2])),
                                             ("non-systematic (1)", (235, 235, 235))]
    assert [label for label, _ in legend_entries(traces, "termination")] == [
        "B blind (2)", "T abutting (1)", "X crossing (1)", "C censored (3)", "unclassified (1)"]
    assert [label for label, _ in legend_entries(traces, "method", {2, 9})] == [
        "eigen (2)", "probabilistic (1)", "manual (1)", "selected (1)"]
    assert legend_entries(traces, "method", {2})[-1][1] == (255, 0, 255)
    # before orient no trace has a set: "no set", not "non-systematic"
    assert legend_entries([trace(1), trace(2)], "set") == [("no set (2)", (235, 235, 235))]
    # components repeat the palette and maps have their scalar bar: no key
    assert legend_entries(traces, "component") == legend_entries(traces, "p21") == []
    assert legend_entries([], "set") == []


def legend_box(image, entries):
    """The upper right corner that holds a legend of `entries` (as `engine.render._legend` places it)."""
    h, w = image.shape[:2]
    rows = len(entries) * LEGEND_ROW_PX
    width = (2.2 + 0.62 * max(len(label) for label, _ in entries)) * LEGEND_ROW_PX
    return image[int(0.02 * h):int(0.02 * h + rows), int(0.98 * w - width):int(0.98 * w)]


def test_render_draws_the_key_of_the_colours_unless_told_not_to(quick_demo, tmp_path):
    project = quick_demo / "demo.tracemap"
    with Project.open(project) as p:
        entries = legend_entries(p.traces3d(), "set")
    assert len(entries) >= 2
    shots = {}
    for name, extra in (("key", []), ("bare", ["--no-legend"])):
        shots[name] = tmp_path / f"{name}.png"
        assert main(["render", str(project), "-o", str(shots[name]), "--size", "800", "500", *extra]) == 0
    key, bare = (legend_box(np.asarray(Image.open(shots[n]).convert("RGB")).astype(int), entries)
                 for n in ("key", "bare"))
    black = lambda box: np.mean(np.all(box < 60, axis=-1))  # noqa: E731
    # the labels: measured 3.4% of the box at 800×500, none without the key (the box is sky there)
    assert black(key) > 0.02 and black(bare) < 0.005, (black(key), black(bare))
    for rgb in {rgb for _, rgb in entries} - {(235, 235, 235)}:  # each set's swatch: measured 16 and 32 px
        assert np.sum(np.all(np.abs(key - rgb) <= 30, axis=-1)) >= 8
        assert np.sum(np.all(np.abs(bare - rgb) <= 30, axis=-1)) == 0


def displayed(plotter, points):
    """Pixel (u, v) of world points as VTK draws them (display x, y: origin bottom-left, pixel corners)."""
    renderer, height = plotter.renderer, plotter.window_size[1]
    out = []
    for p in points:
        renderer.SetWorldPoint(*p, 1.0)
        renderer.WorldToDisplay()
        x, y, _ = renderer.GetDisplayPoint()
        out.append((x - 0.5, height - y - 0.5))
    return np.array(out)


@pytest.mark.parametrize("window", [None, (900, 450)])
def test_a_view_from_a_photo_draws_each_point_where_the_photo_shows_it(quick_demo, window):
    """Against `Camera.project` (the oracle every reader is tested with), with the principal point moved well
    off centre; in a window of another aspect the photo's frame fits its height, centred."""
    import pyvista as pv

    from engine.cameras import Camera
    from engine.render import look_from

    with Project.open(quick_demo / "demo.tracemap") as p:
        mesh, camera = p.load_mesh(), p.cameras()["photo_02"]
    K = camera.K.copy()
    K[:2, 2] += (37.3, -21.1)
    camera = Camera("off centre", camera.width, camera.height, K, camera.distortion, camera.R, camera.t)
    size = window or (camera.width, camera.height)
    plotter = pv.Plotter(off_screen=True, window_size=list(size))
    try:
        look_from(plotter, camera, mesh)
        uv = camera.project(mesh.vertices[::101])
        inside = np.all((uv > 0) & (uv < (camera.width, camera.height)), axis=1)
        assert inside.sum() > 100
        scale = size[1] / camera.height
        expected = (uv[inside] + 0.5 - np.array([camera.width, camera.height]) / 2) * scale \
            + np.array(size) / 2 - 0.5
        np.testing.assert_allclose(displayed(plotter, mesh.vertices[::101][inside]), expected, atol=1e-6)
    finally:
        plotter.close()


def test_render_from_a_photo_shows_the_rock_where_the_photo_does(quick_demo, tmp_path):
    from engine.raytrace import RayTracer

    shot = tmp_path / "from2.png"
    assert main(["render", str(quick_demo / "demo.tracemap"), "-o", str(shot), "--view", "photo_02",
                 "--no-legend"]) == 0
    with Project.open(quick_demo / "demo.tracemap") as p:
        mesh, camera = p.load_mesh(), p.cameras()["photo_02"]
    image = np.asarray(Image.open(shot).convert("RGB"))
    assert image.shape == (camera.height, camera.width, 3)  # the photo's size: under 1600 px a side
    v, u = np.mgrid[:camera.height, :camera.width]
    uv = np.column_stack([u.ravel(), v.ravel()]).astype(float)
    hit = RayTracer(mesh.vertices, mesh.faces).intersect(camera.centre, camera.pixel_rays(uv)).hit
    rock, drawn = hit.reshape(camera.height, camera.width), ~np.all(image == 255, axis=-1)
    iou = np.sum(rock & drawn) / np.sum(rock | drawn)
    assert iou > 0.99, iou  # measured 0.9976: 515 of 214,052 px differ, along the outline


@pytest.mark.parametrize("option", ["--view", "--drape"])
def test_render_from_an_unknown_photo_names_the_photos(quick_demo, tmp_path, capsys, option):
    assert main(["render", str(quick_demo / "demo.tracemap"), "-o", str(tmp_path / "x.png"),
                 option, "photo_9"]) == 2
    assert f"{option} 'photo_9': no photo of that name; the photos are photo_01, photo_02, photo_03" \
        in capsys.readouterr().err
    assert not (tmp_path / "x.png").exists()


def test_a_photo_draped_and_seen_from_itself_is_the_photo(quick_demo, tmp_path):
    """Rock pixels away from the traces and the outline: the render gives back the photo (texture lookups
    interpolated on each face; occluded faces keep the mesh colours)."""
    import cv2

    from engine.raytrace import RayTracer

    shot = tmp_path / "draped.png"
    assert main(["render", str(quick_demo / "demo.tracemap"), "-o", str(shot), "--view", "photo_02",
                 "--drape", "photo_02", "--no-legend"]) == 0
    with Project.open(quick_demo / "demo.tracemap") as p:
        mesh, camera, traces = p.load_mesh(), p.cameras()["photo_02"], p.traces3d()
        photo = np.asarray(Image.open(p.image_path("photo_02")).convert("RGB")).astype(int)
    v, u = np.mgrid[:camera.height, :camera.width]
    rays = camera.pixel_rays(np.column_stack([u.ravel(), v.ravel()]).astype(float))
    rock = RayTracer(mesh.vertices, mesh.faces).intersect(camera.centre, rays).hit.reshape(v.shape)
    drawn = np.zeros(v.shape, np.uint8)
    for t in traces:
        uv = np.rint(camera.project(t.points)).astype(int)
        uv = uv[np.all((uv >= 0) & (uv < (camera.width, camera.height)), axis=1)]
        drawn[uv[:, 1], uv[:, 0]] = 1
    kept = cv2.erode(rock.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool) \
        & ~cv2.dilate(drawn, np.ones((11, 11), np.uint8)).astype(bool)
    difference = np.abs(np.asarray(Image.open(shot).convert("RGB")).astype(int) - photo).max(axis=-1)[kept]
    assert kept.sum() > 100_000
    # measured: median 2, 95th percentile 5 grey levels
    assert np.median(difference) <= 3 and np.percentile(difference, 95) <= 8, np.percentile(difference, [50, 95])


def test_a_view_from_a_distorted_photo_draws_the_rock_where_the_photo_shows_it(quick_demo):
    """VTK draws pinhole views: a photo with lens distortion is drawn on a wider pinhole canvas and resampled
    through its distortion. Oracle: the photo's own rays (`Camera.pixel_rays`, undistorted by Newton's
    method), ray traced."""
    from engine.cameras import Camera
    from engine.raytrace import RayTracer
    from engine.render import photo_view

    with Project.open(quick_demo / "demo.tracemap") as p:
        mesh, pinhole, traces = p.load_mesh(), p.cameras()["photo_02"], p.traces3d()
    camera = Camera("barrel", pinhole.width, pinhole.height, pinhole.K, np.array([-0.2, 0.05, 0.001, -0.002]),
                    pinhole.R, pinhole.t)  # corners move about 60 px
    v, u = np.mgrid[:camera.height, :camera.width]
    rays = camera.pixel_rays(np.column_stack([u.ravel(), v.ravel()]).astype(float))
    rock = RayTracer(mesh.vertices, mesh.faces).intersect(camera.centre, rays).hit.reshape(v.shape)
    style = SceneStyle(size=(camera.width, camera.height), legend=False)

    def overlap(view):
        drawn = ~np.all(photo_view(mesh, traces, style, view) == 255, axis=-1)
        return np.sum(rock & drawn) / np.sum(rock | drawn)

    # measured 0.9945 (1,089 px differ, along the outline); the same photo drawn as a pinhole: 0.911
    assert overlap(camera) > 0.99 > 0.95 > overlap(Camera("pinhole", camera.width, camera.height, camera.K,
                                                          np.zeros(0), camera.R, camera.t))
    keyed = photo_view(mesh, traces, SceneStyle(size=style.size), camera)  # the legend upright, on top
    entries = legend_entries(traces, "set")
    assert np.mean(np.all(legend_box(keyed.astype(int), entries) < 60, axis=-1)) > 0.02
    with pytest.raises(InputError, match=r"--size 800 500: a view from barrel is drawn in its frame, 640×480; "
                                         r"e\.g\. --size 800 600"):
        photo_view(mesh, traces, SceneStyle(size=(800, 500)), camera)


def changed_by(project_path, tmp_path, option: str) -> np.ndarray:
    """The pixels of the view from photo_02 that `render option` changes (H, W) bool."""
    shots = {}
    for name, extra in (("with", [option]), ("without", [])):
        shots[name] = tmp_path / f"{name}.png"
        assert main(["render", str(project_path), "-o", str(shots[name]), "--view", "photo_02", "--no-legend",
                     *extra]) == 0
    return np.any(np.asarray(Image.open(shots["with"]).convert("RGB")).astype(int)
                  != np.asarray(Image.open(shots["without"]).convert("RGB")), axis=-1)


def test_render_draws_the_scanlines_where_the_photo_sees_them(quick_demo, tmp_path, capsys):
    """`--scanlines`: each scanline drawn along the rock it sampled, seen from a photo: the pixels that change
    against the same render without them lie along that rock's projection in the photo, or on a crossing."""
    import shutil

    from engine.analysis import measure_scanlines

    shutil.copytree(quick_demo, tmp_path / "demo")
    project_path = tmp_path / "demo" / "demo.tracemap"
    with Project.open(project_path) as p:
        mesh, camera, origin = p.load_mesh(), p.cameras()["photo_02"], p.origin
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    mid = 0.5 * (lo + hi)
    ends = [mesh.vertices[np.argmin(np.linalg.norm(mesh.vertices[:, [0, 2]] - [x, mid[2]], axis=1))] + origin
            for x in (lo[0] + 0.25 * (hi[0] - lo[0]), lo[0] + 0.75 * (hi[0] - lo[0]))]
    with Project.open(project_path) as p:  # the demo's own scanline goes: only the one laid here is drawn
        for line in p.scanlines():
            p.remove_scanline(line.id)
    assert main(["scanline", str(project_path), "--from", *map(str, ends[0]), "--to", *map(str, ends[1])]) == 0
    changed = changed_by(project_path, tmp_path, "--scanlines")
    with Project.open(project_path) as p:
        (measure,) = measure_scanlines(p)
    drawn = camera.project(np.vstack([measure.rock.section.reshape(-1, 3), [c.point for c in measure.crossings]]))
    v, u = np.nonzero(changed)
    gap = np.min(np.linalg.norm(np.column_stack([u, v])[:, None] - drawn[None], axis=2), axis=1)
    assert changed.sum() > 500 and np.mean(gap < 8) > 0.99  # on the rock (4 px wide) or a mark (12 px)
    with Project.open(project_path) as p:
        p.remove_scanline(p.scanlines()[0].id)
    assert main(["render", str(project_path), "-o", str(tmp_path / "x.png"), "--scanlines"]) == 2
    assert "--scanlines: the project has no scanlines" in capsys.readouterr().err


def test_render_draws_the_scan_circles_where_the_photo_sees_them(quick_demo, tmp_path, capsys):
    """`--scan-circles`: each window's edge on the rock and its marks, seen from a photo: the pixels that change
    against the same render without them lie along the edge's projection in the photo, or on a mark."""
    import shutil

    from engine.analysis import measure_scan_circles

    shutil.copytree(quick_demo, tmp_path / "demo")
    project_path = tmp_path / "demo" / "demo.tracemap"
    with Project.open(project_path) as p:
        mesh, camera, origin = p.load_mesh(), p.cameras()["photo_02"], p.origin
    mid = 0.5 * (mesh.vertices.min(axis=0) + mesh.vertices.max(axis=0))
    centre = mesh.vertices[np.argmin(np.linalg.norm(mesh.vertices[:, [0, 2]] - mid[[0, 2]], axis=1))] + origin
    assert main(["scan-circle", str(project_path), "--at", *map(str, centre), "--radius", "2"]) == 0
    changed = changed_by(project_path, tmp_path, "--scan-circles")
    with Project.open(project_path) as p:
        (window,) = measure_scan_circles(p)
    assert len(window.crossings) > 0
    drawn = camera.project(np.vstack([window.rock.edge.reshape(-1, 3), window.crossings, window.ends, window.cut_ends]))
    v, u = np.nonzero(changed)
    gap = np.min(np.linalg.norm(np.column_stack([u, v])[:, None] - drawn[None], axis=2), axis=1)
    assert changed.sum() > 500 and np.mean(gap < 8) > 0.99  # on the edge (4 px wide) or a mark (12 px)
    # and the edge is drawn whole where the photo sees the rock (drawn in a plain colour, VTK hid a quarter
    # of it in pieces: 0.75 of the segments shown)
    middles = np.rint(camera.project(window.rock.edge.mean(axis=1))).astype(int)
    near = [changed[max(v - 2, 0):v + 3, max(u - 2, 0):u + 3].any() for u, v in middles]
    assert np.mean(near) > 0.9
    with Project.open(project_path) as p:
        p.remove_scan_circle(window.circle.id)
    assert main(["render", str(project_path), "-o", str(tmp_path / "x.png"), "--scan-circles"]) == 2
    assert "--scan-circles: the project has no scan circles" in capsys.readouterr().err
