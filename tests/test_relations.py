"""Abutting and crossing between sets (`engine.relations`): hand counts, a map built set by set with its
truth known, fractopo's relationships on the same map, and the outcrop's stored contacts."""

import csv
import json
import os
import shutil

import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import to_hex
from scipy.stats import binom

from engine.cli import main
from engine.errors import InputError
from engine.maps2d import SNAP, Area, MapTraces, analyse_map, analyse_traces, report_lines
from engine.plots import SET_COLORS, relations_plot
from engine.relations import outcrop_relations, set_relations, stored_contacts
from tests.test_maps2d import HOLE, SHELL, _unit, _write

os.environ.setdefault("FRACTOPO_DISABLE_CACHE", "1")  # fractopo would cache to ./.cache otherwise

LAYERS = (("A", 110, 30.0, 0.0), ("B", 150, 120.0, 0.7), ("C", 110, 75.0, 0.7))
"""The sets of `layered_network` in the order they form: name, traces, mean direction (degrees from +x),
chance that an end stops on an older trace."""


def layered_network(seed, size=100.0):
    """Straight traces laid down set by set: each end of a trace of B and C runs on until it meets an older
    trace (of the sets before) with the chance given, else its own length; A's traces cross each other.
    Returns the lines, their sets and, per end, the trace it stopped on (-1: none)."""
    rng = np.random.default_rng(seed)
    lines, sets, stops = [], [], []
    for name, n, angle, p_stop in LAYERS:
        older = list(lines)
        for _ in range(n):
            c = rng.uniform(-0.1 * size, 1.1 * size, 2)
            d = _unit(rng.normal(angle, 8))
            h = rng.lognormal(np.log(0.22 * size), 0.5) / 2
            ends, stopped = [], []
            for sign in (-1, 1):
                reach, on = _first_hit(c, sign * d, h, older) if rng.random() < p_stop else (h, -1)
                ends.append(c + sign * reach * d)
                stopped.append(on)
            lines.append(np.array(ends))
            sets.append(name)
            stops.append(stopped)
    return lines, sets, np.array(stops)


def _first_hit(c, d, h, lines):
    """(distance, index) of the first of `lines` met from c along d within h, else (h, -1)."""
    best, index = h, -1
    for k, (a, b) in enumerate(lines):
        e, w = b - a, a - c
        den = d[0] * e[1] - d[1] * e[0]
        if den != 0:
            t, u = (w[0] * e[1] - w[1] * e[0]) / den, (w[0] * d[1] - w[1] * d[0]) / den
            if 0 < t < best and 0 <= u <= 1:
                best, index = t, k
    return best, index


def truth(lines, sets, stops, snap=SNAP):
    """What the relations must be, by brute force over every pair of traces (and shapely for the area): an
    end inside the area, farther than `snap` from its edge, abuts a trace within `snap` of it and farther
    than that from the trace's ends; a crossing is where two traces cut each other inside the area, that
    far from its edge and from the four ends. Also the abutting ends the map was built with (`stops`)."""
    from shapely.geometry import Point, Polygon

    area = Polygon(SHELL, [HOLE])
    inside = lambda p: area.contains(Point(p)) and area.boundary.distance(Point(p)) > snap  # noqa: E731
    names = sorted(set(sets))
    group = [names.index(s) for s in sets]
    abuts, built, crosses = (np.zeros((3, 3), int) for _ in range(3))
    for i, line in enumerate(lines):
        for k in (0, 1):
            p = line[k]
            if not inside(p):
                continue
            near = [j for j, (a, b) in enumerate(lines) if j != i and _distance(p, a, b) <= snap
                    and np.linalg.norm(lines[j] - p, axis=1).min() > snap]
            if near:
                abuts[group[i], group[min(near, key=lambda j: _distance(p, *lines[j]))]] += 1
            if stops[i, k] >= 0 and np.linalg.norm(lines[stops[i, k]] - p, axis=1).min() > snap:
                built[group[i], group[stops[i, k]]] += 1
    for i in range(len(lines)):
        for j in range(i + 1, len(lines)):
            (a, b), (c, d) = lines[i], lines[j]
            e, f = b - a, d - c
            den = e[0] * f[1] - e[1] * f[0]
            if den == 0:
                continue
            t = ((c - a)[0] * f[1] - (c - a)[1] * f[0]) / den
            u = ((c - a)[0] * e[1] - (c - a)[1] * e[0]) / den
            p = a + t * e
            if 0 < t < 1 and 0 < u < 1 and inside(p) and min(
                    np.linalg.norm(np.array([a, b, c, d]) - p, axis=1)) > snap:
                crosses[group[i], group[j]] += 1
                crosses[group[j], group[i]] += group[i] != group[j]
    return abuts, built, crosses


