"""The synthetic outcrop: a rough wall, fractures with exact traces, photographs and their ground truth.

It is both the demo data and the test oracle of the project. `make_outcrop(seed)` builds, deterministically:

* a rough, south-facing wall mesh (regular grid; fractional-Brownian roughness plus a bench, steps and a
  buttress that occlude each other from oblique cameras);
* fractures from von Mises–Fisher sets (default: Seers & Hodgetts 2016a, Table 1), as planar discs or
  undulating surfaces, with Poisson centres and lognormal or power-law radii;
* their exact traces on the mesh, calibrated cameras, rendered photographs and the visible 2D traces.

Frames (DESIGN.md: x east, y north, z up, metres). `world = local + origin`, origin = `world_offset`.
  - LOCAL: `mesh.vertices`, `noisy_mesh.vertices` (both carry `origin`), and everything used internally.
  - WORLD: `cameras`, `fractures[i].centre`, `traces3d[i].points`, `traces2d[...].points`, `bounds`,
    and every file `write_outcrop` writes. `SyntheticOutcrop.local_cameras()` gives the cameras in LOCAL.
  - Pixels: (0, 0) is the centre of the top-left pixel, u right, v down.

The wall is the surface y = h(x, z) over x ∈ [-width/2, width/2], z ∈ [0, height]; its outward normal points
roughly to -y (south), where the cameras stand.

Exact traces. Every vertex of a true 3D trace is the exact intersection of a mesh edge with the fracture
surface (for undulating fractures found by bracketed root-finding on the edge, so it lies on the surface to
rounding, not merely on the zero set of the linearly interpolated offset); consecutive vertices share a mesh
face and are joined by the straight chord across it. For planar fractures this is the exact mesh–plane
intersection. Where a trace leaves the disc (|in-plane position| = radius) it ends at a tip on the chord,
refined onto the surface within the face plane. (Where a face cannot resolve the undulation, wavelengths
shorter than about its size, the tip stays on the chord: on the mesh and the rim, off the surface by the
chord's sag; about 1 vertex in 10⁴ at 10 cm spacing, none seen at 2.5 cm.) These polylines are the truth
every test measures against.
"""

from __future__ import annotations

import csv
import json
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path

import cv2
import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation
from scipy.special import ndtr, ndtri
from scipy.stats import vonmises_fisher

from engine.cameras.camera import Camera
from engine.errors import InputError, Progress, report
from engine.mesh import Mesh, barycentric
from engine.orientation import dip_dipdir_to_normal, normal_to_dip_dipdir
from engine.raytrace import RayTracer
from engine.traces import polyline_length, resample_polyline

DEFAULT_SETS = ((85.0, 137.0, 9.8, 0.5), (88.0, 232.0, 13.4, 0.5))
"""(dip°, dip direction°, κ, weight) of each set: Seers & Hodgetts (2016a) Table 1."""

QUICK = {"mesh_spacing": 0.1, "n_cameras": 3, "image_size": (640, 480), "trace_width": 0.035}
"""Small settings for tests: `make_outcrop(seed, **QUICK)` runs in a few seconds (traces ~1.5 px wide)."""

ROUGHNESS_MODES = 128  # random Fourier modes of the wall roughness
UNDULATION_MODES = 24  # ... of each undulating fracture surface
UNDULATION_BOUND = np.sqrt(2 * UNDULATION_MODES)  # max |height| ≤ this × rms (Cauchy–Schwarz)


# ---------------------------------------------------------------------------------------------------------
# results


@dataclass(frozen=True)
class FractureSet:
    """A generating set: mean pole as dip/dip direction (degrees), Fisher κ, weight, realised P32 (m⁻¹).

    `p32` is Σ disc area πr² of the set's fractures / volume of the box their centres were drawn in.
    """

    id: int
    dip: float
    dip_direction: float
    kappa: float
    weight: float
    p32: float

    @property
    def normal(self) -> np.ndarray:
        return dip_dipdir_to_normal(self.dip, self.dip_direction)


@dataclass(frozen=True, eq=False)
class Fracture:
    """A fracture: mean plane through `centre` with upward unit `normal`, disc `radius` (m).

    An undulating fracture is the surface centre + p·a1 + q·a2 + w(p, q)·normal over the disc p² + q² ≤ r²,
    with w = Σ amplitude·cos(kp·p + kq·q + phase) over the rows of `undulation` (M, 4); planar when M = 0.
    (a1, a2) = `axes`: the strike (horizontal) and up-dip directions.
    """

    id: int
    set_id: int
    centre: np.ndarray
    normal: np.ndarray
    radius: float
    undulation: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))

    @property
    def dip(self) -> float:
        return float(normal_to_dip_dipdir(self.normal)[0])

    @property
    def dip_direction(self) -> float:
        return float(normal_to_dip_dipdir(self.normal)[1])

    @cached_property
    def axes(self) -> np.ndarray:
        """In-plane unit vectors (2, 3): strike (horizontal; x for a horizontal plane), then normal × strike."""
        n = self.normal
        strike = np.array([-n[1], n[0], 0.0])
        length = np.linalg.norm(strike)
        strike = strike / length if length > 1e-12 else np.array([1.0, 0.0, 0.0])
        return np.stack([strike, np.cross(n, strike)])

    @property
    def max_height(self) -> float:
        """An upper bound of |w| over the plane (0 for a planar fracture)."""
        return float(np.abs(self.undulation[:, 3]).sum())

    def plane_coords(self, points: np.ndarray) -> np.ndarray:
        """In-plane coordinates (N, 2) of points (N, 3) in the frame of `centre`."""
        return (np.asarray(points) - self.centre) @ self.axes.T

    def height(self, pq: np.ndarray) -> np.ndarray:
        """Undulation w (N,) at in-plane coordinates (N, 2)."""
        m = self.undulation
        return np.cos(pq @ m[:, :2].T + m[:, 2]) @ m[:, 3]

    def height_gradient(self, pq: np.ndarray) -> np.ndarray:
        """(∂w/∂p, ∂w/∂q) (N, 2)."""
        m = self.undulation
        return -(np.sin(pq @ m[:, :2].T + m[:, 2]) * m[:, 3]) @ m[:, :2]

    def offset(self, points: np.ndarray) -> np.ndarray:
        """Signed offset (N,) of points from the surface along the normal: zero on it, positive above."""
        points = np.asarray(points, dtype=float)
        along = (points - self.centre) @ self.normal
        return along - self.height(self.plane_coords(points)) if len(self.undulation) else along

    def shifted(self, origin: np.ndarray) -> Fracture:
        """This fracture in a frame whose origin is `origin`: centre - origin."""
        return replace(self, centre=self.centre - np.asarray(origin, dtype=float))

    def to_dict(self) -> dict:
        return {"id": self.id, "set": self.set_id, "centre": self.centre.tolist(),
                "normal": self.normal.tolist(), "radius": self.radius, "dip": self.dip,
                "dip_direction": self.dip_direction, "undulation": self.undulation.tolist()}


