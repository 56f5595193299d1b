"""Calibrated cameras and the readers of the photogrammetry formats users bring."""

from engine.cameras.camera import Camera

__all__ = ["Camera"]
