"""Trace delineation (issue 3): every stage against an oracle.

Phase congruency against phasepack on the same input; auto-tracing against the exact visible traces of the
synthetic outcrop in two rendering styles; guided curves, components and bad input against hand-made cases.
"""

import csv
import importlib
import json
import math
import warnings
from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy import interpolate, ndimage
from scipy.spatial import cKDTree

from engine.cli import main
from engine.cameras import Camera
from engine.delineate import (DelineationParams, autotrace, carried_traces, darkness, denoise, detect_edges,
                              find_segments,
                              grow_traces, label_components, least_cost_curve, line_filter, phase_congruency,
                              phase_congruency_mono, read_params, read_photo, silhouette, spline_curve,
                              supported_traces, trace_cost, trace_map, write_params)
from engine.delineate import guided
from engine.delineate.line_profile import cross_profiles, line_measures, log_brightness
from engine.delineate.segments import Segments
from engine.errors import InputError
from engine.project import Project
from engine.raytrace import RayTracer
from engine.synthetic import QUICK, make_outcrop, write_outcrop
from engine.traces import Trace2D, resample_polyline

PHOTOS = {**QUICK, "image_size": (1024, 768)}  # traces about 2 px wide
INTERIOR = 64  # px: the agreement with phasepack is checked this far from the border
TARGET = (0.85, 0.90)  # issue 3: recall and precision per photo, within 2 px
# What the defaults achieve on seed 1 (measured: see test_autotrace_recall_and_precision), as floors
FLOOR = {"default": TARGET, "alt": (0.80, 0.90)}


@pytest.fixture(scope="module")
def outcrops():
    """The same outcrop rendered in both looks (texture, contrast, lighting and trace width differ)."""
    return {style: make_outcrop(1, **PHOTOS, style=style) for style in ("default", "alt")}


@pytest.fixture(scope="module")
def photo(outcrops):
    """One synthetic photo as a grey float image in [0, 1]."""
    rgb = outcrops["default"].images["photo_02"]
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32) / 255


def phasepack():
    pytest.importorskip("phasepack")
    with warnings.catch_warnings():  # it warns that pyFFTW is missing
        warnings.simplefilter("ignore")
        import phasepack
    return phasepack


def textures():
    rng = np.random.default_rng(3)
    smooth = cv2.GaussianBlur(rng.random((301, 401)).astype(np.float32), (0, 0), 1.5)  # odd sizes
    yy, xx = np.mgrid[:256, :320]
    rings = 0.5 + 0.4 * np.sin(np.hypot(xx - 150, yy - 120) / 5.0) + 0.05 * rng.normal(size=xx.shape)
    return {"smooth noise 301×401": (smooth - smooth.min()) / np.ptp(smooth),
            "rings 256×320": np.clip(rings, 0, 1).astype(np.float32)}


# -- phase congruency ------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["photo", "smooth noise 301×401", "rings 256×320"])
def test_phase_congruency_agrees_with_phasepack(name, photo):
    image = photo if name == "photo" else textures()[name]
    M, m, ori, ft, _, _, T = phasepack().phasecong(image, nscale=4, norient=6)
    ours = phase_congruency(image, nscale=4, norient=6)
    inner = (slice(INTERIOR, -INTERIOR), slice(INTERIOR, -INTERIOR))
    assert np.abs(ours.edge - M)[inner].max() <= 1e-3  # issue 3; measured 4e-7 (float32 rounding)
    assert np.abs(ours.corner - m)[inner].max() <= 1e-3
    assert ours.threshold[-1] == pytest.approx(T, rel=1e-5)  # the same noise threshold
    strong = M[inner] > 0.05
    # phasepack rounds the orientation to whole degrees
    turn = np.abs((np.degrees(ours.orientation[inner]) - ori[inner] + 90) % 180 - 90)
    assert turn[strong].max() <= 0.5 + 1e-3
    assert np.abs(ours.feature_type - ft)[inner][strong].max() <= 1e-3


def test_noise_median_is_numpys():
    """The noise threshold needs phasepack's exact median; ours selects within bit-pattern buckets."""
    from engine.delineate.phase import _median

    rng = np.random.default_rng(0)
    for values in (np.abs(rng.normal(size=n)).astype(np.float32) for n in (1, 2, 7, 10, 100_001)):
        assert _median(values) == pytest.approx(float(np.median(values)), rel=1e-7)
    split = np.r_[np.zeros(500), np.ones(500)].astype(np.float32)  # the two middles in different buckets
    assert _median(split) == 0.5


def test_tiles_match_the_whole_photo(photo):
    whole = phase_congruency(photo)
    tiled = phase_congruency(photo, tile=256, overlap=96)  # 3 × 2 tiles with 96 px margins
    # the median over the whole photo, of amplitudes that carry the tiles' own small error
    np.testing.assert_allclose(tiled.threshold, whole.threshold, rtol=1e-3)
    assert np.abs(tiled.edge - whole.edge).max() <= 2e-2  # the filters' tails beyond 96 px (MATHS §2.3)
    assert np.quantile(np.abs(tiled.edge - whole.edge), 0.999) <= 2e-3


def test_a_tiled_photo_agrees_with_phasepack(outcrops):
    """Issue 3's oracle on a photo too big for one tile, called the same way (default tiling and margins): a
    strip of the synthetic photos side by side, 4296 px wide (tiles of at most 4096 px)."""
    photos = [outcrops["default"].images[k] for k in sorted(outcrops["default"].images)]
    strip = np.hstack([*photos, photos[0], photos[1][:, :200]])
    image = cv2.cvtColor(strip, cv2.COLOR_RGB2GRAY).astype(np.float32) / 255
    M = phasepack().phasecong(image, nscale=4, norient=6)[0]
    ours = phase_congruency(image, nscale=4, norient=6)
    assert ours.edge.shape == (768, 4296)
    inner = (slice(INTERIOR, -INTERIOR), slice(INTERIOR, -INTERIOR))
    assert np.abs(ours.edge - M)[inner].max() <= 1e-3  # measured 3e-4 (6e-3 with 96 px margins)


def test_monogenic_is_close_to_phasepack_away_from_the_border(photo):
    M = phasepack().phasecongmono(photo, nscale=4)[0]
    ours = phase_congruency_mono(photo, nscale=4)
    inner = (slice(INTERIOR, -INTERIOR), slice(INTERIOR, -INTERIOR))
    # phasepack splits off Moisan's smooth component; we mask the border instead
    assert np.quantile(np.abs(ours.edge - M)[inner], 0.99) <= 5e-3
    assert ours.corner is None


@pytest.mark.parametrize("method", [phase_congruency, phase_congruency_mono])
def test_dark_line_orientation_and_feature_type(method):
    """A dark line at 30° from the x axis: feature normal at 120° (anticlockwise, y up), feature type −π/2."""
    yy, xx = np.mgrid[:256, :256].astype(np.float64)
    angle = math.radians(30)
    distance = (xx - 128) * math.sin(angle) + (yy - 128) * math.cos(angle)  # y down: the line rises to the right
    image = 0.7 - 0.4 * np.exp(-0.5 * (distance / 1.0) ** 2)
    pc = method(image.astype(np.float32))
    on = (np.abs(distance) < 0.5) & (np.hypot(xx - 128, yy - 128) < 60)
    normal = np.degrees(pc.axis[on])
    assert np.abs((normal - 120 + 90) % 180 - 90).max() <= 2.0
    assert np.median(pc.feature_type[on]) < -math.pi / 3  # a dark line (−π/2), not a step (0)
    assert pc.edge[on].min() > 0.3


def test_no_spurious_edges_at_the_border():
    """A textured photo lit from one side: its periodic extension has steps at every border."""
    rng = np.random.default_rng(5)
    yy, xx = np.mgrid[:300, :400]
    image = (cv2.GaussianBlur(rng.random((300, 400)), (0, 0), 2) * 0.3 + xx / 400 * 0.5 + yy / 300 * 0.2)
    inner = np.zeros(image.shape, bool)
    inner[24:-24, 24:-24] = True
    for border in (8, 0):  # hysteresis above the texture's level, so the wrap-round steps stand out
        pc = phase_congruency(image.astype(np.float32), border=border)
        skeleton = detect_edges(pc, low=0.05, high=0.15).skeleton
        ring = np.zeros(image.shape, bool)  # the 4 px next to the masked strip
        ring[border:-border or None, border:-border or None] = True
        ring[border + 4:-border - 4, border + 4:-border - 4] = False
        density = skeleton[ring].mean() / skeleton[inner].mean()
        if border:
            assert not (skeleton[:border].any() or skeleton[-border:].any()
                        or skeleton[:, :border].any() or skeleton[:, -border:].any())
            assert density <= 1.5  # no more edges next to the strip than inside (measured 0.2×)
        else:  # without the mask the wrap-round steps show up as edges along the border (measured 4.6×)
            assert density > 3.0


