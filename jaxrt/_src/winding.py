"""Generalized winding numbers, inside tests and signed distances.

The generalized winding number of a triangle soup at a point (Jacobson, Kavan and Sorkine-Hornung, "Robust
Inside-Outside Segmentation using Generalized Winding Numbers", SIGGRAPH 2013) is the sum of the triangles'
signed solid angles over ``4 pi`` (:func:`~jaxrt._src.primitives.point_triangle.solid_angle`): 1 inside a
closed counterclockwise-outward mesh, 0 outside, and close to those values across small holes, so
``w >= 1/2`` is a robust inside test. A bounding-box primitive counts as a closed solid: 1 inside it.

The exact sum costs one solid angle per triangle and point. The fast evaluation follows Barill, Dickson,
Schmidt, Levin and Jacobson, "Fast Winding Numbers for Soups and Clouds", SIGGRAPH 2018: a walk of the BVH
per point that replaces a subtree whose box is far from the point (distance to the box centre greater than
``beta`` times the box's half diagonal) by its first-order dipole term
``N . (c - p) / (4 pi |c - p|^3)``, ``N`` the subtree's area-weighted normal sum and ``c`` its
area-weighted centroid, and sums exact solid angles at the leaves it reaches (the distance test uses the
radius from ``c`` to the farthest corner of the subtree's box). A closed box primitive has no dipole (its far field is
0). Every internal node of the LBVH covers a contiguous range of leaves, so every node's sums are a
difference of prefix sums over the leaves in leaf order (computed per block of leaves, so that a small node
does not lose its digits to a large running sum).

The walk here is the portable one; the compiled walks (:mod:`jaxrt._src.traversal.points`) take the same dipoles
and sum the same terms in the same order, and run by default where they cover the structure.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from jaxrt._src.kinds.kind import Kind
from jaxrt._src.kinds.registry import KINDS
from jaxrt._src.point_query import _box_table, check_not_empty, check_points, check_structure, closest_point, run_flat
from jaxrt._src.point_traversal import in_morton_order, lanes_for_backend, walk_points
from jaxrt._src.primitives import point_triangle as geo
from jaxrt._src.structures import PrimitiveAccelerationStructure
from jaxrt._src.topology import warn_if_open
from jaxrt._src.traversal import points as points_backend

__all__ = ["winding_number", "signed_distance", "contains", "range_sums"]

_FOUR_PI = 4 * math.pi
#: Leaves per block of the prefix sums of :func:`range_sums`.
_BLOCK = 256
#: Points in flight in the fast walk, and the most (points x leaves) of one exact chunk.
_LANES = 256
_EXACT_CHUNK = 1 << 22


def range_sums(values: jax.Array, first: jax.Array, last: jax.Array) -> jax.Array:
    """``values[first:last + 1].sum(0)`` for every pair of ``first``/``last`` (inclusive leaf ranges).

    Prefix sums within blocks of leaves and over whole blocks: a range within one block or across one
    boundary reads only sums of its own blocks, so its rounding error scales with a block, not the array.
    """
    n = values.shape[0]
    block = min(_BLOCK, n)
    blocks = n // block
    shaped = values.reshape(blocks, block, -1)
    inclusive = jnp.cumsum(shaped, axis=1)
    exclusive = inclusive - shaped
    totals = inclusive[:, -1]
    block_prefix = jnp.cumsum(totals, axis=0) - totals  # sum of the blocks before each block
    inclusive, exclusive = inclusive.reshape(n, -1), exclusive.reshape(n, -1)
    bf, bl = first // block, last // block
    same = bf == bl
    adjacent = bl == bf + 1
    # Whole blocks strictly between: a difference of block prefixes.
    middle = block_prefix[bl] - block_prefix[jnp.minimum(bf + 1, blocks - 1)]
    middle = jnp.where(adjacent[:, None] | same[:, None], 0, middle)
    tail = totals[bf] - exclusive[first]  # from first to the end of its block
    spanning = tail + middle + inclusive[last]
    within = inclusive[last] - exclusive[first]
    return jnp.where(same[:, None], within, spanning)


class _Dipoles(NamedTuple):
    normal: jax.Array  # (M, 2, 3) area-weighted normal sum of each child subtree
    center: jax.Array  # (M, 2, 3) its area-weighted centroid (the box centre without area)
    reach2: jax.Array  # (M, 2) (beta * radius)^2, radius: from the centre to the farthest corner of the box


def _dipoles(structure: PrimitiveAccelerationStructure, beta: float) -> _Dipoles:
    tri = structure.leaf_triangle
    normals = 0.5 * jnp.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # zero for non-triangle leaves
    for _, solid in _solid_leaves(structure):  # a solid's row is no triangle: solids count near the point only
        normals = jnp.where(solid[:, None], 0.0, normals)
    area = jnp.sqrt(jnp.sum(normals * normals, axis=-1, keepdims=True))
    lower, upper = structure.node_lower, structure.node_upper
    finite = jnp.all(lower <= upper, axis=-1, keepdims=True)
    mid = 0.5 * (jnp.min(lower[0], axis=0) + jnp.max(upper[0], axis=0))  # centroids relative to the root box
    mid = jnp.where(jnp.isfinite(mid), mid, 0)
    weighted = area * (jnp.mean(tri, axis=1) - mid)
    children = structure.node_children
    internal = children >= 0
    leaf = -1 - children
    child = jnp.maximum(children, 0)
    last_leaf = tri.shape[0] - 1
    first = jnp.clip(jnp.where(internal, structure.node_range[child, 0], leaf), 0, last_leaf)
    last = jnp.clip(jnp.where(internal, structure.node_range[child, 1], leaf), 0, last_leaf)
    last = jnp.maximum(last, first)
    values = jnp.concatenate([normals, area, weighted], axis=-1)
    sums = range_sums(values, first.reshape(-1), last.reshape(-1)).reshape(children.shape + (7,))
    total_area = sums[..., 3:4]
    box_center = jnp.where(finite, 0.5 * (lower + upper), 0)
    has_area = total_area > 0
    center = jnp.where(has_area, sums[..., 4:] / jnp.where(has_area, total_area, 1) + mid, box_center)
    center = jnp.where(finite, jnp.clip(center, lower, upper), 0)
    corner = jnp.where(finite, jnp.maximum(upper - center, center - lower), 0)
    return _Dipoles(sums[..., :3], center, beta * beta * jnp.sum(corner * corner, axis=-1))


def _solid_leaves(structure: PrimitiveAccelerationStructure) -> tuple[tuple[Kind, jax.Array], ...]:
    """``(kind, (C,) whether each leaf is of the kind)`` of each kind present that counts as a solid
    (:attr:`~jaxrt._src.kinds.kind.Kind.inside`: spheres)."""
    solids = []
    for kind in KINDS:
        if kind.inside is not None and any(kind.holds(g) for g in structure.geometry_info):
            table = jnp.asarray(np.array([kind.holds(g) for g in structure.geometry_info] + [False]))
            solids.append((kind, table[jnp.where(structure.leaf_geometry < 0, -1, structure.leaf_geometry)]))
    return tuple(solids)


def _leaf_winding(structure, box_table, p: jax.Array, leaf: jax.Array) -> jax.Array:
    """Winding number of leaf ``leaf``'s primitive at ``p``: a solid angle, or 1 inside a box primitive or a
    solid (a sphere)."""
    w = geo.solid_angle(p, structure.leaf_triangle[leaf]) / _FOUR_PI
    geometry = structure.leaf_geometry[leaf]
    for kind, solid in _solid_leaves(structure):
        inside = kind.inside(p, getattr(structure, kind.leaf_arrays[0].name)[leaf])
        w = jnp.where(solid[leaf], inside.astype(w.dtype), w)
    w = jnp.where(geometry < 0, 0, w)
    if box_table is not None:
        box = structure.leaf_box[leaf]
        inside = jnp.all((p >= box[0]) & (p <= box[1]))
        w = jnp.where(box_table[jnp.where(geometry < 0, -1, geometry)], inside.astype(w.dtype), w)
    return w


class _State(NamedTuple):
    stack: jax.Array
    size: jax.Array
    total: jax.Array


def _fast_walk(structure: PrimitiveAccelerationStructure, box_table, dipoles: _Dipoles):
    stack_size = structure.max_depth + 1
    children = structure.node_children

    def start(p):
        return _State(jnp.zeros((stack_size,), jnp.int32), jnp.int32(1), jnp.zeros((), p.dtype))

    def step(p, s: _State) -> _State:
        live = s.size > 0
        top = jnp.maximum(s.size - 1, 0)
        node = s.stack[top]
        size = top
        total = s.total
        stack = s.stack
        kids = children[node]
        offset = dipoles.center[node] - p  # (2, 3)
        dist2 = jnp.sum(offset * offset, axis=-1)
        far = dist2 > dipoles.reach2[node]
        safe = jnp.where(far, dist2, 1)
        dipole = jnp.sum(dipoles.normal[node] * offset, axis=-1) / (_FOUR_PI * safe * jnp.sqrt(safe))
        for j in range(2):
            is_leaf = kids[j] < 0
            exact = _leaf_winding(structure, box_table, p, jnp.where(is_leaf, -1 - kids[j], 0))
            add = jnp.where(is_leaf, exact, jnp.where(far[j], dipole[j], 0))
            total = total + jnp.where(live, add, 0)
            push = live & ~is_leaf & ~far[j]
            stack = stack.at[jnp.where(push, size, stack_size)].set(kids[j], mode="drop")
            size = size + push
        return _State(stack, size, total)

    return start, step, lambda s: s.size == 0


@functools.partial(jax.jit, static_argnames=("exact", "beta", "backend"))
def _winding_flat(
    points: jax.Array, structure: PrimitiveAccelerationStructure, *, exact: bool, beta: float, backend: str
):
    structure = lax.stop_gradient(structure)
    points = lax.stop_gradient(points)
    table = _box_table(structure)
    if backend == "cpu":
        if exact:
            return points_backend.cpu_exact_winding(points, structure, table)
        return points_backend.cpu_winding(points, structure, table, _dipoles(structure, beta))
    if backend == "gpu":
        if exact:
            return points_backend.gpu_exact_winding(points, structure, table)
        dipoles = _dipoles(structure, beta)
        return in_morton_order(lambda p: points_backend.gpu_winding(p, structure, table, dipoles), points)
    if exact:
        leaves = jnp.arange(structure.capacity)
        per_point = jax.vmap(lambda p: jnp.sum(jax.vmap(lambda k: _leaf_winding(structure, table, p, k))(leaves)))
        chunk = max(1, min(points.shape[0], _EXACT_CHUNK // structure.capacity))
        n = points.shape[0]
        chunks = -(-n // chunk)
        padded = jnp.concatenate([points, jnp.zeros((chunks * chunk - n, 3), points.dtype)])
        return lax.map(per_point, padded.reshape(chunks, chunk, 3)).reshape(-1)[:n]
    start, step, done = _fast_walk(structure, table, _dipoles(structure, beta))
    return walk_points(points, start, step, done, lambda s: s.total, lanes=lanes_for_backend(_LANES))


def _check_options(name: str, beta: float) -> float:
    beta = float(beta)
    if not beta > 0 or not math.isfinite(beta):
        raise ValueError(f"{name}: beta must be positive and finite, got {beta}")
    return beta


def winding_number(
    points: jax.Array,
    structure: PrimitiveAccelerationStructure,
    *,
    exact: bool = False,
    beta: float = 2.0,
    backend: str = "auto",
) -> jax.Array:
    """The generalized winding number of the structure's surface at each point (Jacobson et al. 2013).

    About 1 inside a closed mesh whose triangles wind counterclockwise seen from outside, 0 outside, -1
    inside an inward-facing one; a bounding-box primitive adds 1 inside it. Not differentiated (a constant
    for gradients).

    Args:
      points: ``(..., 3)`` finite points.
      structure: a :class:`~jaxrt.PrimitiveAccelerationStructure` of triangles and boxes (instances and
        curves raise ``NotImplementedError``).
      exact: sum every triangle's solid angle (Van Oosterom and Strackee 1983; one per triangle and point)
        instead of the hierarchical approximation of Barill et al. 2018 (the default, much faster).
      beta: the approximation's accuracy: a subtree is replaced by its dipole when the point is farther than
        ``beta`` half diagonals from its box centre (larger: more accurate and slower).
      backend: the walk: ``"auto"``, ``"portable"``, ``"cpu"`` or ``"gpu"``, as for
        :func:`~jaxrt.closest_point`.

    Returns:
      ``float`` array of the points' batch shape.

    Examples:
      >>> import jaxrt as rt
      >>> vertices = [[1., 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]
      >>> faces = [[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]]
      >>> s = rt.build_primitive_structure(rt.TriangleGeometry(vertices, faces))  # an octahedron
      >>> [round(float(w), 2) + 0.0 for w in rt.winding_number([[0., 0, 0], [3., 0, 0]], s)]
      [1.0, 0.0]
    """
    return _winding(points, structure, exact, beta, "winding_number", backend)


def _winding(points, structure, exact: bool, beta: float, name: str, backend: str) -> jax.Array:
    structure = check_structure(structure, name)
    walk = points_backend.resolve(backend, structure, name)
    check_not_empty(structure, name)
    beta = _check_options(name, beta)
    points = lax.stop_gradient(check_points(points, name, structure.leaf_triangle.dtype))
    return run_flat(_winding_flat, points, lax.stop_gradient(structure), exact=bool(exact), beta=beta, backend=walk)


def contains(
    points: jax.Array,
    structure: PrimitiveAccelerationStructure,
    *,
    exact: bool = False,
    beta: float = 2.0,
    backend: str = "auto",
) -> jax.Array:
    """Whether each point is inside the structure's surface: winding number ``>= 1/2`` (robust to small
    holes and self-intersections; see :func:`winding_number` for the arguments).

    Meaningful for closed surfaces (:func:`~jaxrt.is_closed`): both sides of an open one (a quad, a terrain)
    read as outside. Warns once per open structure (outside ``jit``).

    Examples:
      >>> import jaxrt as rt
      >>> vertices = [[1., 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]
      >>> faces = [[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]]
      >>> s = rt.build_primitive_structure(rt.TriangleGeometry(vertices, faces))  # an octahedron
      >>> rt.contains([[0., 0, 0], [3., 0, 0]], s).tolist()
      [True, False]
    """
    warn_if_open(check_structure(structure, "contains"), "contains")
    return _winding(points, structure, exact, beta, "contains", backend) >= 0.5


def signed_distance(
    points: jax.Array,
    structure: PrimitiveAccelerationStructure,
    *,
    exact: bool = False,
    beta: float = 2.0,
    backend: str = "auto",
) -> jax.Array:
    """The distance from each point to the structure's nearest primitive (:func:`~jaxrt.closest_point`),
    negative inside (winding number ``>= 1/2``, :func:`winding_number`).

    Differentiable with respect to the points and the vertices (the sign is held fixed). The sign needs a
    closed surface (:func:`~jaxrt.is_closed`): near an open one (a quad) it is positive on both sides. Warns
    once per open structure (outside ``jit``).

    Examples:
      >>> import jaxrt as rt
      >>> vertices = [[1., 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]
      >>> faces = [[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]]
      >>> s = rt.build_primitive_structure(rt.TriangleGeometry(vertices, faces))  # an octahedron
      >>> [round(float(d), 3) for d in rt.signed_distance([[0., 0, 0], [3., 0, 0]], s)]
      [-0.577, 2.0]
    """
    warn_if_open(check_structure(structure, "signed_distance"), "signed_distance")
    inside = _winding(points, structure, exact, beta, "signed_distance", backend) >= 0.5
    distance = closest_point(points, structure, backend=backend).distance
    return jnp.where(inside, -distance, distance)
