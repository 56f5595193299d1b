"""The 3D scene of a project (mesh + traces), built with pyvista: shared by the 3D viewer and `tracemap render`.

Qt-free, so publication screenshots can be made with no display (VTK renders offscreen through EGL or
OSMesa). Everything is drawn in the project's local frame: VTK is float32, like Embree.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from weakref import WeakKeyDictionary

import cv2
import numpy as np
import pyvista as pv
from vtkmodules.vtkCommonCore import vtkLogger
from vtkmodules.vtkRenderingAnnotation import vtkLegendBoxActor
from vtkmodules.vtkRenderingCore import vtkMapper, vtkRenderWindow
from vtkmodules.vtkRenderingFreeType import vtkVectorText
from vtkmodules.vtkRenderingOpenGL2 import vtkTextureObject

from engine.cameras import Camera
from engine.drape import Drape
from engine.errors import InputError
from engine.mesh import Mesh
from engine.scale_bar import ScaleBar
from engine.scan_circle import WindowMeasure
from engine.scanline import Scanline, ScanlineMeasure
from engine.traces import Trace3D

# With no X server VTK first tries X, warns "bad X server connection", then renders through EGL: not news
vtkLogger.SetStderrVerbosity(vtkLogger.VERBOSITY_ERROR)

COLOR_BY = ("set", "component", "termination", "method", "kind", "p21", "p32")
PALETTE = np.array([[228, 26, 28], [55, 126, 184], [77, 175, 74], [152, 78, 163], [255, 127, 0],
                    [255, 255, 51], [166, 86, 40], [247, 129, 191], [0, 206, 209], [128, 128, 0]], np.uint8)
UNASSIGNED = np.array([235, 235, 235], np.uint8)  # set -1, no component, unclassified
TERMINATION_COLORS = {"B": (0, 114, 178), "T": (230, 159, 0), "X": (204, 121, 167), "C": (120, 120, 120),
                      "": (255, 255, 255)}
METHOD_COLORS = {"eigen": (0, 158, 115), "probabilistic": (213, 94, 0), "manual": (86, 180, 233),
                 "": (235, 235, 235)}
KIND_COLORS = {"fracture": (0, 114, 178), "vein": (240, 228, 66), "fault": (213, 94, 0), "bedding": (20, 20, 20)}
SELECTED = (255, 0, 255)
TERMINATION_NAMES = {"B": "B blind", "T": "T abutting", "X": "X crossing", "C": "C censored", "": "unclassified"}
METHOD_NAMES = {"eigen": "eigen", "probabilistic": "probabilistic", "manual": "manual", "": "not oriented"}
TRACE_ACTORS = ("traces", "nodes", "legend")  # the actors `add_traces` makes, by name
DEFAULT_VIEW_ANGLE = 30.0  # degrees, VTK's
MAP_ROWS = 256  # rows of a distorted photo view resampled at a time
LEGEND_ROW_PX = 20  # height of one legend entry in the picture (px)
SCANLINE_COLOR, CROSSING_COLOR = (255, 120, 0), (20, 20, 20)
SCANLINE_ACTORS = ("scanlines", "scanline-crossings")
WINDOW_COLOR = (0, 190, 200)  # scan circles: cyan, apart from the sets' palette and the scanlines' orange
WINDOW_ACTORS = ("scan-circles", "scan-circle-crossings", "scan-circle-ends", "scan-circle-cut-ends")
SCANLINE_WIDTH, MARK_SIZE = 4.0, 12.0  # px


@dataclass
class SceneStyle:
    """How the scene looks: colour scheme, sizes (pixels) and the window size."""

    color_by: str = "set"
    size: tuple[int, int] = (1600, 1000)
    line_width: float = 4.0
    node_size: float = 12.0
    background: str = "white"
    map_name: str | None = None  # the vertex map colouring the mesh, e.g. "p32:set1"; with color_by p21/p32
    # the default is "p21" / "p32", with another color_by the traces keep that scheme over the map
    clim: tuple[float, float] | None = None  # colour range of the vertex map; None: its finite min–max
    selected: set[int] = field(default_factory=set)
    legend: bool = True  # the key of a categorical colouring (`legend_entries`), upper right

    def __post_init__(self) -> None:
        if self.color_by not in COLOR_BY:
            raise InputError(None, f"--color-by {self.color_by!r}: expected one of {', '.join(COLOR_BY)}")
        if min(self.size) < 16 or max(self.size) > 16384:
            raise InputError(None, f"--size {self.size[0]} {self.size[1]}: each side must be in 16..16384 px")


def mesh_polydata(mesh: Mesh, face_mask: np.ndarray | None = None) -> pv.PolyData:
    """The mesh (or the faces of `face_mask`, keeping every vertex) with its colours or texture."""
    poly = _triangles(mesh, face_mask)
    if mesh.vertex_colors is not None:
        poly.point_data["rgb"] = mesh.vertex_colors
    if mesh.texture_uv is not None:
        poly.active_texture_coordinates = mesh.texture_uv
    return poly


def _triangles(mesh: Mesh, face_mask: np.ndarray | None) -> pv.PolyData:
    # regular faces go to VTK as they are (offsets + connectivity): no (F, 4) "3, i, j, k" copy on the GUI
    # thread, and compress, not a boolean index (4× faster on (F, 3))
    faces = mesh.faces if face_mask is None else np.compress(face_mask, mesh.faces, axis=0)
    return pv.PolyData.from_regular_faces(mesh.vertices, faces)


def map_title(name: str) -> str:
    """Scalar-bar title of a vertex map, with its unit: "p32:set1" → "P32 set 1 (m²/m³ = 1/m)"."""
    quantity, _, subset = name.partition(":")
    unit = "m²/m³ = 1/m" if quantity == "p32" else "1/m"  # VTK's font has no superscript minus
    which = f" {subset.replace('set', 'set ')}" if subset else ""
    return f"{quantity.upper()}{which} ({unit})"


def max_texture_size(target: pv.Plotter | vtkRenderWindow) -> int | None:
    """The longest texture side the OpenGL context of a plotter (or of a render window, used on the thread
    that draws it) takes; None until it has drawn a frame."""
    window = target if isinstance(target, vtkRenderWindow) else target.render_window
    size = -1 if window is None else vtkTextureObject.GetMaximumTextureSize(window)
    return size if size > 0 else None


def traces_polydata(traces: list[Trace3D]) -> pv.PolyData:
    """All traces as one PolyData of polylines, with cell data 'trace_id' (so a pick gives the trace)."""
    if not traces:
        return pv.PolyData()
    points = np.vstack([t.points for t in traces])
    sizes = np.array([len(t.points) for t in traces])
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    lines = np.concatenate([np.concatenate([[n], np.arange(s, s + n)]) for s, n in zip(starts, sizes)])
    poly = pv.PolyData(points, lines=lines)
    poly.cell_data["trace_id"] = np.array([t.id for t in traces])
    return poly


def trace_colors(traces: list[Trace3D], color_by: str) -> np.ndarray:
    """One RGB colour (uint8) per trace for the categorical schemes; by set, bedding (in no set) in its kind's
    colour."""
    if color_by == "set":
        return np.array([PALETTE[t.set_id % len(PALETTE)] if t.set_id >= 0 else
                         KIND_COLORS["bedding"] if t.kind == "bedding" else UNASSIGNED for t in traces], np.uint8)
    if color_by == "kind":
        return np.array([KIND_COLORS[t.kind] for t in traces], np.uint8)
    if color_by == "component":
        return np.array([PALETTE[t.component % len(PALETTE)] if t.component >= 0 else UNASSIGNED
                         for t in traces])
    if color_by == "method":
        return np.array([METHOD_COLORS.get(t.method, METHOD_COLORS[""]) for t in traces], np.uint8)
    return np.tile(np.array([40, 40, 40], np.uint8), (len(traces), 1))  # termination: nodes carry colour


def legend_entries(traces: list[Trace3D], color_by: str,
                   selected: set[int] | frozenset[int] = frozenset()) -> list[tuple[str, tuple[int, int, int]]]:
    """The key of a colouring: (label with its count, RGB) of each class the traces show, in a fixed order.

    Sets are numbered as `orient` and the exports number them; traces outside every set are
    "non-systematic" once sets exist, "no set" before, bedding apart. Termination counts end nodes, the others traces.
    Components have no key (their colours repeat every len(PALETTE) groups), nor p21/p32 (the scalar bar
    is theirs). Selected traces, drawn in magenta whatever their class, are counted last.
    """
    if color_by == "set":
        counts = _counts("bedding" if t.kind == "bedding" and t.set_id < 0 else t.set_id for t in traces)
        other = "non-systematic" if any(k != "bedding" and k >= 0 for k in counts) else "no set"
        entries = [(f"set {k} ({n})", tuple(PALETTE[k % len(PALETTE)].tolist()))
                   for k, n in sorted((k, n) for k, n in counts.items() if k != "bedding" and k >= 0)]
        entries += [(f"{other} ({counts[-1]})", tuple(UNASSIGNED.tolist()))] if -1 in counts else []
        entries += [(f"bedding ({counts['bedding']})", KIND_COLORS["bedding"])] if "bedding" in counts else []
    elif color_by == "kind":
        counts = _counts(t.kind for t in traces)
        entries = [(f"{kind} ({counts[kind]})", colour) for kind, colour in KIND_COLORS.items() if kind in counts]
    elif color_by == "termination":
        counts = _counts(c for t in traces for c in (t.term_start, t.term_end))
        entries = [(f"{name} ({counts[c]})", TERMINATION_COLORS[c]) for c, name in TERMINATION_NAMES.items()
                   if c in counts]
    elif color_by == "method":
        counts = _counts(t.method for t in traces)
        entries = [(f"{name} ({counts[m]})", METHOD_COLORS[m]) for m, name in METHOD_NAMES.items() if m in counts]
    else:
        entries = []
    chosen = sum(t.id in selected for t in traces)
    return entries + [(f"selected ({chosen})", SELECTED)] if chosen else entries


def _counts(values) -> dict:
    counts: dict = {}
    for v in values:
        counts[v] = counts.get(v, 0) + 1
    return counts


def add_scene(plotter: pv.Plotter, mesh: Mesh, traces: list[Trace3D], style: SceneStyle, *,
              vertex_map: np.ndarray | None = None, drape: Drape | None = None) -> dict[str, object]:
    """Add the mesh, the traces and their end nodes to `plotter`; returns the actors by name.

    vertex_map : per-vertex values colouring the mesh (see `SceneStyle.map_name`).
    drape : a photo draped on the faces it saw (actor "drape"); the other faces keep the mesh colours.
    Nothing is rendered here: the caller renders once (a frame of a 3M-face mesh takes seconds without a GPU).
    """
    return add_surface(plotter, mesh, style, vertex_map=vertex_map, drape=drape) | add_traces(plotter, traces, style)


def add_surface(plotter: pv.Plotter, mesh: Mesh, style: SceneStyle, *, vertex_map: np.ndarray | None = None,
                drape: Drape | None = None) -> dict[str, object]:
    """The mesh (and the draped photo) of `add_scene`, replacing those already there."""
    actors = {"mesh": _add_mesh(plotter, mesh, style, vertex_map, drape)}
    if drape is not None:
        actors["drape"] = _add_drape(plotter, mesh, drape)
    else:
        plotter.remove_actor("drape", render=False)
    return actors


def add_traces(plotter: pv.Plotter, traces: list[Trace3D], style: SceneStyle) -> dict[str, object]:
    """The traces, end nodes and legend of `add_scene`, replacing those already there (the selected in
    magenta)."""
    for name in TRACE_ACTORS:
        plotter.remove_actor(name, render=False)
    if not traces:
        return {}
    lines = traces_polydata(traces)
    colors = trace_colors(traces, style.color_by)
    colors[[i for i, t in enumerate(traces) if t.id in style.selected]] = SELECTED
    lines.cell_data["rgb"] = colors
    actors = {"traces": plotter.add_mesh(lines, scalars="rgb", rgb=True, line_width=style.line_width,
                                         render_lines_as_tubes=True, lighting=False, name="traces", render=False)}
    if style.color_by == "termination":
        actors["nodes"] = _add_nodes(plotter, traces, style)
    entries = legend_entries(traces, style.color_by, style.selected) if style.legend else []
    if entries:
        actors["legend"] = plotter.add_actor(_legend(entries, tuple(plotter.window_size)), reset_camera=False, name="legend",
                                             pickable=False, render=False)[0]
    return actors


def _legend(entries: list[tuple[str, tuple[int, int, int]]], size: tuple[int, int]) -> vtkLegendBoxActor:
    """A white key box: black labels beside swatches outlined in grey (a white or light grey class stays
    visible on the white box), placed by `place_legend`."""
    legend = vtkLegendBoxActor()
    legend.SetNumberOfEntries(len(entries))
    for i, (text, rgb) in enumerate(entries):
        # the entry colour colours the label; the swatch takes its own cell colours (ScalarVisibility)
        legend.SetEntry(i, _swatch(rgb), text, (0.0, 0.0, 0.0))
    legend.ScalarVisibilityOn()
    legend.SetUseBackground(True)
    legend.SetBackgroundColor(1.0, 1.0, 1.0)
    legend.BorderOn()
    legend.SetPadding(4)
    legend.GetProperty().SetColor(0.5, 0.5, 0.5)
    legend.GetEntryTextProperty().SetFontFamilyToArial()
    _place(legend, size)
    return legend


def place_legend(plotter: pv.Plotter, size: tuple[int, int]) -> None:
    """Lay the legend (if any) out again for a window of `size` px: LEGEND_ROW_PX px a row in the upper
    right corner. Its place is kept as fractions of the window (all a copy of it keeps), so a window that
    was resized needs this to keep the rows that high."""
    legend = plotter.actors.get("legend")
    if legend is not None:
        _place(legend, size)


def _place(legend: vtkLegendBoxActor, size: tuple[int, int]) -> None:
    rows = legend.GetNumberOfEntries()
    chars = max(len(legend.GetEntryString(i)) for i in range(rows))
    width, height = max(size[0], 1), max(size[1], 1)
    w = min(0.5, (2.2 + 0.62 * chars) * LEGEND_ROW_PX / width)
    h = min(0.9, rows * LEGEND_ROW_PX / height)
    legend.GetPositionCoordinate().SetValue(0.98 - w, 0.98 - h)
    legend.GetPosition2Coordinate().SetValue(w, h)


def _swatch(rgb: tuple[int, int, int]) -> pv.PolyData:
    """A square of colour `rgb` inside a grey one (drawn after it, so on top), and a point of no cell to its
    right: the legend fits the symbol's bounds to its slot, so the point keeps the label off the square."""
    square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    inner = 0.15 + 0.7 * square
    swatch = pv.PolyData(np.vstack([square, inner, [[1.5, 0.5, 0]]]), faces=[4, 0, 1, 2, 3, 4, 4, 5, 6, 7])
    swatch.cell_data["rgb"] = np.array([(110, 110, 110), rgb], np.uint8)
    return swatch