@dataclass(frozen=True, eq=False)
class TrueTrace:
    """An exact fracture trace on the clean mesh: `points` (N, 3) WORLD, `face` (N,) the face of each vertex.

    `ends` says how each end terminates: "C" at the mesh border (censored), "B" at the fracture tip;
    ("", "") for a closed loop, whose last point repeats the first.
    """

    id: int
    fracture_id: int
    points: np.ndarray
    face: np.ndarray
    closed: bool
    ends: tuple[str, str]

    @property
    def length(self) -> float:
        return polyline_length(self.points)


@dataclass(frozen=True, eq=False)
class TrueTrace2D:
    """The visible part of true trace `trace_id` on photo `image`: `polyline` (N, 2) pixels.

    `points` (N, 3) WORLD are the trace points whose projections are the polyline vertices; `id` is unique
    over all photos (the `trace` column of traces2d_true.csv).
    """

    id: int
    image: str
    fracture_id: int
    trace_id: int
    polyline: np.ndarray
    points: np.ndarray


@dataclass(eq=False)
class SyntheticOutcrop:
    """Everything `make_outcrop` built; see the module docstring for the frame of each array."""

    mesh: Mesh
    noisy_mesh: Mesh
    cameras: dict[str, Camera]
    images: dict[str, np.ndarray]
    fractures: list[Fracture]
    traces3d: list[TrueTrace]
    traces2d: dict[str, list[TrueTrace2D]]
    sets: list[FractureSet]
    bounds: np.ndarray
    parameters: dict

    @property
    def origin(self) -> np.ndarray:
        """World coordinates of the local origin (= `world_offset`)."""
        return self.mesh.origin

    def local_cameras(self) -> dict[str, Camera]:
        """The cameras in the LOCAL frame of `mesh`, as the ray tracer needs them."""
        return {name: cam.shifted(self.origin) for name, cam in self.cameras.items()}


# ---------------------------------------------------------------------------------------------------------
# the rendering looks


@dataclass(frozen=True)
class Style:
    """Colours (linear RGB in [0, 1]), lighting and trace appearance of one rendering look."""

    light: tuple[float, float, float]
    dark: tuple[float, float, float]
    bed_period: float  # m
    bed_contrast: float
    grain: float  # relative amplitude of the fine texture
    sun: tuple[float, float]  # azimuth, elevation (degrees) of the sun
    ambient: float
    trace_width: float  # full width at half darkness, m
    trace_contrast: tuple[float, float]  # range of per-fracture darkening
    sensor_noise: float  # standard deviation, 8-bit counts
    ground: tuple[float, float, float] = (0.36, 0.33, 0.28)
    sky: tuple[float, float, float] = (0.55, 0.70, 0.92)


STYLES = {
    "default": Style(light=(0.78, 0.60, 0.44), dark=(0.58, 0.41, 0.30), bed_period=0.45, bed_contrast=0.7,
                     grain=0.22, sun=(150.0, 40.0), ambient=0.35, trace_width=0.012,
                     trace_contrast=(0.45, 0.8), sensor_noise=2.0),
    "alt": Style(light=(0.70, 0.72, 0.72), dark=(0.42, 0.44, 0.47), bed_period=0.8, bed_contrast=0.45,
                 grain=0.4, sun=(235.0, 22.0), ambient=0.22, trace_width=0.016,
                 trace_contrast=(0.3, 0.6), sensor_noise=3.5, ground=(0.30, 0.31, 0.30),
                 sky=(0.78, 0.80, 0.84)),
}


# ---------------------------------------------------------------------------------------------------------
# public entry points


