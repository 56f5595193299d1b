"""Ray casting against the mesh with Embree 4 (`RayTracer`, `Hits`): see `engine.raytrace.tracer`.

The tracer's scene is built from the mesh's triangles paired into quads (`quads`), which faces lie across
each edge (`adjacency`), and the mesh's main sheet (`sheet`), the part traced with Embree's fast test.
"""

from engine.raytrace.tracer import Hits, RayTracer

__all__ = ["Hits", "RayTracer"]