def _distance(p, a, b):
    s = np.clip(np.dot(p - a, b - a) / np.dot(b - a, b - a), 0.0, 1.0)
    return np.linalg.norm(a + s * (b - a) - p)


def test_hand_counted_relations():
    sets = ["1", "1", "2", None, "10"]
    codes = [("T", "B"), ("T", "T"), ("T", "C"), ("T", "B"), ("T", "B")]
    abutting = np.array([[2, -1], [2, 0], [0, 1], [0, -1], [-1, -1]])  # trace 2's end is C: not an abutment
    crossings = np.array([[0, 1], [0, 2], [1, 3], [2, 4]])
    r = set_relations(sets, codes, abutting, crossings)
    assert r.sets == ("1", "2", "10")  # natural order
    np.testing.assert_array_equal(r.abuts, [[1, 2, 0], [1, 0, 0], [0, 0, 0]])
    np.testing.assert_array_equal(r.crosses, [[1, 1, 0], [1, 0, 1], [0, 1, 0]])
    assert (r.unplaced, r.unset) == (1, 2)  # trace 4's T against nothing; trace 3's end and crossing
    pairs = {(p.first, p.second): p for p in r.pairs()}
    assert list(pairs) == [("1", "1"), ("1", "2"), ("1", "10"), ("2", "2"), ("2", "10"), ("10", "10")]
    one_two = pairs["1", "2"]
    assert (one_two.crossings, one_two.first_abuts, one_two.second_abuts) == (1, 2, 1)
    assert one_two.p_value == pytest.approx(1.0)
    assert pairs["1", "1"].second_abuts is None and np.isnan(pairs["1", "1"].p_value)
    assert np.isnan(pairs["2", "10"].p_value)  # no abutting end either way
    assert r.rows()[1] == ("1", "2", 1, 2, 1, 1.0) and r.rows()[0][4:] == ("", "")
    assert json.loads(json.dumps(r.to_dict()))["pairs"][0] == {
        "sets": ["1", "1"], "crossings": 1, "first_ends_against_second": 1, "second_ends_against_first": None,
        "binomial_p": None}
    assert r.describe()[-1] == "left out: 1 T ends against no trace, 2 contacts with a trace of no set"
    ordered = set_relations(sets, codes, abutting, crossings, names=["10", "2", "1"])
    np.testing.assert_array_equal(ordered.abuts, r.abuts[::-1, ::-1])


def test_binomial_p_value_and_verdict():
    sets = ["a"] * 12 + ["b"]
    codes = [("T", "B")] * 12 + [("T", "B")]
    abutting = np.array([[12, -1]] * 12 + [[0, -1]])  # eleven... twelve of a's ends against b, one of b's against a
    pair = set_relations(sets, codes, abutting, np.zeros((0, 2), int)).pairs()[1]
    assert (pair.first_abuts, pair.second_abuts) == (12, 1)
    assert pair.p_value == pytest.approx(2 * binom.cdf(1, 13, 0.5), rel=1e-12)  # two-sided, symmetric
    assert pair.describe() == ("sets a and b: 0 crossings; set a ends against set b in 12 of 13 abutting ends "
                               f"(binomial p {pair.p_value:.2g}: set a the younger)")
    even = set_relations(["a", "a", "b", "b"], [("T", "B")] * 4, np.array([[2, -1], [3, -1], [0, -1], [1, -1]]),
                         np.zeros((0, 2), int)).pairs()[1]
    assert even.p_value == pytest.approx(1.0) and "younger" not in even.describe()