def _add_mesh(plotter: pv.Plotter, mesh: Mesh, style: SceneStyle, vertex_map: np.ndarray | None,
              drape: Drape | None):
    poly = mesh_polydata(mesh, None if drape is None else ~drape.seen)
    # traces lie exactly on the surface: push the polygons back in depth so lines are not half-hidden
    vtkMapper.SetResolveCoincidentTopologyToPolygonOffset()
    vtkMapper.SetResolveCoincidentTopologyPolygonOffsetParameters(4.0, 8.0)
    name = style.map_name or (style.color_by if style.color_by in ("p21", "p32") else None)
    if name is not None:
        if vertex_map is None or len(vertex_map) != len(mesh.vertices):
            raise InputError(None, f"colour by {name} needs a per-vertex map of the mesh")
        poly.point_data[name] = vertex_map
        # vertices outside the imaged area are NaN: neutral grey
        return plotter.add_mesh(poly, scalars=name, cmap="viridis", nan_color="lightgrey", clim=style.clim,
                                scalar_bar_args={"title": map_title(name), "render": False},
                                name="mesh", render=False)  # pyvista renders a replaced scalar bar unless told
    if mesh.vertex_colors is not None:
        return plotter.add_mesh(poly, scalars="rgb", rgb=True, name="mesh", render=False)
    if mesh.texture_image is not None:
        return plotter.add_mesh(poly, texture=pv.Texture(mesh.texture_image), name="mesh", render=False)
    return plotter.add_mesh(poly, color="tan", smooth_shading=True, name="mesh", render=False)


