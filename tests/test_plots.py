import csv
import shutil
from dataclasses import asdict, replace

import numpy as np
import pytest
from matplotlib.collections import PathCollection
from matplotlib.contour import ContourSet
from scipy.stats import vonmises_fisher

from engine.cli import main
from engine.errors import InputError
from engine.lengths import LengthTable, analyse_lengths, kaplan_meier
from engine.orientation import dip_dipdir_to_normal
from engine.plots import (SET_COLORS, PlotData, build_plots, cl_line, current_nodes, density_grid, equal_area,
                          frozen_fit, inverse_equal_area, km_groups, pole_density, save_figure, set_color,
                          ternary_xy, write_plots, write_table_csv)
from engine.sets import density_peaks, set_statistics


def synthetic_data(seed: int = 0, *, n: int = 80) -> PlotData:
    """Two Fisher sets of poles and censored lognormal lengths, with the fits `tracemap analyse` stores."""
    rng = np.random.default_rng(seed)
    means = dip_dipdir_to_normal(np.array([80.0, 30.0]), np.array([120.0, 250.0]))
    poles = np.vstack([vonmises_fisher(m, 25.0).rvs(n // 2, random_state=rng) for m in means])
    poles *= rng.choice([-1.0, 1.0], (len(poles), 1))  # axial: either sign
    set_id = np.repeat([0, 1], n // 2)
    set_id[:3] = -1
    sets = tuple({**asdict(set_statistics(poles[set_id == k], set_id=k))} for k in (0, 1))
    true = rng.lognormal(0.3, 0.7, n)
    window = rng.uniform(0.5, 6.0, n)
    surface, censored = np.minimum(true, window), true > window
    table = LengthTable(np.arange(n) + 1, set_id, surface * 0.95, surface, censored.astype(np.int64))
    ends = tuple(("C" if c else "B", "T" if k % 4 == 0 else "B") for k, c in enumerate(censored))
    fits = {"all": asdict(analyse_lengths(surface, censored, n_bootstrap=19))["fits"]}
    return PlotData(lengths=table, poles=poles, pole_ids=table.id.copy(), pole_sets=set_id, ends=ends, sets=sets,
                    crossings=12, fits=fits, p21={"p21": 0.8, "p21:set0": 0.5, "p21:set1": 0.3})


@pytest.fixture(scope="module")
def data():
    return synthetic_data()


@pytest.fixture(scope="module")
def plots(data):
    return build_plots(data)


def read_csv(path):
    with open(path, newline="", encoding="utf-8") as f:
        return list(csv.reader(f))


# -- projection and density ------------------------------------------------------------------------------

@pytest.mark.parametrize("dip, dipdir, expected", [
    (90.0, 90.0, (-1.0, 0.0)),  # vertical plane dipping east: pole on the primitive at azimuth 270
    (90.0, 0.0, (0.0, -1.0)),  # dipping north: pole due south
    (0.0, 123.0, (0.0, 0.0)),  # horizontal plane: pole at the centre
    (60.0, 30.0, tuple(np.sqrt(2) * np.sin(np.radians(30)) * np.array([np.sin(np.radians(210)),
                                                                        np.cos(np.radians(210))]))),
])
def test_equal_area_projection_of_poles(dip, dipdir, expected):
    n = dip_dipdir_to_normal(dip, dipdir)
    np.testing.assert_allclose(equal_area(n), expected, atol=1e-12)
    np.testing.assert_allclose(equal_area(-n), expected, atol=1e-12)  # axial: the sign does not matter


def test_equal_area_radius_and_inverse():
    rng = np.random.default_rng(1)
    v = rng.normal(size=(500, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    down = np.where(v[:, 2:] > 0, -v, v)
    theta = np.arccos(-down[:, 2])  # from the downward vertical
    xy = equal_area(v)
    np.testing.assert_allclose(np.linalg.norm(xy, axis=1), np.sqrt(2) * np.sin(theta / 2), atol=1e-12)
    np.testing.assert_allclose(inverse_equal_area(xy), down, atol=1e-12)


def test_density_averages_to_uniform_over_the_net(data):
    # equal area: grid points inside the primitive sample the hemisphere uniformly, so their mean is ∫ f dA
    x, y, density = density_grid(data.poles, n=301)
    gx, gy = np.meshgrid(x, y)
    inside = gx**2 + gy**2 <= 1.0
    assert density[inside].mean() == pytest.approx(1.0, abs=0.01)
    assert density.max() > 3.0  # two tight sets, far from uniform


def test_density_of_one_pole_and_against_the_set_peaks(data):
    n = np.array([[0.0, 0.6, 0.8]])
    kappa = 20.0
    # at the pole itself 4π·½[f(1) + f(−1)] = κ coth κ
    assert pole_density(n, n, kappa=kappa)[0] == pytest.approx(kappa / np.tanh(kappa), rel=1e-12)
    peak = density_peaks(data.poles, kappa=kappa)[0]  # engine.sets' density, same kernel
    assert pole_density(data.poles, peak.normal[None], kappa=kappa)[0] == pytest.approx(peak.density, rel=1e-9)


# -- figures and their tables ----------------------------------------------------------------------------

def test_stereonet_draws_poles_contours_and_labelled_set_means(data, plots):
    plot = plots["stereonet"]
    ax = plot.figure.axes[0]
    scatter = next(c for c in ax.collections if isinstance(c, PathCollection))
    np.testing.assert_allclose(scatter.get_offsets(), equal_area(data.poles), atol=1e-12)
    grey = np.array([0.55, 0.55, 0.55, 1.0])
    np.testing.assert_allclose(scatter.get_facecolors()[:3], [grey] * 3)  # non-systematic
    assert tuple(scatter.get_facecolors()[-1][:3]) == pytest.approx(tuple(int(SET_COLORS[1][k:k + 2], 16) / 255
                                                                          for k in (1, 3, 5)))
    contours = [c for c in ax.get_children() if isinstance(c, ContourSet)]
    assert contours and contours[0].levels[0] == 1.0  # multiples of uniform density
    labels = {t.get_text() for t in ax.texts}
    assert {"0", "1", "N", "E", "S", "W"} <= labels
    legend = [t.get_text() for t in plot.figure.legends[0].get_texts()]
    s = data.sets[0]
    assert legend[0] == f"set 0: {s['dip']:.0f}/{s['dip_direction']:03.0f}, κ {s['kappa']:.1f}, n {s['n']}"
    means = [r for r in plot.table.rows if r[0] == "set mean"]
    assert [r[1] for r in means] == [0, 1]
    np.testing.assert_allclose([r[5:] for r in means], equal_area(np.array([s["normal"] for s in data.sets])))


def test_length_histogram_bars_fits_and_csv(data, plots, tmp_path):
    plot = plots["length_histogram"]
    ax = plot.figure.axes[0]
    heights = np.array([p.get_height() for p in ax.patches])
    complete, censored = heights[:len(heights) // 2], heights[len(heights) // 2:]
    assert complete.sum() == (~data.lengths.censored).sum() and censored.sum() == data.lengths.censored.sum()
    legend = [t.get_text() for t in ax.get_legend().get_texts()]
    pvalues = {f["model"]: f["ad_pvalue"] for f in data.fits["all"]}
    assert f"lognormal (AD p {pvalues['lognorm']:.2f})" in legend
    assert len(ax.lines) == 4  # lognormal, exponential, Weibull, power law
    write_table_csv(plot.table, tmp_path / "h.csv")
    rows = read_csv(tmp_path / "h.csv")
    assert tuple(rows[0]) == plot.table.columns
    np.testing.assert_array_equal([int(r[2]) for r in rows[1:]], complete)
    np.testing.assert_array_equal([int(r[3]) for r in rows[1:]], censored)
    # expected counts are n·ΔF of the fitted law: over all bins n·(F(last edge) − F(first edge))
    fit = next(f for f in data.fits["all"] if f["model"] == "lognorm")
    edges = [float(rows[1][0]), float(rows[-1][1])]
    total = sum(float(r[rows[0].index("expected_lognorm")]) for r in rows[1:])
    assert total == pytest.approx(fit["n_fit"] * np.diff(frozen_fit(fit).cdf(edges))[0], rel=1e-9)


def test_frozen_power_law_is_pareto_above_x_min():
    dist = frozen_fit({"model": "powerlaw", "params": {"alpha": 2.5, "x_min": 1.5}})
    x = np.array([1.5, 3.0, 10.0])
    np.testing.assert_allclose(dist.pdf(x), 1.5 / 1.5 * (x / 1.5) ** -2.5, rtol=1e-12)
    assert dist.cdf(1.0) == 0.0


def test_kaplan_meier_curves_bands_censoring_marks_and_csv(data, plots, tmp_path):
    plot = plots["kaplan_meier"]
    ax = plot.figure.axes[0]
    km = kaplan_meier(data.lengths.surface, data.lengths.censored)
    step, marks = ax.lines[0], ax.lines[1]  # all traces first: the curve, then its censored ticks
    np.testing.assert_allclose(step.get_xdata(), np.r_[0.0, km.times])
    np.testing.assert_allclose(step.get_ydata(), np.r_[1.0, km.survival])
    censored_lengths = np.unique(data.lengths.surface[data.lengths.censored])
    np.testing.assert_allclose(marks.get_xdata(), censored_lengths)
    assert len(ax.collections) == 4  # a confidence band per group: all, set 0, set 1, non-systematic
    write_table_csv(plot.table, tmp_path / "km.csv")
    rows = [r for r in read_csv(tmp_path / "km.csv")[1:] if r[0] == "all"]
    np.testing.assert_array_equal([float(r[2]) for r in rows], km.survival)
    np.testing.assert_array_equal([float(r[3]) for r in rows], km.ci_low)
    assert sum(int(r[7]) for r in rows) == data.lengths.censored.sum()
    assert {r[0] for r in plot.table.rows} == {"all", "0", "1", "-1"}


def test_terminations_bars_ternary_point_and_connection_lines(data, plots):
    plot = plots["terminations"]
    bars, tern = plot.figure.axes
    nodes, left_out = current_nodes(data)
    assert left_out == 0
    assert [p.get_height() for p in bars.patches] == [nodes.B, nodes.T, nodes.X, nodes.C]
    assert nodes.X == data.crossings
    point = next(line for line in tern.lines if line.get_marker() == "o")
    p = nodes.proportions
    xy = np.array([point.get_xdata()[0], point.get_ydata()[0]])
    np.testing.assert_allclose(xy, ternary_xy(p["P_I"], p["P_Y"], p["P_X"]))
    # the point lies on the line of its own C_L
    a, b = cl_line(nodes.C_L)
    (u0, v0), (u1, v1) = b - a, xy - a
    assert abs(u0 * v1 - v0 * u1) < 1e-12
    assert dict(plot.table.rows)["C_L"] == nodes.C_L


def test_connection_lines_meet_the_sides_where_expected():
    # C_L = 2: P_X = 0 → P_I = 1 − C/4 = 0.5; P_Y = 0 → P_I = 4/(C + 4) = 2/3
    ends = cl_line(2.0)
    expected = np.array([ternary_xy(0.5, 0.5, 0.0), ternary_xy(2 / 3, 0.0, 1 / 3)])
    np.testing.assert_allclose(ends[np.argsort(ends[:, 0])], expected[np.argsort(expected[:, 0])], atol=1e-12)
    # C_L = 6 (> 4) runs from the I–X side to the Y–X side: P_I = 0 → P_Y = 4/C
    ends = cl_line(6.0)
    assert any(np.allclose(e, ternary_xy(0.0, 4 / 6, 2 / 6)) for e in ends)


def test_unclassified_and_x_ends_are_left_out_of_the_node_counts(data):
    ends = (("B", ""), ("X", "C"), *data.ends[2:])
    nodes, left_out = current_nodes(replace(data, ends=ends))
    assert left_out == 2
    assert nodes.B + nodes.T + nodes.C == 2 * (len(ends) - 2)


def test_summary_rows_per_group(data, plots, tmp_path):
    plot = plots["summary"]
    write_table_csv(plot.table, tmp_path / "s.csv")
    rows = {r[0]: r for r in read_csv(tmp_path / "s.csv")[1:]}
    assert list(rows) == ["all traces", "set 0", "set 1", "non-systematic"]
    assert int(rows["all traces"][1]) == len(data.lengths.id)
    assert int(rows["set 1"][2]) == data.lengths.censored[data.lengths.set_id == 1].sum()
    km = km_groups(data.lengths)["0"]
    assert float(rows["set 0"][7]) == km.median
    assert float(rows["set 0"][3]) == data.sets[0]["dip"]
    assert float(rows["set 1"][6]) == 0.3  # the stored P21 map of set 1
    assert rows["non-systematic"][3] == ""  # NaN: no set mean
    cells = {c.get_text().get_text() for c in plot.figure.axes[0].tables[0].get_celld().values()}
    assert {"set 0", f"{km.median:.2f}", "0.300"} <= cells


def test_missing_results_skip_plots_with_a_reason(data):
    empty = replace(data, poles=np.zeros((0, 3)), pole_ids=np.zeros(0, int), pole_sets=np.zeros(0, int),
                    crossings=None, fits={})
    plots = build_plots(empty)
    assert plots["stereonet"].figure is None and "tracemap orient" in plots["stereonet"].reason
    assert plots["terminations"].figure is None and "tracemap analyse" in plots["terminations"].reason
    histogram = plots["length_histogram"]  # the lengths are there, only the fits are missing
    assert histogram.figure is not None and len(histogram.figure.axes[0].lines) == 0
    assert histogram.table.columns == ("bin_low_m", "bin_high_m", "complete", "censored")
    censored = replace(data, lengths=replace(data.lengths, n_censored_ends=np.ones(len(data.lengths.id), int)))
    assert "all" in build_plots(censored)["kaplan_meier"].reason


def test_a_project_without_traces_skips_every_plot():
    from engine.lengths import length_table

    empty = PlotData(length_table([]), np.zeros((0, 3)), np.zeros(0, int), np.zeros(0, int), (), (), 0, {}, {})
    reasons = {name: plot.reason for name, plot in build_plots(empty).items() if plot.figure is None}
    assert reasons.keys() == {"stereonet", "length_histogram", "kaplan_meier", "terminations", "relations", "summary"}
    assert "tracemap extract" in reasons["summary"] and "no traces" in reasons["kaplan_meier"]
    assert "tracemap analyse" in reasons["relations"]


def test_set_colours_match_the_3d_view():
    from engine.render import PALETTE

    assert [tuple(int(c[k:k + 2], 16) for k in (1, 3, 5)) for c in SET_COLORS] == [tuple(p) for p in PALETTE]
    assert set_color(12) == SET_COLORS[2]  # wraps round the palette as engine.render does


# -- files --------------------------------------------------------------------------------------------------

def test_save_figure_by_suffix(plots, tmp_path):
    fig = plots["terminations"].figure
    save_figure(fig, tmp_path / "t.png")
    save_figure(fig, tmp_path / "t.SVG")
    assert (tmp_path / "t.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "<svg" in (tmp_path / "t.SVG").read_text(encoding="utf-8")
    with pytest.raises(InputError, match=r"\.jpg.*expected \.png or \.svg"):
        save_figure(fig, tmp_path / "t.jpg")


def test_write_plots_is_all_or_nothing(data, tmp_path):
    plots = build_plots(replace(data, crossings=None))  # terminations skipped
    with pytest.raises(InputError, match="unknown image format"):
        write_plots(plots, tmp_path / "out", ("png", "pdf"))
    assert not (tmp_path / "out").exists()
    written = write_plots(plots, tmp_path / "out", ("svg",))
    names = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert names == sorted(p.name for p in written)
    assert names == ["kaplan_meier.csv", "kaplan_meier.svg", "length_histogram.csv", "length_histogram.svg",
                     "stereonet.csv", "stereonet.svg", "summary.csv", "summary.svg"]


def test_plot_command_on_the_quick_demo(quick_demo, tmp_path, capsys):
    shutil.copytree(quick_demo / "data", tmp_path / "data")
    shutil.copy2(quick_demo / "demo.tracemap", tmp_path / "demo.tracemap")
    out = tmp_path / "plots"
    assert main(["plot", str(tmp_path / "demo.tracemap"), "-o", str(out)]) == 0  # SVG: test_write_plots_…
    assert "wrote" in capsys.readouterr().out
    for name in ("stereonet", "length_histogram", "kaplan_meier", "terminations", "summary"):
        for suffix in (".png", ".csv"):
            assert (out / f"{name}{suffix}").stat().st_size > 0
    from engine.project import Project

    with Project.open(tmp_path / "demo.tracemap") as project:
        traces = project.traces3d()
        topology = project.result("topology")
    poles = [r for r in read_csv(out / "stereonet.csv")[1:] if r[0] == "pole"]
    assert len(poles) == sum(t.normal is not None for t in traces)
    summary = {r[0]: r for r in read_csv(out / "summary.csv")[1:]}
    assert int(summary["all traces"][1]) == len(traces)
    terminations = dict(read_csv(out / "terminations.csv")[1:])
    assert int(terminations["X"]) == topology["crossings"]
    assert float(terminations["C_L"]) == pytest.approx(topology["nodes"]["C_L"])
    assert main(["plot", str(tmp_path / "demo.tracemap"), "-o", str(tmp_path / "bad"), "--format", "gif"]) == 2
    assert "unknown image format(s) gif" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()
