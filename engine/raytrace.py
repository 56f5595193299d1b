"""Ray casting against the mesh with Embree 4: first hits and occlusion queries.

Seers & Hodgetts (2016a §3.2) cast one ray per trace pixel; a photo of traces is ~10⁵–10⁶ rays on a mesh of
millions of faces. We drive the Embree 4 library that the `embreex` wheel ships through a thin ctypes layer:
the mesh is shared with Embree without a copy and rays go in packets of 16 from two threads, which builds
~3× and traces ~2× faster than `embreex.mesh_construction` (tests/benchmarks/bench_raytrace.py).

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

import numpy as np

from engine.errors import TracemapError

PACKET = 16
_STRIDE = 2048  # bytes per RTCRayHit16 record: 768 ray + 448 hit + instance ids, padded, 64-aligned
_W = _STRIDE // 4  # float32 words per record
# word offsets of the RTCRay16 / RTCHit16 fields (Embree 4 rtcore_ray.h, SoA of 16)
_ORG, _DIR, _TFAR, _MASK = 0, 64, 128, 144  # tnear, time, id, flags stay 0
_U, _V, _PRIM, _GEOM = 240, 256, 272, 288
_INVALID = 0xFFFFFFFF
_BUFFER_INDEX, _BUFFER_VERTEX = 0, 1
_FORMAT_UINT3, _FORMAT_FLOAT3 = 0x5003, 0x9003
_GEOMETRY_TRIANGLE = 0
_SCENE_FLAG_ROBUST = 1 << 2
_RAYS_PER_CALL = 1 << 18  # bounds the packet buffer to 32 MB


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
        "rtcCommitGeometry": ([vp], None), "rtcAttachGeometry": ([vp, vp], u32),
        "rtcIntersect16": ([vp, vp, vp, vp], None),
    }
    for name, (args, res) in signatures.items():
        fn = getattr(lib, name)
        fn.argtypes, fn.restype = args, res
    return lib


_EMBREE = _load_embree()


@dataclass(frozen=True)
class Hits:
    """First hits of N rays. Misses have hit False, face -1, t inf and NaN points/barycentric."""

    hit: np.ndarray
    face: np.ndarray
    t: np.ndarray
    points: np.ndarray
    barycentric: np.ndarray

    @property
    def n_missed(self) -> int:
        return int(np.count_nonzero(~self.hit))


class RayTracer:
    """Embree BVH over a triangle mesh in its local frame (vertices (V, 3), faces (F, 3)).

    Build once per mesh and reuse for every photo. `threads` defaults to the number of CPU cores.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, *, threads: int | None = None):
        self.vertices = np.asarray(vertices, dtype=np.float64)
        self.faces = np.asarray(faces, dtype=np.int64)
        self.threads = threads or os.cpu_count() or 1
        extent = float(np.ptp(self.vertices, axis=0).max())
        self.epsilon = 1e-6 * max(extent, 1e-3)
        # Embree reads vertices with 16-byte loads, so the shared buffer has one float of padding at the end
        self._v32 = np.zeros(self.vertices.size + 1, dtype=np.float32)
        self._v32[:-1] = self.vertices.ravel()
        self._f32 = np.ascontiguousarray(self.faces, dtype=np.uint32)
        lib = _EMBREE
        self._device = lib.rtcNewDevice(f"threads={self.threads}".encode())
        self._scene = lib.rtcNewScene(self._device)
        lib.rtcSetSceneFlags(self._scene, _SCENE_FLAG_ROBUST)
        geometry = lib.rtcNewGeometry(self._device, _GEOMETRY_TRIANGLE)
        lib.rtcSetSharedGeometryBuffer(geometry, _BUFFER_VERTEX, 0, _FORMAT_FLOAT3, self._v32.ctypes.data,
                                       0, 12, len(self.vertices))
        lib.rtcSetSharedGeometryBuffer(geometry, _BUFFER_INDEX, 0, _FORMAT_UINT3, self._f32.ctypes.data,
                                       0, 12, len(self._f32))
        lib.rtcCommitGeometry(geometry)
        lib.rtcAttachGeometry(self._scene, geometry)
        lib.rtcReleaseGeometry(geometry)
        lib.rtcCommitScene(self._scene)
        if error := lib.rtcGetDeviceError(self._device):
            raise TracemapError(f"Embree could not build the ray-tracing structure (error code {error})")
        self._pool = ThreadPoolExecutor(self.threads) if self.threads > 1 else None
        weakref.finalize(self, _release, self._device, self._scene, self._pool)

    def intersect(self, origins: np.ndarray, directions: np.ndarray) -> Hits:
        """First hit of each ray origin + t·direction with t > 0 (directions need not be unit)."""
        origins, directions = _broadcast(origins, directions)
        unit = directions / np.linalg.norm(directions, axis=1, keepdims=True)
        n = len(origins)
        face = np.full(n, -1, dtype=np.int64)
        t = np.full(n, np.inf)
        bary = np.full((n, 2), np.nan)
        for start in range(0, n, _RAYS_PER_CALL):
            sl = slice(start, min(start + _RAYS_PER_CALL, n))
            face[sl], t[sl], bary[sl] = self._trace(origins[sl], unit[sl])
        hit = face >= 0
        t[~hit] = np.inf
        bary[~hit] = np.nan
        points = origins + np.where(hit, t, np.nan)[:, None] * unit
        return Hits(hit, face, t, points, bary)

    def occluded(self, origins: np.ndarray, targets: np.ndarray, *, tolerance: float | None = None) -> np.ndarray:
        """True where the mesh blocks the segment from origin to target, short of the target.

        A surface within `tolerance` (metres; default 1e-6 of the mesh extent) of the target does not
        count, so a point on the mesh seen from a camera is not occluded by its own face.
        """
        origins, targets = _broadcast(origins, targets)
        tol = self.epsilon if tolerance is None else float(tolerance)
        delta = targets - origins
        hits = self.intersect(origins, delta)
        return hits.hit & (hits.t < np.linalg.norm(delta, axis=1) - tol)

    def _trace(self, origins: np.ndarray, unit: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Embree's first hit of each ray: face index (-1 for a miss), distance and barycentric (u, v)."""
        n = len(origins)
        packets = -(-n // PACKET)
        buf = _aligned_records(packets)
        words = buf.view(np.uint32)
        for k in range(3):
            buf[:, _ORG + 16 * k:_ORG + 16 * (k + 1)] = _packed(origins[:, k], packets)
            buf[:, _DIR + 16 * k:_DIR + 16 * (k + 1)] = _packed(unit[:, k], packets)
        buf[:, _TFAR:_TFAR + 16] = np.inf
        words[:, _MASK:_MASK + 16] = _INVALID
        words[:, _GEOM:_GEOM + 16] = _INVALID
        valid = np.full(PACKET, -1, dtype=np.int32)
        last_valid = np.where(np.arange(PACKET) < n - (packets - 1) * PACKET, -1, 0).astype(np.int32)
        base = buf.ctypes.data
        bounds = np.linspace(0, packets, min(self.threads, packets) + 1).astype(int)

        def run(lo: int, hi: int) -> None:
            call, scene, vp = _EMBREE.rtcIntersect16, self._scene, valid.ctypes.data
            for p in range(lo, min(hi, packets - 1)):
                call(vp, scene, base + p * _STRIDE, None)
            if hi == packets:
                call(last_valid.ctypes.data, scene, base + (packets - 1) * _STRIDE, None)

        jobs = list(zip(bounds[:-1], bounds[1:]))
        if self._pool is None or len(jobs) == 1:
            for lo, hi in jobs:
                run(lo, hi)
        else:
            list(self._pool.map(lambda job: run(*job), jobs))
        geom = words[:, _GEOM:_GEOM + 16].ravel()[:n]
        face = np.where(geom == _INVALID, -1, words[:, _PRIM:_PRIM + 16].ravel()[:n].astype(np.int64))
        bary = np.column_stack([buf[:, _U:_U + 16].ravel()[:n], buf[:, _V:_V + 16].ravel()[:n]])
        return face, buf[:, _TFAR:_TFAR + 16].ravel()[:n], bary


def _release(device: int, scene: int, pool: ThreadPoolExecutor | None) -> None:
    if pool is not None:
        pool.shutdown(wait=False)
    _EMBREE.rtcReleaseScene(scene)
    _EMBREE.rtcReleaseDevice(device)


def _aligned_records(packets: int) -> np.ndarray:
    """A zeroed (packets, _W) float32 array whose rows start on 64-byte boundaries (Embree's alignment)."""
    raw = np.zeros(packets * _STRIDE + 64, dtype=np.uint8)
    offset = (-raw.ctypes.data) % 64
    return raw[offset:offset + packets * _STRIDE].view(np.float32).reshape(packets, _W)


def _packed(values: np.ndarray, packets: int) -> np.ndarray:
    out = np.zeros(packets * PACKET, dtype=np.float32)
    out[: len(values)] = values
    return out.reshape(packets, PACKET)


def _broadcast(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.atleast_2d(np.asarray(a, dtype=np.float64))
    b = np.atleast_2d(np.asarray(b, dtype=np.float64))
    a, b = np.broadcast_arrays(a, b)
    return np.ascontiguousarray(a), np.ascontiguousarray(b)