# -- line filter -----------------------------------------------------------------------------------------

def gaussian_line(angle: float, width: float, depth: float, size: int = 256) -> np.ndarray:
    """A straight dark line through the centre along `angle` (degrees, image axes), Gaussian across (σ `width`)."""
    y, x = np.mgrid[:size, :size].astype(np.float64) - size / 2
    t = math.radians(angle)
    across = -x * math.sin(t) + y * math.cos(t)
    return (-depth * np.exp(-across ** 2 / (2 * width ** 2))).astype(np.float32)


@pytest.mark.parametrize("angle", [0.0, 30.0, 75.0, 120.0])
def test_line_filter_answers_a_thin_line_as_the_convolution_does(angle):
    """A line of depth d and σ s under the filter (σ across σ_c, normalised by its positive lobe LOBE/σ_c²)
    answers d s σ_c² / ((s² + σ_c²)^1.5 LOBE) at its centre (the along Gaussian integrates to 1), at every
    angle; measured within 0.05% (a filter off the line's direction would answer less)."""
    from engine.delineate.line_filter import LOBE
    lines = line_filter(gaussian_line(angle, 1.0, 0.2))
    expected = 0.2 * 1.0 / (2 ** 1.5 * LOBE)
    assert lines.strength[128, 128] == pytest.approx(expected, rel=2e-3)
    y, x = np.nonzero(lines.mask)
    t = math.radians(angle)
    distance = np.abs(-(x - 128) * math.sin(t) + (y - 128) * math.cos(t))
    assert len(x) >= 240 and distance.max() <= 1.5  # the whole line, on it (a pixel or two wide)


@pytest.mark.parametrize("shape", [(181, 403), (450, 97), (1500, 2100)])
def test_line_filter_is_the_same_in_tiles_as_whole(shape, monkeypatch):
    """Any photo size (one tile, a thin strip, 2×3 tiles) gives what one transform of the whole reflected
    photo gives: the filters reach MARGIN σ along, where their tail is e^-8 of the peak. Measured: the same
    in one tile; in 2×3 tiles 0.006% of the pixels fall the other way in non-maximum suppression (ties) and
    the rest differ by 7e-5 at most."""
    module = importlib.import_module("engine.delineate.line_filter")  # the package's name is the function
    rng = np.random.default_rng(5)
    image = cv2.GaussianBlur(rng.random(shape).astype(np.float32), (0, 0), 1.2)
    tiled = line_filter(image, low=0.01, high=0.03)  # the noise's ridges as lines
    monkeypatch.setattr(module, "TILE", 4096)
    whole = line_filter(image, low=0.01, high=0.03)
    assert tiled.strength.shape == shape and tiled.mask.any()
    same = (tiled.strength > 0) == (whole.strength > 0)
    assert same.mean() > 0.9999
    assert np.abs(tiled.strength - whole.strength)[same].max() < 2e-4


def test_line_filter_keeps_a_thin_line_and_not_a_broad_band_or_a_bright_line():
    """A band 3× wider and twice as dark answers the wide filter more than the thin one (ratio 0.30 < 0.8);
    a bright line is found only in the negated image."""
    thin = line_filter(gaussian_line(30.0, 1.0, 0.2))
    band = line_filter(gaussian_line(30.0, 3.0, 0.4))
    bright = -gaussian_line(30.0, 1.0, 0.2)
    assert thin.mask.sum() > 240 and not band.mask.any()
    assert not line_filter(bright).mask.any() and line_filter(-bright).mask.sum() > 240


def test_line_filter_checks_its_parameters():
    image = np.zeros((32, 32), np.float32)
    with pytest.raises(InputError, match=r"sigma=0 is out of range: expected a number in \[0.5, 10\]"):
        line_filter(image, sigma=0)
    with pytest.raises(InputError, match="wide=1.0 must exceed sigma=1.5"):
        line_filter(image, sigma=1.5, wide=1.0)
    with pytest.raises(InputError, match="low=0.2 must not exceed high=0.1"):
        line_filter(image, low=0.2, high=0.1)
    with pytest.raises(InputError, match=r"norient=2.5 is out of range: expected an integer"):
        line_filter(image, norient=2.5)
    with pytest.raises(InputError, match="line_wide=1.0 must exceed line_sigma=1.0"):
        DelineationParams(line_wide=1.0)


# -- the mesh's silhouette ------------------------------------------------------------------------------

def looking_down(width=400, height=300, f=300.0) -> Camera:
    """A camera 10 m above the origin looking straight down (image u along +x, v along −y)."""
    K = [[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]]
    R = np.diag([1.0, -1.0, -1.0])
    return Camera("down", width, height, K, [], R, -R @ np.array([0.0, 0.0, 10.0]))


def square(x0, x1, y0, y1, z):
    return np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], float)


def test_silhouette_is_the_outline_and_the_occluding_contour_of_two_squares():
    """A 8 × 6 m square at depth 10 m and a 2 m one 1 m above it (a range jump of ln(10/9) = 0.105): the
    silhouette is the pixels along both outlines, within 1 px, and nothing else."""
    camera = looking_down()
    far, near = square(-4.03, 3.91, -2.94, 3.07, 0.0), square(-1.02, 0.97, -0.93, 1.06, 1.0)
    faces = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    found = silhouette(camera, RayTracer(np.vstack([far, near]), faces))
    outlines = [camera.project(np.vstack([q, q[:1]])) for q in (far, near)]
    assert recall_precision(found, trace_pixels(outlines, found.shape), tolerance=1.0) == (1.0, 1.0)
    # a range step too small to count leaves only the outline
    near[:, 2] = 0.2  # ln(10/9.8) = 0.02
    found = silhouette(camera, RayTracer(np.vstack([far, near]), faces))
    assert recall_precision(found, trace_pixels(outlines[:1], found.shape), tolerance=1.0) == (1.0, 1.0)


def every_pixel_silhouette(camera: Camera, tracer: RayTracer, depth_step: float = 0.03) -> np.ndarray:
    """The silhouette by brute force: a ray through every pixel, then the same test between 4-neighbours."""
    v, u = np.mgrid[0:camera.height, 0:camera.width]
    hits = tracer.intersect(camera.centre, camera.pixel_rays(np.column_stack([u.ravel(), v.ravel()])))
    hit = hits.hit.reshape(u.shape)
    log_range = np.log(np.where(hits.hit, hits.t, 1.0)).reshape(u.shape)
    out = np.zeros(u.shape, bool)
    for axis in (0, 1):
        a = [slice(None)] * 2
        b = [slice(None)] * 2
        a[axis], b[axis] = slice(0, -1), slice(1, None)
        a, b = tuple(a), tuple(b)
        edge = (hit[a] != hit[b]) | (hit[a] & hit[b] & (np.abs(log_range[a] - log_range[b]) > depth_step))
        out[a] |= edge
        out[b] |= edge
    return out


def test_silhouette_in_two_passes_is_the_every_pixel_one(outcrops):
    """Rays every 4 px, then every pixel of the cells that disagree: measured equal to a ray through every
    pixel on 5 of 6 synthetic photos (seeds 1 and 3), 16 of 6594 pixels apart on the sixth (slivers of
    occluding contour thinner than the 4 px grid)."""
    outcrop = outcrops["alt"]
    mesh = outcrop.noisy_mesh
    tracer = RayTracer(mesh.vertices, mesh.faces)
    for name, camera in outcrop.local_cameras().items():
        found, every = silhouette(camera, tracer), every_pixel_silhouette(camera, tracer)
        assert every.sum() > 1000 and (found != every).sum() <= 0.005 * every.sum(), name


@pytest.mark.parametrize("size", [(1, 7), (7, 1), (2, 2), (41, 29), (43, 33), (600, 261)])
def test_silhouette_of_small_and_odd_sized_photos_is_the_every_pixel_one(size, monkeypatch):
    """Sizes that are not multiples of the 4 px grid, photos a pixel wide, and (with 8-row strips) a photo
    cut into many strips of the second pass."""
    module = importlib.import_module("engine.delineate.silhouette")  # the package's name is the function
    monkeypatch.setattr(module, "STRIP", 8)
    width, height = size
    camera = looking_down(width, height, f=0.75 * max(width, height))
    far, near = square(-4.03, 3.91, -2.94, 3.07, 0.0), square(-1.02, 0.97, -0.93, 1.06, 1.0)
    tracer = RayTracer(np.vstack([far, near]), np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]]))
    assert np.array_equal(silhouette(camera, tracer), every_pixel_silhouette(camera, tracer))


