"""The outcrop mesh: triangles in a float64 local frame, with colours or texture kept for display.

Photogrammetric meshes often sit at UTM-sized coordinates; Embree is float32, so every mesh is shifted to a
local origin on load (DESIGN.md) and every export adds the origin back.
"""

from __future__ import annotations

import locale
import threading
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from engine.errors import InputError

MESH_SUFFIXES = (".ply", ".obj", ".stl", ".off", ".glb", ".gltf", ".vtk", ".vtp")
_TREE_LOCK = threading.Lock()  # one face-tree build at a time: threads asking at once share the first's tree
_HIT_SLACK = 1e-9  # barycentric slack of `first_hit`: a ray through a shared edge is not lost to rounding


@dataclass(eq=False)
class Mesh:
    """A triangle mesh. `vertices` are local (world = vertices + origin); `faces` index them."""

    vertices: np.ndarray
    faces: np.ndarray
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))
    vertex_colors: np.ndarray | None = None
    texture_uv: np.ndarray | None = None
    texture_image: np.ndarray | None = None
    source: str | None = None

    def __post_init__(self) -> None:
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float64)
        self.faces = np.ascontiguousarray(self.faces, dtype=np.int64)
        self.origin = np.asarray(self.origin, dtype=np.float64).reshape(3)
        _validate(self.vertices, self.faces, self.source)

    @property
    def world_vertices(self) -> np.ndarray:
        return self.vertices + self.origin

    @cached_property
    def face_normals(self) -> np.ndarray:
        """Unit normals (F, 3), right-handed from the vertex order."""
        cross = self._face_cross
        return cross / np.linalg.norm(cross, axis=1, keepdims=True)

    @cached_property
    def face_areas(self) -> np.ndarray:
        return 0.5 * np.linalg.norm(self._face_cross, axis=1)

    @cached_property
    def face_centroids(self) -> np.ndarray:
        return self.vertices[self.faces].mean(axis=1)

    @property
    def face_tree(self) -> cKDTree:
        """A k-d tree of the face centroids, built on first use (0.3 s at 0.5M faces, 1–3 s at 3.2M) and shared
        by every neighbour search on this mesh; a thread asking while another builds it waits for that build."""
        with _TREE_LOCK:  # not cached_property: from Python 3.12 it no longer keeps two threads from both building
            if "_face_tree" not in self.__dict__:
                self.__dict__["_face_tree"] = cKDTree(self.face_centroids)
            return self.__dict__["_face_tree"]

    @cached_property
    def face_reach(self) -> np.ndarray:
        """Distance (F,) from each face's centroid to its farthest vertex: the face lies in that ball."""
        reach = np.zeros(len(self.faces))
        for k in range(3):  # one vertex of every face at a time: no (F, 3, 3) array
            np.maximum(reach, np.linalg.norm(self.vertices[self.faces[:, k]] - self.face_centroids, axis=1), out=reach)
        return reach

    @cached_property
    def vertex_areas(self) -> np.ndarray:
        """Area attributed to each vertex: a third of each adjacent face (sums to the mesh area)."""
        return np.bincount(self.faces.ravel(), np.repeat(self.face_areas / 3.0, 3),
                           minlength=len(self.vertices))

    @cached_property
    def vertex_normals(self) -> np.ndarray:
        """Area-weighted unit vertex normals."""
        n = np.zeros_like(self.vertices)
        for k in range(3):
            np.add.at(n, self.faces[:, k], self._face_cross)
        length = np.linalg.norm(n, axis=1, keepdims=True)
        return n / np.where(length > 0, length, 1.0)

    @cached_property
    def boundary_edges(self) -> np.ndarray:
        """Edges (E, 2) used by exactly one face: the mesh border and the rims of holes."""
        edges = np.sort(self.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1).astype(np.int64)
        # one integer per edge: a plain sort, several times faster than np.unique(axis=0)'s row sort, which
        # also held the GIL for 0.14 s on a 64k-face mesh (a stall of the application's window)
        keys, counts = np.unique(edges[:, 0] * len(self.vertices) + edges[:, 1], return_counts=True)
        once = keys[counts == 1]
        return np.column_stack([once // len(self.vertices), once % len(self.vertices)])

    @cached_property
    def mean_edge_length(self) -> float:
        return mean_edge_length(self.vertices, self.faces)

    @cached_property
    def _face_cross(self) -> np.ndarray:
        v = self.vertices
        f = self.faces
        return np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])


