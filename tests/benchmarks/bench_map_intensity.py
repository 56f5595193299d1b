"""The P21 map of a 2D trace map side by side with fractopo's contour grid, on the same cells.

Map: `tests.test_maps2d.random_network` scaled up: two sets of straight traces, abutting and crossing, over a
non-convex 200 × 200 area with a hole (UTM-sized coordinates), 1,600 traces. Cells of 10 (400 cells),
discs of r 15. Ours: `engine.map_intensity.intensity_grid` on the traces clipped to the area (as
`analyse-map --grid` calls it, topology not included). fractopo: `run_grid_sampling` on the network's
traces, branches and nodes (the topology built beforehand, not timed), its joblib workers on both cores.
Where a disc lies wholly inside the area the lengths agree within 0.5% (fractopo's disc is a 64-gon).

Run:  python tests/benchmarks/bench_map_intensity.py
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("FRACTOPO_DISABLE_CACHE", "1")  # else joblib would return the first run's grid
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from tests.test_maps2d import HOLE, OFFSET, SHELL, random_network  # noqa: E402

SCALE = 2.0
CELL = 10.0


def main() -> None:
    said = []
    say = said.append
    import geopandas as gpd
    from fractopo import Network
    from fractopo.analysis.contour_grid import run_grid_sampling
    from shapely.geometry import LineString, Polygon, box

    from engine.map_intensity import intensity_grid
    from engine.maps2d import Area, MapTraces, analyse_traces

    lines, sets = random_network(4, n1=150 * 4, n2=250 * 4, size=100.0 * SCALE)
    shell, hole = SHELL * SCALE, HOLE * SCALE
    area = Area([[shell + OFFSET, hole + OFFSET]], "area")
    t = time.perf_counter()
    analysis = analyse_traces(MapTraces([line + OFFSET for line in lines], sets, np.arange(len(lines)), "map"),
                              area, n_bootstrap=0)
    say(f"map: {len(lines):,} traces, {len(analysis.traces):,} pieces in the area "
          f"(topology {time.perf_counter() - t:.1f} s, not timed below)")
    origin = OFFSET
    pieces = [p - origin for p in analysis.traces]
    boundary = tuple(e - origin for e in area.boundary)
    ours = []
    for _ in range(3):
        t = time.perf_counter()
        grid = intensity_grid(pieces, boundary, CELL, sets=analysis.sets)
        ours.append(time.perf_counter() - t)
    say(f"tracemap intensity_grid: {grid.area.size:,} cells in {min(ours):.3f} s (best of 3)")

    traces = gpd.GeoDataFrame({"set": sets}, geometry=[LineString(p + OFFSET) for p in lines], crs="EPSG:3067")
    polygon = gpd.GeoDataFrame(geometry=[Polygon(shell + OFFSET, [hole + OFFSET])], crs="EPSG:3067")
    t = time.perf_counter()
    network = Network(traces, polygon, name="bench", determine_branches_nodes=True, truncate_traces=True,
                      snap_threshold=0.001)
    say(f"fractopo network (topology, not timed below): {time.perf_counter() - t:.1f} s")
    xx, yy = np.meshgrid(grid.x + origin[0], grid.y + origin[1])
    cells = gpd.GeoDataFrame(geometry=[box(x - CELL / 2, y - CELL / 2, x + CELL / 2, y + CELL / 2)
                                       for x, y in zip(xx.ravel(), yy.ravel())], crs="EPSG:3067")
    t = time.perf_counter()
    theirs = run_grid_sampling(network.trace_gdf, network.branch_gdf, network.node_gdf, cell_width=CELL,
                               snap_threshold=0.001, precursor_grid=cells)
    peer = time.perf_counter() - t
    say(f"fractopo run_grid_sampling: {peer:.2f} s")
    whole = (grid.share > 1 - 1e-9).ravel()
    their_length = (theirs["Fracture Intensity P21"] * theirs["Area"]).to_numpy()[whole]
    error = np.abs(grid.length["all"].ravel()[whole] - their_length) / np.maximum(their_length, 1.0)
    say(f"cells wholly inside: {whole.sum()}, length within {error.max():.2%} of fractopo's")
    say(f"speed-up: {peer / min(ours):.0f}×")
    print("\n".join(said))


if __name__ == "__main__":
    main()