def test_silhouette_checks_its_depth_step():
    with pytest.raises(InputError, match=r"depth_step=0 is out of range: expected a number in \(0, 5\]"):
        silhouette(looking_down(), RayTracer(square(-1, 1, -1, 1, 0), np.array([[0, 1, 2]])), depth_step=0)


# -- auto-tracing on synthetic photos --------------------------------------------------------------------

def trace_pixels(polylines, shape):
    """Pixels the true polylines pass through (sampled every 0.5 px)."""
    mask = np.zeros(shape, bool)
    for p in polylines:
        uv = np.rint(resample_polyline(p, 0.5)[0]).astype(int)
        ok = (uv[:, 0] >= 0) & (uv[:, 0] < shape[1]) & (uv[:, 1] >= 0) & (uv[:, 1] < shape[0])
        mask[uv[ok, 1], uv[ok, 0]] = True
    return mask


def recall_precision(found: np.ndarray, true: np.ndarray, tolerance: float = 2.0) -> tuple[float, float]:
    """Fraction of true pixels within `tolerance` px of a found one, and of found pixels near a true one."""
    near_found = ndimage.distance_transform_edt(~found) <= tolerance
    near_true = ndimage.distance_transform_edt(~true) <= tolerance
    return float(near_found[true].mean()), float(near_true[found].mean()) if found.any() else 1.0


@pytest.fixture(scope="module")
def silhouettes(outcrops):
    """The mesh's silhouette in every photo (the same outcrop in both looks), as the CLI and editor give it."""
    outcrop = outcrops["default"]
    tracer = RayTracer(outcrop.noisy_mesh.vertices, outcrop.noisy_mesh.faces)
    return {name: silhouette(camera, tracer) for name, camera in outcrop.local_cameras().items()}


@pytest.fixture(scope="module")
def autotraced(outcrops, silhouettes):
    """The default auto-trace (with the mesh's silhouette, as the CLI and editor run it) of every photo, by
    style and photo name: its traces, the segments it turned down and its skeleton."""
    out = {}
    for style, outcrop in outcrops.items():
        out[style] = {}
        for name, rgb in outcrop.images.items():
            result = autotrace(rgb, image_name=name, silhouette=silhouettes[name])
            assert all(t.source == "auto" and t.image == name and t.component >= 0 for t in result.traces)
            out[style][name] = (result.traces, result.segments.rejected, result.skeleton)
    return out


def scored(outcrop, name, traces) -> tuple[float, float]:
    true = trace_pixels([t.polyline for t in outcrop.traces2d[name]], outcrop.images[name].shape[:2])
    return recall_precision(trace_map(traces, true.shape), true)


@pytest.fixture(scope="module")
def scores(outcrops, autotraced):
    """(recall, precision) of the default auto-trace on every photo, by style and photo name."""
    return {style: {name: scored(outcrops[style], name, traces) for name, (traces, *_) in autotraced[style].items()}
            for style in outcrops}


@pytest.mark.parametrize("style", ["default", "alt"])
def test_autotrace_recall_and_precision(style, scores):
    """Measured at 1024×768, seed 1: default recall 0.91–0.94, precision 0.92–0.97; alt recall 0.82–0.89,
    precision 0.91–0.95 (seed 2: default 0.93–0.965 / 0.955–0.97, alt 0.85–0.895 / 0.92–0.97).
    Alt misses are traces inside the shadowed strips, where they are hardly visible, traces along the wall's
    outline, and faint traces on mottled rock that break into pieces too short to judge. The crease, skyline
    and foot false traces of the default look fail the brightness-profile test (line_profile.py)."""
    for name, (recall, precision) in scores[style].items():
        assert recall >= FLOOR[style][0], f"{style} {name}: recall {recall:.3f}"
        assert precision >= FLOOR[style][1], f"{style} {name}: precision {precision:.3f}"


def test_autotrace_meets_the_issue_target(surveyed_scores):
    """As `tracemap autotrace` traces the survey: each photo, then the support between them and the traces
    carried between them. Seed 1, both looks (session 16): alt recall 0.853, 0.899, 0.891 and precision
    0.947, 0.905, 0.922; held out, seeds 2–8, see the next test. Alt is limited by the
    judgement of chains: keeping exactly the chains of the skeleton (phase congruency's edges with the line
    filter's lines) that lie on true traces (an oracle judge) reaches recall 0.89, 0.94, 0.89 on seed 1's
    alt photos (seed 3: 0.91, 0.92, 0.95)."""
    for style, by_name in surveyed_scores.items():
        assert all(r >= TARGET[0] and p >= TARGET[1] for r, p in by_name.values()), (style, by_name)


def _short_of_target(reason: str):
    return pytest.mark.xfail(strict=True, reason=f"issue 3 target not reached: {reason}")


HELD_OUT = [("default", seed) for seed in range(2, 9)] + [
    ("alt", 2),
    pytest.param("alt", 3, marks=_short_of_target("recall 0.834, 0.835 on photos 1 and 2 (traces in the shadowed "
                                                  "strips that no photo traced)")),
    pytest.param("alt", 4, marks=_short_of_target("photo 3 precision 0.867 (texture streaks on a face seen "
                                                  "obliquely, pieces on the ground)")),
    ("alt", 5),
    pytest.param("alt", 6, marks=_short_of_target("recall 0.801, 0.844 on photos 1 and 2; precision 0.887 on "
                                                  "photos 1 and 3")),
    pytest.param("alt", 7, marks=_short_of_target("recall 0.836 and precision 0.896 on photo 1; photo 3 "
                                                  "precision 0.852")),
    pytest.param("alt", 8, marks=_short_of_target("photo 1 recall 0.840; photo 3 precision 0.840 (the wall's "
                                                  "foot, streaks beside the step)"))]


@pytest.mark.parametrize("style, seed", HELD_OUT)
def test_autotrace_meets_the_issue_target_on_held_out_outcrops(style, seed):
    """Seeds 2–8 in both looks, traced as `tracemap autotrace` does (measured session 17): the default look
    meets the target on all 21 photos (recall 0.914–0.982, precision 0.922–0.988); the alt look on 11 of 21,
    the others marked. On the five alt outcrops short of it, a judge dropping exactly the false traces (under
    half their length on true ones) would lift precision to 0.954–0.985, recall unchanged, and keeping as well
    exactly the true turned-down chains (10 px or more) would lift recall to 0.864–0.937: the target on every
    photo. The chains hold what the target needs; the judge of them falls short (README → Status, session 17).
    """
    outcrop = make_outcrop(seed, **PHOTOS, style=style)
    tracer = RayTracer(outcrop.noisy_mesh.vertices, outcrop.noisy_mesh.faces)
    cameras = outcrop.local_cameras()
    results = {name: autotrace(rgb, image_name=name, silhouette=silhouette(cameras[name], tracer))
               for name, rgb in outcrop.images.items()}
    found = _survey({n: ([t.polyline for t in r.traces], r.segments.rejected, r.skeleton) for n, r in results.items()},
                    cameras, tracer, carry=True)
    got = {name: scored(outcrop, name, [Trace2D(0, name, line, "auto") for line in lines]) for name, lines in found.items()}
    assert all(r >= TARGET[0] and p >= TARGET[1] for r, p in got.values()), got


def _survey(runs: dict, cameras: dict, tracer: RayTracer, *, carry: bool) -> dict[str, list[np.ndarray]]:
    """Every photo's traces (polylines) as `tracemap autotrace` leaves them, from each photo's run (its traces,
    turned-down segments and skeleton, by name): with the segments the other photos support and, with
    `carry`, the other photos' traces carried into it."""
    traces = {name: list(lines) for name, (lines, _, _) in runs.items()}
    extra = supported_traces({name: chains for name, (_, chains, _) in runs.items()}, traces, cameras, tracer)
    traces = {name: traces[name] + extra[name] for name in traces}
    if carry:
        carried = carried_traces(traces, cameras, tracer, {name: skeleton for name, (*_, skeleton) in runs.items()})
        traces = {name: traces[name] + carried[name] for name in traces}
    return traces


def _surveyed(outcrops, autotraced, carry: bool) -> dict:
    out = {}
    for style, outcrop in outcrops.items():
        tracer = RayTracer(outcrop.noisy_mesh.vertices, outcrop.noisy_mesh.faces)
        runs = {name: ([t.polyline for t in found], chains, skeleton)
                for name, (found, chains, skeleton) in autotraced[style].items()}
        found = _survey(runs, outcrop.local_cameras(), tracer, carry=carry)
        out[style] = {name: scored(outcrop, name, [Trace2D(0, name, line, "auto") for line in lines])
                      for name, lines in found.items()}
    return out


