"""The analysis plots of a project (DESIGN.md "GUI": plots; issue 5 "Panels"), each with the table it shows.

Stereonet of trace poles with Fisher-kernel density contours and set means, length histogram with the
fitted distributions, Kaplan–Meier curves, termination counts with the I–Y–X ternary diagram, and a
summary table. Figures are `matplotlib.figure.Figure` objects made without pyplot: no global state, so a
worker thread can build them and the Agg backend saves them with no display.

What a plot draws comes from the traces as they are now (poles, lengths, end codes) and from the results
of the last `tracemap analyse` (length fits, crossing count, P21 maps): a trace edit shows at once, while
the fits wait for the next analysis. Conventions: local frame x east, y north, z up; planes as dip / dip
direction in degrees; stereonets lower hemisphere, equal area (PEERS.md).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Circle, Polygon
from scipy import stats

from engine.errors import InputError, Progress, report
from engine.io import atomic_directory, write_csv
from engine.lengths import KaplanMeier, LengthTable, kaplan_meier, length_table
from engine.orientation import normal_to_dip_dipdir, upward
from engine.register import length_scale, rotate_directions
from engine.relations import BEDDING, PAIR_COLUMNS, SetRelations, outcrop_relations
from engine.topology import END_CODES, NodeCounts, node_counts
from engine.traces import NETWORK_KINDS, Trace3D, network

if TYPE_CHECKING:
    from engine.project import Project

# engine.render's PALETTE and TERMINATION_COLORS (ColorBrewer Set1, Okabe–Ito), so a set or an end code
# has one colour in the 3D view and on the plots; not imported, as engine.render pulls in VTK
SET_COLORS = ("#e41a1c", "#377eb8", "#4daf4a", "#984ea3", "#ff7f00", "#ffff33", "#a65628", "#f781bf",
              "#00ced1", "#808000")
NON_SYSTEMATIC = "0.55"
BEDDING_COLOR = "#141414"  # engine.render.KIND_COLORS["bedding"], as the 3D view draws bedding
TERMINATION_COLORS = {"B": "#0072b2", "T": "#e69f00", "X": "#cc79a7", "C": "#787878"}
MODEL_NAMES = {"lognorm": "lognormal", "expon": "exponential", "weibull_min": "Weibull", "powerlaw": "power law"}
FORMATS = ("png", "svg")
PERCOLATION_CL = 3.57
"""Connections per line at the percolation threshold of 2D random lines (Robinson 1983; MATHS §6): a
reference line on the ternary diagram only."""
CL_LINES = (1.0, 2.0, PERCOLATION_CL)
GRID = 121  # density grid points across the stereonet (about 1.5° apart)
FIGSIZE = (6.4, 5.0)  # inches
DPI = 150  # of saved PNGs


@dataclass(frozen=True)
class Table:
    """Rows of what a plot shows, for CSV export: one tuple of values per row, in `columns` order."""

    columns: tuple[str, ...]
    rows: list[tuple]


@dataclass(frozen=True)
class Plot:
    """One plot: `name` (a file stem), its figure and table, or None and the `reason` it was skipped."""

    name: str
    title: str
    figure: Figure | None
    table: Table | None
    reason: str = ""


@dataclass(frozen=True)
class PlotData:
    """What the plots show, read from a project (module docstring): plain arrays, safe to hand to a worker.

    lengths : every fracture, vein and fault trace with a positive length. poles, pole_ids, pole_sets : upward
    poles of those oriented, their trace ids and sets; bedding_poles, bedding_ids : those of the oriented
    bedding traces, which are in no set. ends : the end codes of every fracture, vein and fault trace. sets : the stored set statistics
    (`tracemap orient`). crossings : X nodes of the last analysis (None before one). fits : the stored length
    fits per group label ("all", "0", …, "-1"). p21 : the mean of each stored P21 map over the vertices
    the photos see, by map name. out_of_date : the stored results computed before the traces last changed
    (`Project.stale_results`).
    """

    lengths: LengthTable
    poles: np.ndarray
    pole_ids: np.ndarray
    pole_sets: np.ndarray
    ends: tuple[tuple[str, str], ...]
    sets: tuple[dict, ...]
    crossings: int | None
    fits: dict[str, list[dict]]
    p21: dict[str, float]
    relations: SetRelations | None = None
    out_of_date: tuple[str, ...] = ()
    bedding_poles: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    bedding_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))


def plot_data(project: Project, traces: Sequence[Trace3D] | None = None) -> PlotData:
    """Gather a project's plot inputs; `traces` defaults to the stored 3D traces (the GUI passes its cache).
    With a registration they are in its frame, as the exports: poles and set means turned, lengths and the
    fits' scales times its scale, P21 divided by it."""
    traces = project.traces3d() if traces is None else traces
    fractures = network(traces)
    registration = project.registration()
    sim = None if registration is None else registration.similarity
    k = length_scale(sim)
    table = length_table(fractures)
    table = LengthTable(table.id, table.set_id, k * table.chord, k * table.surface, table.n_censored_ends)
    oriented = [t for t in fractures if t.normal is not None]
    bedding = [t for t in traces if t.kind not in NETWORK_KINDS and t.normal is not None]
    topology = project.result("topology")
    lengths = project.result("lengths") or {}
    p21 = {name: _mean(project.vertex_map(name)[0]) / k for name in project.map_names() if name.startswith("p21")}
    normals = np.array([t.normal for t in oriented], dtype=float).reshape(-1, 3)
    return PlotData(lengths=table.subset(table.surface > 0),
                    poles=upward(rotate_directions(normals, sim)),
                    pole_ids=np.array([t.id for t in oriented], dtype=np.int64),
                    pole_sets=np.array([t.set_id for t in oriented], dtype=np.int64),
                    ends=tuple((t.term_start, t.term_end) for t in fractures),
                    sets=tuple(_turned_set(s, sim) for s in project.result("sets") or ()),
                    crossings=None if topology is None else int(topology["crossings"]),
                    fits={label: [_scaled_fit(f, k) for f in a["fits"]] for label, a in lengths.items()}, p21=p21,
                    relations=(outcrop_relations(traces, topology["contacts"])
                               if topology is not None and "contacts" in topology else None),
                    out_of_date=tuple(project.stale_results(list(traces))),
                    bedding_poles=upward(rotate_directions(np.array([t.normal for t in bedding], dtype=float)
                                                           .reshape(-1, 3), sim)),
                    bedding_ids=np.array([t.id for t in bedding], dtype=np.int64))