def make_outcrop(
    seed: int = 0,
    *,
    width: float = 20.0,
    height: float = 8.0,
    mesh_spacing: float = 0.025,
    roughness: float = 0.15,
    hurst: float = 0.75,
    relief: float = 0.6,
    world_offset: Sequence[float] = (0.0, 0.0, 0.0),
    mesh_noise: float = 0.0,
    sets: Sequence[Sequence[float]] = DEFAULT_SETS,
    density: float = 0.2,
    size_distribution: str = "lognormal",
    radius_median: float = 1.0,
    radius_sigma: float = 0.6,
    radius_min: float = 0.25,
    radius_max: float = 6.0,
    radius_exponent: float = 2.6,
    fracture_model: str = "planar",
    undulation: float = 0.02,
    undulation_hurst: float = 0.8,
    n_cameras: int = 5,
    image_size: tuple[int, int] = (1600, 1200),
    camera_distance: tuple[float, float] = (8.0, 12.0),
    distortion: Sequence[float] | None = None,
    style: str = "default",
    trace_width: float | None = None,
    min_trace_pixels: float = 5.0,
    occlusion_tolerance: float = 0.005,
    progress: Progress | None = None,
) -> SyntheticOutcrop:
    """Build the synthetic outcrop for `seed` (same seed and parameters → identical arrays and images).

    Wall: `width` × `height` m, grid triangulation every `mesh_spacing` m; roughness of RMS `roughness` m
    and Hurst exponent `hurst`; bench, steps and buttress of about `relief` m; world = local + `world_offset`;
    `mesh_noise` m of isotropic Gaussian noise on the copy handed to the user (`noisy_mesh`).
    Fractures: `sets` of (dip°, dip direction°, κ, weight); Poisson centres, `density` per m³, in the wall's
    box padded by the largest radius; radii "lognormal" (`radius_median` m, log-sd `radius_sigma`) or
    "powerlaw" (density ∝ r^-`radius_exponent`), truncated to [`radius_min`, `radius_max`] m.
    `fracture_model` "planar" (discs) or "undulating" (RMS height `undulation` × radius, Hurst
    `undulation_hurst`, wavelengths radius/8 to 2·radius).
    Photos: `n_cameras` at `camera_distance` m, `image_size` (width, height) px, optional `distortion`
    (k1, k2, p1, p2); `style` "default" or "alt"; `trace_width` m (default from the style).
    Truth: 2D runs shorter than `min_trace_pixels` px are dropped; a surface within `occlusion_tolerance` m
    of a trace point does not hide it.
    """
    args = dict(locals())
    _check_parameters(args)
    parameters = _jsonable({k: v for k, v in args.items() if k != "progress"})
    look = STYLES[style]
    if trace_width is not None:
        look = replace(look, trace_width=float(trace_width))
    origin = np.asarray(world_offset, dtype=float)
    # one child stream per part, so changing e.g. mesh_noise leaves the fractures and photos unchanged
    wall_rng, fracture_rng, camera_rng, texture_rng, ink_rng, noise_rng, photo_rng = \
        np.random.default_rng(seed).spawn(7)

    report(progress, 0.0, "wall")
    vertices, faces = wall_mesh(wall_rng, width=width, height=height, spacing=mesh_spacing,
                                roughness=roughness, hurst=hurst, relief=relief)
    texture = _Texture(texture_rng, look)
    colours = np.clip(255 * texture.albedo(vertices), 0, 255).astype(np.uint8)
    mesh = Mesh(vertices, faces, origin, colours)
    noisy = Mesh(vertices + noise_rng.normal(0.0, mesh_noise, vertices.shape), faces, origin, colours)

    report(progress, 0.1, "fractures")
    pad = radius_max * (1 + UNDULATION_BOUND * undulation * (fracture_model == "undulating"))
    lo, hi = vertices.min(axis=0) - pad, vertices.max(axis=0) + pad
    fractures, fracture_sets = sample_fractures(
        fracture_rng, (lo, hi), sets=sets, density=density, size_distribution=size_distribution,
        radius_median=radius_median, radius_sigma=radius_sigma, radius_min=radius_min, radius_max=radius_max,
        radius_exponent=radius_exponent, fracture_model=fracture_model, undulation=undulation,
        undulation_hurst=undulation_hurst)
    traces = mesh_traces(vertices, faces, fractures)

    report(progress, 0.2, "photographs")
    cameras = survey_cameras(camera_rng, vertices, n_cameras=n_cameras, image_size=image_size,
                             distance=camera_distance, distortion=distortion)
    tracer = RayTracer(vertices, faces)
    ink = _TraceInk(ink_rng, traces, fractures, texture)
    images, traces2d, next_id = {}, {}, 0
    for k, (camera, rng) in enumerate(zip(cameras, photo_rng.spawn(len(cameras)))):
        images[camera.name] = _render_photo(camera, tracer, mesh, texture, ink, rng)
        runs = visible_traces(camera, tracer, traces, min_pixels=min_trace_pixels, tolerance=occlusion_tolerance)
        traces2d[camera.name] = [TrueTrace2D(next_id + i, camera.name, traces[j].fracture_id, j, uv, p + origin)
                                 for i, (j, uv, p) in enumerate(runs)]
        next_id += len(runs)
        report(progress, 0.2 + 0.8 * (k + 1) / len(cameras), f"photograph {k + 1} of {len(cameras)}")

    return SyntheticOutcrop(
        mesh=mesh, noisy_mesh=noisy,
        cameras={c.name: c.shifted(-origin) for c in cameras},
        images=images,
        fractures=[f.shifted(-origin) for f in fractures],
        traces3d=[replace(t, points=t.points + origin) for t in traces],
        traces2d=traces2d, sets=fracture_sets, bounds=np.stack([lo, hi]) + origin, parameters=parameters)