@pytest.fixture(scope="module")
def supported_scores(outcrops, autotraced):
    """(recall, precision) of every photo with the segments it turned down that the other photos' traces
    show (`supported_traces`)."""
    return _surveyed(outcrops, autotraced, carry=False)


@pytest.fixture(scope="module")
def surveyed_scores(outcrops, autotraced):
    """(recall, precision) of every photo as `tracemap autotrace` gives them: with the support and the traces
    carried from the other photos (`carried_traces`)."""
    return _surveyed(outcrops, autotraced, carry=True)


def test_traces_carried_from_other_photos_fill_what_a_photo_did_not_trace(supported_scores, surveyed_scores):
    """Seed 1 (session 16): alt recall 0.848, 0.899, 0.840 → 0.853, 0.899, 0.891 for precision +0, +0, +0.5
    points; default recall +0, +1.3, +0 for precision −1.6, +0.1, +0. Held out, seeds 2–5: alt recall +0 to
    +2.2 points, precision −0.5 to +0.2; default recall +0 to +2.4, precision −0.4 to +0.1
    (engine/delineate/support.py)."""
    gains = {(style, name): (r - supported_scores[style][name][0], p - supported_scores[style][name][1])
             for style, by_name in surveyed_scores.items() for name, (r, p) in by_name.items()}
    assert all(dr >= 0 and dp >= -0.02 for dr, dp in gains.values()), gains
    assert gains[("alt", "photo_03")][0] >= 0.04, gains


def test_support_from_other_photos_finds_traces_a_photo_shows_too_faintly(scores, supported_scores):
    """Seed 1: recall alt 0.832, 0.887, 0.822 → 0.848, 0.899, 0.840 and default 0.914, 0.941, 0.934 → 0.947,
    0.943, 0.939; precision −0.1 to −0.8 points. Seeds 2–5, both looks: recall +0 to +3.8 points, precision
    +0.2 to −1.4 (engine/delineate/support.py)."""
    gains = {(style, name): (r - scores[style][name][0], p - scores[style][name][1])
             for style, by_name in supported_scores.items() for name, (r, p) in by_name.items()}
    assert all(dr >= 0 and dp >= -0.01 for dr, dp in gains.values()), gains
    assert all(dr >= 0.01 for (style, _), (dr, _) in gains.items() if style == "alt"), gains


def test_the_line_filter_finds_faint_traces_phase_congruency_misses(outcrops, silhouettes, scores):
    """Seed 1's alt photos without the line filter: recall 0.801, 0.855, 0.815 and precision 0.933, 0.909,
    0.905; with it (`scores`) 0.832, 0.887, 0.822 and 0.951, 0.913, 0.920: +0.7 to +3.2 points of recall
    (session 11, before the silhouette and with contrast 0.08: seed 2 +0.8 to +4.4; held out, seeds 3–5,
    +0.8 to +6.3, precision −1.1 to +1.5)."""
    gains = []
    for name, rgb in outcrops["alt"].images.items():
        result = autotrace(rgb, params=DelineationParams(line_filter=False), image_name=name,
                           silhouette=silhouettes[name])
        assert result.lines is None and result.skeleton is result.edges.skeleton
        true = trace_pixels([t.polyline for t in outcrops["alt"].traces2d[name]], rgb.shape[:2])
        recall, _ = recall_precision(trace_map(result.traces, rgb.shape[:2]), true)
        gains.append(scores["alt"][name][0] - recall)
    assert min(gains) >= 0.005 and np.mean(gains) >= 0.015, gains


def test_traces_along_the_silhouette_are_dropped(outcrops, silhouettes, scores):
    """Seed 1 without the silhouette: precision alt 0.935, 0.907, 0.890 and default 0.953, 0.949, 0.918 (with
    it see `scores`); recall the same within 0.3 points. Held out (seeds 2–5, both looks, contrast 0.08):
    precision +0 to +4.0 points (alt 0.870 → 0.910 and 0.842 → 0.877 on the two worst photos), recall −0
    to −1.0."""
    for style, outcrop in outcrops.items():
        gains = []
        for name, rgb in outcrop.images.items():
            result = autotrace(rgb, image_name=name)
            assert result.silhouette is None
            true = trace_pixels([t.polyline for t in outcrop.traces2d[name]], rgb.shape[:2])
            recall, precision = recall_precision(trace_map(result.traces, rgb.shape[:2]), true)
            assert scores[style][name][0] >= recall - 0.005
            gains.append(scores[style][name][1] - precision)
        assert min(gains) >= 0 and np.mean(gains) >= 0.005, (style, gains)


def test_judging_chains_on_the_photo_before_denoising_finds_more_alt_traces(outcrops, silhouettes, scores):
    """Seed 1's alt photos judged on the denoised photo alone (raw_contrast off): recall 0.830, 0.863, 0.819
    and precision 0.956, 0.917, 0.922; with it (`scores`) 0.832, 0.887, 0.822 and 0.951, 0.913, 0.920.
    Held out (seeds 3–5): alt recall +0 to +2.3 points (mean +0.9), precision −0 to −1.4 (mean −0.65);
    the default look +0.2 and −0.3 in the mean."""
    gains = []
    for name, rgb in outcrops["alt"].images.items():
        result = autotrace(rgb, params=DelineationParams(raw_contrast=5.0), silhouette=silhouettes[name])
        true = trace_pixels([t.polyline for t in outcrops["alt"].traces2d[name]], rgb.shape[:2])
        recall, precision = recall_precision(trace_map(result.traces, rgb.shape[:2]), true)
        gains.append(scores["alt"][name][0] - recall)
        assert scores["alt"][name][1] >= precision - 0.01
    assert min(gains) >= 0 and np.mean(gains) >= 0.005, gains


def test_a_silhouette_of_another_size_is_refused(outcrops):
    rgb = outcrops["default"].images["photo_01"]
    with pytest.raises(InputError, match=r"the silhouette is \(10, 10\) px but the photo \(768, 1024\)"):
        autotrace(rgb, silhouette=np.zeros((10, 10), bool))


def test_autotrace_returns_every_stage(outcrops):
    rgb = outcrops["default"].images["photo_01"]
    result = autotrace(rgb, params=DelineationParams(pc_method="monogenic"), image_name="photo_01")
    h, w = rgb.shape[:2]
    assert result.denoised.shape == result.phase.edge.shape == result.edges.skeleton.shape == (h, w)
    assert result.lines.strength.shape == result.skeleton.shape == result.components.shape == (h, w)
    assert (result.skeleton >= result.lines.mask).mean() > 0.95  # the lines are in what segments were found in
    assert len(result.segments.polylines) == len(result.segments.free) > 0
    assert result.traces and all(t.length >= result.params.min_length for t in result.traces)


def test_an_empty_result_is_a_result():
    result = autotrace(np.full((120, 160), 128, np.uint8))
    assert result.traces == [] and result.segments.polylines == []
    assert (result.components == -1).all()


# -- segments and growing --------------------------------------------------------------------------------

def test_segments_split_at_junctions_and_pair_straight_branches():
    """A straight line crossed by a short spur and by a branch at 60°: the line continues through."""
    skeleton = np.zeros((80, 120), bool)
    skeleton[40, 10:110] = True  # the main line
    skeleton[33:40, 60] = True  # a 7 px spur
    for k in range(1, 30):  # a branch leaving at 60° below the line
        skeleton[40 + int(round(k * math.sin(math.radians(60)))), 30 - int(round(k * 0.5))] = True
    segments = find_segments(skeleton, simplify=0.5)
    lengths = sorted(round(float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())) for p in segments.polylines)
    assert len(segments.polylines) == 2  # the spur is gone, the main line is whole
    assert lengths[-1] == pytest.approx(99, abs=1)
    main = max(segments.polylines, key=lambda p: np.linalg.norm(np.diff(p, axis=0), axis=1).sum())
    assert np.abs(main[:, 1] - 40).max() <= 0.5


