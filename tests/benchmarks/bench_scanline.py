"""Virtual scanlines at the paper's scale, the rock under them side by side with VTK's cutter.

Scene: bench_intensity's rough 40 m × 20 m wall of 1.6M vertices (3.2M faces) and 650 traces sampled every
5 mm. Five level scanlines 38 m long, reach 0.5 m. For each: `engine.scanline.rock_under` (the mesh cut by
the plane of the line and the rock's mean normal, clipped to the line and its reach) against the peer,
pyvista's `slice` (vtkCutter) of the same mesh by the same plane, clipped the same way in numpy; the two
sections must have the same length (1e-6) and cover the same stretches of the line. Then the whole
`measure_scanline` (crossings of the 650 traces, spacing) with the rock known, as the 3D viewer measures
again after an edit.

Run:  python tests/benchmarks/bench_scanline.py
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import pyvista as pv

sys.path.insert(0, str(Path(__file__).resolve().parent))  # beside bench_intensity.py
from bench_intensity import HEIGHT, WIDTH, paper_scene  # noqa: E402


def best_of(f, n: int = 3) -> tuple[float, object]:
    best, out = np.inf, None
    for _ in range(n):
        t = time.perf_counter()
        out = f()
        best = min(best, time.perf_counter() - t)
    return best, out


def peer_section(surface: pv.PolyData, line, plane_normal: np.ndarray) -> np.ndarray:
    """VTK's cut of the mesh by the plane, as segments (K, 2, 3), clipped to the line and its reach."""
    from engine.scanline import _within

    cut = surface.slice(normal=plane_normal, origin=line.start, generate_triangles=False)
    lines = cut.lines.reshape(-1, 3)[:, 1:]  # vtkCutter gives two-point lines
    return _within(np.asarray(cut.points)[lines], line)


def main() -> None:
    from engine.scanline import Scanline, measure_scanline, rock_under, sampled_runs

    mesh, traces = paper_scene()
    print(f"mesh: {len(mesh.vertices):,} vertices, {len(mesh.faces):,} faces; {len(traces)} traces")
    t = time.perf_counter()
    mesh.face_tree, mesh.face_reach, mesh.face_normals, mesh.face_areas  # noqa: B018 - the caches a viewer holds
    print(f"face caches (once per mesh): {time.perf_counter() - t:.2f} s")
    surface = pv.PolyData(mesh.vertices, np.column_stack([np.full(len(mesh.faces), 3), mesh.faces]).ravel())
    ours_total = peer_total = 0.0
    for z in np.linspace(2.0, HEIGHT - 2.0, 5):
        ends = [mesh.vertices[np.argmin(np.abs(mesh.vertices[:, 0] - x) + np.abs(mesh.vertices[:, 2] - z))]
                for x in (1.0, WIDTH - 1.0)]
        line = Scanline(*ends, reach=0.5)
        ours, rock = best_of(lambda: rock_under(mesh, line))
        theirs, section = best_of(lambda: peer_section(surface, line, rock.plane_normal))
        length = np.linalg.norm(np.diff(rock.section, axis=1), axis=2).sum()
        peer_length = np.linalg.norm(np.diff(section, axis=1), axis=2).sum()
        assert abs(length - peer_length) <= 1e-6 * peer_length, (length, peer_length)
        np.testing.assert_allclose(rock.runs, sampled_runs(section, line), atol=1e-9)
        again, measure = best_of(lambda: measure_scanline(mesh, traces, line, rock=rock))
        print(f"z {z:5.2f} m: rock under the line {ours:.3f} s, VTK slice {theirs:.3f} s ({theirs / ours:.2f}×); "
              f"section {length:.3f} m ({len(rock.section):,} segments, the same length to 1e-6); "
              f"{measure.all.n} crossings measured again in {again:.3f} s")
        ours_total, peer_total = ours_total + ours, peer_total + theirs
    print(f"five scanlines: rock_under {ours_total:.2f} s, VTK slice {peer_total:.2f} s, "
          f"ratio {peer_total / ours_total:.2f}")


if __name__ == "__main__":
    main()