def write_outcrop(outcrop: SyntheticOutcrop, directory: str | Path) -> dict[str, Path]:
    """Write the outcrop as a user would receive it; returns the paths by kind.

    mesh.ply (noisy mesh, WORLD coordinates in float64, vertex colours), cameras.json (the native
    "tracemap-cameras" format, image_path = photo file name), images/<camera>.png, traces2d_true.csv
    (image,trace,u,v; image = camera name) and truth.json (sets, fractures, 3D traces in WORLD).
    """
    out = Path(directory)
    (out / "images").mkdir(parents=True, exist_ok=True)
    paths = {"mesh": out / "mesh.ply", "cameras": out / "cameras.json", "images": out / "images",
             "traces2d": out / "traces2d_true.csv", "truth": out / "truth.json"}
    mesh = outcrop.noisy_mesh
    _write_ply(paths["mesh"], mesh.world_vertices, mesh.faces, mesh.vertex_colors)
    cameras = []
    for name, camera in outcrop.cameras.items():
        file_name = f"{name}.png"
        if not cv2.imwrite(str(paths["images"] / file_name), cv2.cvtColor(outcrop.images[name], cv2.COLOR_RGB2BGR)):
            raise InputError(paths["images"] / file_name, "OpenCV could not write the photo")
        cameras.append(replace(camera, image_path=file_name).to_dict())
    _write_json(paths["cameras"], {"format": "tracemap-cameras", "version": 1, "cameras": cameras}, indent=1)
    with open(paths["traces2d"], "w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh)
        writer.writerow(("image", "trace", "u", "v"))
        for traces in outcrop.traces2d.values():
            for t in traces:
                writer.writerows((t.image, t.id, f"{u:.4f}", f"{v:.4f}") for u, v in t.polyline)
    _write_json(paths["truth"], {
        "format": "tracemap-synthetic-truth", "version": 1, "frame": "world",
        "origin": outcrop.origin.tolist(), "bounds": outcrop.bounds.tolist(), "parameters": outcrop.parameters,
        "sets": [vars(s) for s in outcrop.sets],
        "fractures": [f.to_dict() for f in outcrop.fractures],
        "traces3d": [{"id": t.id, "fracture": t.fracture_id, "closed": t.closed, "ends": list(t.ends),
                      "face": t.face.tolist(), "points": t.points.tolist()} for t in outcrop.traces3d]})
    return paths


def distance_to_true_traces(points: np.ndarray, outcrop: SyntheticOutcrop, *,
                            local: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Distance (N,) in metres from each point (N, 3) to the nearest true 3D trace, and that trace's fracture id.

    Points are WORLD coordinates, or LOCAL (the mesh frame) with `local=True`. Distances are exact to the
    trace polylines (segments), not to sampled points.
    """
    origin = outcrop.origin
    p = np.asarray(points, dtype=float).reshape(-1, 3) - (0.0 if local else origin)
    if not outcrop.traces3d:
        return np.full(len(p), np.inf), np.full(len(p), -1)
    a = np.concatenate([t.points[:-1] for t in outcrop.traces3d]) - origin
    b = np.concatenate([t.points[1:] for t in outcrop.traces3d]) - origin
    owner = np.concatenate([np.full(len(t.points) - 1, t.fracture_id) for t in outcrop.traces3d])
    tree = cKDTree(0.5 * (a + b))
    half = 0.5 * np.linalg.norm(b - a, axis=1).max()
    k = min(16, len(a))
    dmid, idx = tree.query(p, k=k)
    dmid, idx = dmid.reshape(len(p), k), idx.reshape(len(p), k)
    d = _segment_distance(p[:, None], a[idx], b[idx])
    best = idx[np.arange(len(p)), d.argmin(axis=1)]
    dist = d.min(axis=1)
    # a segment not among the k nearest midpoints can only be nearer if its midpoint is within dist + half
    for i in np.flatnonzero(dist + half > dmid[:, -1]):
        cand = np.asarray(tree.query_ball_point(p[i], dist[i] + half), dtype=int)
        dc = _segment_distance(p[i], a[cand], b[cand])
        best[i], dist[i] = cand[dc.argmin()], dc.min()
    return dist, owner[best]


# ---------------------------------------------------------------------------------------------------------
# the wall


def wall_mesh(rng: np.random.Generator, *, width: float, height: float, spacing: float, roughness: float,
              hurst: float, relief: float) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) and faces (F, 3) of the wall y = h(x, z), faces wound so normals point out (-y).

    h = lean + roughness (random Fourier modes, wavelengths 8 cm–12 m, amplitude ∝ λ^hurst) + a bench
    (the upper wall set back), two steps and a buttress standing out toward the cameras: the features
    that hide parts of the wall from oblique and low viewpoints. The surface is a continuous function, so
    meshes of different `spacing` sample the same wall.
    """
    nx, nz = int(round(width / spacing)) + 1, int(round(height / spacing)) + 1
    X, Z = np.meshgrid(np.linspace(-width / 2, width / 2, nx), np.linspace(0.0, height, nz))
    x, z = X.ravel(), Z.ravel()
    modes = fbm_modes(rng, ROUGHNESS_MODES, (0.08, 12.0), hurst=hurst, rms=roughness)
    y = 0.1 * z - 0.01 * x**2 + _evaluate_modes(np.column_stack([x, z]), modes)

    def rise(s, edge=0.04):  # a smooth step from 0 to 1 over a few centimetres
        return 0.5 * (1 + np.tanh(s / edge))

    y += relief * rng.uniform(0.7, 1.2) * rise(z - height * rng.uniform(0.35, 0.6))
    for x0 in rng.uniform(-0.4, 0.4, 2) * width:
        y += relief * rng.choice([-1, 1]) * rng.uniform(0.4, 0.8) * rise(x - x0)
    centre, half = rng.uniform(-0.35, 0.35) * width, rng.uniform(0.6, 1.2)
    y -= relief * rng.uniform(1.0, 1.5) * (rise(x - centre + half, 0.05) - rise(x - centre - half, 0.05))
    vertices = np.column_stack([x, y, z])
    idx = np.arange(nx * nz).reshape(nz, nx)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    faces = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    return vertices, faces


def fbm_modes(rng: np.random.Generator, n: int, wavelengths: tuple[float, float], *, hurst: float,
              rms: float) -> np.ndarray:
    """Random Fourier modes (n, 4) = (kx, ky, phase, amplitude) of a 2D fractional-Brownian field.

    Spectral synthesis with one mode per log-spaced wavelength band: a band's variance ∝ λ^(2·hurst) gives
    the fBm power spectrum ∝ k^-(2·hurst + 2); amplitudes are scaled to the given RMS.
    """
    lo, hi = np.log(wavelengths[0]), np.log(wavelengths[1])
    edges = np.linspace(lo, hi, n + 1)
    lam = np.exp(edges[:-1] + rng.uniform(0, 1, n) * np.diff(edges))
    theta = rng.uniform(0, 2 * np.pi, n)
    k = 2 * np.pi / lam
    amp = lam**hurst
    amp *= rms / np.sqrt(0.5 * np.sum(amp**2))
    return np.column_stack([k * np.cos(theta), k * np.sin(theta), rng.uniform(0, 2 * np.pi, n), amp])


def _evaluate_modes(xy: np.ndarray, modes: np.ndarray, chunk: int = 32768) -> np.ndarray:
    out = np.empty(len(xy))
    for s in range(0, len(xy), chunk):  # bounds the (chunk, modes) temporary
        out[s:s + chunk] = np.cos(xy[s:s + chunk] @ modes[:, :2].T + modes[:, 2]) @ modes[:, 3]
    return out


# ---------------------------------------------------------------------------------------------------------
# fractures


def sample_fractures(rng: np.random.Generator, bounds: tuple[np.ndarray, np.ndarray], *,
                     sets: Sequence[Sequence[float]] = DEFAULT_SETS, density: float = 0.2,
                     size_distribution: str = "lognormal", radius_median: float = 1.0, radius_sigma: float = 0.6,
                     radius_min: float = 0.25, radius_max: float = 6.0, radius_exponent: float = 2.6,
                     fracture_model: str = "planar", undulation: float = 0.02,
                     undulation_hurst: float = 0.8) -> tuple[list[Fracture], list[FractureSet]]:
    """Poisson fractures with centres uniform in the box `bounds` = (lo, hi) (m), in that box's frame.

    The count is Poisson(density × volume); each fracture joins set k with probability weight_k and takes
    a pole from vMF(mean pole of the set, κ_k) (`scipy.stats.vonmises_fisher`), stored upward. Parameters
    as in `make_outcrop`.
    """
    lo, hi = (np.asarray(b, dtype=float) for b in bounds)
    volume = float(np.prod(hi - lo))
    n = rng.poisson(density * volume)
    weights = np.array([s[3] for s in sets], dtype=float)
    set_id = rng.choice(len(sets), size=n, p=weights / weights.sum())
    normals = np.empty((n, 3))
    for k, (dip, dipdir, kappa, _) in enumerate(sets):
        members = set_id == k
        if members.any():
            mu = dip_dipdir_to_normal(dip, dipdir)
            normals[members] = vonmises_fisher(mu, kappa).rvs(int(members.sum()), random_state=rng)
    normals[normals[:, 2] < 0] *= -1
    radii = _radii(rng, n, size_distribution, radius_median, radius_sigma, radius_min, radius_max,
                   radius_exponent)
    centres = rng.uniform(lo, hi, (n, 3))
    fractures = []
    for i in range(n):
        modes = (fbm_modes(rng, UNDULATION_MODES, (radii[i] / 8, 2 * radii[i]), hurst=undulation_hurst,
                           rms=undulation * radii[i]) if fracture_model == "undulating" else np.zeros((0, 4)))
        fractures.append(Fracture(i, int(set_id[i]), centres[i], normals[i], float(radii[i]), modes))
    area = np.bincount(set_id, np.pi * radii**2, minlength=len(sets))
    fracture_sets = [FractureSet(k, float(s[0]), float(s[1]), float(s[2]), float(weights[k] / weights.sum()),
                                 float(area[k] / volume)) for k, s in enumerate(sets)]
    return fractures, fracture_sets


def _radii(rng, n, distribution, median, sigma, r_min, r_max, exponent) -> np.ndarray:
    """Truncated lognormal or power-law radii by inversion of the CDF (no atoms at the bounds)."""
    if distribution == "lognormal":
        mu = np.log(median)
        a, b = ndtr((np.log(r_min) - mu) / sigma), ndtr((np.log(r_max) - mu) / sigma)
        return np.exp(mu + sigma * ndtri(rng.uniform(a, b, n)))
    e = 1.0 - exponent
    u = rng.uniform(0, 1, n)
    if abs(e) < 1e-12:
        return r_min * (r_max / r_min) ** u
    return (r_min**e + u * (r_max**e - r_min**e)) ** (1 / e)


# ---------------------------------------------------------------------------------------------------------
# exact traces


def mesh_traces(vertices: np.ndarray, faces: np.ndarray, fractures: Sequence[Fracture]) -> list[TrueTrace]:
    """Every fracture's exact traces on the mesh (module docstring), in the frame of `vertices`."""
    tri = vertices[faces]
    centroids = tri.mean(axis=1)
    tree = cKDTree(centroids)
    reach = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max()
    keys, count = np.unique(_edge_keys(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), len(vertices)),
                            return_counts=True)
    border = keys[count == 1]
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    traces: list[TrueTrace] = []
    for fracture in fractures:
        extent = fracture.radius + fracture.max_height + reach
        if np.linalg.norm(np.maximum(0, np.maximum(lo - fracture.centre, fracture.centre - hi))) > extent:
            continue  # cannot reach the wall's bounding box
        near = np.asarray(tree.query_ball_point(fracture.centre, extent), dtype=np.int64)
        slab = np.abs((centroids[near] - fracture.centre) @ fracture.normal) <= fracture.max_height + reach
        near = near[slab]
        for points, face, closed, ends in _fracture_traces(vertices, faces, near, fracture, border):
            traces.append(TrueTrace(len(traces), fracture.id, points, face, closed, ends))
    return traces


def _fracture_traces(vertices, faces, near, fracture, border):
    """Chains of (points, face, closed, ends) where one fracture cuts the faces `near`."""
    vid, inverse = np.unique(faces[near], return_inverse=True)
    local = inverse.reshape(-1, 3)
    v = vertices[vid]
    f = fracture.offset(v)
    above = f >= 0  # a vertex exactly on the surface counts as above; it yields zero-length steps, dropped below
    cut = above[local].any(axis=1) & ~above[local].all(axis=1)
    if not cut.any():
        return []
    local, near = local[cut], near[cut]
    edges3 = local[:, [[0, 1], [1, 2], [2, 0]]]
    crossed = above[edges3[..., 0]] != above[edges3[..., 1]]  # exactly two per cut face
    face_edges = np.sort(edges3[crossed], axis=1)
    edges, node = np.unique(face_edges, axis=0, return_inverse=True)
    node = node.reshape(-1, 2)
    points = _edge_roots(v[edges[:, 0]], v[edges[:, 1]], f[edges[:, 0]], f[edges[:, 1]], fracture)
    on_border = np.isin(_edge_keys(vid[edges], len(vertices)), border)

    all_points, u, w, keep = _clip_to_disc(fracture, points, node, v[local])
    near, n_edges = near[keep], len(points)

    chains = []
    for nodes, segments in _chain(u, w, len(all_points)):
        closed = bool(nodes[0] == nodes[-1])
        p = all_points[nodes]
        face = near[np.append(segments, segments[-1])]
        step = np.r_[True, np.any(np.diff(p, axis=0) != 0, axis=1)]
        p, face = p[step], face[step]
        if len(p) < 2:
            continue
        ends = ("", "") if closed else tuple("B" if k >= n_edges else "C" for k in (nodes[0], nodes[-1]))
        # an open chain can only end on a border edge or a tip: the face search radius covers the whole disc
        assert closed or all(k >= n_edges or on_border[k] for k in (nodes[0], nodes[-1]))
        chains.append((p, face, closed, ends))
    return chains


def _clip_to_disc(fracture, points, node, tri):
    """Keep the part of each chord node[k] (indices into `points`) inside the disc; add tip nodes where it leaves.

    Returns all node points (the given ones, then the tips), the chords' new end nodes u, w and which chords
    were kept. `tri` (N, 3, 3) are the faces of the chords, within which tips are refined.
    """
    pa, pb = points[node[:, 0]], points[node[:, 1]]
    pq = fracture.plane_coords(points)
    # a node is in the disc or not once for all its chords, so chains never break at an interior node
    inside = (pq**2).sum(axis=1) <= fracture.radius**2
    ia, ib = inside[node[:, 0]], inside[node[:, 1]]
    s0, s1 = _disc_interval(pq[node[:, 0]], pq[node[:, 1]], fracture.radius, ia, ib)
    keep = ia | ib | (s1 > s0)
    pa, pb, s0, s1, node, tri, start, end = (x[keep] for x in (pa, pb, s0, s1, node, tri, ~ia, ~ib))
    tips = np.concatenate([pa[start] + s0[start, None] * (pb - pa)[start], pa[end] + s1[end, None] * (pb - pa)[end]])
    if len(fracture.undulation) and len(tips):
        tips = _refine_tips(fracture, tips, np.concatenate([tri[start], tri[end]]))
    n = len(points)
    u, w = node[:, 0].copy(), node[:, 1].copy()
    u[start] = n + np.arange(start.sum())
    w[end] = n + start.sum() + np.arange(end.sum())
    return np.concatenate([points, tips]), u, w, keep


def _edge_roots(a, b, fa, fb, fracture, iterations=100):
    """The point on each edge a→b where the fracture offset is zero (fa, fb have opposite signs).

    Linear interpolation is exact for a plane, whose offset is linear along the edge; an undulating
    surface is solved by the Illinois (modified regula falsi) method, which keeps the root bracketed.
    """
    s = fa / (fa - fb)
    if not len(fracture.undulation):
        return a + s[:, None] * (b - a)
    d = b - a
    lo, hi, flo, fhi = np.zeros_like(s), np.ones_like(s), fa.copy(), fb.copy()
    kept = np.zeros(len(s), dtype=np.int8)  # the end kept by the last step: -1 lo, +1 hi
    tol = 1e-13 * fracture.radius
    for _ in range(iterations):
        fs = fracture.offset(a + s[:, None] * d)
        if np.all((np.abs(fs) <= tol) | (hi - lo <= 1e-15)):
            break
        low = np.sign(fs) == np.sign(flo)  # the root lies in [s, hi]
        fhi = np.where(low & (kept == 1), 0.5 * fhi, fhi)  # halve the end kept twice: no stalling
        flo = np.where(~low & (kept == -1), 0.5 * flo, flo)
        lo, flo = np.where(low, s, lo), np.where(low, fs, flo)
        hi, fhi = np.where(low, hi, s), np.where(low, fhi, fs)
        kept = np.where(low, 1, -1).astype(np.int8)
        s = np.where(fhi == flo, s, (lo * fhi - hi * flo) / (fhi - flo))
    return a + s[:, None] * d


def _disc_interval(pa, pb, r, inside_a, inside_b):
    """The part [s0, s1] ⊂ [0, 1] of each chord pa→pb (in-plane, (N, 2)) inside the disc |p| ≤ r.

    An end flagged inside is kept exactly (s = 0 or 1); otherwise the circle crossing is used. A chord with
    both ends outside that misses the disc gets NaN or s1 ≤ s0.
    """
    d = pb - pa
    A = np.einsum("ij,ij->i", d, d)
    B = 2 * np.einsum("ij,ij->i", pa, d)
    C = np.einsum("ij,ij->i", pa, pa) - r * r
    with np.errstate(divide="ignore", invalid="ignore"):
        root = np.sqrt(B * B - 4 * A * C)
        lo, hi = (-B - root) / (2 * A), (-B + root) / (2 * A)
    return np.where(inside_a, 0.0, np.clip(lo, 0, 1)), np.where(inside_b, 1.0, np.clip(hi, 0, 1))


def _refine_tips(fracture, x, tri, iterations=8):
    """Move tips (N, 3), within the plane of their face tri (N, 3, 3), onto surface ∩ {|p| = radius}.

    Newton on the two conditions in the face's 2D frame; a tip that would leave its face keeps its estimate
    on the chord (within O(h² curvature) of the surface).
    """
    e1 = tri[:, 1] - tri[:, 0]
    u1 = e1 / np.linalg.norm(e1, axis=1, keepdims=True)
    u2 = np.cross(np.cross(e1, tri[:, 2] - tri[:, 0]), u1)
    u2 /= np.linalg.norm(u2, axis=1, keepdims=True)
    a1, a2 = fracture.axes
    y = x.copy()
    for _ in range(iterations):
        pq = fracture.plane_coords(y)
        g = np.column_stack([fracture.offset(y), (pq**2).sum(axis=1) - fracture.radius**2])
        dw = fracture.height_gradient(pq)
        grad_f = fracture.normal - dw[:, :1] * a1 - dw[:, 1:] * a2
        grad_r = 2 * (pq[:, :1] * a1 + pq[:, 1:] * a2)
        J = np.stack([[np.einsum("ij,ij->i", grad_f, u1), np.einsum("ij,ij->i", grad_f, u2)],
                      [np.einsum("ij,ij->i", grad_r, u1), np.einsum("ij,ij->i", grad_r, u2)]])
        det = J[0, 0] * J[1, 1] - J[0, 1] * J[1, 0]
        ok = np.abs(det) > 1e-12
        det = np.where(ok, det, 1.0)
        da = np.where(ok, (J[1, 1] * g[:, 0] - J[0, 1] * g[:, 1]) / det, 0.0)
        db = np.where(ok, (J[0, 0] * g[:, 1] - J[1, 0] * g[:, 0]) / det, 0.0)
        y -= da[:, None] * u1 + db[:, None] * u2
    inside = np.all(barycentric(y, tri) >= -1e-9, axis=1)
    return np.where(inside[:, None], y, x)


def _chain(u, w, n_nodes):
    """Ordered paths (node list, segment list) through segments u[k]–w[k]; each node has degree ≤ 2.

    Open paths start at degree-1 nodes; whatever is left are cycles, whose node list returns to its start.
    """
    adjacent = [[] for _ in range(n_nodes)]
    for k, (a, b) in enumerate(zip(u.tolist(), w.tolist())):
        adjacent[a].append(k)
        adjacent[b].append(k)
    used = np.zeros(len(u), dtype=bool)
    ends = [i for i in range(n_nodes) if len(adjacent[i]) == 1]
    paths = []
    for start in ends + list(range(n_nodes)):
        if all(used[k] for k in adjacent[start]):
            continue
        nodes, segments, here = [start], [], start
        while (k := next((k for k in adjacent[here] if not used[k]), None)) is not None:
            used[k] = True
            here = int(w[k] if u[k] == here else u[k])
            nodes.append(here)
            segments.append(k)
        paths.append((np.array(nodes), np.array(segments)))
    return paths


def _edge_keys(edges, n_vertices):
    e = np.sort(np.asarray(edges, dtype=np.int64), axis=1)
    return e[:, 0] * n_vertices + e[:, 1]


# ---------------------------------------------------------------------------------------------------------
# cameras, photographs and what they show


def survey_cameras(rng: np.random.Generator, vertices: np.ndarray, *, n_cameras: int = 5,
                   image_size: tuple[int, int] = (1600, 1200), distance: tuple[float, float] = (8.0, 12.0),
                   distortion: Sequence[float] | None = None) -> list[Camera]:
    """Overlapping photos of the wall (in the frame of `vertices`), as a geologist would take them.

    Cameras stand 1.4–2.4 m above the wall foot, `distance` m from aim points spread along the wall, with
    obliquities from +35° to -35° (±5°), a little roll, and a principal point off the image centre. Each
    photo covers about max(0.55, 2.2/n) of the wall width, so every part is in two or more photos.
    """
    w_px, h_px = image_size
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    wall_y = float(np.median(vertices[:, 1]))
    width, mid_z = hi[0] - lo[0], 0.5 * (lo[2] + hi[2])
    cover = min(1.1, max(0.55, 2.2 / n_cameras)) * width
    aims = np.linspace(lo[0] + 0.4 * cover, hi[0] - 0.4 * cover, n_cameras) if n_cameras > 1 else [0.5 * (lo + hi)[0]]
    coefficients = np.asarray(() if distortion is None else distortion, dtype=float)
    azimuths = np.radians(np.linspace(35, -35, n_cameras) + rng.uniform(-5, 5, n_cameras))
    cameras = []
    for k, (x, az) in enumerate(zip(aims, azimuths)):
        target = np.array([x, wall_y, mid_z + rng.uniform(-0.5, 0.5)])
        centre = target + rng.uniform(*distance) * np.array([np.sin(az), -np.cos(az), 0.0])
        centre[2] = lo[2] + rng.uniform(1.4, 2.4)
        R = _look_at(centre, target, roll=np.radians(rng.normal(0, 1.0)))
        f = 0.5 * w_px / (0.5 * cover / np.linalg.norm(target - centre))
        cx, cy = (w_px - 1) / 2 + rng.uniform(-0.01, 0.01) * w_px, (h_px - 1) / 2 + rng.uniform(-0.01, 0.01) * h_px
        K = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
        cameras.append(Camera(f"photo_{k + 1:02d}", w_px, h_px, K, coefficients, R, -R @ centre))
    return cameras


def _look_at(centre, target, roll):
    """World→camera rotation (rows: camera x right, y down, z forward) looking from centre at target."""
    forward = (target - centre) / np.linalg.norm(target - centre)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    c, s = np.cos(roll), np.sin(roll)
    return np.stack([c * right + s * down, -s * right + c * down, forward])


class _Texture:
    """Procedural rock colour: 3D value-noise fBm, warped bedding with partings, fine grain."""

    TABLE = 128  # lattice cells per period of the value noise

    def __init__(self, rng: np.random.Generator, style: Style):
        self.style = style
        self.table = rng.random((self.TABLE,) * 3, dtype=np.float32)
        self.rotations = Rotation.random(8, random_state=rng).as_matrix()  # one per octave: hides the lattice
        self.bed_normal = dip_dipdir_to_normal(rng.uniform(4, 12), rng.uniform(0, 360))

    def noise(self, points: np.ndarray, frequencies: Sequence[float], octave0: int = 0) -> np.ndarray:
        """fBm in about [0, 1]: value noise at the given frequencies (1/m), amplitude halving per octave."""
        total, norm = 0.0, 0.0
        for k, f in enumerate(frequencies):
            p = (points @ self.rotations[octave0 + k].T * f).T.astype(np.float32)
            total = total + 0.5**k * ndimage.map_coordinates(self.table, p, order=1, mode="grid-wrap",
                                                              prefilter=False)
            norm += 0.5**k
        return total / norm

    def albedo(self, points: np.ndarray) -> np.ndarray:
        """Rock colour (N, 3) in [0, 1] at points (N, 3), independent of viewpoint and light."""
        st = self.style
        large = self.noise(points, (0.25, 0.6))
        grain = self.noise(points, (5.0, 13.0, 33.0), octave0=2)
        bed = points @ self.bed_normal / st.bed_period + 1.5 * large  # warped bed coordinate, in periods
        layer = np.clip(0.5 + st.bed_contrast * np.sin(2 * np.pi * bed), 0, 1)
        parting = np.exp(-((np.abs((bed / 3) % 1 - 0.5) * 3 * st.bed_period) / 0.008) ** 2)
        light, dark = np.asarray(st.light), np.asarray(st.dark)
        colour = light + layer[:, None] * (dark - light)
        tone = (1 + st.grain * (2 * grain - 1)) * (1 + 0.35 * (large - 0.5)) * (1 - 0.2 * parting)
        return colour * tone[:, None]


class _TraceInk:
    """How dark each point is for lying near a true trace (3D distance, Gaussian profile)."""

    def __init__(self, rng: np.random.Generator, traces: list[TrueTrace], fractures: list[Fracture],
                 texture: _Texture):
        self.width = texture.style.trace_width
        contrast = rng.uniform(*texture.style.trace_contrast, max(len(fractures), 1))
        points, strength = [], []
        for t in traces:
            p, _ = resample_polyline(t.points, self.width / 4)
            points.append(p)
            strength.append(np.full(len(p), contrast[t.fracture_id]))
        if points:
            points = np.concatenate(points)
            # traces fade and darken along their length, as weathered fractures do
            self.strength = np.concatenate(strength) * (0.55 + 0.45 * texture.noise(points, (2.0,), octave0=5))
            self.tree = cKDTree(points)
        else:
            self.tree = None

    def darkness(self, points: np.ndarray) -> np.ndarray:
        out = np.zeros(len(points))
        if self.tree is None:
            return out
        d, i = self.tree.query(points, distance_upper_bound=2.5 * self.width, workers=-1)
        near = np.isfinite(d)
        sigma = self.width / 2.3548  # width is the full width at half maximum
        out[near] = self.strength[i[near]] * np.exp(-0.5 * (d[near] / sigma) ** 2)
        return out


def _render_photo(camera: Camera, tracer: RayTracer, mesh: Mesh, texture: _Texture, ink: _TraceInk,
                 rng: np.random.Generator, *, rows: int = 64) -> np.ndarray:
    """The photo (H, W, 3) uint8 RGB that `camera` (LOCAL frame) takes of the clean `mesh`.

    One ray per pixel centre: rock albedo × (1 - trace darkness) × Lambert shading (no cast shadows), a
    textured ground plane z = 0 and a sky gradient for misses; then a slight optical blur and sensor noise.
    Rows are processed `rows` at a time so memory stays bounded.
    """
    st = texture.style
    az, el = np.radians(st.sun)
    sun = np.array([np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el)])
    normals = mesh.vertex_normals
    image = np.empty((camera.height, camera.width, 3), dtype=np.float32)
    u = np.arange(camera.width, dtype=float)
    centre = camera.centre
    for r0 in range(0, camera.height, rows):
        v = np.arange(r0, min(r0 + rows, camera.height), dtype=float)
        uv = np.column_stack([np.tile(u, len(v)), np.repeat(v, len(u))])
        d = camera.pixel_rays(uv)
        hits = tracer.intersect(centre, d)
        colour = _background(centre, d, texture, sun)
        h = hits.hit
        if h.any():
            b = hits.barycentric[h]
            tri_n = normals[mesh.faces[hits.face[h]]]
            n = (1 - b[:, :1] - b[:, 1:]) * tri_n[:, 0] + b[:, :1] * tri_n[:, 1] + b[:, 1:] * tri_n[:, 2]
            n /= np.linalg.norm(n, axis=1, keepdims=True)
            shade = st.ambient + (1 - st.ambient) * np.clip(n @ sun, 0, None)
            p = hits.points[h]
            rock = texture.albedo(p) * (1 - ink.darkness(p))[:, None]
            colour[h] = rock * shade[:, None]
        image[r0:r0 + len(v)] = colour.reshape(len(v), camera.width, 3)
    image = cv2.GaussianBlur(image, (0, 0), 0.6)
    image = 255 * image + rng.normal(0, st.sensor_noise, image.shape).astype(np.float32)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def _background(centre, d, texture, sun):
    """Sky for upward rays, a textured flat ground at z = 0 for downward ones (N, 3)."""
    st = texture.style
    up = np.clip(d[:, 2], 0, 1)[:, None]
    colour = np.asarray(st.sky) * (1.15 - 0.35 * up)
    down = d[:, 2] < 0
    if down.any() and centre[2] > 0:
        t = -centre[2] / d[down, 2]
        ground = centre + t[:, None] * d[down]
        shade = st.ambient + (1 - st.ambient) * sun[2]
        mottle = 0.7 + 0.6 * texture.noise(ground, (1.5, 7.0), octave0=6)
        colour[down] = np.asarray(st.ground) * shade * mottle[:, None]
    return colour