def profile_image(profile, rows=120, shade=None, seed=6):
    """8-bit photo of vertical features: brightness profile(u) down every row, times `shade(u)` if given,
    slightly blurred (as by a lens) and with sensor noise."""
    u = np.arange(240, dtype=np.float64)
    brightness = profile(u) * (1 if shade is None else shade(u))
    image = np.tile(brightness, (rows, 1)).astype(np.float32)
    image = cv2.GaussianBlur(image, (0, 0), 0.6) + np.random.default_rng(seed).normal(0, 2, image.shape)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def trace_profile(centre, depth=0.4):
    """Rock of brightness 150 darkened by a Gaussian trace 1.5 px wide at half depth."""
    return lambda u: 150 * (1 - depth * np.exp(-0.5 * ((u - centre) / 0.64) ** 2))


def crease_profile(centre):
    """The side face of a step seen edge-on: dark for 2 px with a sharp left edge, then a 6 px shading ramp."""
    return lambda u: np.interp(u, [centre - 1.5, centre - 1, centre + 1, centre + 7], [150, 60, 60, 150])


def vertical(u, rows=120):
    return np.column_stack([np.full(rows - 20, float(u)), np.arange(10, rows - 10, dtype=np.float64)])


def test_line_profile_tells_a_trace_from_a_crease_and_a_step():
    width = DelineationParams().trace_width
    measures = {}
    for name, profile in (("trace", trace_profile(120)), ("crease", crease_profile(120)),
                          ("step", lambda u: np.where(u < 120, 150.0, 80.0))):
        log_image = log_brightness(profile_image(profile))
        contrast, asymmetry = line_measures(*cross_profiles(log_image, [vertical(120)], width), width)
        measures[name] = (contrast[0], asymmetry[0])
    # a 40% darkening, blurred to 30% (ln 0.36); symmetric (measured asymmetry 0.001)
    assert measures["trace"][0] == pytest.approx(0.36, abs=0.04) and measures["trace"][1] < 0.05
    assert measures["crease"][0] > 0.3 and measures["crease"][1] > 0.4  # a dark line, but lopsided (0.52)
    assert measures["step"][0] < 0.05  # no side brighter than the centre (measured 0.004)


def test_a_trace_in_shade_has_the_contrast_it_has_in_sun():
    """In log brightness, traces darkening the rock by 30% in sun and at a quarter of the light (u ≥ 120) have
    the same contrast; in grey levels the one in shade is 4× fainter (31 against 8 levels deep)."""
    traces = lambda u: trace_profile(60, depth=0.3)(u) * trace_profile(180, depth=0.3)(u) / 150
    image = profile_image(traces, shade=lambda u: np.where(u < 120, 1.0, 0.25))
    log_image, width = log_brightness(image), DelineationParams().trace_width
    lit, shaded = line_measures(*cross_profiles(log_image, [vertical(60), vertical(180)], width), width)[0]
    assert lit == pytest.approx(shaded, abs=0.03)  # measured 0.257 and 0.261
    assert lit > 0.2


def test_a_faint_trace_in_shade_is_judged_on_the_photo_before_denoising():
    """A trace darkening the rock by 40% at a fifth of the light (30 grey levels; noise σ 2): non-local means
    (h 4) flattens it to a contrast of 0.02–0.04, so the denoised photo rejects it on all 10 noise draws; on
    the photo before denoising, recentred where the denoised photo has its dip, it passes on 6. A chain on
    bare rock beside it never passes: recentred on its own darkest sample, the noise alone would measure
    0.06–0.08 deep."""
    width = DelineationParams().trace_width
    skeleton = np.zeros((120, 240), bool)
    skeleton[10:110, 80] = skeleton[10:110, 160] = True  # the trace, and bare rock
    kept = {"denoised": 0, "with the photo": 0, "bare rock": 0}
    for seed in range(6, 16):
        photo = profile_image(trace_profile(80, 0.4), shade=lambda u: np.full_like(u, 0.2), seed=seed)
        denoised = denoise(photo, h=4.0)
        kept["denoised"] += len(find_segments(skeleton, image=denoised).polylines)
        with_photo = find_segments(skeleton, image=denoised, photo=photo).polylines
        kept["with the photo"] += sum(p[0, 0] == 80 for p in with_photo)
        kept["bare rock"] += sum(p[0, 0] == 160 for p in with_photo)
        bare = [vertical(160)]
        own = line_measures(*cross_profiles(log_brightness(photo), bare, width), width)[0]
        guided = line_measures(*cross_profiles(log_brightness(photo), bare, width,
                                               centre_on=log_brightness(denoised)), width)[0]
        assert own[0] > 0.05 and abs(guided[0]) < 0.02
    assert kept == {"denoised": 0, "with the photo": 6, "bare rock": 0}


def test_profiles_recentred_on_another_image_need_the_same_grid():
    with pytest.raises(InputError, match=r"centre_on is \(5, 5\) but the image \(120, 240\)"):
        cross_profiles(np.zeros((120, 240)), [vertical(80)], 3.0, centre_on=np.zeros((5, 5)))
    with pytest.raises(InputError, match="photo must be the 8-bit grey photo of the skeleton's shape"):
        find_segments(np.zeros((120, 240), bool), image=np.zeros((120, 240), np.uint8),
                      photo=np.zeros((5, 5), np.uint8))


def rim_trace_profile(depth, drop):
    """A trace at u = 120 on the rim of a mottle: the rock darkens by `drop` over ~2 px just right of it."""
    return lambda u: trace_profile(120, depth)(u) * (1 - drop * 0.5 * (1 + np.tanh(u - 123.5)))


def test_a_faint_trace_on_a_mottle_rim_is_kept_and_a_strong_lopsided_line_is_not():
    """The mottle skews the trace's dip (asymmetry 0.20, above the 0.15 that rejects creases): a faint line
    (contrast 0.13) passes under `faint_asymmetry`, the same shape twice as dark (0.39, a crease's strength)
    does not."""
    skeleton = np.zeros((120, 240), bool)
    skeleton[10:110, 120] = True
    faint, strong = profile_image(rim_trace_profile(0.25, 0.12)), profile_image(rim_trace_profile(0.6, 0.3))
    width = DelineationParams().trace_width
    for image, expected in ((faint, (0.13, 0.20)), (strong, (0.39, 0.18))):
        measured = line_measures(*cross_profiles(log_brightness(image), [vertical(120)], width), width)
        assert np.ravel(measured) == pytest.approx(expected, abs=0.02)
    assert len(find_segments(skeleton, image=faint).polylines) == 1
    assert find_segments(skeleton, image=faint, faint_asymmetry=0.15).polylines == []  # the old rule
    assert find_segments(skeleton, image=strong).polylines == []


def test_segments_keep_the_trace_and_drop_the_crease():
    image = profile_image(lambda u: trace_profile(60)(u) * crease_profile(180)(u) / 150)
    skeleton = np.zeros(image.shape, bool)
    skeleton[10:110, 60] = skeleton[10:110, 180] = True
    kept = find_segments(skeleton, image=image).polylines
    assert len(kept) == 1 and np.all(kept[0][:, 0] == 60)
    assert len(find_segments(skeleton, image=image, feature="any").polylines) == 2


def test_a_trace_paired_with_a_crease_is_judged_alone():
    """A crease (rows < 70) running on into a trace through a junction (a 15 px branch to the right): the
    two are one chain, which fails the profile test; its branches are judged again, and the trace passes."""
    vv, uu = np.mgrid[:120, :240].astype(np.float64)
    along = np.array([-13.0, 40.0]) / math.hypot(13, 40)  # the trace, from (180, 70) down to (167, 110)
    off_trace = np.abs((uu - 180) * along[1] - (vv - 70) * along[0])
    brightness = np.where(vv < 70, crease_profile(180)(uu), 150 * (1 - 0.4 * np.exp(-0.5 * (off_trace / 0.64) ** 2)))
    image = cv2.GaussianBlur(brightness.astype(np.float32), (0, 0), 0.6)
    image = np.clip(np.rint(image + np.random.default_rng(7).normal(0, 2, image.shape)), 0, 255).astype(np.uint8)
    skeleton = np.zeros(image.shape, np.uint8)
    for a, b in (((180, 10), (180, 70)), ((180, 70), (167, 110)), ((181, 70), (196, 70))):
        cv2.line(skeleton, a, b, 1)
    skeleton = skeleton.astype(bool)
    assert len(find_segments(skeleton, image=image, feature="any").polylines) == 2  # crease + trace, branch
    (kept,) = find_segments(skeleton, image=image).polylines
    assert kept[:, 1].min() >= 69 and kept[:, 1].max() == 110 and kept[:, 0].min() == 167


