"""Scan circles at the paper's scale, the window's rock side by side with VTK's clip and cut by a sphere.

Scene: bench_intensity's rough 40 m × 20 m wall of 1.6M vertices (3.2M faces) and 650 traces sampled every
5 mm. A grid of windows of r 2 m over the face (`engine.scan_circle.grid_scan_circles`). For each:
`engine.scan_circle.window_rock` (the area within the sphere, the edge where it cuts the mesh) against the
peer, VTK on the same mesh: `clip_scalar` of the distance from the centre (vtkClipPolyData, the area
inside) and `contour` of it at r (the edge), on the faces near the centre, as ours. Areas agree within 0.5%
(VTK clips each face along a straight chord, ours counts 16² sub-triangles) and edge lengths within 1e-6
(the same linear interpolation along the mesh's edges). Then `measure_scan_circle` of the 650 traces with
the rock known, as the 3D viewer measures again after an edit.

Run:  python tests/benchmarks/bench_scan_circle.py
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import pyvista as pv

sys.path.insert(0, str(Path(__file__).resolve().parent))  # beside bench_intensity.py
from bench_intensity import paper_scene  # noqa: E402
from bench_scanline import best_of  # noqa: E402

RADIUS = 2.0


def peer_window(surface: pv.PolyData, centres: np.ndarray, centre: np.ndarray) -> tuple[float, float]:
    """VTK's area inside the sphere and length of its cut, on the faces whose centroid lies within r + 1 m."""
    near = surface.extract_cells(np.flatnonzero(np.linalg.norm(centres - centre, axis=1) <= RADIUS + 1.0))
    near = near.extract_surface(algorithm="dataset_surface")
    near.point_data["d"] = np.linalg.norm(np.asarray(near.points) - centre, axis=1)
    inside = near.clip_scalar(scalars="d", value=RADIUS, invert=True)
    edge = near.contour([RADIUS], scalars="d")
    lines = edge.lines.reshape(-1, 3)[:, 1:]
    return inside.area, float(np.linalg.norm(np.diff(np.asarray(edge.points)[lines], axis=1), axis=2).sum())


def main() -> None:
    from engine.scan_circle import grid_scan_circles, measure_scan_circle, pooled_windows, window_rock

    mesh, traces = paper_scene()
    print(f"mesh: {len(mesh.vertices):,} vertices, {len(mesh.faces):,} faces; {len(traces)} traces")
    t = time.perf_counter()
    mesh.face_tree, mesh.face_reach, mesh.face_centroids, mesh.face_areas, mesh.boundary_edges  # noqa: B018
    print(f"face caches (once per mesh): {time.perf_counter() - t:.2f} s")
    t = time.perf_counter()
    circles = grid_scan_circles(mesh, RADIUS)
    print(f"grid of {len(circles)} windows of r {RADIUS:g} m laid in {time.perf_counter() - t:.2f} s")
    surface = pv.PolyData(mesh.vertices, np.column_stack([np.full(len(mesh.faces), 3), mesh.faces]).ravel())
    ours_total = peer_total = again_total = 0.0
    measures = []
    for circle in circles[:: max(1, len(circles) // 6)]:
        ours, rock = best_of(lambda: window_rock(mesh, circle))
        theirs, (area, length) = best_of(lambda: peer_window(surface, mesh.face_centroids, circle.centre))
        assert abs(rock.area - area) <= 5e-3 * area, (rock.area, area)
        assert abs(rock.perimeter - length) <= 1e-6 * length, (rock.perimeter, length)
        again, measure = best_of(lambda: measure_scan_circle(mesh, traces, circle, rock=rock))
        measures.append(measure)
        print(f"{circle.name}: window's rock {ours:.3f} s, VTK clip and contour {theirs:.3f} s "
              f"({theirs / ours:.2f}×); area {rock.area:.3f} m² (VTK {area:.3f}), edge {rock.perimeter:.3f} m "
              f"(the same to 1e-6); {measure.counts.cuts} cuts, {measure.counts.ends} ends measured again in "
              f"{again:.3f} s")
        ours_total, peer_total, again_total = ours_total + ours, peer_total + theirs, again_total + again
    pool = pooled_windows(measures)
    print(f"{len(measures)} windows: window_rock {ours_total:.2f} s, VTK {peer_total:.2f} s, ratio "
          f"{peer_total / ours_total:.2f}; counts again {again_total:.2f} s; pooled P21 {pool.p21:.3f} /m, "
          f"mean trace length {pool.mean_length:.2f} m")


if __name__ == "__main__":
    main()
