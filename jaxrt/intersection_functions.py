"""Analytic intersection functions for ``rt.BoundingBoxGeometry``: sphere, disk, capped cylinder, and their bounds.

Examples:
  >>> import jaxrt as rt
  >>> lower, upper = rt.intersection_functions.sphere_bounds([[0., 0, 0]], [1.0])
  >>> lower.tolist(), upper.tolist()
  ([[-1.0, -1.0, -1.0]], [[1.0, 1.0, 1.0]])
"""

from jaxrt._src.primitives.analytic import (
    capped_cylinder,
    capped_cylinder_bounds,
    disk,
    disk_bounds,
    sphere,
    sphere_bounds,
)

__all__ = ["capped_cylinder", "capped_cylinder_bounds", "disk", "disk_bounds", "sphere", "sphere_bounds"]