def visible_traces(camera: Camera, tracer: RayTracer, traces: Sequence[TrueTrace], *, min_pixels: float = 5.0,
                   tolerance: float = 0.005) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """(trace index, polyline (N, 2) px, points (N, 3)) of each visible run of each trace on one photo.

    Traces are resampled about every 0.5 px, projected, and kept where inside the image, inside the field
    of view (so strong distortion cannot fold outside points in) and not hidden by the mesh. `camera`,
    `tracer` and `traces` share one frame.
    """
    centre = camera.centre
    fov = _field_of_view(camera)
    dense = []
    for t in traces:
        spacing = 0.5 * np.linalg.norm(t.points.mean(axis=0) - centre) / camera.K[0, 0]
        dense.append(resample_polyline(t.points, spacing)[0])
    if not dense:
        return []
    allp = np.concatenate(dense)
    xc = allp @ camera.R.T + camera.t
    with np.errstate(divide="ignore", invalid="ignore"):
        normalised = np.linalg.norm(xc[:, :2] / xc[:, 2:], axis=1)
    uv = camera.project(allp)
    seen = (xc[:, 2] > 0) & (normalised <= fov) & np.all(uv >= -0.5, axis=1) \
        & (uv[:, 0] <= camera.width - 0.5) & (uv[:, 1] <= camera.height - 0.5)
    seen[seen] = ~tracer.occluded(centre, allp[seen], tolerance=tolerance)
    out = []
    splits = np.cumsum([len(p) for p in dense])[:-1]
    for t, p, q, ok in zip(traces, dense, np.split(uv, splits), np.split(seen, splits)):
        if t.closed and ok.any() and not ok.all():
            shift = -int(np.argmin(ok[:-1]))  # start the loop where it is hidden, so no run wraps round
            p, q, ok = (np.roll(a[:-1], shift, axis=0) for a in (p, q, ok))
        edges = np.flatnonzero(np.diff(np.r_[0, ok.astype(np.int8), 0]))
        for a, b in zip(edges[::2], edges[1::2]):
            if b - a >= 2 and polyline_length(q[a:b]) >= min_pixels:
                out.append((t.id, q[a:b], p[a:b]))
    return out