_TEXTURES: WeakKeyDictionary = WeakKeyDictionary()
"""The VTK texture of each live drape: a 24 MP photo is converted and uploaded once, not on every redraw."""


def _add_drape(plotter: pv.Plotter, mesh: Mesh, drape: Drape):
    poly = _triangles(mesh, drape.seen)
    poly.active_texture_coordinates = drape.uv
    if drape not in _TEXTURES:
        texture = pv.Texture(drape.texture)
        texture.interpolate = True
        texture.mipmap = True  # a photo seen from afar: averaged, not aliased
        texture.repeat = False
        _TEXTURES[drape] = texture
    # unlit: the photo already holds the light of the day it was taken
    return plotter.add_mesh(poly, texture=_TEXTURES[drape], lighting=False, name="drape", render=False)


def _add_nodes(plotter: pv.Plotter, traces: list[Trace3D], style: SceneStyle):
    ends = np.vstack([t.points[[0, -1]] for t in traces])
    codes = [c for t in traces for c in (t.term_start, t.term_end)]
    nodes = pv.PolyData(ends)
    nodes.point_data["rgb"] = np.array([TERMINATION_COLORS.get(c, (255, 255, 255)) for c in codes], np.uint8)
    return plotter.add_mesh(nodes, scalars="rgb", rgb=True, point_size=style.node_size,
                            render_points_as_spheres=True, name="nodes", render=False)