@pytest.fixture(scope="module")
def layered():
    lines, sets, stops = layered_network(4)
    result = analyse_traces(MapTraces(lines, sets, np.arange(len(lines)), "layered"), Area([[SHELL, HOLE]], "area"),
                            n_bootstrap=0)
    return lines, sets, stops, result


def test_a_map_built_set_by_set_gives_its_relations(layered):
    lines, sets, stops, result = layered
    abuts, built, crosses = truth(lines, sets, stops)
    r = result.relations
    print(f"\nends against (rows A, B, C):\n{r.abuts}\ncrossings:\n{r.crosses}")
    assert r.sets == ("A", "B", "C")
    np.testing.assert_array_equal(r.abuts, abuts)
    np.testing.assert_array_equal(r.crosses, crosses)
    assert built[1, 0] > 60 and built[2, :2].min() > 20 and np.triu(built).sum() == 0  # only on older sets
    accidental = abuts - built  # ends that happen to lie on a trace: two nearly collinear traces of A
    assert accidental.min() == 0 and accidental.sum() <= 2
    assert crosses[~np.eye(3, dtype=bool)].min() > 10  # plenty of crossings between every two sets
    assert (r.unplaced, r.unset) == (0, 0)
    assert sum(r.abuts.flat) == result.nodes.N_Y  # every Y node is an abutting end between sets
    lines_out = report_lines(result)
    assert any("set B ends against set A in" in line and "set B the younger" in line for line in lines_out)


def test_relations_agree_with_fractopo(tmp_path, layered):
    """fractopo's crosscut and abutting relationships (x, y, y-reverse per pair of sets) from its own nodes,
    with our sets, on the same map file."""
    fractopo = pytest.importorskip("fractopo")
    from fractopo.analysis.relationships import determine_crosscut_abutting_relationships

    lines, sets, _, _ = layered
    (traces_path, area_path), traces, area = _write(tmp_path, lines, sets, [[SHELL, HOLE]], "GPKG", ".gpkg")
    ours = analyse_map(traces_path, area_path, tmp_path / "out", n_bootstrap=0).analysis.relations
    network = fractopo.Network(traces, area, name="layered", determine_branches_nodes=True, truncate_traces=True,
                               snap_threshold=SNAP, circular_target_area=False)
    theirs = determine_crosscut_abutting_relationships(
        network.trace_series, network.node_series, network.node_types, np.asarray(network.trace_gdf["set"]),
        ("A", "B", "C"), SNAP, "layered")
    print(f"\nfractopo:\n{theirs}")
    pairs = {(p.first, p.second): p for p in ours.pairs()}
    for _, row in theirs.iterrows():
        first, second = row["sets"]
        pair = pairs[first, second]
        assert (pair.crossings, pair.first_abuts, pair.second_abuts) == (row["x"], row["y"], row["y-reverse"])
        assert row["error-count"] == 0
    assert len(theirs) == 3


