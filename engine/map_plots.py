"""The figures of a 2D trace map (`tracemap analyse-map`): what fractopo and FracAbility users look at.

The network on its sampling area with the I/Y/X/E nodes, the trace lengths with their censored fits, the
Kaplan–Meier curves, the node counts with the I–Y–X ternary diagram, the rose diagram, and the P21 and
connections-per-branch maps when a grid was asked for. The length, survival and topology figures are those
of an outcrop's plots (`engine.plots`), labelled in map units and with Sanderson & Nixon's node names (the
counts are the same, PEERS.md): one look across the 2D and the 3D tools.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict
from typing import TYPE_CHECKING

import numpy as np
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import PathPatch

from engine.map_intensity import MAPS, area_path, intensity_grid_plot, map_axes
from engine.plots import (FIGSIZE, SET_COLORS, TERMINATION_COLORS, Plot, Table, histogram_plot, km_plot,
                          relations_plot, topology_plot)
from engine.rose import axial_mean, azimuth_groups, rose_bins, rose_plot

if TYPE_CHECKING:
    from engine.maps2d import MapAnalysis

UNIT = "map units"
# each end code's node (as engine.maps2d.NODE_TYPES) and marker; X nodes are crossings
NODE_MARKERS = {"B": ("I", "o"), "T": ("Y", "^"), "X": ("X", "D"), "C": ("E", "s")}
NODE_COLUMNS = ("node", "x", "y", "type", "trace")


def map_plots(result: MapAnalysis, polygons: Sequence[Sequence[np.ndarray]]) -> dict[str, Plot]:
    """Every figure of a map's analysis, by name (a file stem); `polygons` are the sampling area's
    (`engine.maps2d.Area.polygons`). The grid maps are there when the analysis made a grid."""
    plots = [network_map(result, polygons), length_plot(result), survival_plot(result),
             topology_plot(result.nodes, codes="IYXE"), rose_plot(*roses(result.traces, result.sets)),
             set_relations_plot(result)]
    if result.grid is not None:
        plots += [intensity_grid_plot(result.grid, result.traces, polygons, measure) for measure in MAPS]
    return {plot.name: plot for plot in plots}


def set_names(sets: Sequence[str | None]) -> list[str]:
    """The sets of a map's traces in sorted order (a trace with none is in no set)."""
    return sorted({s for s in sets if s})


def set_color(name: str, names: Sequence[str]) -> str:
    """The colour of a set of the map, by its place among `names` (as the rose diagram's)."""
    return SET_COLORS[names.index(name) % len(SET_COLORS)]


def set_relations_plot(result: MapAnalysis) -> Plot:
    """The sets' abutting and crossing counts (`engine.plots.relations_plot`), in the sets' colours; skipped,
    saying why, when the traces have no sets."""
    names = list(result.relations.sets)
    if not names:
        return Plot("relations", "Abutting and crossing between sets", None, None,
                    "the traces have no sets: give the attribute that holds them (--set-column)")
    return relations_plot(result.relations, [set_color(s, names) for s in names])


def network_map(result: MapAnalysis, polygons: Sequence[Sequence[np.ndarray]]) -> Plot:
    """The traces (coloured by set) on the sampling area (grey, holes white) with every node marked; map
    units, +y up, equal scale. Its table lists the nodes, as nodes.csv."""
    names = set_names(result.sets)
    fig = Figure(figsize=FIGSIZE, layout="constrained")
    ax = fig.add_subplot()
    ax.add_patch(PathPatch(area_path(polygons), facecolor="0.93", edgecolor="black", linewidth=1.0))
    for line, s in zip(result.traces, result.sets):
        ax.plot(*np.asarray(line).T, color=set_color(s, names) if s else "black", linewidth=0.9)
    rows = _node_rows(result)
    handles = [Line2D([], [], color=set_color(s, names), label=f"set {s}") for s in names]
    for code, (node, marker) in NODE_MARKERS.items():
        xy = np.array([(x, y) for _, x, y, kind, _ in rows if kind == node]).reshape(-1, 2)
        ax.plot(*xy.T, linestyle="none", marker=marker, markersize=4, color=TERMINATION_COLORS[code],
                markeredgecolor="k", markeredgewidth=0.3)
        handles.append(Line2D([], [], linestyle="none", marker=marker, color=TERMINATION_COLORS[code],
                              markeredgecolor="k", markeredgewidth=0.3, label=f"{node} ({len(xy)})"))
    ax.legend(handles=handles, fontsize="small", loc="upper left", bbox_to_anchor=(1.01, 1.0))
    map_axes(ax)
    ax.autoscale_view()
    ax.set_title(f"{len(result.traces)} traces in an area of {result.area:.4g} square {UNIT}", fontsize="medium")
    return Plot("map", "Trace map and nodes", fig, Table(NODE_COLUMNS, rows))


def _node_rows(result: MapAnalysis) -> list[tuple]:
    """(node, x, y, type, trace): each trace's two end nodes, then the X nodes (trace: the first one)."""
    rows = [(0, float(x), float(y), NODE_MARKERS[code][0], i)
            for i, (line, codes) in enumerate(zip(result.traces, result.terminations))
            for code, (x, y) in zip(codes, (line[0], line[-1]))]
    rows += [(0, float(x), float(y), "X", int(i)) for (i, _), (x, y) in zip(result.crossings.traces,
                                                                          result.crossings.points)]
    return [(k, *row[1:]) for k, row in enumerate(rows)]


def length_plot(result: MapAnalysis) -> Plot:
    """Trace lengths inside the area, complete and censored (an end at the area's edge), with the censored
    fits of all traces."""
    table = result.lengths
    lengths = np.array([_length(t) for t in result.traces])
    censored = np.array([codes.count("C") > 0 for codes in result.terminations], dtype=bool)
    fits = [asdict(f) for f in table.fits if f.params]
    return histogram_plot(lengths, censored, fits, unit=UNIT, quantity="trace length",
                          hint="" if fits else table.message)


def survival_plot(result: MapAnalysis) -> Plot:
    """Kaplan–Meier survival of all traces and of each set."""
    names = set_names(result.sets)
    groups = {"all": result.lengths, **result.lengths_by_set}
    curves = {label: a.kaplan_meier if a.kaplan_meier is not None else (a.message or "no complete trace")
              for label, a in groups.items()}

    def style(label: str) -> tuple[str, str]:
        return ("all traces", "k") if label == "all" else (f"set {label}", set_color(label, names))

    return km_plot(curves, unit=UNIT, quantity="trace length", style=style)


def roses(traces: Sequence[np.ndarray], sets: Sequence[str | None]):
    """The rose of every group ("all", then each set), the sets in the bins of all traces (so their bars
    compare), and each group's axial mean."""
    groups = azimuth_groups(traces, sets)
    bins = len(rose_bins(*groups["all"]).lengths)
    return ({k: rose_bins(a, w, bins=bins) for k, (a, w) in groups.items()},
            {k: axial_mean(a, w) for k, (a, w) in groups.items()})


def _length(line: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(line, axis=0), axis=1).sum())