def test_growing_bridges_collinear_gaps_only():
    left = np.array([[10.0, 50.0], [50.0, 50.0]])
    right = np.array([[62.0, 51.0], [120.0, 52.0]])  # 12 px gap, nearly collinear
    across = np.array([[55.0, 60.0], [55.0, 90.0]])  # starts 10 px below the gap, at right angles
    far = np.array([[150.0, 50.0], [200.0, 50.0]])  # 30 px beyond the right segment: too far
    segments = Segments([left, right, across, far], np.ones((4, 2), bool), np.zeros(4))
    grown = grow_traces(segments, min_length=0)
    assert len(grown) == 3
    joined = max(grown, key=len)
    np.testing.assert_allclose(joined[[0, -1]], [[10, 50], [120, 52]])
    assert len(grow_traces(segments, min_length=45)) == 2  # the 30 px "across" is dropped


# -- guided curves ---------------------------------------------------------------------------------------

def wavy_line_image(rng):
    """A 2 px dark sinusoidal line v = 100 + 20 sin(2πu/150) on a noisy bright background."""
    vv, uu = np.mgrid[:200, :300].astype(np.float64)
    centre = 100 + 20 * np.sin(2 * np.pi * uu / 150)
    image = 190 - 80 * np.exp(-0.5 * ((vv - centre) / 1.0) ** 2) + rng.normal(0, 6, uu.shape)
    return np.clip(image, 0, 255).astype(np.uint8), lambda u: 100 + 20 * np.sin(2 * np.pi * u / 150)


@pytest.mark.parametrize("cost_from", ["darkness", "phase congruency"])
def test_least_cost_path_follows_a_dark_line(cost_from):
    image, line = wavy_line_image(np.random.default_rng(2))
    strength = darkness(image) if cost_from == "darkness" else phase_congruency(image).edge
    clicks = np.array([[20.0, line(20) + 2], [150.0, line(150) - 2], [280.0, line(280) + 1.5]])  # sloppy
    path = least_cost_curve(trace_cost(strength), clicks)
    assert np.abs(path[:, 1] - line(path[:, 0])).max() <= 1.0
    assert path[0, 0] == pytest.approx(20, abs=3) and path[-1, 0] == pytest.approx(280, abs=3)
    assert np.linalg.norm(np.diff(path, axis=0), axis=1).max() <= 1.0 + 1e-9  # pixel spacing


def dark_line_photo(shape, seed):
    """A 2 px dark line v = h/2 + 60 sin(2πu/900) drawn across a noisy bright photo of `shape`, and the line."""
    height, width = shape

    def line(u):
        return height / 2 + 60 * np.sin(2 * np.pi * np.asarray(u) / 900)

    noise = np.random.default_rng(seed).normal(170, 12, shape).clip(0, 255).astype(np.uint8)
    image = cv2.GaussianBlur(noise, (0, 0), 1.0)
    u = np.arange(width)
    cv2.polylines(image, [np.column_stack([u, line(u)]).round().astype(np.int32)], False, 90, 2)
    return image, line


def exact_path(cost, clicks):
    """The least-cost path searched at full resolution over the whole window, however far the clicks."""
    return least_cost_curve(cost, clicks, exact_span=1e9)


@pytest.mark.parametrize("style", ["default", "alt"])
def test_coarse_to_fine_paths_keep_to_the_exact_ones_along_the_traces(outcrops, style):
    """Between the ends of every true trace of 150 px or more, the path joined coarse to fine (exact_span=50
    makes these short spans go through one or two coarser levels) stays within a pixel of the exact
    least-cost path wherever that follows the trace (within 2 px of it)."""
    outcrop, joined = outcrops[style], 0
    for name, rgb in outcrop.images.items():
        cost = trace_cost(darkness(rgb))
        for trace in outcrop.traces2d[name]:
            line = resample_polyline(np.asarray(trace.polyline, np.float64), 1.0)[0]
            if len(line) < 150:
                continue
            clicks = line[[0, -1]]
            exact, quick = exact_path(cost, clicks), least_cost_curve(cost, clicks, exact_span=50.0)
            on_trace = cKDTree(line).query(exact)[0] <= 2.0
            assert cKDTree(quick).query(exact[on_trace])[0].max(initial=0.0) <= 1.0, (name, trace.id)
            joined += 1
    assert joined >= 30


def test_a_long_span_follows_a_dark_line_as_the_exact_path_does():
    image, line = dark_line_photo((1200, 2400), seed=5)
    cost = trace_cost(darkness(image))
    clicks = np.array([[700.0, line(700) + 2], [1700.0, line(1700) - 2]])  # 1000 px apart, sloppy
    path = least_cost_curve(cost, clicks)  # coarse to fine: 1000 px is 5 × exact_span
    assert cKDTree(path).query(exact_path(cost, clicks))[0].max() <= 1.0
    assert np.abs(path[:, 1] - line(path[:, 0])).max() <= 2.5  # the line is drawn 2 px wide, rounded
    assert np.linalg.norm(np.diff(path, axis=0), axis=1).max() <= 1.0 + 1e-9


def test_a_2000_px_span_searches_a_band_along_the_path_not_the_window(monkeypatch):
    """Exactly, the search would settle most of the 9.6 MP window (2 s); coarse to fine searches under 3%
    of it, some 120 px per px of path over every level (0.16 s)."""
    image, line = dark_line_photo((2400, 4000), seed=6)
    cost = trace_cost(darkness(image))
    searched = []
    dijkstra = guided._dijkstra

    def counting(masked, start, stop):
        searched.append(int(np.isfinite(masked).sum()))  # pixels the search may enter
        return dijkstra(masked, start, stop)

    monkeypatch.setattr(guided, "_dijkstra", counting)
    path = least_cost_curve(cost, np.array([[1000.0, line(1000)], [3000.0, line(3000)]]))
    assert np.abs(path[:, 1] - line(path[:, 0])).max() <= 2.5
    assert sum(searched) < 0.03 * cost.size and sum(searched) < 150 * len(path)


def test_darkness_is_scaled_by_its_995th_percentile():
    image, _ = dark_line_photo((300, 400), seed=7)
    hat = cv2.morphologyEx(image, cv2.MORPH_BLACKHAT, cv2.getStructuringElement(cv2.MORPH_RECT, (7, 7)))
    expected = np.clip(hat.astype(np.float32) / np.percentile(hat.astype(np.float32), 99.5), 0, 1)
    np.testing.assert_allclose(darkness(image), expected, rtol=1e-6)


def test_spline_keeps_waviness_that_the_default_smoothing_erases():
    """MATHS §5: s = m·σ² keeps a 5 px waviness; scipy's default s = m − √(2m) erases it at 1 cm per px."""
    rng = np.random.default_rng(4)
    u = np.linspace(0, 200, 41)
    clicks = np.column_stack([u, 100 + 5 * np.sin(2 * np.pi * u / 50)]) + rng.normal(0, 0.3, (41, 2))

    def amplitude(curve):  # of the 50 px waviness: least-squares fit of a + b·u + c·sin + d·cos, px
        u, v = curve[:, 0], curve[:, 1]
        phase = 2 * np.pi * u / 50
        basis = np.column_stack([np.ones_like(u), u, np.sin(phase), np.cos(phase)])
        coefficients = np.linalg.lstsq(basis, v, rcond=None)[0]
        return float(np.hypot(*coefficients[2:]))

    ours = spline_curve(clicks, sigma=0.3)  # the clicks' error
    assert amplitude(ours) == pytest.approx(5, abs=0.5)
    truth = 100 + 5 * np.sin(2 * np.pi * ours[:, 0] / 50)
    assert np.sqrt(np.mean((ours[:, 1] - truth) ** 2)) <= 0.5
    metres = clicks * 0.01  # the same clicks at 1 cm per pixel (a trace in metric units)
    tck, _ = interpolate.splprep(metres.T)  # scipy's default s
    default = np.column_stack(interpolate.splev(np.linspace(0, 1, 400), tck)) / 0.01
    assert amplitude(default) < 0.5
    assert amplitude(spline_curve(metres, sigma=0.003, spacing=0.01) / 0.01) == pytest.approx(5, abs=0.5)


def test_spline_through_two_or_repeated_points():
    line = spline_curve(np.array([[0, 0], [0, 0], [10, 0]]))  # a double click, then one more
    np.testing.assert_allclose(line[[0, -1]], [[0, 0], [10, 0]])
    assert len(line) == 11
    with pytest.raises(InputError, match="at least 2 distinct points"):
        spline_curve(np.array([[3, 4], [3, 4]]))


# -- 2D connectivity -------------------------------------------------------------------------------------

