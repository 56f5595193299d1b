"""tracemap engine: 3D fracture trace maps from calibrated photographs and a mesh.

A plain library (no Qt): cameras, mesh, ray tracing, extraction, project file, CLI.
Seers & Hodgetts (2016, Geosphere 12(4) 1323-1340) is the method it implements.
"""

from engine.errors import Cancelled, TracemapError

__all__ = ["Cancelled", "TracemapError"]
__version__ = "0.1.0"