def _turned_set(s: dict, similarity) -> dict:
    """Stored set statistics with the mean pole (and its dip, dip direction) in the registration's frame."""
    if similarity is None:
        return s
    normal = upward(rotate_directions(np.asarray(s["normal"], dtype=float), similarity))
    dip, dip_direction = normal_to_dip_dipdir(normal)
    return {**s, "normal": normal.tolist(), "dip": float(dip), "dip_direction": float(dip_direction)}


def _scaled_fit(fit: dict, k: float) -> dict:
    """A stored length fit for lengths k times longer: its scale (or x_min) times k, shapes unchanged."""
    if k == 1.0 or not fit["params"]:
        return fit
    return {**fit, "params": {name: value * k if name in ("scale", "x_min") else value
                              for name, value in fit["params"].items()}}


def project_plots(project: Project) -> dict[str, Plot]:
    """Every plot of a project, by name; a plot that cannot be made yet has no figure and says why."""
    return build_plots(plot_data(project))


def build_plots(data: PlotData, *, progress: Progress | None = None) -> dict[str, Plot]:
    """Every plot of `data`, by name (a `workers.Task` function: pure, no project access)."""
    report(progress, 0.0, "Kaplan–Meier curves")
    curves = km_groups(data.lengths)
    builders = ((stereonet, (data,)), (length_histogram, (data,)), (km_plot, (curves,)),
                (terminations_plot, (data,)), (set_relations_plot, (data,)), (summary_plot, (data, curves)))
    plots = {}
    for k, (builder, args) in enumerate(builders):
        report(progress, (k + 1) / (len(builders) + 1), builder.__name__.replace("_", " "))
        plot = builder(*args)
        plots[plot.name] = plot
    report(progress, 1.0, "done")
    return plots


# -- stereonet ----------------------------------------------------------------------------------------

def equal_area(axes: np.ndarray) -> np.ndarray:
    """Lower-hemisphere equal-area (Schmidt) projection (..., 2) of axes (..., 3), primitive radius 1.

    An axis at angle θ from the downward vertical lands at radius √2·sin(θ/2) along its trend (x east,
    y north); as √2·sin(θ/2) = √(1 + v_z) for the downward unit vector v, that is (v_x, v_y)/√(1 − v_z).
    """
    v = -upward(axes)
    return v[..., :2] / np.sqrt(1.0 - v[..., 2:3])


def inverse_equal_area(xy: np.ndarray) -> np.ndarray:
    """The downward unit axes (..., 3) at projected points (..., 2) within the primitive (radius ≤ 1)."""
    xy = np.asarray(xy, dtype=float)
    r2 = np.minimum(np.sum(xy**2, axis=-1, keepdims=True), 1.0)
    return np.concatenate([xy * np.sqrt(2.0 - r2), r2 - 1.0], axis=-1)