def test_components_of_a_hand_made_map():
    lines = {"a": [[10, 20], [90, 20]], "b": [[50, 5], [50, 60]],  # crossing
             "c": [[10, 80], [40, 80]], "d": [[41, 81], [60, 95]],  # touching diagonally only
             "e": [[70, 80], [90, 80]], "f": [[70, 83], [90, 83]]}  # parallel, 3 px apart
    traces = [Trace2D(k, "img", np.array(p, float), "auto") for k, p in enumerate(lines.values())]
    labelled, labels = label_components(traces, (100, 100))
    c = dict(zip(lines, (t.component for t in labelled)))
    assert c["a"] == c["b"] and c["c"] == c["d"]
    assert len({c["a"], c["c"], c["e"], c["f"]}) == 4
    assert sorted(np.unique(labels)) == [-1, 0, 1, 2, 3]
    assert labels[20, 50] == c["a"] and labels[0, 0] == -1
    assert [t.id for t in labelled] == [t.id for t in traces] and traces[0].component == -1  # copies


# -- bad input -------------------------------------------------------------------------------------------

@pytest.mark.parametrize("kwargs, message", [
    ({"nscale": 0}, r"nscale=0 is out of range: expected an integer in \[2, 8\]"),
    ({"nlm_template": 4}, r"nlm_template=4 is out of range: expected an odd integer in \[3, 21\]"),
    ({"sigma_onf": 1.0}, r"sigma_onf=1.0 is out of range: expected a number in \(0, 1\)"),
    ({"feature": "light"}, r"feature='light' is out of range: expected one of 'dark', 'bright', 'any'"),
    ({"link_angle": float("nan")}, r"link_angle=nan is out of range"),
    ({"low": 0.5, "high": 0.2}, r"low=0.5 must not exceed high=0.2"),
    ({"trace_width": 0.5}, r"trace_width=0.5 is out of range: expected a number in \[1, 50\]"),
])
def test_bad_parameters_name_the_parameter_and_its_range(kwargs, message):
    with pytest.raises(InputError, match=message):
        DelineationParams(**kwargs)


def test_stage_defaults_are_the_parameter_defaults():
    """Each stage function's keyword defaults are DelineationParams' (both are written out), except that
    phase congruency keeps Kovesi's 4 scales where auto-tracing uses 3 (params.py says why)."""
    import inspect

    params = DelineationParams()
    renamed = {"h": "nlm_h", "template_window": "nlm_template", "search_window": "nlm_search"}
    line = {name: "line_" + name for name in ("sigma", "length", "norient", "wide", "ratio", "low", "high")}
    kovesi = {"nscale": 4}
    for stage in (denoise, phase_congruency, phase_congruency_mono, detect_edges, line_filter, find_segments,
                  grow_traces):
        for name, parameter in inspect.signature(stage).parameters.items():
            field = (line if stage is line_filter else renamed).get(name, name)
            if stage in (phase_congruency, phase_congruency_mono) and name in kovesi:
                assert parameter.default == kovesi[name] != getattr(params, field)
            elif hasattr(params, field):
                assert parameter.default == getattr(params, field), f"{stage.__name__}({name}=…)"


def test_stage_functions_check_their_parameters():
    image = np.zeros((64, 64), np.uint8)
    with pytest.raises(InputError, match=r"k=-1 is out of range"):
        phase_congruency(image, k=-1)
    with pytest.raises(InputError, match=r"h_color=-2 is out of range"):
        denoise(np.zeros((8, 8, 3), np.uint8), h_color=-2)
    with pytest.raises(InputError, match="8-bit"):
        denoise(image.astype(np.float32))
    with pytest.raises(InputError, match="8-bit"):
        autotrace(image.astype(np.float64))
    with pytest.raises(InputError, match="NaN"):
        phase_congruency(np.full((32, 32), np.nan))
    with pytest.raises(InputError, match="outside"):
        least_cost_curve(np.ones((10, 10)), np.array([[1, 1], [20, 5]]))
    with pytest.raises(InputError, match="8-bit grey photo of the skeleton's shape"):
        find_segments(np.zeros((64, 64), bool), image=image.astype(np.float32))


GREY = np.full((20, 20), 200, np.uint8)
CLICKS = np.array([[2.0, 3.0], [15.0, 12.0]])


@pytest.mark.parametrize("call, message", [
    (lambda: darkness(GREY, line_width=0), "line_width=0 is out of range: expected an integer in [1, inf]"),
    (lambda: darkness(GREY, line_width=2.5), "line_width=2.5 is out of range: expected an integer in [1, inf]"),
    (lambda: trace_cost(GREY / 255, epsilon=0.0), "epsilon=0.0 is out of range: expected a number in (0, inf]"),
    (lambda: trace_cost(GREY / 255, epsilon=math.nan), "epsilon=nan is out of range"),
    (lambda: least_cost_curve(np.ones((20, 20)), CLICKS, snap_radius=math.nan),
     "snap_radius=nan is out of range: expected a number in [0, inf]"),
    (lambda: least_cost_curve(np.ones((20, 20)), CLICKS, snap_radius=-1.0), "snap_radius=-1.0 is out of range"),
    (lambda: least_cost_curve(np.ones((20, 20)), CLICKS, margin=-4.0),
     "margin=-4.0 is out of range: expected a number in [0, inf]"),
    (lambda: least_cost_curve(np.ones((20, 20)), CLICKS, margin=math.inf), "margin=inf is out of range"),
    (lambda: least_cost_curve(np.ones((20, 20)), CLICKS, exact_span=-1.0),
     "exact_span=-1.0 is out of range: expected a number in [0, inf]"),
    (lambda: least_cost_curve(np.ones((20, 20)), CLICKS, corridor=math.nan), "corridor=nan is out of range"),
    (lambda: least_cost_curve(np.ones((20, 20)), CLICKS, slack=math.inf), "slack=inf is out of range"),
    (lambda: spline_curve(CLICKS, sigma=-0.5), "sigma=-0.5 is out of range: expected a number in [0, inf]"),
    (lambda: spline_curve(CLICKS, spacing=0), "spacing=0 is out of range: expected a number in (0, inf]"),
])
def test_guided_curves_check_their_parameters(call, message):
    with pytest.raises(InputError) as error:
        call()
    assert str(error.value).startswith(message)


def test_guided_curves_accept_the_ends_of_their_ranges():
    path = least_cost_curve(np.ones((20, 20)), CLICKS, snap_radius=0.0, margin=0.0)
    np.testing.assert_array_equal(path[[0, -1]], CLICKS)  # no snapping: the path runs from click to click
    for search in ({"exact_span": 0.0}, {"exact_span": 0.0, "corridor": 0.0, "slack": 0.0}):  # coarse to fine
        path = least_cost_curve(np.ones((20, 20)), CLICKS, snap_radius=0.0, **search)
        np.testing.assert_array_equal(path[[0, -1]], CLICKS)
    assert darkness(GREY, line_width=1).max() == 0.0  # a 1 px square has no surroundings


def test_read_photo_reports_missing_unreadable_and_mis_sized(tmp_path, outcrops):
    camera = outcrops["default"].cameras["photo_01"]
    with pytest.raises(InputError, match="photo not found"):
        read_photo(tmp_path / "nowhere.png", camera)
    (tmp_path / "junk.png").write_bytes(b"not an image")
    with pytest.raises(InputError, match="cannot read"):
        read_photo(tmp_path / "junk.png", camera)
    cv2.imwrite(str(tmp_path / "small.png"), np.zeros((100, 120, 3), np.uint8))
    with pytest.raises(InputError, match=r"120×100 px but camera 'photo_01' is 1024×768"):
        read_photo(tmp_path / "small.png", camera)


def test_read_photo_keeps_the_stored_pixel_grid_of_an_exif_rotated_photo(tmp_path):
    from PIL import Image

    from engine.cameras import check_images
    from tests.scenes import facing_camera

    stored = np.zeros((80, 120, 3), np.uint8)
    stored[:, :60] = (255, 0, 0)  # left half red, right half blue
    stored[:, 60:] = (0, 0, 255)
    exif = Image.Exif()
    exif[0x0112] = 6  # Orientation: shown rotated 90° clockwise
    Image.fromarray(stored).save(tmp_path / "cam.jpg", exif=exif.tobytes(), quality=95)
    camera = facing_camera("cam", width=120, height=80)
    assert check_images({"cam": camera}, tmp_path) == {"cam": tmp_path / "cam.jpg"}
    image = read_photo(tmp_path / "cam.jpg", camera)
    assert image.shape == (80, 120, 3)
    assert np.abs(image[:, :55].astype(int) - (255, 0, 0)).max() <= 8
    assert np.abs(image[:, 65:].astype(int) - (0, 0, 255)).max() <= 8


# -- command line ----------------------------------------------------------------------------------------

