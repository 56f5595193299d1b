"""Ray casting against the mesh with Embree 4: first hits and occlusion queries.

Seers & Hodgetts (2016a §3.2) cast one ray per trace pixel; a photo of traces is ~10⁵–10⁶ rays on a mesh of
millions of faces. We drive the Embree 4 library that the `embreex` wheel ships: the scene is built through
ctypes, and rays are traced by a numba-compiled loop that fills 16-ray packets (one AVX-512 register per
field) and releases the GIL, on two threads.

Two measured choices make a photo's rays ~30% cheaper than Embree's robust triangles, which Open3D runs
(tests/benchmarks/bench_raytrace.py): the triangles are paired across shared edges into quads
(`engine.raytrace.quads`: half the primitives, a shallower tree), and rays are traced first with Embree's fast
(Möller) test. That test is not watertight: a ray within float rounding of an edge can slip between two
triangles (about one of a photo's rays in 10⁵; one in ten aimed at edges). So the fast test is used only on
the mesh's main sheet (`engine.raytrace.sheet`: its largest piece joined by edges that two faces share and
wind oppositely), where a ray through a crack either misses or goes on behind the sheet and meets its next
face from the back, as behind an outcrop's surface is rock: the misses, and the hits on faces turned the other
way from most of the call's, are traced again in a robust (watertight) scene of all the quads. Other pieces of
the mesh (loose blocks, debris, a second chunk) are traced robustly for every ray, as a crack in them may show
the wall's front. On 23M rays through every pixel of synthetic outcrops' photos and the benchmark's this
agrees with robust tracing but for 2 rays within 1e-6 of the mesh's outline.

Embree works in float32, so the mesh must be in its local frame (DESIGN.md): hit points are then exact to
~1e-7 of the ray length (micrometres at outcrop range), far below any pixel footprint.
"""

from __future__ import annotations

import ctypes
import os
import weakref
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numba
import numpy as np
from llvmlite import binding
from numba import types

from engine.errors import TracemapError
from engine.raytrace.adjacency import edge_neighbours
from engine.raytrace.quads import pair_triangles, to_faces
from engine.raytrace.sheet import main_sheet

PACKET = 16
_W = 512  # float32 words per RTCRayHit16 record: 192 ray + 112 hit + instance ids, padded to 2 kB
# word offsets of the RTCRay16 / RTCHit16 fields (Embree 4 rtcore_ray.h, SoA of 16); tnear, time, id and
# flags stay 0
_ORG, _DIR, _TFAR, _MASK = 0, 64, 128, 144
_NG, _U, _V, _PRIM, _GEOM = 192, 240, 256, 272, 288
_INVALID = np.uint32(0xFFFFFFFF)
_BUFFER_INDEX, _BUFFER_VERTEX = 0, 1
_FORMAT_UINT4, _FORMAT_FLOAT3 = 0x5004, 0x9003
_GEOMETRY_QUAD = 1
_SCENE_FLAG_FAST, _SCENE_FLAG_ROBUST = 0, 1 << 2
_MIN_RAYS_PER_CHUNK = 4096  # below this a second thread costs more than it saves
_CHUNKS_PER_THREAD = 8