def mean_edge_length(vertices: np.ndarray, faces: np.ndarray, *, most: int | None = None) -> float:
    """Mean edge length of a triangle mesh (m): its spacing. With `most`, from at most that many faces spread
    evenly over the mesh (a few ms at millions of faces instead of 0.5 s)."""
    if most is not None:
        faces = faces[::max(1, len(faces) // most)]
    total = 0.0
    for k in range(3):  # one edge of every face at a time: 0.5 s at 3M faces, not 2.7 s via (F, 3, 3)
        d = vertices[faces[:, k]] - vertices[faces[:, (k + 1) % 3]]
        total += np.sqrt(np.einsum("ij,ij->i", d, d)).sum()
    return float(total / (3 * len(faces)))


def first_hit(mesh: Mesh, origin: np.ndarray, direction: np.ndarray) -> np.ndarray | None:
    """Where the ray origin + t·direction (t ≥ 0) first meets the mesh, or None: one ray (a click in the 3D view)
    cast through `Mesh.face_tree`, with no ray tracer to build (Embree's takes 1 s and 250 MB at 3.2M faces).

    The ray is sampled every `step` (two mean edge lengths) across the box of the face centroids, widened by
    `step`. A face it crosses whose `face_reach` is at most `step` lies in that box and has its centroid within
    1.5 `step` of a sample; the few larger faces are all tested. Each candidate is intersected exactly
    (Möller–Trumbore).
    """
    o = np.asarray(origin, dtype=float).reshape(3)
    d = np.asarray(direction, dtype=float).reshape(3)
    d = d / np.linalg.norm(d)
    step = 2.0 * mesh.mean_edge_length
    tree = mesh.face_tree
    with np.errstate(divide="ignore", invalid="ignore"):  # a ray parallel to a side of the box
        a, b = (tree.mins - step - o) / d, (tree.maxes + step - o) / d
    near, far = max(float(np.nanmax(np.minimum(a, b))), 0.0), float(np.nanmin(np.maximum(a, b)))
    n = int(np.ceil((far - near) / step)) + 1 if near <= far else 0  # none when the ray misses the box
    samples = o + (near + step * np.arange(n))[:, None] * d
    found = tree.query_ball_point(samples, 1.5 * step)
    candidates = np.unique(np.concatenate([np.asarray(f, dtype=np.int64) for f in found]
                                          + [np.flatnonzero(mesh.face_reach > step)]))
    t = _ray_triangles(o, d, mesh.vertices[mesh.faces[candidates]])
    return o + np.nanmin(t) * d if np.isfinite(t).any() else None


def _ray_triangles(o: np.ndarray, d: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Ray parameter t (N,) where the ray o + t·d meets each triangle (N, 3, 3); NaN where it misses or t < 0."""
    e1, e2, s = triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0], o - triangles[:, 0]
    p, q = np.cross(d, e2), np.cross(s, e1)
    with np.errstate(divide="ignore", invalid="ignore"):  # det 0: the ray runs parallel to the face, a miss
        det = np.einsum("ij,ij->i", e1, p)
        u, v, t = np.einsum("ij,ij->i", s, p) / det, q @ d / det, np.einsum("ij,ij->i", e2, q) / det
        hit = (u >= -_HIT_SLACK) & (v >= -_HIT_SLACK) & (u + v <= 1 + _HIT_SLACK) & (t >= 0)
    return np.where(hit, t, np.nan)


def contour_segments(vertices: np.ndarray, corners: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Segments (K, 2, 3) where a scalar, given at each corner (F, 3) of the faces `corners` (F, 3 vertex
    indices), crosses zero inside them (marching triangles): on each face it crosses, between the points
    interpolated on its two edges across. A corner at exactly zero counts as ahead, so every face the
    contour crosses has exactly two such edges and a contour through a vertex is not doubled."""
    ahead = values >= 0
    cut = ahead.any(axis=1) & ~ahead.all(axis=1)
    corners, values, ahead = corners[cut], values[cut], ahead[cut]
    points, crosses = [], []
    for a, b in ((0, 1), (1, 2), (2, 0)):
        crosses.append(ahead[:, a] != ahead[:, b])
        t = values[:, a] / np.where(crosses[-1], values[:, a] - values[:, b], 1.0)
        pa, pb = vertices[corners[:, a]], vertices[corners[:, b]]
        points.append(pa + t[:, None] * (pb - pa))
    crosses, points = np.stack(crosses, axis=1), np.stack(points, axis=1)
    order = np.argsort(~crosses, axis=1, kind="stable")[:, :2]
    return np.take_along_axis(points, order[:, :, None], axis=1)


def barycentric(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (N, 3) of points (N, 3) projected onto the planes of triangles (N, 3, 3)."""
    e1, e2, w = triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0], points - triangles[:, 0]
    d11, d12, d22 = (np.einsum("ij,ij->i", s, t) for s, t in ((e1, e1), (e1, e2), (e2, e2)))
    w1, w2 = np.einsum("ij,ij->i", w, e1), np.einsum("ij,ij->i", w, e2)
    det = d11 * d22 - d12 * d12
    b1, b2 = (d22 * w1 - d12 * w2) / det, (d11 * w2 - d12 * w1) / det
    return np.column_stack([1 - b1 - b2, b1, b2])


def local_origin(world_vertices: np.ndarray) -> np.ndarray:
    """A local origin for these coordinates: the bounding-box centre rounded to whole metres."""
    return np.round(0.5 * (world_vertices.min(axis=0) + world_vertices.max(axis=0)))


def read_mesh(path: str | Path, *, origin: np.ndarray | None = None) -> Mesh:
    """Read PLY/OBJ/STL/OFF/GLB/glTF/VTK/VTP, triangulate polygons and shift to a local origin.

    `origin` (world metres) defaults to `local_origin` of the vertices; pass the project's origin to
    re-read a mesh into an existing frame. Colours or texture are kept for display.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "mesh file not found")
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise InputError(path, f"unknown mesh format {suffix!r}; expected one of {', '.join(MESH_SUFFIXES)}")
    try:
        arrays = _read_vtk(path) if suffix in (".vtk", ".vtp") else _read_trimesh(path)
    except InputError:
        raise
    except KeyError as exc:  # trimesh's PLY reader, on a vertex or face element without a field it needs
        raise InputError(path, f"cannot read mesh: it has no {exc.args[0]!r} field (expected vertices with x, y "
                               f"and z, and faces as lists of vertex indices)") from exc
    except Exception as exc:  # the readers raise many types on corrupt files
        raise InputError(path, f"cannot read mesh ({type(exc).__name__}: {exc})") from exc
    vertices, faces, colors, uv, image = arrays
    _validate(vertices, faces, str(path))
    o = local_origin(vertices) if origin is None else np.asarray(origin, dtype=np.float64)
    return Mesh(vertices - o, faces, o, colors, uv, image, str(path))


def _read_trimesh(path: Path):
    import trimesh

    loaded = trimesh.load(str(path), process=False)
    if isinstance(loaded, trimesh.Scene):  # glTF, or an OBJ of several parts: placed and joined into one mesh
        loaded = loaded.to_mesh()  # (force="mesh" does this to one-mesh files too: 3 s of copies at 3M faces)
    if not isinstance(loaded, trimesh.Trimesh):
        raise InputError(path, "no triangle faces found (is it a point cloud?)")
    vertices = np.asarray(loaded.vertices, dtype=np.float64)
    faces = np.asarray(loaded.faces, dtype=np.int64)
    colors = uv = image = None
    visual = loaded.visual
    if visual.kind == "texture" and getattr(visual, "uv", None) is not None:
        material_image = getattr(visual.material, "image", None)
        if material_image is None:
            material_image = getattr(visual.material, "baseColorTexture", None)
        if material_image is not None:
            uv = np.asarray(visual.uv, dtype=np.float64)
            image = np.asarray(material_image.convert("RGB"))
    elif visual.kind == "vertex":
        colors = np.asarray(visual.vertex_colors)[:, :3].astype(np.uint8)
    return vertices, faces, colors, uv, image


_QUIET_VTK = threading.Lock()
"""Held while VTK's global warning display is switched off for a read (and the locale put back after it)."""


def _read_vtk(path: Path):
    import pyvista as pv
    from vtkmodules.vtkCommonCore import vtkObject

    with _QUIET_VTK:  # one read at a time, so each restores what it found and not another read's "off"
        shown = vtkObject.GetGlobalWarningDisplay()
        found = locale.setlocale(locale.LC_ALL)
        vtkObject.GlobalWarningDisplayOff()  # a damaged file is told below, not by pages of VTK pipeline errors
        try:
            data = pv.read(str(path))
        finally:
            vtkObject.SetGlobalWarningDisplay(shown)
            # VTK 9.4's legacy reader leaves the process in the "C" locale after a damaged file: Python's text
            # files would then default to ASCII
            locale.setlocale(locale.LC_ALL, found)
    if data.n_points == 0:
        raise InputError(path, "VTK read no points from it: the file is empty or damaged (expected VTK legacy "
                               ".vtk or XML .vtp/.vtu polygon data)")
    surface = data.extract_surface(algorithm="dataset_surface") if not isinstance(data, pv.PolyData) else data
    if surface.n_cells == 0 or surface.n_faces == 0:
        raise InputError(path, "no polygon faces found")
    surface = surface.triangulate()
    faces = surface.regular_faces.astype(np.int64)
    colors = None
    for name in ("RGB", "RGBA", "Colors", "colors"):
        if name in surface.point_data and surface.point_data[name].ndim == 2:
            colors = np.asarray(surface.point_data[name])[:, :3].astype(np.uint8)
            break
    return np.asarray(surface.points, dtype=np.float64), faces, colors, None, None


def _validate(vertices: np.ndarray, faces: np.ndarray, source: str | None) -> None:
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise InputError(source, f"the mesh has no triangle faces (faces array has shape {faces.shape})")
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) == 0:
        raise InputError(source, f"vertices must be an (N, 3) array with N > 0, got shape {vertices.shape}")
    if not np.all(np.isfinite(vertices)):
        bad = int(np.count_nonzero(~np.isfinite(vertices).all(axis=1)))
        raise InputError(source, f"{bad} vertices have NaN or infinite coordinates")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise InputError(source, f"face indices must lie in [0, {len(vertices) - 1}]")
    # one face of non-zero area will do: the first few nearly always have it, so a 3M-face mesh is not
    # crossed whole (that took 2 s of a 7 s mesh read)
    for some in (faces[:1024], faces):
        v = vertices[some]
        if np.any(np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1) > 0):
            return
    raise InputError(source, "every face is degenerate (zero area)")
