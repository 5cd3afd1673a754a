"""jaxrt: a purely functional ray tracer in JAX, after Metal's ray tracing API.

Examples:
  >>> import jaxrt as rt
  >>> geometry = rt.TriangleGeometry([[0., 0, 0], [1, 0, 0], [0, 1, 0]])
  >>> structure = rt.build_primitive_structure(geometry)
  >>> result = rt.Intersector().intersect(rt.Ray([.25, .25, 1], [0., 0, -1]), structure)
  >>> int(result.type) == rt.IntersectionType.TRIANGLE, float(result.distance)
  (True, 1.0)
"""

# First, before any jax computation: warns on an untested jax and works around known defects of tested ones.
from jaxrt._src import versions as _versions  # noqa: F401

# isort: split
from jaxrt import debug, intersection_functions, io, shading, tags, visibility
from jaxrt._src.candidate import BoundingBoxCandidate, TriangleCandidate
from jaxrt._src.checks import BuildCheckError, build_check_errors
from jaxrt._src.compaction import compact
from jaxrt._src.curves import CurveBasis, CurveEndCaps, CurveGeometry, CurveType, MotionCurveGeometry
from jaxrt._src.geometry import BoundingBoxGeometry, MotionBoundingBoxGeometry, MotionTriangleGeometry, TriangleGeometry
from jaxrt._src.instances import (
    InstanceAccelerationStructure,
    InstanceOptions,
    Instances,
    build_instance_structure,
)
from jaxrt._src.intersector import Intersector, count_intersections
from jaxrt._src.io.structure_file import load, save
from jaxrt._src.motion import MotionSpec
from jaxrt._src.numerics import offset_ray_origin
from jaxrt._src.pixel_integral import pixel_integral
from jaxrt._src.point_query import ClosestPointResult, closest_point
from jaxrt._src.prepacked import build_primitive_structure, refit
from jaxrt._src.primitives.curve import CurveOptions
from jaxrt._src.query import IntersectionQuery, intersection_query
from jaxrt._src.ray import Ray
from jaxrt._src.result import IntersectionResult, IntersectionType
from jaxrt._src.sdf_grid import sdf_grid
from jaxrt._src.sharding import device_mesh, intersect_sharded, replicate
from jaxrt._src.sizes import StructureSizes, sah_cost, structure_sizes
from jaxrt._src.spheres import MotionSphereGeometry, SphereGeometry
from jaxrt._src.structures import PrimitiveAccelerationStructure
from jaxrt._src.topology import boundary_edge_count, is_closed
from jaxrt._src.visibility import DirectionalLight, PinholeCamera, PointLight, SilhouetteMesh
from jaxrt._src.winding import contains, signed_distance, winding_number
from jaxrt._src.worlds import update_worlds, worlds_capacity

__version__ = _versions.VERSION

__all__ = [
    "BoundingBoxCandidate",
    "BuildCheckError",
    "BoundingBoxGeometry",
    "ClosestPointResult",
    "CurveBasis",
    "CurveEndCaps",
    "CurveGeometry",
    "CurveOptions",
    "CurveType",
    "DirectionalLight",
    "InstanceAccelerationStructure",
    "InstanceOptions",
    "Instances",
    "IntersectionQuery",
    "IntersectionResult",
    "IntersectionType",
    "Intersector",
    "MotionBoundingBoxGeometry",
    "MotionCurveGeometry",
    "MotionSpec",
    "MotionSphereGeometry",
    "MotionTriangleGeometry",
    "PinholeCamera",
    "PointLight",
    "PrimitiveAccelerationStructure",
    "Ray",
    "SilhouetteMesh",
    "SphereGeometry",
    "StructureSizes",
    "TriangleCandidate",
    "TriangleGeometry",
    "boundary_edge_count",
    "build_check_errors",
    "build_instance_structure",
    "build_primitive_structure",
    "closest_point",
    "compact",
    "contains",
    "count_intersections",
    "debug",
    "device_mesh",
    "intersect_sharded",
    "intersection_functions",
    "intersection_query",
    "io",
    "is_closed",
    "load",
    "offset_ray_origin",
    "pixel_integral",
    "refit",
    "replicate",
    "sah_cost",
    "save",
    "shading",
    "sdf_grid",
    "signed_distance",
    "structure_sizes",
    "tags",
    "update_worlds",
    "visibility",
    "winding_number",
    "worlds_capacity",
]