def _load_embree() -> ctypes.CDLL:
    import embreex

    libs = sorted((Path(embreex.__file__).parent.parent / "embreex.libs").glob("libembree4*"))
    if not libs:
        raise TracemapError("the Embree 4 library of the embreex package was not found; "
                            "reinstall with `pip install --force-reinstall embreex`")
    lib = ctypes.CDLL(str(libs[0]))
    vp, u32, sz = ctypes.c_void_p, ctypes.c_uint32, ctypes.c_size_t
    signatures = {
        "rtcNewDevice": ([ctypes.c_char_p], vp), "rtcReleaseDevice": ([vp], None),
        "rtcGetDeviceError": ([vp], ctypes.c_int),
        "rtcNewScene": ([vp], vp), "rtcReleaseScene": ([vp], None),
        "rtcSetSceneFlags": ([vp, ctypes.c_int], None), "rtcCommitScene": ([vp], None),
        "rtcNewGeometry": ([vp, ctypes.c_int], vp), "rtcReleaseGeometry": ([vp], None),
        "rtcSetSharedGeometryBuffer": ([vp, ctypes.c_int, u32, ctypes.c_int, vp, sz, sz, sz], None),
        "rtcCommitGeometry": ([vp], None), "rtcAttachGeometryByID": ([vp, vp, u32], None),
    }
    for name, (args, res) in signatures.items():
        fn = getattr(lib, name)
        fn.argtypes, fn.restype = args, res
    # the compiled loop calls rtcIntersect16 by name: tell LLVM where it is before anything is compiled or
    # loaded from numba's cache
    binding.add_symbol("rtcIntersect16", ctypes.cast(lib.rtcIntersect16, ctypes.c_void_p).value)
    return lib


_EMBREE = _load_embree()
# rtcIntersect16(const int* valid, RTCScene, RTCRayHit16*, RTCIntersectArguments*); pointers as integers
_intersect16 = types.ExternalFunction("rtcIntersect16", types.void(types.intp, types.intp, types.intp, types.intp))


@dataclass(frozen=True)
class Hits:
    """First hits of N rays. Misses have hit False, face -1, t inf and NaN points/barycentric/cosine.
    `cosine` is |cos| of the angle between each ray and the normal of the face it hits (1 head-on, 0 grazing)."""

    hit: np.ndarray
    face: np.ndarray
    t: np.ndarray
    points: np.ndarray
    barycentric: np.ndarray
    cosine: np.ndarray

    @property
    def n_missed(self) -> int:
        return int(np.count_nonzero(~self.hit))