def _field_of_view(camera: Camera) -> float:
    """The largest normalised image radius x/z of the image border, plus 5 %."""
    u = np.linspace(-0.5, camera.width - 0.5, 33)
    v = np.linspace(-0.5, camera.height - 0.5, 33)
    border = np.concatenate([np.column_stack([u, np.full_like(u, v[0])]), np.column_stack([u, np.full_like(u, v[-1])]),
                             np.column_stack([np.full_like(v, u[0]), v]), np.column_stack([np.full_like(v, u[-1]), v])])
    return 1.05 * float(np.linalg.norm(camera.undistort_normalised(border), axis=1).max())


# ---------------------------------------------------------------------------------------------------------
# helpers


def _segment_distance(p, a, b):
    """Distance from points p to segments a–b (broadcast over leading axes, last axis 3)."""
    d = b - a
    dd = np.einsum("...i,...i->...", d, d)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.clip(np.where(dd > 0, np.einsum("...i,...i->...", p - a, d) / dd, 0.0), 0.0, 1.0)
    return np.linalg.norm(p - (a + s[..., None] * d), axis=-1)


def _write_ply(path: Path, vertices: np.ndarray, faces: np.ndarray, colours: np.ndarray | None) -> None:
    """Binary PLY with float64 vertices: float32 would lose centimetres at UTM-sized coordinates."""
    colour_props = "property uchar red\nproperty uchar green\nproperty uchar blue\n" if colours is not None else ""
    header = (f"ply\nformat binary_little_endian 1.0\ncomment tracemap synthetic outcrop, world coordinates\n"
              f"element vertex {len(vertices)}\nproperty double x\nproperty double y\nproperty double z\n"
              f"{colour_props}element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n")
    vdtype = [("xyz", "<f8", 3)] + ([("rgb", "u1", 3)] if colours is not None else [])
    v = np.empty(len(vertices), dtype=vdtype)
    v["xyz"] = vertices
    if colours is not None:
        v["rgb"] = colours
    f = np.empty(len(faces), dtype=[("n", "u1"), ("idx", "<i4", 3)])
    f["n"], f["idx"] = 3, faces
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(v.tobytes())
        fh.write(f.tobytes())


