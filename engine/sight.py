"""What the photos see of the mesh: lines of sight and where a plane cuts the surface.

A fracture crossing a bench edge or a buttress is often seen as two pieces with a gap between them that no
photo shows (the bench top or the far side of the buttress). Whether a gap is hidden, and where the
fracture would cut the rock there, are questions about the survey, not about the traces: this module
answers them for engine.merge (hidden-gap bridges) from the mesh, the calibrated cameras and the ray tracer.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree
from trimesh.triangles import closest_point

from engine.cameras import Camera
from engine.extract import on_occluding_edge
from engine.mesh import Mesh, mean_edge_length
from engine.raytrace import RayTracer

BORDER_PX = 3.0
"""A point projecting closer than this to a photo's border is not counted as seen by it."""

SEEN_INCIDENCE = 75.0
"""Degrees from the surface normal beyond which a line of sight does not count as seeing the rock: a trace
there is foreshortened more than 4× and lies along the silhouette, where engine.extract drops or trims its
rays. Measured on the merge of the synthetic outcrops (2 mm mesh noise): the planes' cuts through hidden gaps
were "seen" only at 79–90° incidence; counting those views, planar seed 0 merged to 97 traces (87 true),
to 91 at 80° and to 88 at 75°."""


@dataclass
class Sight:
    """The survey as the photos saw it: the mesh (local frame), its cameras (local frame), a ray tracer
    of the same mesh (its BVH is reused), and the `edge_px` each photo's traces were extracted with
    (engine.extract.extracted_edge_px; a photo left out was extracted with the automatic one)."""

    mesh: Mesh
    cameras: Mapping[str, Camera]
    tracer: RayTracer
    edge_px: Mapping[str, float | None] = field(default_factory=dict)

    def seen(self, points: np.ndarray, tolerance: float) -> np.ndarray:
        """For each point on the mesh (N, 3): does some photo see it? A photo sees a point that projects
        inside it (BORDER_PX clear of the border) when the first surface on the line of sight lies within
        `tolerance` (m) of the point (not hidden in front of it, and not a different surface behind it) and
        the line of sight meets that surface less than SEEN_INCIDENCE from its normal."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        seen = np.zeros(len(points), dtype=bool)
        for camera in self.cameras.values():
            if seen.all():
                break
            seen |= self._seen_by(camera, points, tolerance, ~seen)
        return seen

    def shows(self, path: np.ndarray, tolerance: float) -> np.ndarray:
        """For each point of a path on the mesh (M, 3, in order): would some photo show a trace running along
        it? One would where it sees the point (`seen`) and the path's image there is not on an occluding edge:
        engine.extract drops a trace's pixels on such an edge (the rock either side of the line of sight lies
        at other depths), so a photo that sees the rock at a bench edge or a rib crest cannot show the trace
        there either (with the photo's `edge_px`: 0 keeps such pixels, and then seeing is showing). Measured on
        planar seed 5: the cuts through two hidden gaps left between pieces of one trace were 33% and 17%
        "seen", every seen point on an occluding edge of the photo seeing it."""
        path = np.asarray(path, dtype=np.float64).reshape(-1, 3)
        shown = np.zeros(len(path), dtype=bool)
        for name, camera in self.cameras.items():
            seen = self._seen_by(camera, path, tolerance, ~shown)
            edge_px = self.edge_px.get(name)
            if len(path) < 2 or not seen.any() or edge_px == 0:
                shown |= seen
                continue
            uv = camera.project(path)
            tangent = np.gradient(uv, axis=0)[seen]
            tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-12)
            edge = on_occluding_edge(camera, self.tracer, uv[seen], np.column_stack([-tangent[:, 1], tangent[:, 0]]),
                                     mesh_spacing=self._spacing, edge_px=edge_px)
            shown[np.flatnonzero(seen)[~edge]] = True
        return shown

    @cached_property
    def _spacing(self) -> float:
        return mean_edge_length(self.mesh.vertices, self.mesh.faces, most=10_000)  # as engine.extract takes it

    def _seen_by(self, camera: Camera, points: np.ndarray, tolerance: float, ask: np.ndarray) -> np.ndarray:
        """`seen` for one photo, on the points where `ask` (N,) is True (False elsewhere)."""
        seen = np.zeros(len(points), dtype=bool)
        uv = camera.project(points)
        inside = (np.isfinite(uv).all(axis=1) & (uv[:, 0] >= BORDER_PX - 0.5) & (uv[:, 1] >= BORDER_PX - 0.5)
                  & (uv[:, 0] <= camera.width - 0.5 - BORDER_PX) & (uv[:, 1] <= camera.height - 0.5 - BORDER_PX))
        k = np.flatnonzero(inside & ask)
        if len(k):
            rays = points[k] - camera.centre
            hits = self.tracer.intersect(camera.centre, rays)
            near = hits.hit & (np.abs(hits.t - np.linalg.norm(rays, axis=1)) <= tolerance)
            seen[k] = near & (hits.cosine > np.cos(np.radians(SEEN_INCIDENCE)))
        return seen

    def distance(self, point: np.ndarray) -> float:
        """Distance (m) from a point (3,) to the mesh's surface, exact up to twice the mean edge length from
        it (inf beyond)."""
        reach = 2 * self.mesh.mean_edge_length
        near = np.asarray(self.mesh.face_tree.query_ball_point(point, reach), dtype=np.int64)
        if not len(near):
            return np.inf
        triangles = self.mesh.vertices[self.mesh.faces[near]]
        closest = closest_point(triangles, np.broadcast_to(point, (len(near), 3)))
        return float(np.linalg.norm(closest - point, axis=1).min())

    def plane_path(self, point: np.ndarray, normal: np.ndarray, start: np.ndarray, end: np.ndarray,
                   radius: float, snap: float) -> np.ndarray | None:
        """The plane's section through the mesh followed from `start` to `end` (points (M, 3) in order, on
        the mesh's edges), over the faces whose centroids lie within `radius` (m) of their midpoint; None if
        no piece of the section passes within `snap` (m) of both, or none joins them. Where the plane cuts
        the rock in several curves (round a buttress, across a gully), only the one that joins the two points
        is the fracture's trace between them."""
        faces = self.mesh.faces[np.asarray(self.mesh.face_tree.query_ball_point((start + end) / 2, radius),
                                           dtype=np.int64)]
        if not len(faces):
            return None
        above = (self.mesh.vertices[faces] - point) @ normal > 0  # (F, 3)
        edges = np.sort(faces[:, [[0, 1], [1, 2], [2, 0]]], axis=2)  # (F, 3, 2)
        crossed = above != np.roll(above, -1, axis=1)  # edge k runs from vertex k to vertex k + 1
        cut = crossed.sum(axis=1) == 2  # the plane enters a face through one edge and leaves by another
        if not cut.any():
            return None
        pairs = edges[cut][crossed[cut]].reshape(-1, 2, 2)  # (C, 2 edges, 2 vertices)
        keys, node = np.unique(pairs.reshape(-1, 2), axis=0, return_inverse=True)
        ends = self.mesh.vertices[keys]  # (N, 2, 3)
        height = (ends - point) @ normal
        points = ends[:, 0] + (height[:, 0] / (height[:, 0] - height[:, 1]))[:, None] * (ends[:, 1] - ends[:, 0])
        links = node.reshape(-1, 2)
        length = np.linalg.norm(points[links[:, 0]] - points[links[:, 1]], axis=1) + 1e-12
        graph = coo_matrix((length, (links[:, 0], links[:, 1])), shape=(len(points), len(points))).tocsr()
        tree = cKDTree(points)
        first, last = tree.query_ball_point(start, snap), tree.query_ball_point(end, snap)
        if not first or not last:
            return None
        source = min(first, key=lambda i: np.linalg.norm(points[i] - start))
        distance, previous = dijkstra(graph, directed=False, indices=source, return_predecessors=True)
        reached = [i for i in last if np.isfinite(distance[i])]
        if not reached:
            return None
        k = min(reached, key=lambda i: np.linalg.norm(points[i] - end))
        path = [k]
        while path[-1] != source:
            path.append(previous[path[-1]])
        return points[path[::-1]]