class RayTracer:
    """Embree BVH over a triangle mesh in its local frame (vertices (V, 3), faces (F, 3)).

    Build once per mesh and reuse for every photo. `threads` defaults to the number of CPU cores.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, *, threads: int | None = None):
        self.vertices = np.ascontiguousarray(vertices, dtype=np.float64)
        self.faces = np.ascontiguousarray(faces, dtype=np.int64)
        if self.faces.ndim != 2 or self.faces.shape[1] != 3 or (self.faces.size and not (
                0 <= self.faces.min() and self.faces.max() < len(self.vertices))):
            raise TracemapError(f"faces must be (F, 3) indices into the {len(self.vertices)} vertices")
        self.threads = threads or os.cpu_count() or 1
        extent = float(np.ptp(self.vertices, axis=0).max())
        self.epsilon = 1e-6 * max(extent, 1e-3)
        # Embree reads vertices with 16-byte loads, so the shared buffer has one float of padding at the end
        self._v32 = np.zeros(self.vertices.size + 1, dtype=np.float32)
        self._v32[:-1] = self.vertices.ravel()
        self._pool = ThreadPoolExecutor(self.threads) if self.threads > 1 else None
        across, alike = edge_neighbours(self.faces, len(self.vertices), pool=self._pool)
        quads, lookup = pair_triangles(self.faces, self.vertices, across, pool=self._pool)
        # the main sheet's quads first (a pair shares an edge, so both its faces are in the sheet or neither)
        in_sheet = main_sheet(across, alike)[lookup[:, 0] & 0xFFFFFFFF]
        order = np.argsort(~in_sheet, kind="stable")
        self._quads, self._lookup = np.ascontiguousarray(quads[order]), np.ascontiguousarray(lookup[order])
        self._n_sheet_quads = int(np.count_nonzero(in_sheet))
        lib = _EMBREE
        self._device = lib.rtcNewDevice(f"threads={self.threads}".encode())
        n, q = len(self._quads), self._n_sheet_quads
        # the main sheet, traced fast; the other pieces, traced robustly with it; everything, for the rays
        # the fast test may have let through
        self._fast = self._scene(_SCENE_FLAG_FAST, 0, q) if q else 0
        self._rest = self._scene(_SCENE_FLAG_ROBUST, q, n, geometry_id=1) if q and n > q else 0
        self._robust = self._scene(_SCENE_FLAG_ROBUST, 0, n)
        release = weakref.finalize(self, _release, self._device, (self._fast, self._rest, self._robust), self._pool)
        if error := lib.rtcGetDeviceError(self._device):
            release()
            raise TracemapError(f"Embree could not build the ray-tracing structure (error code {error})")

    def _scene(self, flags: int, lo: int, hi: int, *, geometry_id: int = 0) -> int:
        """An Embree scene of quads lo..hi, sharing the index and vertex buffers."""
        lib = _EMBREE
        scene = lib.rtcNewScene(self._device)
        lib.rtcSetSceneFlags(scene, flags)
        geometry = lib.rtcNewGeometry(self._device, _GEOMETRY_QUAD)
        lib.rtcSetSharedGeometryBuffer(geometry, _BUFFER_VERTEX, 0, _FORMAT_FLOAT3, self._v32.ctypes.data,
                                       0, 12, len(self.vertices))
        lib.rtcSetSharedGeometryBuffer(geometry, _BUFFER_INDEX, 0, _FORMAT_UINT4, self._quads.ctypes.data,
                                       16 * lo, 16, hi - lo)
        lib.rtcCommitGeometry(geometry)
        lib.rtcAttachGeometryByID(scene, geometry, geometry_id)
        lib.rtcReleaseGeometry(geometry)
        lib.rtcCommitScene(scene)
        return scene

    def intersect(self, origins: np.ndarray, directions: np.ndarray) -> Hits:
        """First hit of each ray origin + t·direction with t > 0 (directions need not be unit)."""
        origins, directions, n = _rays(origins, directions)
        # filled by the compiled loop, on the threads: they are as big as the rays and cost as much to fill
        face, t, cosine = np.empty(n, dtype=np.int64), np.empty(n), np.empty(n)
        points, bary = np.empty((n, 3)), np.empty((n, 2))
        facing = np.empty(n, dtype=np.int8)
        # several chunks per thread, taken as threads come free: a thread the OS delays does not hold up the rest
        parts = min(_CHUNKS_PER_THREAD * self.threads, max(1, n // _MIN_RAYS_PER_CHUNK))
        bounds = np.linspace(0, -(-n // PACKET), parts + 1).astype(np.int64) * PACKET
        jobs = [(int(lo), min(int(hi), n)) for lo, hi in zip(bounds[:-1], bounds[1:])]
        outputs = (face, t, points, bary, cosine, facing)
        first = self._fast or self._robust
        counts = self._map(lambda job: _trace_first(first, self._rest, self._n_sheet_quads, origins, directions,
                                                    *job, *outputs), jobs)
        front, back = np.sum(counts, axis=0)
        # a ray through a crack in the main sheet goes on behind it, where the next face of the sheet turns
        # its back to the ray: the rays that missed the sheet or met faces turned the other way from most
        # are traced again (0: none, when the sheet was not traced fast)
        doubtful = 0 if not self._fast else -1 if front >= back else 1
        self._map(lambda job: _trace_again(self._robust, origins, directions, *job, *outputs, self._lookup,
                                           doubtful), jobs)
        return Hits(face >= 0, face, t, points, bary, cosine)

    def _map(self, work, jobs: list[tuple[int, int]]) -> list:
        if len(jobs) == 1 or self._pool is None:
            return [work(job) for job in jobs]
        return list(self._pool.map(work, jobs))

    def occluded(self, origins: np.ndarray, targets: np.ndarray, *, tolerance: float | None = None) -> np.ndarray:
        """True where the mesh blocks the segment from origin to target, short of the target.

        A surface within `tolerance` (metres; default 1e-6 of the mesh extent) of the target does not
        count, so a point on the mesh seen from a camera is not occluded by its own face.
        """
        origins = np.atleast_2d(np.asarray(origins, dtype=np.float64))
        tol = self.epsilon if tolerance is None else float(tolerance)
        delta = np.atleast_2d(np.asarray(targets, dtype=np.float64)) - origins
        hits = self.intersect(origins, delta)
        return hits.hit & (hits.t < np.linalg.norm(delta, axis=1) - tol)


def _release(device: int, scenes: tuple[int, ...], pool: ThreadPoolExecutor | None) -> None:
    if pool is not None:
        pool.shutdown(wait=False)
    for scene in scenes:
        _EMBREE.rtcReleaseScene(scene)
    _EMBREE.rtcReleaseDevice(device)


@numba.njit(nogil=True, cache=True)
def _load(rec: np.ndarray, words: np.ndarray, valid: np.ndarray, unit: np.ndarray, origins: np.ndarray,
          directions: np.ndarray, rays: np.ndarray, m: int) -> None:
    """Fill the packet's lanes with rays[:m] (unit directions kept in `unit`); the other lanes off."""
    for j in range(PACKET):
        valid[j] = -1 if j < m else 0
        if j < m:
            io = 0 if len(origins) == 1 else rays[j]
            di = 0 if len(directions) == 1 else rays[j]
            scale = 1.0 / np.sqrt(directions[di, 0] ** 2 + directions[di, 1] ** 2 + directions[di, 2] ** 2)
            for k in range(3):  # scalar loops: no temporary arrays in the inner loop
                unit[j, k] = directions[di, k] * scale
                rec[_ORG + 16 * k + j] = origins[io, k]
                rec[_DIR + 16 * k + j] = unit[j, k]
            rec[_TFAR + j] = np.inf
            words[_MASK + j] = _INVALID
            words[_GEOM + j] = _INVALID