def _write_json(path: Path, data: dict, indent: int | None = None) -> None:
    # json.dumps without indent uses the C encoder (json.dump never does): the truth file is large
    path.write_text(json.dumps(data, indent=indent))


def _jsonable(value):
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def _check_parameters(p: dict) -> None:
    """Raise InputError naming the parameter when a value cannot make an outcrop."""
    choices = {"size_distribution": ("lognormal", "powerlaw"), "fracture_model": ("planar", "undulating"),
               "style": tuple(STYLES)}
    for name, allowed in choices.items():
        if p[name] not in allowed:
            raise InputError(None, f"{name}={p[name]!r}: expected one of {', '.join(allowed)}")
    for name in ("width", "height", "mesh_spacing", "radius_median", "radius_sigma", "radius_min"):
        if not p[name] > 0:
            raise InputError(None, f"{name}={p[name]!r}: expected a positive number")
    if p["mesh_spacing"] * 2 > min(p["width"], p["height"]):
        raise InputError(None, f"mesh_spacing={p['mesh_spacing']!r}: expected less than half the wall size")
    if not p["radius_max"] > p["radius_min"]:
        raise InputError(None, "radius_max must exceed radius_min")
    if p["n_cameras"] < 1 or min(p["image_size"]) < 16:
        raise InputError(None, "n_cameras must be ≥ 1 and image_size at least 16×16 px")
    if len(p["sets"]) == 0:
        raise InputError(None, "sets: expected at least one (dip, dip direction, kappa, weight)")
    for s in p["sets"]:
        if len(s) != 4 or not (0 <= s[0] <= 90 and s[2] > 0 and s[3] > 0):
            raise InputError(None, f"sets: {tuple(s)!r} is not (dip in [0, 90], dip direction, kappa > 0, "
                                   "weight > 0)")