def pole_density(poles: np.ndarray, axes: np.ndarray, *, kappa: float | None = None) -> np.ndarray:
    """Axial Fisher-kernel density of `poles` (N, 3) at `axes` (M, 3), in multiples of uniform density.

    The exponential Kamb density of Vollmer (1995), as engine.sets.density_peaks: 4π times the mean of the
    axial Fisher densities ½[f(x; n) + f(x; −n)], f = κ e^{κ x·n} / (4π sinh κ), so that its mean over the
    sphere (or, being axial, over a hemisphere) is 1. kappa : default 2(1 + N/9), capped at 100.
    """
    poles, axes = upward(poles), np.asarray(axes, dtype=float)
    kappa = min(2.0 * (1.0 + len(poles) / 9.0), 100.0) if kappa is None else float(kappa)
    total = np.zeros(len(axes))
    chunk = max(1, 4_000_000 // max(len(axes), 1))  # poles per step: bounded memory for large maps
    for start in range(0, len(poles), chunk):
        cos = axes @ poles[start:start + chunk].T
        total += (np.exp(kappa * (cos - 1.0)) + np.exp(kappa * (-cos - 1.0))).sum(axis=1)
    return total * kappa / -np.expm1(-2.0 * kappa) / len(poles)


def density_grid(poles: np.ndarray, n: int = GRID, *, kappa: float | None = None):
    """Pole density on an n × n grid over the stereonet: x (n,), y (n,), density (n, n) indexed [y, x].

    Points outside the primitive take the density at the primitive (contours are clipped to it there).
    """
    x = np.linspace(-1.0, 1.0, n)
    gx, gy = np.meshgrid(x, x)
    axes = inverse_equal_area(np.stack([gx.ravel(), gy.ravel()], axis=-1))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    return x, x, pole_density(poles, axes, kappa=kappa).reshape(n, n)


def stereonet(data: PlotData) -> Plot:
    """Poles coloured by set, their density contours and labelled set means, and the bedding traces' poles
    apart (squares; in no set or contour), lower hemisphere, equal area."""
    name, title = "stereonet", "Poles to fracture traces"
    if len(data.poles) == 0:
        return Plot(name, title, None, None, "no oriented traces yet; run `tracemap orient`")
    fig = Figure(figsize=FIGSIZE, layout="compressed")  # compressed: keeps the round net centred
    ax = fig.add_subplot()
    primitive = _stereonet_frame(ax)
    x, y, density = density_grid(data.poles)
    step = max(1.0, np.ceil(density.max() / 8.0))
    levels = np.arange(1.0, density.max() + step, step)
    filled = ax.contourf(x, y, density, levels=levels, cmap="Greys", alpha=0.6, zorder=1)
    lines = ax.contour(x, y, density, levels=levels, colors="0.3", linewidths=0.5, zorder=1)
    for contours in (filled, lines):
        contours.set_clip_path(primitive)
    fig.colorbar(filled, ax=ax, shrink=0.7, label="multiples of uniform density")
    xy = equal_area(data.poles)
    ax.scatter(xy[:, 0], xy[:, 1], c=[set_color(s) for s in data.pole_sets], s=14, edgecolors="k",
               linewidths=0.3, zorder=3)
    bedding = equal_area(data.bedding_poles).reshape(-1, 2)
    if len(bedding):
        ax.scatter(bedding[:, 0], bedding[:, 1], marker="s", c=BEDDING_COLOR, s=20, edgecolors="k", linewidths=0.3,
                   zorder=3, label=f"bedding (n {len(bedding)})")
    _set_means(ax, data.sets)
    if data.sets or len(bedding):
        fig.legend(loc="outside lower center", ncols=2, fontsize="small", frameon=False)
    ax.set_title(f"{title} (n {len(xy)}), lower hemisphere, equal area", fontsize="medium")
    dip, dipdir = normal_to_dip_dipdir(data.poles)
    rows = [("pole", int(i), int(s), float(a), float(b), float(u), float(v))
            for i, s, a, b, (u, v) in zip(data.pole_ids, data.pole_sets, dip, dipdir, xy)]
    bed_dip, bed_dipdir = normal_to_dip_dipdir(data.bedding_poles)
    rows += [("bedding pole", int(i), -1, float(a), float(b), float(u), float(v))
             for i, a, b, (u, v) in zip(data.bedding_ids, bed_dip, bed_dipdir, bedding)]
    for s in data.sets:
        u, v = equal_area(np.asarray(s["normal"], dtype=float))
        rows.append(("set mean", int(s["id"]), int(s["id"]), float(s["dip"]), float(s["dip_direction"]),
                     float(u), float(v)))
    return Plot(name, title, fig, Table(("kind", "id", "set", "dip", "dip_direction", "x", "y"), rows))


def set_color(set_id: int) -> str:
    """The colour of a set, as in the 3D view; non-systematic traces (−1) grey."""
    return SET_COLORS[set_id % len(SET_COLORS)] if set_id >= 0 else NON_SYSTEMATIC


def _stereonet_frame(ax) -> Circle:
    ax.set_aspect("equal")
    ax.set_axis_off()
    ax.set_xlim(-1.12, 1.12)
    ax.set_ylim(-1.12, 1.12)
    primitive = Circle((0, 0), 1.0, fill=False, edgecolor="k", linewidth=1.0, zorder=4)
    ax.add_patch(primitive)
    for label, (u, v) in {"N": (0, 1), "E": (1, 0), "S": (0, -1), "W": (-1, 0)}.items():
        ax.plot([0.97 * u, 1.03 * u], [0.97 * v, 1.03 * v], color="k", linewidth=1.0)
        ax.text(1.08 * u, 1.08 * v, label, ha="center", va="center", fontsize="small")
    ax.plot(0, 0, "+", color="k", markersize=6)
    return primitive


def _set_means(ax, sets: Sequence[dict]) -> None:
    for s in sets:
        u, v = equal_area(np.asarray(s["normal"], dtype=float))
        ax.plot(u, v, marker="s", markersize=9, color=set_color(int(s["id"])), markeredgecolor="k", zorder=5,
                linestyle="none", label=f"set {s['id']}: {s['dip']:.0f}/{s['dip_direction']:03.0f}, "
                                        f"κ {s['kappa']:.1f}, n {s['n']}")
        ax.annotate(str(s["id"]), (u, v), xytext=(6, 6), textcoords="offset points", fontweight="bold",
                    zorder=6)


# -- lengths ------------------------------------------------------------------------------------------

def length_histogram(data: PlotData) -> Plot:
    """Surface lengths (complete and censored stacked) with the stored fits as expected counts per bin."""
    table = data.lengths
    if len(table.surface) == 0:
        return Plot("length_histogram", "Trace lengths", None, None,
                    "no 3D traces with a length yet; run `tracemap extract`")
    fits = [f for f in data.fits.get("all", []) if f["params"]]
    return histogram_plot(table.surface, table.censored, fits,
                          hint="" if fits else "no fitted distributions yet:\nrun `tracemap analyse`")


def histogram_plot(lengths: np.ndarray, censored: np.ndarray, fits: Sequence[dict], *, unit: str = "m",
                   quantity: str = "surface length", hint: str = "") -> Plot:
    """Lengths in `unit` (complete and censored stacked) with fitted models (`LengthFit`s as dicts) drawn
    as densities and tabled as expected counts per bin; `hint` is said where there are no fits."""
    name, title = "length_histogram", "Trace lengths"
    edges = np.histogram_bin_edges(lengths, bins="auto")
    if len(edges) > 41:  # a few long outliers make "auto" bins too fine to read
        edges = np.linspace(edges[0], edges[-1], 41)
    complete = np.histogram(lengths[~censored], edges)[0]
    n_censored = np.histogram(lengths[censored], edges)[0]
    fig = Figure(figsize=FIGSIZE, layout="constrained")
    ax = fig.add_subplot()
    width = np.diff(edges)
    ax.bar(edges[:-1], complete, width, align="edge", color="0.65", edgecolor="k", linewidth=0.4,
           label=f"complete ({complete.sum()})")
    ax.bar(edges[:-1], n_censored, width, bottom=complete, align="edge", color="white", edgecolor="k",
           hatch="///", linewidth=0.4, label=f"censored ({n_censored.sum()})")
    expected = []
    curve_x = np.linspace(max(edges[0], 1e-9), edges[-1], 400)
    for fit in fits:
        dist = frozen_fit(fit)
        expected.append(fit["n_fit"] * np.diff(dist.cdf(edges)))
        p = fit["ad_pvalue"]
        x = curve_x[curve_x >= dist.support()[0]]  # the power law starts at x_min
        ax.plot(x, fit["n_fit"] * width[0] * dist.pdf(x), linewidth=1.6,
                label=f"{MODEL_NAMES[fit['model']]} (AD p {'n/a' if not np.isfinite(p) else f'{p:.2f}'})")
    if hint:
        ax.text(0.98, 0.7, hint, transform=ax.transAxes, ha="right", fontsize="small", color="0.3")
    ax.set_xlabel(f"{quantity} ({unit})")
    ax.set_ylabel("traces per bin")
    ax.set_title(f"{title} (n {len(lengths)}); fits by censored MLE")
    ax.legend(fontsize="small")
    columns = (_in("bin_low", unit), _in("bin_high", unit), "complete", "censored",
               *(f"expected_{f['model']}" for f in fits))
    rows = [(float(lo), float(hi), int(a), int(b), *(float(e[k]) for e in expected))
            for k, (lo, hi, a, b) in enumerate(zip(edges[:-1], edges[1:], complete, n_censored))]
    return Plot(name, title, fig, Table(columns, rows))


def _in(column: str, unit: str) -> str:
    """A table column of a length: `_m` when in metres (the project's tables), bare in map units."""
    return f"{column}_m" if unit == "m" else column


def frozen_fit(fit: dict):
    """The scipy distribution of a stored `LengthFit` (as a dict): the power law as Pareto above x_min."""
    params = fit["params"]
    if fit["model"] == "powerlaw":
        return stats.pareto(params["alpha"] - 1.0, scale=params["x_min"])
    return getattr(stats, fit["model"])(**params)


def km_groups(table: LengthTable) -> dict[str, KaplanMeier | str]:
    """Kaplan–Meier of all traces and of each set (labels as `tracemap analyse`: "all", "0", …, "-1"); a
    group that has none (every trace censored) gets the reason instead."""
    groups = {"all": np.ones(len(table.id), bool)}
    if np.any(table.set_id >= 0):  # the sets in order, then the non-systematic traces
        groups.update({str(s): table.set_id == s for s in sorted(np.unique(table.set_id), key=lambda s: (s < 0, s))})
    out: dict[str, KaplanMeier | str] = {}
    for label, mask in groups.items():
        try:
            out[label] = kaplan_meier(table.surface[mask], table.censored[mask])
        except InputError as error:
            out[label] = str(error)
    return out


def group_name(label: str) -> str:
    return "all traces" if label == "all" else "non-systematic" if label == "-1" else f"set {label}"


def set_style(label: str) -> tuple[str, str]:
    """The name and colour of a project's group ("all", a set id, "-1")."""
    return group_name(label), "k" if label == "all" else set_color(int(label))


def km_plot(curves: dict[str, KaplanMeier | str], *, unit: str = "m", quantity: str = "surface length",
            style: Callable[[str], tuple[str, str]] | None = None) -> Plot:
    """Survival P(length > L) per group, with its pointwise confidence band and the censored lengths ticked;
    `style` gives a group's name and colour from its label (default: the project's sets, `set_style`)."""
    name, title = "kaplan_meier", "Kaplan–Meier survival of trace lengths"
    fitted = {k: v for k, v in curves.items() if isinstance(v, KaplanMeier)}
    if not fitted:
        return Plot(name, title, None, None, curves.get("all", "no 3D traces yet; run `tracemap extract`"))
    fig = Figure(figsize=FIGSIZE, layout="constrained")
    ax = fig.add_subplot()
    rows = []
    for label, km in fitted.items():
        group, color = (style or set_style)(label)
        t = np.r_[0.0, km.times]
        ax.fill_between(t, np.r_[1.0, km.ci_low], np.r_[1.0, km.ci_high], step="post", color=color, alpha=0.12,
                        linewidth=0)
        median = f"{km.median:.3g} {unit}" if np.isfinite(km.median) else "not reached"
        ax.step(t, np.r_[1.0, km.survival], where="post", color=color, linewidth=1.5,
                label=f"{group}: median {median} (n {km.n}, {km.n_censored} censored)")
        n_censored = km.n_at_risk - km.n_events - np.r_[km.n_at_risk[1:], 0]
        marked = n_censored > 0
        ax.plot(km.times[marked], km.survival[marked], linestyle="none", marker="|", markersize=8, color=color)
        rows += [(label, float(a), float(b), float(c), float(d), int(e), int(f), int(g)) for a, b, c, d, e, f, g
                 in zip(km.times, km.survival, km.ci_low, km.ci_high, km.n_at_risk, km.n_events, n_censored)]
    ax.set_ylim(0, 1.02)
    ax.set_xlim(left=0)
    ax.set_xlabel(f"{quantity} L ({unit})")
    ax.set_ylabel("P(length > L)")
    ax.set_title(f"{title}\n(band: pointwise {next(iter(fitted.values())).confidence:.0%}; | censored)")
    ax.legend(fontsize="small")
    columns = ("group", _in("length", unit), "survival", "ci_low", "ci_high", "n_at_risk", "n_events", "n_censored")
    return Plot(name, title, fig, Table(columns, rows))


# -- terminations ---------------------------------------------------------------------------------------

def current_nodes(data: PlotData) -> tuple[NodeCounts, int]:
    """Node counts from the traces' end codes and the crossings of the last analysis, and how many traces
    were left out for an end that is not B, T or C (unclassified, or set to X by hand)."""
    kept = [pair for pair in data.ends if all(code in END_CODES for code in pair)]
    return node_counts(kept, data.crossings or 0), len(data.ends) - len(kept)


def ternary_xy(p_i: float, p_y: float, p_x: float) -> tuple[float, float]:
    """Position in the I–Y–X triangle (fractopo's layout: I top, Y bottom left, X bottom right, side 1)."""
    return 0.5 * p_i + p_x, np.sqrt(3.0) / 2.0 * p_i


def cl_line(c_l: float) -> np.ndarray:
    """Ends (2, 2) of the ternary line of constant connections per line C_L = 4(P_Y + P_X)/(P_I + P_Y).

    C_L(P_I + P_Y) − 4(P_Y + P_X) = 0 is linear in the proportions, so the line runs between the two
    points where it meets the triangle's sides.
    """
    a = np.array([c_l, c_l - 4.0, -4.0])  # coefficients of P_I, P_Y, P_X
    ends = []
    for i, j in ((0, 1), (0, 2), (1, 2)):
        if a[j] != a[i] and 0.0 <= (t := a[j] / (a[j] - a[i])) <= 1.0:
            p = np.zeros(3)
            p[i], p[j] = t, 1.0 - t
            ends.append(ternary_xy(*p))
    return np.unique(np.round(ends, 12), axis=0)[:2]


def terminations_plot(data: PlotData) -> Plot:
    """B/T/X/C bars and the I–Y–X ternary point with lines of equal connections per line (MATHS §6)."""
    if data.crossings is None:
        return Plot("terminations", "Terminations and topology", None, None, "no topology yet; run `tracemap analyse`")
    nodes, left_out = current_nodes(data)
    if nodes.B + nodes.T + nodes.X == 0:
        return Plot("terminations", "Terminations and topology", None, None,
                    "no classified end nodes; run `tracemap analyse`")
    return topology_plot(nodes, left_out=left_out)


NODE_NAMES = {"B": "B blind, T abutting, X crossing,\nC censored",
              "I": "I isolated, Y abutting, X crossing,\nE at the area's edge"}


def topology_plot(nodes: NodeCounts, *, codes: str = "BTXC", left_out: int = 0) -> Plot:
    """Node count bars and the I–Y–X ternary point with lines of equal connections per line (MATHS §6);
    `codes` names the bars: the paper's BTXC on an outcrop, Sanderson & Nixon's IYXE on a 2D map (the same
    counts, PEERS.md)."""
    name, title = "terminations", "Terminations and topology"
    fig = Figure(figsize=(9.0, 4.4), layout="compressed")
    bars, tern = fig.subplots(1, 2, width_ratios=(1, 1.4))
    counts = [nodes.B, nodes.T, nodes.X, nodes.C]
    bars.bar(list(codes), counts, color=[TERMINATION_COLORS[c] for c in "BTXC"], edgecolor="k", linewidth=0.5)
    for k, n in enumerate(counts):
        bars.annotate(str(n), (k, n), xytext=(0, 2), textcoords="offset points", ha="center")
    bars.set_ylabel("nodes")
    bars.set_title(NODE_NAMES[codes[0]] + (f" ({left_out} traces unclassified)" if left_out else ""),
                   fontsize="small")
    _ternary(tern, nodes)
    fig.suptitle(f"{title}: $C_L$ {nodes.C_L:.2f} connections per line, $C_B$ {nodes.C_B:.2f} per branch")
    p = nodes.proportions
    rows = [*zip(codes, counts), ("P_I", p["P_I"]), ("P_Y", p["P_Y"]), ("P_X", p["P_X"]), ("C_L", nodes.C_L),
            ("C_B", nodes.C_B), ("censored_fraction", nodes.censored_fraction), ("traces_left_out", left_out)]
    return Plot(name, title, fig, Table(("quantity", "value"), rows))


def _ternary(ax, nodes: NodeCounts) -> None:
    ax.set_aspect("equal")
    ax.set_axis_off()
    corners = np.array([ternary_xy(1, 0, 0), ternary_xy(0, 1, 0), ternary_xy(0, 0, 1)])
    ax.add_patch(Polygon(corners, closed=True, fill=False, edgecolor="k", linewidth=1.2))
    for f in (0.2, 0.4, 0.6, 0.8):  # 20 % grid lines parallel to each side
        for line in ((ternary_xy(f, 1 - f, 0), ternary_xy(f, 0, 1 - f)),
                     (ternary_xy(1 - f, f, 0), ternary_xy(0, f, 1 - f)),
                     (ternary_xy(1 - f, 0, f), ternary_xy(0, 1 - f, f))):
            ax.plot(*np.transpose(line), color="0.85", linewidth=0.5, zorder=0)
    for label, (u, v), align in zip("IYX", corners, ("bottom", "top", "top")):
        ax.text(u, v + (0.03 if align == "bottom" else -0.03), label, ha="center", va=align, fontweight="bold")
    for c_l in CL_LINES:
        (u0, v0), (u1, v1) = cl_line(c_l)
        ax.plot([u0, u1], [v0, v1], linestyle="--", color="0.4", linewidth=0.8)
        angle = (np.degrees(np.arctan2(v1 - v0, u1 - u0)) + 90.0) % 180.0 - 90.0  # upright text
        ax.text((u0 + u1) / 2, (v0 + v1) / 2, f"$C_L$ {c_l:g}" + (" percolation" if c_l == PERCOLATION_CL else ""),
                fontsize="x-small", color="0.3", ha="center", va="bottom", rotation=angle, rotation_mode="anchor",
                transform_rotates_text=True)
    p = nodes.proportions
    u, v = ternary_xy(p["P_I"], p["P_Y"], p["P_X"])
    ax.plot(u, v, marker="o", markersize=9, color="#d62728", markeredgecolor="k", linestyle="none")
    ax.set_xlim(-0.08, 1.08)
    ax.set_ylim(-0.1, 0.95)
    ax.set_title(f"I–Y–X nodes (Sanderson & Nixon 2015): I {p['P_I']:.0%}, Y {p['P_Y']:.0%}, X {p['P_X']:.0%}",
                 fontsize="small")


# -- relations between sets ----------------------------------------------------------------------------

def set_relations_plot(data: PlotData) -> Plot:
    """The sets' abutting and crossing (`relations_plot`), or why there is none yet."""
    name, title = "relations", "Abutting and crossing between sets"
    if data.relations is None:
        return Plot(name, title, None, None, "no contacts between traces yet; run `tracemap analyse`"
                    + (" again (the last analysis did not store them)" if data.crossings is not None else ""))
    if not data.relations.sets:
        return Plot(name, title, None, None, "no sets yet; run `tracemap orient`")
    return relations_plot(data.relations, [BEDDING_COLOR if s == BEDDING else set_color(int(s))
                                           for s in data.relations.sets])


def relations_plot(relations: SetRelations, colors: Sequence[str], *, label: str = "set") -> Plot:
    """Two matrices of the sets' contacts (`engine.relations`): the ends of each row set's traces against
    each column set's traces, and the crossings between them (lower triangle, the diagonal within a set);
    tick labels in the sets' colours. Bedding (last, if traced) has no ends and no crossings of its own: only
    its column of ends is shown. Its table is the pairs, as relations.csv."""
    name, title = "relations", "Abutting and crossing between sets"
    k = len(relations.sets)
    fig = Figure(figsize=(max(6.4, 3.2 + 2.4 * k), 1.8 + 0.9 * k), layout="compressed")
    ends, crosses = fig.subplots(1, 2)
    fracture = np.array([s != BEDDING for s in relations.sets])
    lower = np.tril(np.ones((k, k), dtype=bool)) & fracture[:, None] & fracture[None, :]
    for ax, counts, shown, cmap, what in (
            (ends, relations.abuts, np.repeat(fracture[:, None], k, axis=1), "Oranges",
             "ends of the row's traces against\nthe column's (T): the row the younger"),
            (crosses, relations.crosses, lower, "RdPu", "crossings (X)")):
        values = np.where(shown, counts, np.nan).astype(float)
        ax.imshow(values, cmap=cmap, vmin=0, vmax=max(1, np.nanmax(values, initial=0)))
        for (i, j), n in np.ndenumerate(counts):
            if shown[i, j]:
                dark = n > 0.6 * max(1, np.nanmax(values, initial=0))
                ax.text(j, i, str(n), ha="center", va="center", color="white" if dark else "black")
        ticks = [s if s == BEDDING else f"{label} {s}" for s in relations.sets]
        ax.set_xticks(range(k), ticks, rotation=30 if k > 3 else 0)
        ax.set_yticks(range(k), ticks)
        for tick, color in zip([*ax.get_xticklabels(), *ax.get_yticklabels()], [*colors, *colors]):
            tick.set_color(color)
        ax.set_title(what, fontsize="small")
    left_out = (f" ({relations.unplaced} T ends against no trace, {relations.unset} contacts with no set left out)"
                if relations.unplaced or relations.unset else "")
    fig.suptitle(title + left_out, fontsize="medium")
    return Plot(name, title, fig, Table(PAIR_COLUMNS, relations.rows()))


# -- summary --------------------------------------------------------------------------------------------

SUMMARY_COLUMNS = ("group", "traces", "censored", "dip", "dip_direction", "kappa", "p21_mean_per_m",
                   "km_median_m", "km_median_low_m", "km_median_high_m")


def summary_plot(data: PlotData, curves: dict[str, KaplanMeier | str]) -> Plot:
    """One row per group (all traces, each set, non-systematic): counts, set mean, mean P21, KM median."""
    name, title = "summary", "Summary"
    table = data.lengths
    if len(table.id) == 0:
        return Plot(name, title, None, None, "no 3D traces yet; run `tracemap extract`")
    sets = {int(s["id"]): s for s in data.sets}
    nan = float("nan")
    rows = []
    for label, km in curves.items():
        mask = np.ones(len(table.id), bool) if label == "all" else table.set_id == int(label)
        s = sets.get(int(label), {}) if label != "all" else {}
        p21 = data.p21.get("p21" if label == "all" else f"p21:set{label}", nan)
        median, (low, high) = (km.median, km.median_ci) if isinstance(km, KaplanMeier) else (nan, (nan, nan))
        rows.append((group_name(label), int(mask.sum()), int(table.censored[mask].sum()), s.get("dip", nan),
                     s.get("dip_direction", nan), s.get("kappa", nan), p21, median, low, high))
    fig = Figure(figsize=(9.0, 0.9 + 0.32 * len(rows)), layout="constrained")
    ax = fig.add_subplot()
    ax.set_axis_off()
    headers = ("group", "traces", "censored", "dip", "dip dir.", "κ", "P21 mean (/m)", "KM median (m)",
               f"{_confidence(curves):.0%} interval (m)")
    cells = [[r[0], str(r[1]), str(r[2]), _fmt(r[3], ".0f"), _fmt(r[4], "03.0f"), _fmt(r[5], ".1f"),
              _fmt(r[6], ".3f"), _fmt(r[7], ".2f"), _interval(r[8], r[9])] for r in rows]
    shown = ax.table(cellText=cells, colLabels=headers, loc="center", cellLoc="center")
    shown.auto_set_font_size(False)
    shown.set_fontsize(8)
    shown.auto_set_column_width(range(len(headers)))
    ax.set_title(f"{title}: {len(table.id)} traces, {len(data.sets)} sets")
    return Plot(name, title, fig, Table(SUMMARY_COLUMNS, [tuple(_number(v) for v in r) for r in rows]))


def _confidence(curves: dict[str, KaplanMeier | str]) -> float:
    return next((km.confidence for km in curves.values() if isinstance(km, KaplanMeier)), 0.95)


def _interval(low: float, high: float) -> str:
    return "–" if np.isnan(low) and np.isnan(high) else f"{_fmt(low, '.2f')} – {_fmt(high, '.2f')}"


def _fmt(x: float, spec: str) -> str:
    if np.isinf(x):
        return "not reached"
    return "–" if np.isnan(x) else format(x, spec)


def _number(v: object) -> object:
    return float(v) if isinstance(v, (float, np.floating)) else v


def _mean(values: np.ndarray) -> float:
    finite = values[np.isfinite(values)]  # NaN: vertices no photo sees
    return float(finite.mean()) if len(finite) else float("nan")


# -- files ----------------------------------------------------------------------------------------------

def save_figure(fig: Figure, path: str | Path) -> None:
    """Write `fig` as PNG (150 dpi) or SVG, chosen by the suffix of `path`."""
    path = Path(path)
    fmt = path.suffix.lower().lstrip(".")
    if fmt not in FORMATS:
        raise InputError(path, f"unknown image type {path.suffix!r}; expected .png or .svg")
    fig.savefig(path, format=fmt, dpi=DPI)


def write_table_csv(table: Table, path: str | Path) -> None:
    """Write `table` as CSV: full-precision numbers, empty cells for NaN."""
    write_csv(Path(path), table.columns, [tuple(_cell(v) for v in row) for row in table.rows])


def _cell(v: object) -> str:
    if isinstance(v, (float, np.floating)):
        return "" if np.isnan(v) else repr(float(v))
    return str(int(v)) if isinstance(v, np.integer) else str(v)


def write_plots(plots: dict[str, Plot], outdir: str | Path, formats: Sequence[str] = ("png",)) -> list[Path]:
    """Write each plot as <name>.<format> and <name>.csv into `outdir`, all or nothing; skipped plots are
    left out (their `reason` says why). Returns the files written."""
    unknown = sorted(set(formats) - set(FORMATS))
    if unknown or not formats:
        raise InputError(None, f"--format: unknown image format(s) {', '.join(unknown) or '(none)'}; "
                               f"available: {', '.join(FORMATS)}")
    with atomic_directory(outdir) as scratch:
        for plot in plots.values():
            if plot.figure is None:
                continue
            for fmt in formats:
                save_figure(plot.figure, scratch / f"{plot.name}.{fmt}")
            write_table_csv(plot.table, scratch / f"{plot.name}.csv")
        names = sorted(p.name for p in scratch.iterdir())
    return [Path(outdir) / n for n in names]
