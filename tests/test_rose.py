"""Trace azimuths, their axial mean and the rose diagram of 2D maps, against fractopo and analytic cases."""

import os

import numpy as np
import pytest

from engine.rose import axial_mean, rose_bins, rose_plot, trace_azimuths
from tests.test_maps2d import random_network

os.environ.setdefault("FRACTOPO_DISABLE_CACHE", "1")


def test_azimuths_are_fractopos_trace_by_trace():
    pytest.importorskip("fractopo")
    from fractopo.general import determine_azimuth
    from shapely.geometry import LineString

    lines, _ = random_network(2)
    lines += [np.array([[0.0, 0], [0, 1]]), np.array([[0.0, 0], [0, -1]]), np.array([[0.0, 0], [1, 0]]),
              np.array([[0.0, 0], [-1, 0]]), np.array([[0.0, 0], [-1, -1], [3, 2]])]
    theirs = np.array([determine_azimuth(LineString(line), halved=True) for line in lines])
    np.testing.assert_allclose(trace_azimuths(lines), theirs, atol=1e-9)
    assert trace_azimuths([]).shape == (0,)


def test_rose_bins_are_fractopos():
    pytest.importorskip("fractopo")
    from fractopo.analysis.azimuth import determine_azimuth_bins

    rng = np.random.default_rng(4)
    for n in (7, 90, 1000):
        azimuths, lengths = rng.uniform(0, 180, n), rng.lognormal(0, 1, n)
        ours, theirs = rose_bins(azimuths, lengths), determine_azimuth_bins(azimuths, lengths)
        assert np.diff(ours.edges) == pytest.approx(theirs.bin_width)
        np.testing.assert_allclose(ours.lengths, theirs.bin_heights, rtol=1e-12)
        assert ours.counts.sum() == n


def test_axial_mean_wraps_at_north():
    mean = axial_mean(np.array([170.0, 10.0]))
    assert mean.azimuth == pytest.approx(0.0, abs=1e-9) or mean.azimuth == pytest.approx(180.0)
    assert mean.resultant == pytest.approx(np.cos(np.radians(20)))  # doubled: 340° and 20°
    weighted = axial_mean(np.array([40.0, 80.0]), np.array([3.0, 1.0]))
    doubled = np.angle(3 * np.exp(1j * np.radians(80)) + np.exp(1j * np.radians(160)), deg=True)
    assert weighted.azimuth == pytest.approx(doubled / 2)
    assert axial_mean(np.arange(0.0, 180.0, 1.0)).resultant == pytest.approx(0.0, abs=1e-12)  # no preference
    assert np.isnan(axial_mean(np.zeros(0)).azimuth)


def test_the_rose_of_two_sets_shows_their_strikes():
    lines, sets = random_network(1)  # set 1 at azimuth 60° ± 8°, set 2 at 150° ± 10°
    sets = np.array(sets)
    azimuths = trace_azimuths(lines)
    lengths = np.array([np.linalg.norm(line[-1] - line[0]) for line in lines])
    groups = {"all": (azimuths, lengths), **{k: (azimuths[sets == k], lengths[sets == k]) for k in ("1", "2")}}
    means = {k: axial_mean(a, w) for k, (a, w) in groups.items()}
    assert means["1"].azimuth == pytest.approx(60, abs=2) and means["2"].azimuth == pytest.approx(150, abs=2)
    assert means["1"].resultant > 0.9 and means["all"].resultant < 0.5
    plot = rose_plot({k: rose_bins(a, w) for k, (a, w) in groups.items()}, means)
    table = plot.table
    assert plot.figure is not None and {row[0] for row in table.rows} == {"all", "1", "2"}
    fullest = max((row for row in table.rows if row[0] == "2"), key=lambda row: row[3])  # most of set 2's length
    assert abs(0.5 * (fullest[1] + fullest[2]) - 150) < 15, fullest