def add_scale_bar(plotter: pv.Plotter, bar: ScaleBar | None):
    """Draw `bar` (`engine.scale_bar`) in black: the bar with ticks at its ends and middle and its label
    above it, the north arrow with "N" beyond its tip, the words upright and facing the photos; None
    removes it. Actor "scale_bar"."""
    plotter.remove_actor("scale_bar", render=False)
    if bar is None:
        return None
    length = float(np.linalg.norm(bar.end - bar.start))
    radius, tick = 0.012 * length, 0.1 * length
    parts = [pv.Line(bar.start, bar.end).tube(radius=radius)]
    parts += [pv.Line(p, p + tick * bar.up).tube(radius=radius)
              for p in (bar.start, 0.5 * (bar.start + bar.end), bar.end)]
    parts.append(_words(bar.label, 0.5 * (bar.start + bar.end) + 2.9 * tick * bar.up, bar, 0.25 * length))
    base, tip = bar.arrow
    span = float(np.linalg.norm(tip - base))
    parts.append(pv.Arrow(start=base, direction=tip - base, scale=span, tip_length=0.3, tip_radius=0.09, shaft_radius=0.03))
    parts.append(_words("N", tip + 0.3 * (tip - base) + 0.05 * length * bar.up, bar, 0.25 * length))
    return plotter.add_mesh(pv.merge(parts), color="black", lighting=False, name="scale_bar", pickable=False,
                            render=False)


