"""The figures of a 2D map's analysis (`engine.map_plots`): what each draws, checked against the analysis."""

import numpy as np
import pytest
from matplotlib.colors import to_hex

from engine.map_plots import map_plots, set_names
from engine.maps2d import Area, MapTraces, analyse_map, analyse_traces, report_lines
from engine.plots import SET_COLORS, TERMINATION_COLORS
from tests.test_maps2d import HOLE, SHELL, _write, random_network

SQUARE = [[np.array([[0.0, 0], [10, 0], [10, 10], [0, 10]])]]
HAND = [np.array([[1.0, 5], [9, 5]]),  # I, I
        np.array([[5.0, 5], [5, 8]]),  # Y on the first, I
        np.array([[3.0, 2], [3, 7]]),  # I, I; X with the first
        np.array([[7.0, 8], [12, 8]]),  # I, E (clipped at x = 10)
        np.array([[2.0, -1], [2, 1]]),  # E (clipped at y = 0), I
        np.array([[-1.0, 9], [11, 9.5]])]  # E, E: crosses the area


@pytest.fixture(scope="module")
def hand():
    sets = ["a", "b", "a", None, "b", "a"]
    result = analyse_traces(MapTraces(HAND, sets, np.arange(6), "hand"), Area(SQUARE, "square"), snap=0.01,
                            n_bootstrap=0, grid=2.5)
    return result, map_plots(result, SQUARE)


def _markers(ax):
    """Marker lines by marker symbol: their points (n, 2)."""
    return {line.get_marker(): np.asarray(line.get_xydata()).reshape(-1, 2) for line in ax.lines
            if line.get_linestyle() == "None"}


def test_every_figure_is_made(hand):
    _, plots = hand
    assert list(plots) == ["map", "length_histogram", "kaplan_meier", "terminations", "rose", "relations",
                           "p21_grid", "c_b_grid"]
    assert all(p.figure is not None for p in plots.values())


def test_map_draws_each_trace_by_set_and_each_node_where_it_is(hand):
    result, plots = hand
    ax = plots["map"].figure.axes[0]
    traces = [line for line in ax.lines if line.get_linestyle() != "None"]
    assert len(traces) == 6
    for line, drawn, s in zip(result.traces, traces, result.sets):
        np.testing.assert_allclose(drawn.get_xydata(), line)
        assert to_hex(drawn.get_color()) == ({"a": SET_COLORS[0], "b": SET_COLORS[1]}.get(s, "#000000"))
    markers = _markers(ax)
    # the hand count of tests.test_maps2d.test_hand_counted_map: 7 I, 1 Y, 1 X, 4 E
    assert {m: len(xy) for m, xy in markers.items()} == {"o": 7, "^": 1, "D": 1, "s": 4}
    np.testing.assert_allclose(markers["^"], [[5, 5]])
    np.testing.assert_allclose(markers["D"], [[3, 5]])
    np.testing.assert_allclose(sorted(map(tuple, markers["s"])), [(0, 9 + 0.5 / 12), (2, 0), (10, 8), (10, 9 + 5.5 / 12)])
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels == ["set a", "set b", "I (7)", "Y (1)", "X (1)", "E (4)"]
    rows = plots["map"].table.rows
    assert [r[3] for r in rows].count("I") == 7 and [r[0] for r in rows] == list(range(13))


def test_lengths_and_survival_are_the_analysis(hand):
    result, plots = hand
    table = plots["length_histogram"].table
    assert table.columns[:4] == ("bin_low", "bin_high", "complete", "censored")  # map units: no "_m"
    assert sum(r[2] for r in table.rows) == 3 and sum(r[3] for r in table.rows) == 3  # 3 traces reach the edge
    ax = plots["length_histogram"].figure.axes[0]
    assert ax.get_xlabel() == "trace length (map units)"
    km = plots["kaplan_meier"]
    curves = km.figure.axes[0].lines
    steps = [line for line in curves if line.get_linestyle() != "None"]
    np.testing.assert_allclose(steps[0].get_ydata(), np.r_[1.0, result.lengths.kaplan_meier.survival])
    assert to_hex(steps[0].get_color()) == "#000000"
    assert [to_hex(s.get_color()) for s in steps[1:]] == [SET_COLORS[0], SET_COLORS[1]][:len(steps) - 1]
    assert {r[0] for r in km.table.rows} <= {"all", "a", "b"} and km.table.columns[1] == "length"