def test_map_files_and_figure(tmp_path, layered):
    lines, sets, _, _ = layered
    (traces_path, area_path), *_ = _write(tmp_path, lines, sets, [[SHELL, HOLE]], "GeoJSON", ".geojson")
    output = analyse_map(traces_path, area_path, tmp_path / "out", n_bootstrap=0)
    r = output.analysis.relations
    rows = read_csv(tmp_path / "out" / "relations.csv")
    assert tuple(rows[0]) == ("set_a", "set_b", "crossings", "a_ends_against_b", "b_ends_against_a", "binomial_p")
    assert [(a, b, int(x), int(y)) for a, b, x, y, *_ in rows[1:]] == [
        (p.first, p.second, p.crossings, p.first_abuts) for p in r.pairs()]
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["relations"] == json.loads(json.dumps(r.to_dict()))
    assert (tmp_path / "out" / "relations.png").stat().st_size > 0
    figure = output.plots["relations"].figure
    FigureCanvasAgg(figure)
    figure.canvas.draw()
    ends, crosses = figure.axes[:2]
    shown = {(round(t.get_position()[1]), round(t.get_position()[0])): int(t.get_text()) for t in ends.texts}
    assert shown == {(i, j): n for (i, j), n in np.ndenumerate(r.abuts)}
    shown = {(round(t.get_position()[1]), round(t.get_position()[0])): int(t.get_text()) for t in crosses.texts}
    assert shown == {(i, j): n for (i, j), n in np.ndenumerate(r.crosses) if j <= i}  # the lower triangle
    assert [to_hex(t.get_color()) for t in ends.get_yticklabels()] == list(SET_COLORS[:3])
    box = figure.get_tightbbox().transformed(figure.dpi_scale_trans)
    assert box.x0 >= -1 and box.y0 >= -1 and box.x1 <= figure.bbox.width + 1 and box.y1 <= figure.bbox.height + 1


def test_a_map_without_sets_has_no_relations(tmp_path, layered):
    lines, _, _, _ = layered
    (traces_path, area_path), *_ = _write(tmp_path, lines, [""] * len(lines), [[SHELL, HOLE]], "GPKG", ".gpkg")
    output = analyse_map(traces_path, area_path, tmp_path / "out", n_bootstrap=0)
    assert output.analysis.relations.sets == ()
    assert output.plots["relations"].figure is None and "--set-column" in output.plots["relations"].reason
    assert not (tmp_path / "out" / "relations.csv").exists() and not (tmp_path / "out" / "relations.png").exists()
    assert json.loads((tmp_path / "out" / "summary.json").read_text())["relations"] is None


def test_one_set_is_a_one_by_one_figure():
    r = set_relations(["s", "s"], [("T", "B"), ("B", "B")], np.array([[1, -1], [-1, -1]]), np.zeros((0, 2), int))
    plot = relations_plot(r, ["#000000"])
    assert [t.get_text() for t in plot.figure.axes[0].texts] == ["1"] and plot.table.rows == [("s", "s", 0, 1, "", "")]


def read_csv(path):
    with open(path, newline="", encoding="utf-8") as f:
        return list(csv.reader(f))


def _nearest_trace(p, lines, own, tolerance):
    """Brute force: the trace whose polyline comes nearest p (not `own`), if within tolerance and p is
    farther than it from that trace's ends."""
    best, index = tolerance, -1
    for k, q in enumerate(lines):
        if k == own:
            continue
        a, b = q[:-1], q[1:]
        s = np.clip(np.einsum("ij,ij->i", p - a, b - a) / np.einsum("ij,ij->i", b - a, b - a), 0, 1)
        d = np.linalg.norm(a + s[:, None] * (b - a) - p, axis=1).min()
        if d <= best and min(np.linalg.norm(q[0] - p), np.linalg.norm(q[-1] - p)) > tolerance:
            best, index = d, k
    return index


