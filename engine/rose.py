"""Trace azimuths of a 2D map, their axial statistics and the rose diagram (`tracemap analyse-map`).

A trace's azimuth is that of its chord (first to last vertex), clockwise from the map's north (+y), axial
in [0, 180): fractopo's `determine_azimuth(line, halved=True)`, so the two tools agree trace by trace.
Azimuths are axial, so their mean is taken on doubled angles (Mardia & Jupp 2000, §9.3.2): the mean axis
and the mean resultant length R̄ of the doubled angles (1: all parallel, 0: no preferred strike). The rose
diagram weights each trace by its length, in bins of Sanderson & Peacock's (2020) width for n traces,
180° / (2 n^⅓), rounded up to a whole number of bins in 180° (as fractopo bins them).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from matplotlib.figure import Figure

from engine.plots import FIGSIZE, SET_COLORS, Plot, Table


@dataclass(frozen=True)
class AxialMean:
    """Mean azimuth (degrees, [0, 180)) and R̄ of the doubled angles; NaN for no traces or no weight."""

    azimuth: float
    resultant: float


@dataclass(frozen=True)
class Rose:
    """Length-weighted azimuth bins: `edges` (degrees, 0 to 180), `lengths` and `counts` per bin."""

    edges: np.ndarray
    lengths: np.ndarray
    counts: np.ndarray


def trace_azimuths(lines: Sequence[np.ndarray]) -> np.ndarray:
    """Chord azimuth of each polyline (N, 2) in map coordinates: degrees clockwise from +y, in [0, 180)."""
    if not lines:
        return np.zeros(0)
    chords = np.array([line[-1] - line[0] for line in lines], dtype=float)
    azimuth = np.degrees(np.arctan2(chords[:, 0], chords[:, 1])) % 180.0
    return np.where(azimuth >= 180.0, 0.0, azimuth)  # -0.0 % 180 rounds to 180.0


def azimuth_groups(traces: Sequence[np.ndarray],
                   sets: Sequence[str | None]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """(azimuths, lengths) of all traces ("all") and of each set, in the sets' sorted order (a trace whose
    set is None or "" is in "all" only)."""
    azimuths = trace_azimuths(traces)
    lengths = np.array([np.linalg.norm(np.diff(t, axis=0), axis=1).sum() for t in traces], dtype=float)
    labels = np.array([s or "" for s in sets], dtype=object)
    groups = {"all": (azimuths, lengths)}
    for name in sorted(set(labels) - {""}):
        groups[name] = azimuths[labels == name], lengths[labels == name]
    return groups


def axial_mean(azimuths: np.ndarray, weights: np.ndarray | None = None) -> AxialMean:
    """Weighted mean axis of azimuths (degrees) and the mean resultant length of their doubled angles."""
    a = np.radians(2 * np.asarray(azimuths, dtype=float))
    w = np.ones(len(a)) if weights is None else np.asarray(weights, dtype=float)
    total = w.sum()
    if len(a) == 0 or not total > 0:
        return AxialMean(math.nan, math.nan)
    c, s = (w * np.cos(a)).sum() / total, (w * np.sin(a)).sum() / total
    return AxialMean(float(np.degrees(np.arctan2(s, c)) / 2 % 180), float(np.hypot(c, s)))


def rose_bins(azimuths: np.ndarray, lengths: np.ndarray, *, bins: int | None = None) -> Rose:
    """Length-weighted bins of axial azimuths, `bins` in 180°; by default as many as Sanderson & Peacock's
    (2020) width for the number of traces allows (module docstring)."""
    if bins is None:  # the ideal width, then the bins it fits: fractopo's arithmetic, so the rounding agrees
        bins = math.ceil(180.0 / (180.0 / (2 * max(len(azimuths), 1) ** (1 / 3))))
    edges = np.linspace(0.0, 180.0, bins + 1)
    lengths_in, _ = np.histogram(azimuths, edges, weights=lengths)
    counts, _ = np.histogram(azimuths, edges)
    return Rose(edges, lengths_in, counts)


def rose_plot(roses: dict[str, Rose], means: dict[str, AxialMean]) -> Plot:
    """The rose diagram: every group ("all" first, filled; each set outlined, best in the bins of "all") on
    one scale, radius ∝ √ of
    the share of all traces' length (so areas compare), axial (each bin drawn again at +180°), north up,
    clockwise."""
    fig = Figure(figsize=FIGSIZE, layout="compressed")  # compressed: keeps the round rose centred
    ax = fig.add_subplot(projection="polar")
    ax.set_theta_zero_location("N")
    ax.set_theta_direction(-1)
    total = max(roses["all"].lengths.sum(), 1e-300)
    rows = []
    for k, (name, rose) in enumerate(roses.items()):
        whole = name == "all"
        colour = "0.45" if whole else SET_COLORS[(k - 1) % len(SET_COLORS)]
        left, step = np.radians(rose.edges[:-1]), np.radians(np.diff(rose.edges))
        for turn in (0.0, np.pi):
            ax.bar(left + turn, np.sqrt(rose.lengths / total), width=step, align="edge", fill=whole,
                   alpha=0.55 if whole else 1.0, facecolor=colour, edgecolor=colour, linewidth=1.2,
                   label=_label(name, rose, means[name]) if turn == 0.0 else None)
        rows += [(name, float(a), float(b), float(length), int(n))
                 for a, b, length, n in zip(rose.edges[:-1], rose.edges[1:], rose.lengths, rose.counts)]
    ax.set_yticklabels([])
    fig.legend(loc="outside lower center", ncols=1, fontsize="small", frameon=False)
    ax.set_title("Trace azimuths, length-weighted (radius ∝ √share of length)", fontsize="medium")
    table = Table(("group", "azimuth_from", "azimuth_to", "length", "traces"), rows)
    return Plot("rose", "Trace azimuths", fig, table)


def _label(name: str, rose: Rose, mean: AxialMean) -> str:
    which = "all traces" if name == "all" else f"set {name}"
    return f"{which}: mean {mean.azimuth:05.1f}°, R̄ {mean.resultant:.2f}, n {int(rose.counts.sum())}"
