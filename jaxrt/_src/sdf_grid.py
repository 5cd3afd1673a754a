"""A dense grid of signed distances: :func:`sdf_grid`."""

from __future__ import annotations

import functools
import math
import warnings
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from jaxrt._src.point_query import check_not_empty, check_structure
from jaxrt._src.structures import PrimitiveAccelerationStructure
from jaxrt._src.topology import warn_if_open
from jaxrt._src.winding import signed_distance

__all__ = ["sdf_grid"]

#: Grid points per step of the loop over the grid (whole planes of the first axis at a time).
STEP_POINTS = 1 << 20


def _resolution(resolution: int | Sequence[int]) -> tuple[int, int, int]:
    values = (resolution,) * 3 if isinstance(resolution, (int, np.integer)) else tuple(resolution)
    if len(values) != 3 or not all(isinstance(r, (int, np.integer)) and int(r) >= 2 for r in values):
        raise ValueError(f"sdf_grid: resolution must be an integer >= 2 or three of them, got {resolution!r}")
    return tuple(int(r) for r in values)


def sdf_grid(
    structure: PrimitiveAccelerationStructure,
    bounds,
    resolution: int | Sequence[int],
    *,
    beta: float = 2.0,
    backend: str = "auto",
) -> jax.Array:
    """The signed distance (:func:`~jaxrt.signed_distance`) at every point of a regular grid.

    Grid point ``(i, j, k)`` is ``lower + (upper - lower) * (i, j, k) / (resolution - 1)``: the corners of
    ``bounds`` are grid points. The grid is walked a few planes of the first axis at a time (about a million
    points a step), so the query points are never all in memory at once.

    Args:
      structure: a :class:`~jaxrt.PrimitiveAccelerationStructure` of triangles and boxes (closed, for a
        meaningful sign).
      bounds: ``(lower, upper)`` corners, ``(2, 3)``, finite, ``lower <= upper``.
      resolution: grid points along each axis (an integer for all three, or three integers), each ``>= 2``.
      beta: the fast winding number's accuracy (:func:`~jaxrt.winding_number`).
      backend: the walk (:func:`~jaxrt.closest_point`).

    Returns:
      ``(rx, ry, rz)`` signed distances in the structure's float type: negative inside.

    Examples:
      >>> import jaxrt as rt
      >>> vertices = [[1., 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]
      >>> faces = [[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]]
      >>> s = rt.build_primitive_structure(rt.TriangleGeometry(vertices, faces))  # an octahedron
      >>> grid = rt.sdf_grid(s, [[-2., -2, -2], [2, 2, 2]], 5)
      >>> grid.shape, round(float(grid[2, 2, 2]), 3), round(float(grid[0, 2, 2]), 3)
      ((5, 5, 5), -0.577, 1.0)
    """
    structure = check_structure(structure, "sdf_grid")
    rx, ry, rz = _resolution(resolution)
    dtype = structure.leaf_triangle.dtype
    corners = np.asarray(bounds, np.float64)
    if corners.shape != (2, 3) or not np.isfinite(corners).all() or (corners[0] > corners[1]).any():
        raise ValueError(
            f"sdf_grid: bounds must be finite (lower, upper) corners (2, 3), lower <= upper; got {bounds!r}"
        )
    check_not_empty(structure, "sdf_grid")
    warn_if_open(structure, "sdf_grid")
    axes = [jnp.asarray(np.linspace(corners[0, a], corners[1, a], r), dtype) for a, r in enumerate((rx, ry, rz))]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # warned above, once, as sdf_grid
        return _grid(structure, *axes, beta=float(beta), backend=backend, step_points=STEP_POINTS)


@functools.partial(jax.jit, static_argnames=("beta", "backend", "step_points"))
def _grid(
    structure, xs: jax.Array, ys: jax.Array, zs: jax.Array, *, beta: float, backend: str, step_points: int
) -> jax.Array:
    """The grid over the axes' coordinates, a few planes of the first axis a step."""
    rx, ry, rz = xs.shape[0], ys.shape[0], zs.shape[0]
    planes = max(1, min(rx, step_points // (ry * rz)))
    steps = math.ceil(rx / planes)
    yz = jnp.stack(jnp.meshgrid(ys, zs, indexing="ij"), axis=-1)  # (ry, rz, 2)

    def step(first):
        x = xs[jnp.minimum(first + jnp.arange(planes), rx - 1)]  # the last step repeats the last plane
        points = jnp.concatenate(
            [jnp.broadcast_to(x[:, None, None, None], (planes, ry, rz, 1)), jnp.broadcast_to(yz, (planes, ry, rz, 2))],
            axis=-1,
        )
        return signed_distance(points, structure, beta=beta, backend=backend)

    out = lax.map(step, jnp.arange(steps, dtype=jnp.int32) * planes)
    return out.reshape(steps * planes, ry, rz)[:rx]