def test_outcrop_relations_from_the_stored_contacts(quick_demo, tmp_path, capsys):
    from engine.project import Project

    shutil.copytree(quick_demo / "data", tmp_path / "data")
    shutil.copy2(quick_demo / "demo.tracemap", tmp_path / "demo.tracemap")
    path = tmp_path / "demo.tracemap"
    with Project.open(path) as project:
        traces, topology = project.traces3d(), project.result("topology")
    lines = [t.points for t in traces]
    abutting, crossings = stored_contacts(traces, topology["contacts"])
    for i, t in enumerate(traces):  # every stored contact is the nearest trace, found by brute force
        for k in (0, 1):
            assert abutting[i, k] == _nearest_trace(t.points[(0, -1)[k]], lines, i, topology["tolerance_m"])
    assert len(crossings) == topology["crossings"]
    r = outcrop_relations(traces, topology["contacts"])
    assert r.sets == tuple(str(s) for s in sorted({t.set_id for t in traces if t.set_id >= 0}))
    is_t = np.array([(t.term_start == "T", t.term_end == "T") for t in traces])
    with_set = np.array([t.set_id >= 0 for t in traces])
    placed = is_t & (abutting >= 0)
    assert r.unplaced == int((is_t & (abutting < 0)).sum())
    between_sets = placed & with_set[:, None] & with_set[np.maximum(abutting, 0)]
    assert r.abuts.sum() == int(between_sets.sum()) > 0
    assert r.unset == int((placed & ~between_sets).sum()) + int((~with_set[crossings]).any(axis=1).sum())
    assert main(["analyse", str(path), "--bootstrap", "0"]) == 0
    said = capsys.readouterr().out
    assert f"set {r.sets[0]} with itself:" in said
    assert main(["export", str(path), str(tmp_path / "export")]) == 0
    with Project.open(path) as project:
        traces = project.traces3d()
        contacts = project.result("topology")["contacts"]
    again = outcrop_relations(traces, contacts)
    rows = read_csv(tmp_path / "export" / "relations.csv")
    assert [tuple(int(x) for x in row[2:4]) for row in rows[1:]] == [(p.crossings, p.first_abuts) for p in again.pairs()]
    summary = json.loads((tmp_path / "export" / "summary.json").read_text())
    assert summary["relations"] == json.loads(json.dumps(again.to_dict()))
    # a trace gone: the ends against it are T ends against no trace, its own ends and crossings are gone
    by_id = {t.id: t for t in traces}
    gone = next(t for t in traces if t.set_id >= 0 and any(c[2] == t.id and by_id[c[0]].set_id >= 0
                                                           and _code(by_id[c[0]], c[1]) == "T"
                                                           for c in contacts["abutting"]))
    against_it = sum(c[2] == gone.id and _code(by_id[c[0]], c[1]) == "T" for c in contacts["abutting"])
    counted = [c for c in contacts["abutting"] if _code(by_id[c[0]], c[1]) == "T" and by_id[c[0]].set_id >= 0
               and by_id[c[2]].set_id >= 0]
    its_own = sum(gone.id in (c[0], c[2]) for c in counted)
    crossing_it = sum(gone.id in pair for pair in contacts["crossings"]
                      if by_id[pair[0]].set_id >= 0 and by_id[pair[1]].set_id >= 0)
    with Project.open(path) as project:
        project.remove_traces3d([gone.id])
        after = outcrop_relations(project.traces3d(), project.result("topology")["contacts"])
        assert "topology" in project.stale_results()
    assert after.abuts.sum() == again.abuts.sum() - its_own
    assert sum(p.crossings for p in after.pairs()) == sum(p.crossings for p in again.pairs()) - crossing_it
    own_unplaced = sum(_code(gone, end) == "T" and not abutting_of(contacts, gone.id, end) for end in (0, 1))
    assert after.unplaced == again.unplaced + against_it - own_unplaced


def _code(trace, end):
    return trace.term_start if end == 0 else trace.term_end


def abutting_of(contacts, trace_id, end):
    return any(c[0] == trace_id and c[1] == end for c in contacts["abutting"])


def test_damaged_contacts_are_refused_with_a_clear_message(quick_demo):
    from engine.project import Project

    with Project.open(quick_demo / "demo.tracemap") as project:
        traces = project.traces3d()
    with pytest.raises(InputError, match="stored contacts of the last analysis are damaged"):
        stored_contacts(traces, {"abutting": [[traces[0].id, 7, traces[1].id]], "crossings": []})
    with pytest.raises(InputError, match="run `tracemap analyse` again"):
        stored_contacts(traces, {"crossings": []})
