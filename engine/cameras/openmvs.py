"""OpenMVS interface files (.mvs, binary), as written by InterfaceCOLMAP, openMVG_main_openMVG2openMVS, ….

Stream layout: openMVS libs/MVS/Interface.h (ArchiveSave/SerializeSave, MVSI_PROJECT_VER 5): an optional
header "MVSI", uint32 version, uint32 reserved (absent in version 0), then little-endian
    platforms: uint64 n × {name, cameras: uint64 n × {name, [bandName if v > 3], [uint32 width, height if v > 0],
                           K 9 doubles, R 9 doubles, C 3 doubles}, poses: uint64 n × {R 9 doubles, C 3 doubles}}
    images: uint64 n × {name, [maskName if v > 4], uint32 platformID, cameraID, poseID, [uint32 ID if v > 2]}
with strings as uint64 length + bytes and matrices row-major. Stream versions 0 to 5 are read; later
ones are refused (their layout is not verified here). Only platforms and images are read.
Conventions (Interface.h, libs/MVS/Camera.h):
- the image's pose is camera.R·pose.R and C = pose.Rᵀ·camera.C + pose.C, R world→camera, camera x right,
  y down, z forward: t = -R·C;
- pixel (0, 0) is the centre of the top-left pixel (Camera::ComposeK puts the centre at (w-1)/2): no shift;
- K is in pixels when the camera stores its width and height; otherwise it is normalised by max(w, h)
  (Scene::LoadInterface scales fx, fy, cx, cy by it) and the sizes come from the photos or `image_sizes`;
  a normalised K with cx = cy = 0 means the image centre, as Camera::GetK reads it;
- images are undistorted: no distortion; images without a pose (poseID = NO_ID) are skipped;
- the optional absolute-to-relative `transform` (v > 1) is not applied: cameras stay in the frame of the
  scene's points and meshes.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from engine.cameras.binary import BinaryReader, read_bytes
from engine.cameras.camera import Camera, make_camera
from engine.cameras.images import ImageSizes, sizes_for
from engine.cameras.rotations import nearest_rotation
from engine.errors import InputError

MAGIC = b"MVSI"
SUPPORTED_VERSIONS = range(0, 6)
NO_ID = 0xFFFFFFFF
_MATRICES = 8 * (9 + 9 + 3)  # bytes of K, R, C


@dataclass(frozen=True)
class _Platform:
    cameras: list[tuple[int, int, np.ndarray, np.ndarray, np.ndarray]]  # width, height, K, R, C
    poses: list[tuple[np.ndarray, np.ndarray]]  # R, C


def read_openmvs(path: Path, *, image_sizes: ImageSizes | None = None,
                 image_dir: Path | None = None) -> dict[str, Camera]:
    """Posed images of an OpenMVS interface file."""
    reader, version = _open(path)
    platforms = [_platform(reader, version) for _ in range(reader.count("Q", 24, "platforms"))]
    images = _posed_images(reader, version)
    names = [Path(stored).name for stored, _ in images]
    if len(set(names)) != len(names):
        raise InputError(path, "two posed images have the same file name; expected unique names")
    normalised = [stored for stored, (p, c, _) in images if _normalised(_camera(path, platforms, stored, p, c))]
    sizes = sizes_for(normalised, path, image_sizes, image_dir or path.parent) if normalised else {}
    return {name: _to_camera(path, platforms, name, stored, ids, sizes.get(stored), str(path.parent / stored))
            for name, (stored, ids) in zip(names, images)}


def _posed_images(reader: BinaryReader, version: int) -> list[tuple[str, tuple[int, int, int]]]:
    """(stored name, (platformID, cameraID, poseID)) of the images that have a pose."""
    images = []
    for _ in range(reader.count("Q", 20, "images")):
        name = reader.sized_string("the image name")
        if version > 4:
            reader.sized_string("the mask name")
        ids = reader.unpack("3I", f"image {name!r}: platformID cameraID poseID")
        if version > 2:
            reader.unpack("I", f"image {name!r}: ID")
        if ids[2] != NO_ID:
            images.append((name.replace("\\", "/"), ids))
    return images


def _open(path: Path) -> tuple[BinaryReader, int]:
    data = read_bytes(path)
    if not data.startswith(MAGIC):
        if b"serialization::archive" in data[:64]:
            raise InputError(path, "this is an OpenMVS Boost archive (scene saved by DensifyPointCloud or "
                                   "ReconstructMesh), not an interface file; expected the .mvs written by "
                                   "InterfaceCOLMAP or openMVG_main_openMVG2openMVS")
        return BinaryReader(path, data), 0
    reader = BinaryReader(path, data, len(MAGIC))
    version, _ = reader.unpack("II", "the stream version and reserved bytes")
    if version not in SUPPORTED_VERSIONS:
        raise InputError(path, f"OpenMVS interface stream version {version} is not supported; expected "
                               f"{SUPPORTED_VERSIONS.start} to {SUPPORTED_VERSIONS.stop - 1}")
    return reader, version


def _platform(reader: BinaryReader, version: int) -> _Platform:
    name = reader.sized_string("the platform name")
    cameras = []
    for _ in range(reader.count("Q", _MATRICES, f"cameras of platform {name!r}")):
        camera = reader.sized_string("the camera name")
        if version > 3:
            reader.sized_string("the camera band name")
        width, height = reader.unpack("2I", f"camera {camera!r}: width height") if version > 0 else (0, 0)
        K, R, C = (reader.doubles(n, f"camera {camera!r}: {what}") for n, what in ((9, "K"), (9, "R"), (3, "C")))
        cameras.append((width, height, K.reshape(3, 3), R.reshape(3, 3), C))
    poses = [(reader.doubles(9, "a pose R").reshape(3, 3), reader.doubles(3, "a pose C"))
             for _ in range(reader.count("Q", 8 * 12, f"poses of platform {name!r}"))]
    return _Platform(cameras, poses)


def _camera(path: Path, platforms: list[_Platform], name: str, platform: int, camera: int) -> tuple:
    if platform >= len(platforms) or camera >= len(platforms[platform].cameras):
        raise InputError(path, f"image {name!r}: platform {platform} camera {camera} does not exist "
                               f"({len(platforms)} platforms)")
    return platforms[platform].cameras[camera]


def _to_camera(path: Path, platforms: list[_Platform], name: str, stored: str, ids: tuple[int, int, int],
               size: tuple[int, int] | None, image_path: str) -> Camera:
    width, height, K, R_cam, C_cam = _camera(path, platforms, stored, ids[0], ids[1])
    poses = platforms[ids[0]].poses
    if ids[2] >= len(poses):
        raise InputError(path, f"image {stored!r}: pose {ids[2]} does not exist ({len(poses)} poses)")
    R_pose, C_pose = poses[ids[2]]
    if not np.array_equal(K[2], [0.0, 0.0, 1.0]):
        raise InputError(path, f"image {stored!r}: K's last row is {K[2].tolist()}, expected 0 0 1")
    if _normalised((width, height)):
        width, height = size
        K = _denormalised(K, width, height)
    R = nearest_rotation(R_cam @ R_pose, path, f"image {stored!r} rotation")
    C = R_pose.T @ C_cam + C_pose
    return make_camera(path, name, width, height, K, np.zeros(8), R, -R @ C, image_path)


def _normalised(camera: tuple) -> bool:
    """Whether a camera (width, height, …) stores no resolution, so its K is normalised (Camera::HasResolution)."""
    return camera[0] == 0 or camera[1] == 0


def _denormalised(K: np.ndarray, width: int, height: int) -> np.ndarray:
    scale = max(width, height)
    K = K.copy()
    K[:2] *= scale
    if K[0, 2] == 0 and K[1, 2] == 0:
        K[:2, 2] = (width - 1) / 2, (height - 1) / 2
    return K