def linked_project(tmp_path, n_cameras: int) -> str:
    """A project on a small synthetic outcrop of 400×300 photos, linked to them (what autotrace reads)."""
    paths = write_outcrop(make_outcrop(2, **{**QUICK, "n_cameras": n_cameras, "image_size": (400, 300)}),
                          tmp_path / "outcrop")
    project = str(tmp_path / "p.tracemap")
    assert main(["new", project, "--mesh", str(paths["mesh"]), "--cameras", str(paths["cameras"]),
                 "--images", str(paths["images"])]) == 0
    return project


def test_cli_autotrace_stores_auto_traces_and_export_writes_them(tmp_path, capsys):
    project = linked_project(tmp_path, 2)
    with Project.open(project) as p:
        p.add_traces2d([Trace2D(0, "photo_01", np.array([[5.0, 5.0], [50.0, 40.0]]), "manual")])
    assert main(["autotrace", project, "--image", "photo_01", "--min-length", "25"]) == 0
    assert main(["autotrace", project]) == 0  # again, all photos: replaces the auto traces of photo_01
    out = capsys.readouterr().out
    assert "auto-traced 2 images" in out and "replaced" in out
    with Project.open(project) as p:
        traces = p.traces2d()
    auto = [t for t in traces if t.source == "auto"]
    assert {t.image for t in auto} == {"photo_01", "photo_02"} and all(t.component >= 0 for t in auto)
    assert sum(t.source == "manual" for t in traces) == 1  # manual traces are never touched
    assert main(["export", project, str(tmp_path / "out")]) == 0
    with open(tmp_path / "out" / "traces2d.csv") as f:
        rows = list(csv.DictReader(f))
    assert {r["trace"] for r in rows if r["source"] == "auto"} == {str(t.id) for t in auto}


def test_cli_autotrace_drops_traces_along_the_silhouette_as_the_library_does(tmp_path, capsys):
    project = linked_project(tmp_path, 1)
    with Project.open(project) as p:
        photo = read_photo(p.image_path("photo_01"))
        mesh, camera = p.load_mesh(), p.cameras()["photo_01"]
    outline = silhouette(camera, RayTracer(mesh.vertices, mesh.faces))
    expected = {True: autotrace(photo, silhouette=outline).traces, False: autotrace(photo).traces}
    assert len(expected[True]) < len(expected[False])  # some traces run along the silhouette here
    for used in (True, False):
        assert main(["autotrace", project, *([] if used else ["--no-silhouette"])]) == 0
        with Project.open(project) as p:
            stored = p.traces2d()
        assert len(stored) == len(expected[used])
        assert all(np.array_equal(a.polyline, b.polyline) for a, b in zip(stored, expected[used]))
    Path(mesh.source).rename(tmp_path / "elsewhere.ply")
    capsys.readouterr()
    assert main(["autotrace", project]) == 2
    assert "--no-silhouette --no-support runs without it" in capsys.readouterr().err
    with Project.open(project) as p:  # a refused run changes nothing
        assert [t.polyline.tolist() for t in p.traces2d()] == [t.polyline.tolist() for t in stored]


def test_parameter_files_round_trip_and_name_what_is_wrong(tmp_path):
    chosen = DelineationParams(trace_width=5.0, nscale=4, denoise=False, pc_method="monogenic")
    assert read_params(write_params(chosen, tmp_path / "mine.json")) == chosen
    assert [p.name for p in tmp_path.iterdir()] == ["mine.json"]  # no temporary file left behind
    (tmp_path / "some.json").write_text('{"low": 0.02, "nscale": 4.0}')  # a subset; 4.0 is an integer
    assert read_params(tmp_path / "some.json") == DelineationParams(low=0.02, nscale=4)
    for text, message in [('{"trace_widht": 5}', r"unknown parameter\(s\) trace_widht; the parameters are denoise"),
                          ('{"nscale": 4.5}', r"nscale=4\.5 is out of range: expected an integer in \[2, 8\]"),
                          ('{"low": 0.5, "high": 0.1}', "low=0.5 must not exceed high=0.1"),
                          ('[1, 2]', "expected a JSON object of parameter names and values"),
                          ('{"low": 0.02,}', "not JSON: .* at line 1, column 14")]:
        (tmp_path / "bad.json").write_text(text)
        with pytest.raises(InputError, match=f"bad.json: {message}"):
            read_params(tmp_path / "bad.json")
    with pytest.raises(InputError, match="missing.json: parameter file not found"):
        read_params(tmp_path / "missing.json")


def test_cli_autotrace_reads_a_parameter_file_and_the_project_keeps_what_ran(tmp_path, capsys):
    from engine.delineate.params import SETTING

    project = linked_project(tmp_path, 1)
    write_params(DelineationParams(min_length=40.0, trace_width=4.0), tmp_path / "mine.json")
    assert main(["autotrace", project, "--params", str(tmp_path / "mine.json"), "--min-length", "30"]) == 0
    with Project.open(project) as p:  # the option overrides the file, the file the defaults
        ran = DelineationParams(**p.setting(SETTING))
        traces = p.traces2d()
    assert ran == DelineationParams(min_length=30.0, trace_width=4.0)
    assert main(["export", project, str(tmp_path / "out")]) == 0  # summary.json says what ran
    assert json.loads((tmp_path / "out" / "summary.json").read_text())["autotrace_parameters"] == asdict(ran)
    assert traces and all(t.length >= 30.0 for t in traces)
    (tmp_path / "bad.json").write_text('{"trace_width": 0}')
    capsys.readouterr()
    assert main(["autotrace", project, "--params", str(tmp_path / "bad.json")]) == 2
    assert "bad.json: trace_width=0 is out of range" in capsys.readouterr().err
    with Project.open(project) as p:  # a refused run changes nothing
        assert [t.id for t in p.traces2d()] == [t.id for t in traces] and p.setting(SETTING) == asdict(ran)


def test_cli_autotrace_errors(tmp_path, capsys):
    outcrop = make_outcrop(2, **{**QUICK, "n_cameras": 1, "image_size": (160, 120)})
    paths = write_outcrop(outcrop, tmp_path / "outcrop")
    linked, bare = str(tmp_path / "linked.tracemap"), str(tmp_path / "bare.tracemap")
    common = ["--mesh", str(paths["mesh"]), "--cameras", str(paths["cameras"])]
    assert main(["new", linked, *common, "--images", str(paths["images"])]) == 0
    assert main(["new", bare, *common]) == 0
    capsys.readouterr()
    assert main(["autotrace", bare]) == 2
    assert "has no photo linked" in capsys.readouterr().err
    assert main(["autotrace", linked, "--image", "nope"]) == 2
    assert "no image named 'nope'" in capsys.readouterr().err
    assert main(["autotrace", linked, "--nscale", "1"]) == 2
    assert "nscale=1 is out of range: expected an integer in [2, 8]" in capsys.readouterr().err
    (paths["images"] / "photo_01.png").unlink()
    assert main(["autotrace", linked]) == 2
    assert "moved or deleted" in capsys.readouterr().err


def test_cli_autotrace_keeps_the_segments_the_other_photos_support_as_the_library_does(tmp_path, capsys):
    project = linked_project(tmp_path, 3)
    with Project.open(project) as p:
        mesh, cameras = p.load_mesh(), p.cameras()
        photos = {name: read_photo(p.image_path(name)) for name in cameras}
    tracer = RayTracer(mesh.vertices, mesh.faces)
    results = {name: autotrace(photo, image_name=name, silhouette=silhouette(cameras[name], tracer))
               for name, photo in photos.items()}
    traces = {n: [t.polyline for t in r.traces] for n, r in results.items()}
    extra = supported_traces({n: r.segments.rejected for n, r in results.items()}, traces, cameras, tracer)
    traces = {n: traces[n] + extra[n] for n in traces}
    carried = carried_traces(traces, cameras, tracer, {n: r.skeleton for n, r in results.items()})
    assert sum(map(len, extra.values())) > 0 and sum(map(len, carried.values())) > 0
    assert main(["autotrace", project]) == 0
    out = capsys.readouterr().out
    assert f"{sum(map(len, extra.values()))} of them kept on the support of other photos" in out
    assert f"{sum(map(len, carried.values()))} carried from the other photos' traces" in out
    with Project.open(project) as p:
        for name, result in results.items():
            stored = sorted(t.polyline.tolist() for t in p.traces2d([name]))
            assert stored == sorted(line.tolist() for line in traces[name] + carried[name])
    assert main(["autotrace", project, "--no-support"]) == 0
    with Project.open(project) as p:
        assert len(p.traces2d()) == sum(len(r.traces) for r in results.values())