def test_topology_bars_are_the_sanderson_nixon_nodes(hand):
    result, plots = hand
    bars_ax = plots["terminations"].figure.axes[0]
    heights = [p.get_height() for p in bars_ax.patches]
    assert [t.get_text() for t in bars_ax.get_xticklabels()] == ["I", "Y", "X", "E"]
    assert heights == [7, 1, 1, 4]
    assert [to_hex(p.get_facecolor()) for p in bars_ax.patches] == [TERMINATION_COLORS[c].lower() for c in "BTXC"]
    values = dict(plots["terminations"].table.rows)
    assert (values["I"], values["E"], values["C_B"]) == (7, 4, result.nodes.C_B)


def test_sets_are_coloured_alike_in_the_map_and_the_rose():
    lines, sets = random_network(2, n1=30, n2=40)
    result = analyse_traces(MapTraces(lines, sets, np.arange(len(lines)), "random"), Area([[SHELL, HOLE]], "area"),
                            n_bootstrap=0)
    plots = map_plots(result, [[SHELL, HOLE]])
    assert set_names(result.sets) == ["1", "2"]
    drawn = {to_hex(line.get_color()) for line in plots["map"].figure.axes[0].lines if line.get_linestyle() != "None"}
    assert drawn == {SET_COLORS[0], SET_COLORS[1]}
    rose = plots["rose"].figure.axes[0]
    outlined = {to_hex(p.get_edgecolor()) for p in rose.patches if not p.get_fill()}
    assert outlined == drawn
    fits = [f for f in result.lengths.fits if f.params]
    assert len(plots["length_histogram"].figure.axes[0].lines) == len(fits) == 4


def test_analyse_map_writes_the_figures(tmp_path):
    lines, sets = random_network(3, n1=20, n2=30)
    (traces_path, area_path), *_ = _write(tmp_path, lines, sets, [[SHELL, HOLE]], "GeoJSON", ".geojson")
    output = analyse_map(traces_path, area_path, tmp_path / "out", n_bootstrap=0, grid=20)
    for name in ("map", "p21_grid", "c_b_grid"):  # UTM coordinates in full, not as an offset (+6.7e6)
        ax = output.plots[name].figure.axes[0]
        assert [axis.get_major_formatter().get_offset() for axis in (ax.xaxis, ax.yaxis)] == ["", ""]
        assert {t.get_text() for t in ax.get_yticklabels()} & {"6700000", "6700040"}
        figure = output.plots[name].figure
        assert ax.get_tightbbox().x0 >= 0 and max(a.get_tightbbox().x1 for a in figure.axes) <= figure.bbox.x1
    pngs = sorted(p.name for p in (tmp_path / "out").glob("*.png"))
    assert pngs == ["c_b_grid.png", "kaplan_meier.png", "length_histogram.png", "map.png", "p21_grid.png",
                    "relations.png", "rose.png", "terminations.png"]
    assert all((tmp_path / "out" / name).read_bytes()[:4] == b"\x89PNG" for name in pngs)


def test_report_lines_say_what_the_analysis_found(hand):
    result, _ = hand
    lines = report_lines(result)
    assert lines[0] == ("6 traces in the area (0 pieces too short to keep); nodes 7 I, 1 Y, 1 X, 4 E; "
                        "connections per line 1.00, per branch 1.00")  # N_L 4, N_B 7: C_L 2·2/4, C_B 7/7
    assert lines[1].startswith(f"area 100; P21 {result.intensity['P21']:.4g}") and "4 connected groups" in lines[1]
    assert [line.split(":")[0] for line in lines[2:5]] == ["lengths, all traces", "lengths, set a", "lengths, set b"]
    assert "(3 censored)" in lines[2] and lines[-1].startswith("P21 map: ")