def add_scanlines(plotter: pv.Plotter, measures: Sequence[ScanlineMeasure], unmeasured: Sequence[Scanline] = (), *,
                  line_width: float = SCANLINE_WIDTH, mark_size: float = MARK_SIZE) -> None:
    """Draw scanlines (`engine.scanline`) in orange, `line_width` px wide: a measured one along the rock it
    sampled (the tape laid on the rock, where its crossings lie), with a dark mark `mark_size` px across at
    each crossing; an `unmeasured` one as its straight line. None removes them. Actors `SCANLINE_ACTORS`."""
    for name in SCANLINE_ACTORS:
        plotter.remove_actor(name, render=False)
    pieces = [m.rock.section for m in measures] + [np.array([[line.start, line.end]]) for line in unmeasured]
    if not pieces:
        return
    _add_segments(plotter, np.concatenate(pieces).reshape(-1, 3), SCANLINE_COLOR, line_width, SCANLINE_ACTORS[0])
    crossings = [c.point for m in measures for c in m.crossings]
    if crossings:
        plotter.add_mesh(pv.PolyData(np.array(crossings)), color=CROSSING_COLOR, point_size=mark_size,
                         render_points_as_spheres=True, pickable=False, name=SCANLINE_ACTORS[1], render=False)


def add_scan_circles(plotter: pv.Plotter, measures: Sequence[WindowMeasure], *, line_width: float = SCANLINE_WIDTH,
                     mark_size: float = MARK_SIZE) -> None:
    """Draw scan circles (`engine.scan_circle`): each window's edge on the rock in cyan, `line_width` px wide,
    a dark mark `mark_size` px across where a trace crosses it (Mauldon's n), a cyan one at each trace end
    inside (m) and a grey one at each cut end inside (not counted). None removes them. Actors `WINDOW_ACTORS`.
"""
    for name in WINDOW_ACTORS:
        plotter.remove_actor(name, render=False)
    if not measures:
        return
    ends = np.concatenate([m.rock.edge for m in measures]).reshape(-1, 3)
    _add_segments(plotter, ends, WINDOW_COLOR, line_width, WINDOW_ACTORS[0])
    for name, color, field in ((WINDOW_ACTORS[1], CROSSING_COLOR, "crossings"), (WINDOW_ACTORS[2], WINDOW_COLOR, "ends"),
                               (WINDOW_ACTORS[3], TERMINATION_COLORS["C"], "cut_ends")):
        points = np.concatenate([getattr(m, field) for m in measures])
        if len(points):
            plotter.add_mesh(pv.PolyData(points), color=color, point_size=mark_size, render_points_as_spheres=True,
                             pickable=False, name=name, render=False)


