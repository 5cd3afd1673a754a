"""jaxrt as a benchmark subject: the same verbs as the peers (build, closest, any-hit) through the public API."""

from __future__ import annotations

import numpy as np

import jaxrt as rt
from jaxrt.bench.reference import Hits

__all__ = ["Jaxrt"]


class Jaxrt:
    """jaxrt's LBVH build and traversal on the default JAX device.

    Args:
      vertices: ``(V, 3)`` float32.
      indices: ``(T, 3)`` int32.
      backend: the intersectors' ``backend`` option (``"auto"``, ``"portable"``, ``"gpu"`` or ``"cpu"``).
    """

    name = "jaxrt"

    def __init__(self, vertices: np.ndarray, indices: np.ndarray, *, backend: str = "auto"):
        self.geometry = rt.TriangleGeometry(vertices, indices)
        self.nearest = rt.Intersector(backend=backend)
        self.occlusion = rt.Intersector(accept_any_intersection=True, backend=backend)
        self.structure: rt.PrimitiveAccelerationStructure | None = None

    def build(self) -> rt.PrimitiveAccelerationStructure:
        """Build (and keep) the acceleration structure."""
        self.structure = rt.build_primitive_structure(self.geometry)
        return self.structure

    def closest(self, rays: rt.Ray) -> rt.IntersectionResult:
        """Nearest hits of device rays (timed as is: no host transfer)."""
        return self.nearest.intersect(rays, self.structure)

    def any_hit(self, rays: rt.Ray) -> rt.IntersectionResult:
        """Any hit per ray (occlusion)."""
        return self.occlusion.intersect(rays, self.structure)

    @staticmethod
    def hits(result: rt.IntersectionResult) -> Hits:
        """The result's distances and primitive ids on the host."""
        return Hits(np.asarray(result.distance), np.asarray(result.primitive_id).astype(np.int64))

    @staticmethod
    def occluded(result: rt.IntersectionResult) -> np.ndarray:
        """Whether each ray of an any-hit result hit something."""
        return np.asarray(result.primitive_id) >= 0
