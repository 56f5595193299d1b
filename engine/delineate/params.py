"""Delineation parameters: one frozen dataclass holding every default, its unit and its allowed range.

The stage functions take the same names as keyword arguments and validate them with `check`, so a value
out of range raises the same `InputError` (naming the parameter and its range) whichever way it came in.
Defaults: Kovesi's phasecong3 (MATHS §2.1) but for nscale, OpenCV's non-local means windows (§3), PCI LINE
linking (§4.3). The rest were chosen on the synthetic outcrop in both looks, seed 1, and checked on seed 2
(tests/test_delineate.py):
* h = 4 kept faint traces best of 0, 4, 8, 12.
* Phase congruency of log brightness, so a trace in shade is as strong as one in sun.
* 3 scales (3–13 px), not Kovesi's 4. The 28 px filter responds to the rock's mottling and to shadowed strips.
  Their amplitude dilutes the phase congruency of the 1–3 px traces that cross them. With 3 scales the
  skeleton comes within 2 px of 94% of the true trace pixels, against 88%.
* Hysteresis 0.03/0.1, because the brightness profile test (`line_profile`) now rejects the texture that a
  higher threshold used to keep out.
* The profile test itself (session 7): contrast ≥ 0.08 and asymmetry ≤ 0.15 keep 91% (alt) to 95% (default) of the
  true chain pixels and 6–7% of the false ones that the feature-type test lets through. The wall's creases
  measure 0.18–0.5, true traces 0.04 in the median. At 0.2 the creases' 0.19–0.22 would sit on the edge.
* Faint segments (contrast < 0.3) may be more asymmetric (≤ 0.25): a weak trace on the rim of a mottle has
  its dip skewed by the texture beside it, while the creases that the asymmetry limit is there for are
  strong (contrast 0.3 and more, seeds 1–2). Session 7: alt-look recall +1 to +8 points on seeds 1–5
  (precision −0 to −3), default +0 to +2 (precision ≥ 0.91).
* The line filter (session 11; `line_filter`): σ 1 px across and 5 px along, 12 orientations, the wide
  filter's σ 2.5 px with ratio 0.8, hysteresis 0.07/0.12, from a first sweep on seeds 1–2. Nearby values
  (ratio 0.75, 4 or 6 px along, 8 orientations, thresholds 0.06/0.10 or 0.065/0.11) moved mean recall and
  precision on seeds 1–2 by less than a point. Without the ratio test the filter added mottling streaks:
  alt precision 0.90 (0.875 at worst) against 0.93.
* The mesh's silhouette (session 12; `silhouette`): a trace with over 90% of its length within 2 px of it
  is dropped. Seeds 1–5, both looks: precision +0 to +4.0 points, recall −0 to −1.0. A share of 0.5 cost
  up to 1.8 points of recall for little more precision; a range step of 0.1 instead of 0.03 missed the
  lower ledges (half the gain). Creases of the mesh (normals 30° apart) would add about 1 point of
  precision but cost up to 2 points of recall, and on real rock an exposed fracture face ends in a crease
  that is the trace itself, so they are left out. With the rims gone, the contrast limit came down from
  0.08 to 0.07: held out (seeds 3–5) alt recall +0 to +2.5 points (mean +0.9), precision −0 to −2.4
  (mean −0.8); the default look ±0.3. At 0.06 precision fell 1 to 4.7 points.
* raw_contrast 0.12 (session 12): a chain the denoised photo rejects passes if it is 0.12 deep on the
  photo before denoising, its profiles recentred where the denoised photo has the dip (recentred on its
  own noisy minimum, bare rock measures 0.06–0.08 deep). Held out (seeds 3–5): alt recall +0 to +2.3
  points (mean +0.9), precision −0 to −1.4 (mean −0.65); default +0.2 / −0.3. At 0.10: +0.9 / −1.5 on
  seeds 1–2; at 0.14: +0.7 / −0.4 held out.
* min_length 10 px rather than PCI LINE's 30 px. The profile test rejects short texture pieces, and a faint
  trace often survives only as 10–30 px pieces.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

from engine.errors import InputError

SETTING = "autotrace.params"  # the project setting with the parameters of the last auto-trace (CLI or editor)


@dataclass(frozen=True)
class Range:
    """An allowed interval (closed unless marked open), optionally integer or odd, or a set of choices."""

    lo: float = -math.inf
    hi: float = math.inf
    lo_open: bool = False
    hi_open: bool = False
    integer: bool = False
    odd: bool = False
    choices: tuple = ()

    def __str__(self) -> str:
        if self.choices:
            return "one of " + ", ".join(map(repr, self.choices))
        kind = "an odd integer" if self.odd else "an integer" if self.integer else "a number"
        return f"{kind} in {'(' if self.lo_open else '['}{self.lo:g}, {self.hi:g}{')' if self.hi_open else ']'}"

    def admits(self, value: object) -> bool:
        if self.choices:
            return value in self.choices
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            return False
        if self.integer and value != int(value) or self.odd and int(value) % 2 == 0:
            return False
        above = value > self.lo if self.lo_open else value >= self.lo
        below = value < self.hi if self.hi_open else value <= self.hi
        return above and below


def _p(default, unit: str, doc: str, **range_):
    return field(default=default, metadata={"range": Range(**range_), "unit": unit, "doc": doc})


@dataclass(frozen=True)
class DelineationParams:
    """Every parameter of `autotrace`, with its default; see `describe()` for units and ranges."""

    # 1. non-local means (OpenCV units, MATHS §3)
    denoise: bool = _p(True, "", "run non-local means before phase congruency", choices=(True, False))
    nlm_h: float = _p(4.0, "grey levels (0–255)", "filter strength h of cv2.fastNlMeansDenoising",
                      lo=0, hi=100)
    nlm_template: int = _p(7, "px", "templateWindowSize (patch side)", lo=3, hi=21, odd=True)
    nlm_search: int = _p(21, "px", "searchWindowSize (search window side)", lo=3, hi=51, odd=True)
    # 2. phase congruency (Kovesi phasecong3 defaults, MATHS §2.1)
    pc_method: str = _p("oriented", "", "oriented log-Gabor (phasecong3) or monogenic (fast)",
                        choices=("oriented", "monogenic"))
    log_brightness: bool = _p(True, "", "phase congruency of log brightness, so traces in shade are as strong "
                                        "as in sun", choices=(True, False))
    nscale: int = _p(3, "", "number of filter scales", lo=2, hi=8, integer=True)
    norient: int = _p(6, "", "number of filter orientations (oriented method)", lo=2, hi=16, integer=True)
    min_wavelength: float = _p(3.0, "px", "wavelength of the smallest filter", lo=2, hi=64)
    mult: float = _p(2.1, "", "ratio of successive filter wavelengths", lo=1, hi=4, lo_open=True)
    sigma_onf: float = _p(0.55, "", "log-Gabor bandwidth σ/f0", lo=0, hi=1, lo_open=True, hi_open=True)
    k: float = _p(2.0, "noise σ", "noise threshold: standard deviations above the mean noise energy",
                  lo=0, hi=50)
    cutoff: float = _p(0.5, "", "frequency spread below which phase congruency is penalised", lo=0, hi=1)
    g: float = _p(10.0, "", "sharpness of the frequency-spread sigmoid", lo=0, hi=100)
    deviation_gain: float = _p(1.5, "", "phase deviation gain (monogenic method)", lo=0, hi=5)
    tile: int = _p(4096, "px", "largest tile side; a photo no larger is transformed whole",
                   lo=256, hi=16384, integer=True)
    overlap: int = _p(256, "px", "margin added round each tile (the filters' reach)", lo=16, hi=512, integer=True)
    border: int = _p(8, "px", "strip round the photo where edge strength is zeroed", lo=0, hi=256, integer=True)
    # 3. edges (MATHS §2.1 post-processing)
    low: float = _p(0.03, "", "hysteresis low threshold on edge strength (max moment)", lo=0, hi=1)
    high: float = _p(0.1, "", "hysteresis high threshold on edge strength", lo=0, hi=1)
    nms_radius: float = _p(1.5, "px", "non-maximum suppression distance along the feature normal",
                           lo=1, hi=3)
    # 3b. oriented line filter (line_filter.py): a second detector for faint traces
    line_filter: bool = _p(True, "", "add the lines of an oriented line filter to the phase-congruency edges "
                                     "(faint traces on mottled rock); off with feature \"any\"",
                           choices=(True, False))
    line_sigma: float = _p(1.0, "px", "cross-section σ of the line filter (a trace about 2σ wide answers most; "
                                      "about trace_width / 3)", lo=0.5, hi=10)
    line_length: float = _p(5.0, "px", "σ along the line filter: texture is averaged over about twice this",
                            lo=1, hi=50)
    line_norient: int = _p(12, "", "line filter orientations over 180°", lo=2, hi=64, integer=True)
    line_wide: float = _p(2.5, "px", "cross-section σ of the wide filter that broad dark bands (mottling) "
                                     "answer to; must exceed line_sigma", lo=0.5, hi=50)
    line_ratio: float = _p(0.8, "", "least ratio of the line response to the wide one", lo=0, hi=10)
    line_low: float = _p(0.07, "ln brightness", "hysteresis low threshold on the line response (0.07 ≈ a line "
                                                "7% darker)", lo=0, hi=5)
    line_high: float = _p(0.12, "ln brightness", "hysteresis high threshold on the line response", lo=0, hi=5)
    # 4. segments (MATHS §4.1–4.2)
    feature: str = _p("dark", "", "keep segments that are dark lines, bright lines, or of any feature type",
                      choices=("dark", "bright", "any"))
    line_phase: float = _p(20.0, "deg", "least median |feature type| of a kept segment: 90 a pure line, "
                                        "0 a step", lo=0, hi=90)
    line_contrast: float = _p(0.07, "ln brightness", "least contrast of a kept segment against its darker "
                                                     "(brighter) side: 0.07 ≈ 7%", lo=-5, hi=5)
    line_asymmetry: float = _p(0.15, "", "most asymmetric dip across a kept segment: 0 a symmetric line, "
                                         "0.2–0.5 a crease between two faces", lo=0, hi=100)
    faint_asymmetry: float = _p(0.25, "", "most asymmetric dip across a faint kept segment (contrast below "
                                          "faint_contrast): texture beside a weak trace skews its dip",
                                lo=0, hi=100)
    faint_contrast: float = _p(0.3, "ln brightness", "contrast below which a segment is faint: the creases "
                                                     "between faces measure 0.3 and more", lo=0, hi=5)
    raw_contrast: float = _p(0.12, "ln brightness", "least contrast on the photo before denoising (where the "
                                                    "denoised photo has its dip) that keeps a segment the "
                                                    "denoised photo rejects: denoising flattens faint traces in "
                                                    "shade", lo=0, hi=5)
    trace_width: float = _p(3.0, "px", "widest trace expected; sizes the brightness profile across a segment "
                                       "(raise line_sigma in proportion)", lo=1, hi=50)
    spur_length: float = _p(10.0, "px", "side branches shorter than this are removed", lo=0, hi=200)
    junction_angle: float = _p(30.0, "deg", "branches continue through a junction if they deflect less",
                               lo=0, hi=90)
    direction_length: float = _p(10.0, "px", "length of segment end used for its direction", lo=2, hi=100)
    simplify: float = _p(1.0, "px", "polyline simplification tolerance (Douglas–Peucker)", lo=0, hi=10)
    # 5. line growing (MATHS §4.3, PCI LINE defaults)
    link_distance: float = _p(20.0, "px", "longest gap bridged", lo=0, hi=500)
    link_angle: float = _p(30.0, "deg", "largest angle between the two ends' directions", lo=0, hi=90)
    link_buffer: float = _p(4.0, "px", "half-width of the search path along an end's direction",
                            lo=0, hi=100)
    link_weight: float = _p(0.5, "", "score weight of angle (1) versus distance (0)", lo=0, hi=1)
    min_length: float = _p(10.0, "px", "traces shorter than this are dropped", lo=0, hi=10000)
    # 6. the mesh's silhouette (silhouette.py): only where the mesh and the photo's camera are known
    silhouette: bool = _p(True, "", "drop traces that run along the mesh's silhouette in the photo (its outline and "
                                    "occluding contours)", choices=(True, False))
    silhouette_step: float = _p(0.03, "ln range", "least jump in range between neighbouring pixels that makes an "
                                                  "occluding contour: 0.03 ≈ 3%", lo=0, hi=5, lo_open=True)
    silhouette_band: float = _p(2.0, "px", "half-width of the band along the silhouette", lo=0, hi=50)
    silhouette_share: float = _p(0.9, "", "a trace with more of its length than this in the band is dropped",
                                 lo=0, hi=1)
    # 7. support from other photos (support.py): only where the mesh and the other photos' traces are known
    support: bool = _p(True, "", "keep a segment the profile test turned down where most other photos that see "
                                 "it have a trace along it", choices=(True, False))
    support_min_length: float = _p(5.0, "px", "shortest turned-down segment considered", lo=0, hi=10000)
    support_tolerance: float = _p(2.0, "px", "distance from another photo's trace that counts as on it",
                                  lo=0, hi=50, lo_open=True)
    support_share: float = _p(0.5, "", "least share of a segment, as another photo sees it, on that photo's "
                                       "traces for that photo to support it (a majority of the photos that "
                                       "see half of it must)", lo=0, hi=1, lo_open=True)
    carry: bool = _p(True, "", "with support: add the other photos' traces that this photo sees but has not traced "
                               "where its own edges lie along them", choices=(True, False))
    carry_evidence: float = _p(0.3, "", "least share of a carried trace within support_tolerance of this photo's "
                                        "edges (skeleton)", lo=0, hi=1)
    carry_min_length: float = _p(20.0, "px", "shortest piece carried (in this photo)", lo=0, hi=10000)

    def __post_init__(self) -> None:
        for f in fields(self):
            check(f.name, getattr(self, f.name))
        if self.low > self.high:
            raise InputError(None, f"low={self.low!r} must not exceed high={self.high!r}")
        if self.line_low > self.line_high:
            raise InputError(None, f"line_low={self.line_low!r} must not exceed line_high={self.line_high!r}")
        if self.line_wide <= self.line_sigma:
            raise InputError(None, f"line_wide={self.line_wide!r} must exceed line_sigma={self.line_sigma!r}")

    @classmethod
    def describe(cls) -> list[tuple[str, object, str, str, str]]:
        """(name, default, unit, allowed range, meaning) of every parameter, for help texts."""
        return [(f.name, f.default, f.metadata["unit"], str(f.metadata["range"]), f.metadata["doc"])
                for f in fields(cls)]


RANGES = {f.name: f.metadata["range"] for f in fields(DelineationParams)}
# the stage each parameter belongs to, keyed by the stage's first parameter (the fields are in pipeline order):
# headings in the editor's panel and groups in `tracemap autotrace --help`
SECTIONS = {"denoise": "denoising (non-local means)", "pc_method": "phase congruency", "low": "edges",
            "line_filter": "line filter", "feature": "segments", "link_distance": "line growing",
            "silhouette": "silhouette (from the mesh)", "support": "support from other photos (mesh and photos)"}


def check(field_name: str, value: object, name: str | None = None) -> None:
    """Raise InputError naming the parameter (`name`, default `field_name`) and the allowed range of
    DelineationParams field `field_name` if `value` is outside it."""
    check_range(name or field_name, value, RANGES[field_name])


def check_range(name: str, value: object, allowed: Range) -> None:
    """Raise InputError naming the parameter and its allowed range if `value` is outside it (for parameters
    of stages that `autotrace` does not run, hence not in DelineationParams)."""
    if not allowed.admits(value):
        raise InputError(None, f"{name}={value!r} is out of range: expected {allowed}")


def params_from_dict(values: Mapping[str, object], source: str | Path | None = None) -> DelineationParams:
    """Parameters from names and values, any subset (the rest keep their defaults). An unknown name or a value
    out of range raises InputError naming `source` (a file, say) and the parameter."""
    unknown = sorted(set(values) - set(RANGES))
    if unknown:
        raise InputError(source, f"unknown parameter(s) {', '.join(unknown)}; the parameters are "
                                 f"{', '.join(RANGES)}")
    typed = {}
    for f in fields(DelineationParams):
        if f.name in values:
            value = values[f.name]
            whole = isinstance(value, float) and value.is_integer()
            typed[f.name] = int(value) if RANGES[f.name].integer and whole else value  # JSON may write 3 as 3.0
    try:
        return DelineationParams(**typed)
    except InputError as exc:
        raise InputError(source, str(exc)) from None


def read_params(path: str | Path) -> DelineationParams:
    """Parameters from a JSON file holding an object of names and values (as `write_params` writes)."""
    path = Path(path)
    try:
        values = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(path, "parameter file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"cannot read the parameter file ({exc})") from None
    except json.JSONDecodeError as exc:
        raise InputError(path, f"not JSON: {exc.msg} at line {exc.lineno}, column {exc.colno}") from None
    if not isinstance(values, dict):
        raise InputError(path, 'expected a JSON object of parameter names and values, e.g. {"trace_width": 5}')
    return params_from_dict(values, path)


def write_params(params: DelineationParams, path: str | Path) -> Path:
    """Write every parameter to a JSON file, whole or not at all (a failed write leaves no half file)."""
    path = Path(path)
    text = json.dumps(asdict(params), indent=2) + "\n"
    handle, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(handle, "w", encoding="utf-8") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