def _add_segments(plotter: pv.Plotter, ends: np.ndarray, color: tuple[int, int, int], width: float, name: str) -> None:
    """Line segments (consecutive pairs of `ends`) of one colour, `width` px wide, over the rock they lie on.

    Flat lines, not VTK's tubes: tubes of a plain colour without lighting lost the depth test against the
    offset rock in pieces (a quarter of a window's edge hidden, even 0.4 m off the rock), and given their
    colour as cell scalars instead they vanished from the 3D viewer's render thread altogether."""
    cells = np.column_stack([np.full(len(ends) // 2, 2), np.arange(len(ends)).reshape(-1, 2)]).ravel()
    plotter.add_mesh(pv.PolyData(ends, lines=cells), color=color, line_width=width, lighting=False, pickable=False,
                     name=name, render=False)


def _words(text: str, centre: np.ndarray, bar: ScaleBar, height: float) -> pv.PolyData:
    """Flat text `height` tall centred on `centre`, reading along the bar, upright, facing out of the rock."""
    source = vtkVectorText()  # flat glyphs about 1 tall; pv.Text3D fails with pyvista 0.44 on VTK 9.4
    source.SetText(text)
    source.Update()
    words = pv.wrap(source.GetOutput()).copy()
    lo, hi = np.array(words.bounds).reshape(3, 2).T
    local = (np.asarray(words.points) - 0.5 * (lo + hi)) * (height / max(hi[1] - lo[1], 1e-12))
    words.points = local @ np.stack([bar.along, bar.up, bar.out]) + centre
    return words


def frame_view(plotter: pv.Plotter, mesh: Mesh, camera_centres: np.ndarray | None = None) -> None:
    """Look at the mesh from where the photos were taken (their mean centre), z up."""
    lo, hi = _bounds(mesh.vertices)
    centre = 0.5 * (lo + hi)
    extent = float(np.linalg.norm(hi - lo))
    if camera_centres is not None and len(camera_centres):
        direction = np.mean(camera_centres, axis=0) - centre
    else:
        direction = mesh.vertex_normals.mean(axis=0)
    direction = direction / (np.linalg.norm(direction) or 1.0)
    plotter.camera_position = [tuple(centre + 1.1 * extent * direction), tuple(centre), (0.0, 0.0, 1.0)]
    plotter.camera.view_angle = DEFAULT_VIEW_ANGLE  # as VTK's default camera, after a `look_from`
    plotter.camera.SetWindowCenter(0.0, 0.0)


def look_from(plotter: pv.Plotter, camera: Camera, mesh: Mesh) -> None:
    """Look from a photo: its centre, axis and roll, its height in the window, its principal point.

    A pinhole view (distortion and skew are not drawn; VTK has one focal length, fy). In a window of the
    photo's aspect each mesh point lands where `camera.project` puts it (pixel centres: u = x − ½, v = H − y
    − ½ of VTK's display x, y); in another window the photo's frame fits its height, centred. `camera` is in
    the mesh's frame. The focal point (where the view turns about) is the mesh centre's depth on the axis.
    """
    width, height = plotter.window_size
    fy, cx, cy = camera.K[1, 1], camera.K[0, 2], camera.K[1, 2]
    lo, hi = _bounds(mesh.vertices)
    depth = float((0.5 * (lo + hi) - camera.centre) @ camera.R[2])
    depth = depth if depth > 0 else float(np.linalg.norm(hi - lo))
    plotter.camera_position = [tuple(camera.centre), tuple(camera.centre + depth * camera.R[2]), tuple(-camera.R[1])]
    plotter.camera.view_angle = float(np.degrees(2 * np.arctan(camera.height / (2 * fy))))
    # VTK shifts the frustum so that the axis lands at normalised viewport (−wx, −wy) (vtkCamera::WindowCenter)
    wx = -(2 * cx + 1 - camera.width) * height / (camera.height * width)
    wy = (2 * cy + 1 - camera.height) / camera.height
    plotter.camera.SetWindowCenter(wx, wy)
    plotter.renderer.ResetCameraClippingRange()


def _bounds(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lowest and highest coordinates of (N, 3) points, one column at a time: a reduction along axis 0 of a
    C-ordered (N, 3) array takes 20× longer (7 ms at 256k points, on the GUI thread)."""
    columns = points.T
    return np.array([c.min() for c in columns]), np.array([c.max() for c in columns])


def offscreen_texture_size() -> int | None:
    """The longest texture side an offscreen render here takes (for `drape_photo`'s max_size)."""
    plotter = pv.Plotter(off_screen=True, window_size=[16, 16])
    try:
        plotter.render()
        return max_texture_size(plotter)
    finally:
        plotter.close()


def render_to_file(path: str | Path, mesh: Mesh, traces: list[Trace3D], style: SceneStyle, *,
                   camera_centres: np.ndarray | None = None, vertex_map: np.ndarray | None = None,
                   view: Camera | None = None, drape: Drape | None = None, bar: ScaleBar | None = None,
                   scanlines: Sequence[ScanlineMeasure] = (), windows: Sequence[WindowMeasure] = ()) -> Path:
    """Render the scene offscreen to a PNG (the format follows the suffix: .png, .jpg, .tif), seen from the
    photo `view` (`photo_view`) or, by default, from where the photos were taken (`frame_view`), with a
    photo draped on the faces it saw (`engine.drape.drape_photo`), a scale bar, scanlines and scan circles
    (`windows`), if given."""
    path = Path(path)
    if view is None:
        picture = _picture(mesh, traces, style, vertex_map, drape, bar, (scanlines, windows),
                           lambda p: frame_view(p, mesh, camera_centres))
    else:
        picture = photo_view(mesh, traces, style, view, vertex_map=vertex_map, drape=drape, bar=bar,
                             scanlines=scanlines, windows=windows)
    if not cv2.imwrite(str(path), cv2.cvtColor(picture, cv2.COLOR_RGB2BGR)):
        raise InputError(path, "could not write the picture (expected a .png, .jpg or .tif path in a folder "
                               "that exists)")
    return path


def photo_size(camera: Camera, longest: int = 1600) -> tuple[int, int]:
    """A picture in the frame of `camera`'s photo: its aspect, its longer side at most `longest` px."""
    scale = min(1.0, longest / max(camera.width, camera.height))
    return max(16, round(camera.width * scale)), max(16, round(camera.height * scale))


def photo_view(mesh: Mesh, traces: list[Trace3D], style: SceneStyle, camera: Camera, *,
               vertex_map: np.ndarray | None = None, drape: Drape | None = None,
               bar: ScaleBar | None = None, scanlines: Sequence[ScanlineMeasure] = (),
               windows: Sequence[WindowMeasure] = ()) -> np.ndarray:
    """The scene in the frame of photo `camera`, as (H, W, 3) uint8 RGB of `style.size` (the photo's aspect):
    each mesh point drawn on the pixel where the photo shows it, lens distortion included.

    VTK draws pinhole views only, so a distorted photo's view is drawn as the pinhole view of a canvas
    covering everything the photo sees, then resampled through the distortion (bilinear); the legend is
    drawn afterwards, upright.
    """
    width, height = style.size
    if abs(width * camera.height - height * camera.width) > max(camera.width, camera.height):
        raise InputError(None, f"--size {width} {height}: a view from {camera.name} is drawn in its frame, "
                               f"{camera.width}×{camera.height}; e.g. --size {width} "
                               f"{max(1, round(width * camera.height / camera.width))}")
    if not np.any(camera.distortion):
        return _picture(mesh, traces, style, vertex_map, drape, bar, (scanlines, windows),
                        lambda p: look_from(p, camera, mesh))
    scale = height / camera.height
    # the canvas: what the border and a grid of the picture see (a lens's extremes lie on the border)
    u, v = np.linspace(0, width - 1, 64), np.linspace(0, height - 1, 64)
    grid = np.vstack([np.stack(np.meshgrid(u, v), axis=-1).reshape(-1, 2), _border(width, height)])
    ideal = _pinhole_pixels(camera, grid, scale)
    lo, hi = np.floor(ideal.min(axis=0)) - 2, np.ceil(ideal.max(axis=0)) + 2
    canvas_px = np.rint((hi - lo) * scale).astype(int)
    if np.any(canvas_px > np.maximum(3 * np.array([width, height]), 16)) or canvas_px.max() > 16384:
        raise InputError(None, f"camera {camera.name!r}: its lens distortion spreads the view over "
                               f"{canvas_px[0]}×{canvas_px[1]} px, over 3× the picture; expected a photo lens")
    K = camera.K.copy()
    K[:2, 2] -= lo
    canvas = Camera(camera.name, int(hi[0] - lo[0]), int(hi[1] - lo[1]), K, np.zeros(0), camera.R, camera.t)
    pinhole = SceneStyle(**{**vars(style), "size": tuple(canvas_px.tolist()), "legend": False})
    drawn = _picture(mesh, traces, pinhole, vertex_map, drape, bar, (scanlines, windows),
                     lambda p: look_from(p, canvas, mesh))
    # where look_from put each canvas pixel (the canvas fits the window's height, centred), a band of rows at
    # a time: a 24 MP picture's float64 coordinates would take 1.5 GB at once
    fit = canvas_px[1] / canvas.height
    maps = np.empty((height, width, 2), np.float32)
    u = np.arange(width, dtype=float)
    for r0 in range(0, height, MAP_ROWS):
        rows = np.arange(r0, min(r0 + MAP_ROWS, height), dtype=float)
        band = np.column_stack([np.tile(u, len(rows)), np.repeat(rows, width)])
        where = (_pinhole_pixels(camera, band, scale) - lo + 0.5 - np.array([canvas.width, canvas.height]) / 2) \
            * fit + canvas_px / 2 - 0.5
        maps[r0:r0 + len(rows)] = where.reshape(len(rows), width, 2)
    background = tuple(int(255 * c) for c in pv.Color(style.background).float_rgb)
    picture = cv2.remap(drawn, maps[..., 0], maps[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                        borderValue=background)
    entries = legend_entries(traces, style.color_by, style.selected) if style.legend else []
    return _with_legend(picture, entries) if entries else picture


def _pinhole_pixels(camera: Camera, picture_uv: np.ndarray, scale: float) -> np.ndarray:
    """Where pixels of a picture `scale` × the photo fall in the photo without its lens distortion (N, 2)."""
    photo_uv = (picture_uv + 0.5) / scale - 0.5
    return camera.undistort_normalised(photo_uv) @ camera.K[:2, :2].T + camera.K[:2, 2]


def _border(width: int, height: int) -> np.ndarray:
    """Every pixel centre on the edge of a width × height picture (N, 2)."""
    u, v = np.arange(width, dtype=float), np.arange(height, dtype=float)
    return np.vstack([np.column_stack([u, np.zeros(width)]), np.column_stack([u, np.full(width, height - 1.0)]),
                      np.column_stack([np.zeros(height), v]), np.column_stack([np.full(height, width - 1.0), v])])


def _picture(mesh, traces, style, vertex_map, drape, bar, samples, aim) -> np.ndarray:
    """The scene drawn offscreen at `style.size`, the camera set by `aim(plotter)`: (H, W, 3) uint8 RGB.
    `samples`: the scanlines and scan circles to draw."""
    plotter = pv.Plotter(off_screen=True, window_size=list(style.size))
    try:
        plotter.set_background(style.background)
        add_scene(plotter, mesh, traces, style, vertex_map=vertex_map, drape=drape)
        add_scale_bar(plotter, bar)
        add_scanlines(plotter, samples[0])
        add_scan_circles(plotter, samples[1])
        aim(plotter)
        return np.ascontiguousarray(plotter.screenshot(None, return_img=True)[..., :3])
    finally:
        plotter.close()


def _with_legend(picture: np.ndarray, entries: list[tuple[str, tuple[int, int, int]]]) -> np.ndarray:
    """`picture` with the legend drawn over it as `add_traces` places it."""
    height, width = picture.shape[:2]
    plotter = pv.Plotter(off_screen=True, window_size=[width, height])
    try:
        plotter.add_actor(_legend(entries, (width, height)), reset_camera=False, name="legend", pickable=False,
                          render=False)
        key = plotter.screenshot(None, transparent_background=True, return_img=True).astype(np.float32)
    finally:
        plotter.close()
    alpha = key[..., 3:] / 255
    return np.rint(key[..., :3] * alpha + picture * (1 - alpha)).astype(np.uint8)