@numba.njit(nogil=True, cache=True)
def _note_facing(rec: np.ndarray, words: np.ndarray, rays: np.ndarray, m: int, facing: np.ndarray) -> None:
    """Whether each ray of the packet meets the front of the face it hits (1), its back (-1) or nothing (0)."""
    for j in range(m):
        dot = 0.0
        for k in range(3):
            dot += rec[_NG + 16 * k + j] * rec[_DIR + 16 * k + j]
        facing[rays[j]] = 0 if words[_GEOM + j] == _INVALID else (1 if dot < 0.0 else -1)


@numba.njit(nogil=True, cache=True)
def _store(rec: np.ndarray, words: np.ndarray, unit: np.ndarray, origins: np.ndarray, rays: np.ndarray, m: int,
           offset: int, face: np.ndarray, t: np.ndarray, points: np.ndarray, bary: np.ndarray,
           cosine: np.ndarray) -> None:
    """Write the packet's results for rays[:m]: the quad hit (its index, plus `offset` for geometry 1; turned
    into a face by `to_faces`) with Embree's u, v."""
    for j in range(m):
        i = rays[j]
        if words[_GEOM + j] == _INVALID:
            face[i], t[i], cosine[i] = -1, np.inf, np.nan
            points[i, 0] = points[i, 1] = points[i, 2] = bary[i, 0] = bary[i, 1] = np.nan
            continue
        face[i] = words[_PRIM + j] + (offset if words[_GEOM + j] == 1 else 0)
        bary[i, 0] = rec[_U + j]
        bary[i, 1] = rec[_V + j]
        t[i] = rec[_TFAR + j]
        io = 0 if len(origins) == 1 else i
        dot = norm2 = 0.0
        for k in range(3):
            points[i, k] = origins[io, k] + t[i] * unit[j, k]
            dot += rec[_NG + 16 * k + j] * unit[j, k]
            norm2 += rec[_NG + 16 * k + j] ** 2
        cosine[i] = abs(dot) / np.sqrt(norm2)


_OUTPUTS = "int64[::1], float64[::1], float64[:, ::1], float64[:, ::1], float64[::1], int8[::1]"


# compiled (or loaded from numba's cache) when this module is imported, not at the first photo: loading holds
# the GIL for a few hundred ms, which would freeze the GUI if it happened on a worker thread
@numba.njit(f"UniTuple(int64, 2)(intp, intp, int64, float64[:, ::1], float64[:, ::1], intp, intp, {_OUTPUTS})",
            nogil=True, cache=True)
def _trace_first(first: int, rest: int, offset: int, origins: np.ndarray, directions: np.ndarray, lo: int,
                 hi: int, face: np.ndarray, t: np.ndarray, points: np.ndarray, bary: np.ndarray,
                 cosine: np.ndarray, facing: np.ndarray) -> tuple[int, int]:
    """Trace rays lo..hi, 16 at a time, in scene `first`, noting in `facing` how each met it, then in scene
    `rest` (if any; its quads numbered from `offset`) for nearer hits. Returns how many rays met the front
    and the back of a face in `first`."""
    raw = np.zeros(_W + 16, dtype=np.float32)
    rec = raw[((-raw.ctypes.data) % 64) // 4:][:_W]  # Embree wants the packet 64-byte aligned
    words = rec.view(np.uint32)
    valid = np.zeros(PACKET, dtype=np.int32)
    unit = np.empty((PACKET, 3))
    rays = np.empty(PACKET, dtype=np.int64)
    for start in range(lo, hi, PACKET):
        m = min(PACKET, hi - start)
        for j in range(m):
            rays[j] = start + j
        _load(rec, words, valid, unit, origins, directions, rays, m)
        _intersect16(valid.ctypes.data, first, rec.ctypes.data, 0)
        _note_facing(rec, words, rays, m, facing)
        if rest:
            _intersect16(valid.ctypes.data, rest, rec.ctypes.data, 0)
        _store(rec, words, unit, origins, rays, m, offset, face, t, points, bary, cosine)
    front = back = 0
    for i in range(lo, hi):
        front += facing[i] == 1
        back += facing[i] == -1
    return front, back


@numba.njit(f"void(intp, float64[:, ::1], float64[:, ::1], intp, intp, {_OUTPUTS}, int64[:, ::1], int8)",
            nogil=True, cache=True)
def _trace_again(scene: int, origins: np.ndarray, directions: np.ndarray, lo: int, hi: int, face: np.ndarray,
                 t: np.ndarray, points: np.ndarray, bary: np.ndarray, cosine: np.ndarray, facing: np.ndarray,
                 lookup: np.ndarray, doubtful: int) -> None:
    """Trace again in `scene` the rays lo..hi that missed the first scene or met a face turned the
    `doubtful` way (none if `doubtful` is 0); then turn every quad hit into its face."""
    raw = np.zeros(_W + 16, dtype=np.float32)
    rec = raw[((-raw.ctypes.data) % 64) // 4:][:_W]
    words = rec.view(np.uint32)
    valid = np.zeros(PACKET, dtype=np.int32)
    unit = np.empty((PACKET, 3))
    rays = np.empty(PACKET, dtype=np.int64)
    m = 0
    for i in range(lo, hi + 1):
        if doubtful != 0 and i < hi and (facing[i] == 0 or facing[i] == doubtful):
            rays[m] = i
            m += 1
        if m == PACKET or (i == hi and m > 0):
            _load(rec, words, valid, unit, origins, directions, rays, m)
            _intersect16(valid.ctypes.data, scene, rec.ctypes.data, 0)
            _store(rec, words, unit, origins, rays, m, 0, face, t, points, bary, cosine)
            m = 0
    to_faces(lookup, face, bary, lo, hi)


def _rays(origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Origins and directions as float64 (1 or N, 3) arrays, and N: one origin for every ray (a camera's
    centre) is not copied N times."""
    origins = np.ascontiguousarray(np.atleast_2d(origins), dtype=np.float64)
    directions = np.ascontiguousarray(np.atleast_2d(directions), dtype=np.float64)
    shape = np.broadcast_shapes(origins.shape, directions.shape)
    if len(shape) != 2 or shape[1] != 3:
        raise ValueError(f"rays need (N, 3) origins and directions, not {origins.shape} and {directions.shape}")
    return origins, directions, shape[0]
