"""Small, differentiable shading helpers for rendering experiments.

Camera rays, hit points, geometric and interpolated normals, per-vertex attributes and textures at hits,
Lambert, Phong and Blinn-Phong shading, ambient occlusion and a one-bounce diffuse estimator.

All are plain JAX functions (jit/vmap/grad friendly) on arrays of any batch shape; randomness comes from an
explicit ``jax.random`` key, so a fixed key gives a fixed (differentiable) noise pattern. Gradients of
anything computed from hits hold the hit primitive fixed: see ``docs/differentiable.md``.

Conventions: directions "towards the light" and "towards the viewer" point away from the surface; normals
are unit vectors; barycentrics are ``(u, v)`` with ``point = (1 - u - v) v0 + u v1 + v v2`` (the
intersector's ``triangle_barycentric_coord``); misses (``primitive_id == -1``) give zeros, never NaN, except
:func:`hit_points`, whose misses are ``inf`` (a value no hit point has). Helpers that read a hit's triangle
take one geometry's arrays, or one array per geometry with the hits' ``geometry_id``.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxrt import tags
from jaxrt._src.intersector import Intersector
from jaxrt._src.numerics import offset_ray_origin
from jaxrt._src.ray import Ray
from jaxrt._src.result import IntersectionResult
from jaxrt._src.structures import PrimitiveAccelerationStructure

__all__ = [
    "pinhole_rays",
    "hit_points",
    "triangle_normals",
    "vertex_normals",
    "interpolate",
    "interpolate_normals",
    "texture_lookup",
    "face_forward",
    "lambert",
    "phong",
    "blinn_phong",
    "cosine_hemisphere",
    "ambient_occlusion",
    "one_bounce_diffuse",
]


def _normalize(v: jax.Array) -> jax.Array:
    # The epsilon keeps the gradient finite for zero vectors.
    return v / jnp.sqrt(jnp.sum(v * v, axis=-1, keepdims=True) + 1e-30)


def _dot(a: jax.Array, b: jax.Array) -> jax.Array:
    return jnp.sum(a * b, axis=-1)


def _safe_power(x: jax.Array, exponent: Any) -> jax.Array:
    """``max(x, 0) ** exponent`` whose gradient is 0 (not NaN) where ``x <= 0``, also w.r.t. the exponent.

    Prevents: the NaN of ``0 ** s * log(0)`` (the derivative with respect to ``s`` at ``x = 0``) and the
    ``inf`` of ``s * 0 ** (s - 1)`` for ``s < 1``.
    """
    positive = x > 0
    return jnp.where(positive, jnp.where(positive, x, 1.0) ** exponent, 0.0)


def pinhole_rays(
    width: int,
    height: int,
    *,
    eye,
    target,
    up=(0.0, 1.0, 0.0),
    fov_degrees: float = 45.0,
    key: jax.Array | None = None,
) -> Ray:
    """Primary rays of a pinhole camera, one per pixel, in scanline order (shape ``(height, width)``).

    Args:
      width, height: image size in pixels (static).
      eye, target, up: camera position, the point it looks at, and the up direction.
      fov_degrees: vertical field of view.
      key: optional ``jax.random`` key; when given, each ray goes through a uniformly jittered point of its
        pixel instead of the pixel centre (antialiasing).

    Returns:
      A :class:`~jaxrt.Ray` batch with unit directions; row 0 is the top of the image. The rays are
      differentiable with respect to ``eye``, ``target`` and ``up``.

    Examples:
      >>> import jaxrt as rt
      >>> rays = rt.shading.pinhole_rays(4, 3, eye=(0, 0, 5), target=(0, 0, 0))
      >>> rays.shape, [round(float(x), 3) for x in rays.direction[1, 2]]
      ((3, 4), [0.137, 0.0, -0.991])
    """
    eye = jnp.asarray(eye, jnp.float32)
    forward = _normalize(jnp.asarray(target, jnp.float32) - eye)
    right = _normalize(jnp.cross(forward, jnp.asarray(up, jnp.float32)))
    true_up = jnp.cross(right, forward)
    offset = jnp.full((height, width, 2), 0.5, jnp.float32)
    if key is not None:
        offset = jax.random.uniform(key, (height, width, 2), jnp.float32)
    ys, xs = jnp.meshgrid(jnp.arange(height, dtype=jnp.float32), jnp.arange(width, dtype=jnp.float32), indexing="ij")
    scale = jnp.tan(jnp.deg2rad(fov_degrees) * 0.5)
    px = (2.0 * (xs + offset[..., 0]) / width - 1.0) * scale * (width / height)
    py = (1.0 - 2.0 * (ys + offset[..., 1]) / height) * scale
    direction = _normalize(forward + px[..., None] * right + py[..., None] * true_up)
    return Ray(jnp.broadcast_to(eye, direction.shape), direction)


def hit_points(rays: Ray, result: IntersectionResult, *, miss_value: Any = jnp.inf) -> jax.Array:
    """``origin + distance * direction`` for hits; ``miss_value`` (``inf`` by default) for misses.

    Misses are marked by a value no hit can have (``jnp.isfinite(points).all(-1)`` is ``result.type != 0``),
    so a miss cannot pass for a real point; no NaN is produced, and the gradient is 0 for misses. Pass
    ``miss_value=0.0`` where the points feed arithmetic that masks misses later (``inf * 0`` is NaN).

    Args:
      rays: the rays that were traced.
      result: their intersection result.
      miss_value: the coordinates of misses (a scalar or ``(3,)``).

    Returns:
      ``(..., 3)`` hit points; their gradient holds the hit primitive fixed.

    Examples:
      >>> import jaxrt as rt
      >>> s = rt.build_primitive_structure(rt.TriangleGeometry([[0., 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]]))
      >>> rays = rt.Ray(jnp.array([[.2, .2, 1], [5, 5, 1]]), jnp.array([[0., 0, -1], [0, 0, -1]]))
      >>> rt.shading.hit_points(rays, rt.Intersector().intersect(rays, s)).tolist()
      [[0.20000000298023224, 0.20000000298023224, 0.0], [inf, inf, inf]]
    """
    hit = result.type != 0
    distance = jnp.where(hit, result.distance, 0.0)
    points = rays.origin + distance[..., None] * rays.direction
    return jnp.where(hit[..., None], points, jnp.asarray(miss_value, points.dtype))


def _is_sequence(value: Any) -> bool:
    return isinstance(value, (list, tuple))


def _concrete(value: Any) -> bool:
    return not isinstance(value, jax.core.Tracer)


def _triangle_corners(
    name: str, per_vertex: Any, indices: Any, primitive_id: Any, geometry_id: Any
) -> tuple[jax.Array, jax.Array]:
    """``(corners, hit)``: ``per_vertex`` values ``(..., 3, ...)`` at the corners of each hit's triangle, and
    whether the hit names a triangle of the given geometries.

    ``per_vertex`` and ``indices`` are one geometry's arrays, or sequences of them indexed by ``geometry_id``
    (the geometries in the order the structure was built from). Lanes whose ``geometry_id`` or ``primitive_id``
    names no given triangle, or a triangle with an index out of range, count as misses.
    """
    primitive_id = jnp.asarray(primitive_id)
    if _is_sequence(per_vertex) != _is_sequence(indices):
        raise TypeError(
            f"{name}: give one geometry's arrays or one sequence per geometry for both the per-vertex values and "
            f"indices, got {type(per_vertex).__name__} and {type(indices).__name__}"
        )
    if not _is_sequence(indices):
        per_vertex, indices = [per_vertex], [indices]
    if len(per_vertex) != len(indices) or not indices:
        raise ValueError(
            f"{name}: got {len(per_vertex)} per-vertex arrays and {len(indices)} index arrays; give one of each "
            "per geometry"
        )
    geometries = len(indices)
    if geometry_id is None:
        if geometries > 1:
            raise ValueError(
                f"{name}: {geometries} geometries were given but no geometry_id: pass the result's geometry_id so "
                "each hit reads its own geometry's triangle"
            )
        geometry_id = jnp.zeros_like(primitive_id)
    host = np.asarray(geometry_id) if _concrete(geometry_id) else None  # numpy, so that jit traces no max
    if host is not None and host.size and int(host.max()) >= geometries:
        raise ValueError(
            f"{name}: geometry_id holds {int(host.max())} but only {geometries} geometr"
            f"{'y was' if geometries == 1 else 'ies were'} given; pass sequences of every geometry's arrays "
            "(in the order the structure was built from)"
        )
    geometry_id = jnp.broadcast_to(jnp.asarray(geometry_id, jnp.int32), primitive_id.shape)
    per_vertex = [jnp.asarray(a) for a in per_vertex]
    indices = [jnp.asarray(i, jnp.int32) for i in indices]
    counts = np.array([i.shape[0] for i in indices])
    first_triangle = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int32)
    first_vertex = np.concatenate([[0], np.cumsum([a.shape[0] for a in per_vertex])[:-1]]).astype(np.int32)
    all_values = per_vertex[0] if geometries == 1 else jnp.concatenate(per_vertex)
    all_indices = jnp.concatenate([i + int(offset) for i, offset in zip(indices, first_vertex, strict=True)])
    g = jnp.clip(geometry_id, 0, geometries - 1)
    hit = (primitive_id >= 0) & (geometry_id >= 0) & (geometry_id < geometries)
    hit &= primitive_id < jnp.asarray(counts, jnp.int32)[g]
    triangle = jnp.where(hit, jnp.asarray(first_triangle)[g] + primitive_id, 0)
    # A corner index outside its own geometry's vertices (traced indices) would read another geometry's or a
    # clamped vertex: such a triangle counts as a miss.
    vertex_count = jnp.asarray([a.shape[0] for a in per_vertex], jnp.int32)
    local = jnp.concatenate(indices)[triangle]
    hit &= jnp.all((local >= 0) & (local < vertex_count[g][..., None]), axis=-1)
    corner = jnp.where(hit[..., None], all_indices[triangle], 0)
    return all_values[corner], hit


def triangle_normals(
    vertices: Any, indices: Any, primitive_id: jax.Array, geometry_id: jax.Array | None = None
) -> jax.Array:
    """Unit geometric normals ``normalize(cross(v1 - v0, v2 - v0))`` of the hit triangles (misses give 0).

    (``rt.tags.normal`` gives the same normal in the result, through instances too.)

    Args:
      vertices: ``(V, 3)`` vertex positions of one geometry, or a sequence of them, one per geometry in the
        order the structure was built from.
      indices: ``(T, 3)`` vertex indices of that geometry's triangles, or a sequence of them (as ``vertices``).
      primitive_id: ``(...)`` triangle index per hit within its geometry, -1 for a miss.
      geometry_id: ``(...)`` the hits' ``geometry_id``; needed with several geometries (a primitive id alone
        does not say which geometry's triangle it is).

    Returns:
      ``(..., 3)`` unit normals (0 for misses, zero-area triangles, ids naming no given triangle and
      triangles with an index out of range).

    Raises:
      ValueError: several geometries without ``geometry_id``, or (outside ``jit``) a ``geometry_id`` past the
        geometries given.

    Examples:
      >>> import jaxrt as rt
      >>> a = (jnp.array([[0., 0, 0], [1, 0, 0], [0, 1, 0]]), jnp.array([[0, 1, 2]]))
      >>> b = (jnp.array([[0., 0, 0], [0, 1, 0], [1, 0, 0]]), jnp.array([[0, 1, 2]]))
      >>> rt.shading.triangle_normals([a[0], b[0]], [a[1], b[1]], jnp.array([0, 0, -1]), jnp.array([0, 1, -1]))
      Array([[ 0.,  0.,  1.],
             [ 0.,  0., -1.],
             [ 0.,  0.,  0.]], dtype=float32)
    """
    tri, hit = _triangle_corners("triangle_normals", vertices, indices, primitive_id, geometry_id)
    n = _normalize(jnp.cross(tri[..., 1, :] - tri[..., 0, :], tri[..., 2, :] - tri[..., 0, :]))
    return jnp.where(hit[..., None], n, 0.0)


def vertex_normals(vertices: jax.Array, indices: jax.Array) -> jax.Array:
    """Smooth per-vertex normals: the area-weighted mean of the normals of the triangles around each vertex.

    Interpolate them at hits with :func:`interpolate` and renormalise for smooth (Phong) shading normals.

    Args:
      vertices: ``(V, 3)`` vertex positions.
      indices: ``(T, 3)`` vertex indices; the winding decides the side the normals point to.

    Returns:
      ``(V, 3)`` unit normals (0 for vertices used by no triangle). Differentiable in ``vertices``.

    Examples:
      >>> import jaxrt as rt
      >>> n = rt.shading.vertex_normals(jnp.array([[0., 0, 0], [1, 0, 0], [0, 1, 0]]), jnp.array([[0, 1, 2]]))
      >>> n.tolist()
      [[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]
    """
    vertices = jnp.asarray(vertices)
    indices = jnp.asarray(indices)
    # triangles with an index out of range (traced indices) add nothing, rather than a clamped or wrapped face
    in_range = jnp.all((indices >= 0) & (indices < vertices.shape[0]), axis=-1)
    indices = jnp.where(in_range[:, None], indices, 0)
    tri = vertices[indices]
    face = jnp.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # length = twice the area
    face = jnp.where(in_range[:, None], face, 0.0)
    summed = jnp.zeros_like(vertices).at[indices.reshape(-1)].add(jnp.repeat(face, 3, axis=0))
    return _normalize(summed)


def interpolate(
    attribute: Any,
    indices: Any,
    primitive_id: jax.Array,
    barycentrics: jax.Array,
    geometry_id: jax.Array | None = None,
) -> jax.Array:
    """A per-vertex attribute at hits: ``(1 - u - v) a[i0] + u a[i1] + v a[i2]`` of the hit triangle.

    Args:
      attribute: ``(V,)`` or ``(V, C)`` values per vertex (normals, UVs, colours, ...) of one geometry, or a
        sequence of them, one per geometry in the order the structure was built from (same trailing shape).
      indices: ``(T, 3)`` vertex indices of the triangles (the geometry's ``indices``), or a sequence of them.
      primitive_id: ``(...)`` triangle index per hit within its geometry, -1 for a miss.
      barycentrics: ``(..., 2)`` the hit's ``triangle_barycentric_coord``.
      geometry_id: ``(...)`` the hits' ``geometry_id``; needed with several geometries.

    Returns:
      ``(...)`` or ``(..., C)`` interpolated values, 0 for misses (and ids naming no given triangle or a
      triangle with an index out of range).
      Differentiable with respect to ``attribute`` and ``barycentrics`` (and so, through the intersector, to
      vertices and rays).

    Raises:
      ValueError: several geometries without ``geometry_id``, or (outside ``jit``) a ``geometry_id`` past the
        geometries given.

    Examples:
      >>> import jaxrt as rt
      >>> uv = jnp.array([[0., 0], [1, 0], [0, 1]])
      >>> rt.shading.interpolate(uv, jnp.array([[0, 1, 2]]), jnp.array([0, -1]), jnp.array([[.25, .5], [.3, .3]]))
      Array([[0.25, 0.5 ],
             [0.  , 0.  ]], dtype=float32)
    """
    return _interpolate("interpolate", attribute, indices, primitive_id, barycentrics, geometry_id)


def _interpolate(name, attribute, indices, primitive_id, barycentrics, geometry_id):
    corners, hit = _triangle_corners(name, attribute, indices, primitive_id, geometry_id)
    barycentrics = jnp.asarray(barycentrics)
    u, v = barycentrics[..., 0], barycentrics[..., 1]
    weights = jnp.stack([1.0 - u - v, u, v], axis=-1).astype(corners.dtype)
    if corners.ndim == hit.ndim + 1:  # one value per vertex
        return jnp.where(hit, jnp.sum(weights * corners, axis=-1), 0.0)
    value = jnp.sum(weights[..., None] * corners, axis=-2)
    return jnp.where(hit.reshape(*hit.shape, *([1] * (corners.ndim - hit.ndim - 1))), value, 0.0)


def interpolate_normals(
    normals: Any,
    indices: Any,
    primitive_id: jax.Array,
    barycentrics: jax.Array,
    geometry_id: jax.Array | None = None,
) -> jax.Array:
    """Smooth shading normals at hits: per-vertex normals interpolated with :func:`interpolate`, renormalised.

    Args:
      normals: ``(V, 3)`` per-vertex normals, e.g. from :func:`vertex_normals`, or a sequence of them, one
        per geometry.
      indices: ``(T, 3)`` vertex indices of the triangles, or a sequence of them.
      primitive_id: ``(...)`` triangle index per hit within its geometry, -1 for a miss.
      barycentrics: ``(..., 2)`` the hit's ``triangle_barycentric_coord``.
      geometry_id: ``(...)`` the hits' ``geometry_id``; needed with several geometries.

    Returns:
      ``(..., 3)`` unit normals; 0 (with zero gradient, not NaN) for misses.

    Examples:
      >>> import jaxrt as rt
      >>> n = jnp.array([[0., 0, 1], [0, 1, 0], [0, 0, 1]])
      >>> rt.shading.interpolate_normals(n, jnp.array([[0, 1, 2]]), jnp.array([0, -1]), jnp.full((2, 2), .5))
      Array([[0.        , 0.70710677, 0.70710677],
             [0.        , 0.        , 0.        ]], dtype=float32)
    """
    return _normalize(_interpolate("interpolate_normals", normals, indices, primitive_id, barycentrics, geometry_id))


def texture_lookup(texture: jax.Array, uv: jax.Array) -> jax.Array:
    """Bilinear texture lookup with clamp-to-edge addressing.

    Texel ``(row, col)`` has its centre at ``uv = ((col + 0.5) / W, (row + 0.5) / H)``: ``u`` runs along
    the width, ``v`` along the height, and row 0 is at ``v = 0``.

    Args:
      texture: ``(H, W)`` or ``(H, W, C)`` texels.
      uv: ``(..., 2)`` texture coordinates, usually in ``[0, 1]``.

    Returns:
      ``(...)`` or ``(..., C)`` filtered values. Differentiable in ``texture`` and in ``uv`` (piecewise
      linear: the gradient in ``uv`` jumps at texel centres and is 0 outside the clamped range).

    Examples:
      >>> import jaxrt as rt
      >>> rt.shading.texture_lookup(jnp.array([[0., 1.], [2., 3.]]), jnp.array([[0.5, 0.5], [0.25, 0.75]]))
      Array([1.5, 2. ], dtype=float32)
    """
    texture = jnp.asarray(texture)
    uv = jnp.asarray(uv, texture.dtype)
    height, width = texture.shape[0], texture.shape[1]
    x = jnp.clip(uv[..., 0] * width - 0.5, 0.0, width - 1.0)
    y = jnp.clip(uv[..., 1] * height - 0.5, 0.0, height - 1.0)
    x0 = jnp.clip(jnp.floor(x).astype(jnp.int32), 0, max(width - 2, 0))
    y0 = jnp.clip(jnp.floor(y).astype(jnp.int32), 0, max(height - 2, 0))
    x1, y1 = jnp.minimum(x0 + 1, width - 1), jnp.minimum(y0 + 1, height - 1)
    fx, fy = x - x0, y - y0
    if texture.ndim == 3:
        fx, fy = fx[..., None], fy[..., None]
    top = texture[y0, x0] * (1.0 - fx) + texture[y0, x1] * fx
    bottom = texture[y1, x0] * (1.0 - fx) + texture[y1, x1] * fx
    return top * (1.0 - fy) + bottom * fy


def face_forward(normals: jax.Array, directions: jax.Array) -> jax.Array:
    """Normals flipped where needed to face against ``directions`` (e.g. towards the camera for primary rays).

    Args:
      normals: ``(..., 3)``.
      directions: ``(..., 3)`` ray directions (from the viewer towards the surface).

    Returns:
      ``(..., 3)`` normals with ``dot(n, direction) <= 0``.
    """
    return jnp.where(_dot(normals, directions)[..., None] > 0, -normals, normals)


def lambert(normals: jax.Array, light_direction: jax.Array, albedo=1.0) -> jax.Array:
    """Lambertian shading ``albedo * max(0, dot(n, l))`` for unit normals and a direction towards the light.

    Args:
      normals: ``(..., 3)`` unit normals.
      light_direction: ``(3,)`` or ``(..., 3)`` direction towards the light (normalised here).
      albedo: scalar or array broadcasting with the batch shape.

    Returns:
      ``(...)`` shading. Differentiable in all arguments (the ``max`` has gradient 0 below the horizon).
    """
    l = _normalize(jnp.asarray(light_direction, normals.dtype))  # noqa: E741
    return albedo * jnp.maximum(jnp.sum(normals * l, axis=-1), 0.0)


def phong(
    normals: jax.Array,
    light_direction: jax.Array,
    view_direction: jax.Array,
    *,
    albedo: Any = 1.0,
    specular: Any = 0.0,
    shininess: Any = 32.0,
) -> jax.Array:
    """Phong shading: ``albedo * max(0, n.l) + specular * max(0, r.v) ** shininess`` with ``r = reflect(-l, n)``.

    The specular lobe is only lit where ``n.l > 0``.

    Args:
      normals: ``(..., 3)`` unit normals.
      light_direction: ``(3,)`` or ``(..., 3)`` direction towards the light (normalised here).
      view_direction: ``(3,)`` or ``(..., 3)`` direction towards the viewer, e.g. ``-rays.direction``
        (normalised here).
      albedo, specular, shininess: scalars or arrays broadcasting with the batch shape; all differentiable
        (the gradient with respect to ``shininess`` is 0, not NaN, where the lobe is 0).

    Returns:
      ``(...)`` shading.

    References:
      Phong, "Illumination for Computer Generated Pictures", CACM 18(6), 1975.

    Examples:
      >>> import jaxrt as rt
      >>> n = jnp.array([0., 0, 1])
      >>> float(rt.shading.phong(n, jnp.array([0., 0, 1]), jnp.array([0., 0, 1]), albedo=.5, specular=.25))
      0.75
    """
    l = _normalize(jnp.asarray(light_direction, normals.dtype))  # noqa: E741
    v = _normalize(jnp.asarray(view_direction, normals.dtype))
    n_dot_l = _dot(normals, l)
    reflected = 2.0 * n_dot_l[..., None] * normals - l
    lobe = jnp.where(n_dot_l > 0, _safe_power(_dot(reflected, v), shininess), 0.0)
    return albedo * jnp.maximum(n_dot_l, 0.0) + specular * lobe


def blinn_phong(
    normals: jax.Array,
    light_direction: jax.Array,
    view_direction: jax.Array,
    *,
    albedo: Any = 1.0,
    specular: Any = 0.0,
    shininess: Any = 32.0,
) -> jax.Array:
    """Blinn-Phong shading: ``albedo * max(0, n.l) + specular * max(0, n.h) ** shininess``, ``h = normalize(l + v)``.

    Arguments and return value as :func:`phong`.

    References:
      Blinn, "Models of Light Reflection for Computer Synthesized Pictures", SIGGRAPH 1977.

    Examples:
      >>> import jaxrt as rt
      >>> n = jnp.array([0., 0, 1])
      >>> round(float(rt.shading.blinn_phong(n, jnp.array([1., 0, 1]), jnp.array([-1., 0, 1]), specular=1.)), 4)
      1.7071
    """
    l = _normalize(jnp.asarray(light_direction, normals.dtype))  # noqa: E741
    v = _normalize(jnp.asarray(view_direction, normals.dtype))
    n_dot_l = _dot(normals, l)
    half = _normalize(l + v)
    lobe = jnp.where(n_dot_l > 0, _safe_power(_dot(normals, half), shininess), 0.0)
    return albedo * jnp.maximum(n_dot_l, 0.0) + specular * lobe


def cosine_hemisphere(key: jax.Array, normals: jax.Array) -> jax.Array:
    """One cosine-weighted direction per normal on the hemisphere around it (Malley's method).

    Args:
      key: ``jax.random`` key.
      normals: ``(..., 3)`` unit normals.

    Returns:
      ``(..., 3)`` unit directions with density ``cos(theta) / pi``; differentiable in ``normals`` for a
      fixed key.
    """
    u = jax.random.uniform(key, (*normals.shape[:-1], 2), normals.dtype)
    r, phi = jnp.sqrt(u[..., 0]), 2.0 * jnp.pi * u[..., 1]
    local = jnp.stack([r * jnp.cos(phi), r * jnp.sin(phi), jnp.sqrt(jnp.maximum(0.0, 1.0 - u[..., 0]))], axis=-1)
    helper = jnp.where(jnp.abs(normals[..., :1]) > 0.9, jnp.array([0.0, 1.0, 0.0]), jnp.array([1.0, 0.0, 0.0]))
    tangent = _normalize(jnp.cross(helper, normals))
    bitangent = jnp.cross(normals, tangent)
    return local[..., :1] * tangent + local[..., 1:2] * bitangent + local[..., 2:] * normals


def ambient_occlusion(
    key: jax.Array,
    structure,
    points: jax.Array,
    normals: jax.Array,
    *,
    samples: int = 8,
    radius: float = jnp.inf,
    valid: jax.Array | None = None,
) -> jax.Array:
    """Ambient occlusion: the fraction of ``samples`` cosine-weighted rays that escape within ``radius``.

    Args:
      key: ``jax.random`` key (fixed key, fixed noise).
      structure: the acceleration structure to occlude against.
      points, normals: ``(..., 3)`` surface points and unit normals facing the viewer.
      samples: rays per point (static).
      radius: occlusion distance.
      valid: optional ``(...)`` bool; invalid points return 0 and trace no ray.

    Returns:
      ``(...)`` visibility in [0, 1] (1: unoccluded). A count of binary visibility tests: its gradient is 0.
    """
    keys = jax.random.split(key, samples)
    directions = jax.vmap(lambda k: cosine_hemisphere(k, normals))(keys)
    origin = offset_ray_origin(points, normals)
    mask = jnp.uint32(0xFFFFFFFF) if valid is None else jnp.where(valid, jnp.uint32(0xFFFFFFFF), jnp.uint32(0))
    rays = Ray(
        jnp.broadcast_to(origin, directions.shape),
        directions,
        0.0,
        radius,
        jnp.broadcast_to(mask, directions.shape[:-1]),
    )
    occluded = Intersector(accept_any_intersection=True).intersect(rays, structure).type != 0
    visibility = 1.0 - jnp.mean(occluded.astype(points.dtype), axis=0)
    return visibility if valid is None else jnp.where(valid, visibility, 0.0)


def one_bounce_diffuse(
    key: jax.Array,
    structure: PrimitiveAccelerationStructure,
    vertices: jax.Array,
    indices: jax.Array,
    points: jax.Array,
    normals: jax.Array,
    *,
    light_direction: jax.Array,
    light_irradiance: Any = 1.0,
    albedo: Any = 0.8,
    vertex_albedo: jax.Array | None = None,
    sky: Any = 0.0,
    samples: int = 4,
    valid: jax.Array | None = None,
) -> jax.Array:
    """Direct light plus one diffuse bounce at ``points``, per unit albedo, for Lambertian surfaces.

    One directional light of irradiance ``E`` (on a surface facing it) and a constant ``sky`` radiance
    illuminate Lambertian surfaces (BRDF ``albedo / pi``). With ``K = samples`` cosine-weighted directions
    ``w_k``, the estimate is

    ``S(x) = E / pi * max(0, n.l) * V(x, l) + 1/K sum_k L(x, w_k)``

    where ``L`` is ``sky`` if the ray escapes and, if it hits a surface point ``y``, that point's direct
    light ``a(y) E / pi * max(0, n_y.l) V(y, l)`` (visibility ``V`` from shadow rays; ``n_y`` is the geometric
    normal facing the bounce ray). The radiance leaving ``x`` is ``a(x) * S(x)``: multiply by the albedo at
    ``x``, which is left to the caller (a texture, an interpolated attribute, ...).

    Args:
      key: ``jax.random`` key for the bounce directions (fixed key, fixed noise, smooth gradients).
      structure: a structure built from one triangle geometry, ``rt.TriangleGeometry(vertices, indices)``.
      vertices, indices: that geometry's arrays, for the normals and albedo at bounce hits.
      points, normals: ``(..., 3)`` surface points and unit normals facing the viewer, e.g. from
        :func:`hit_points` and :func:`face_forward`.
      light_direction: ``(3,)`` direction towards the light (normalised here).
      light_irradiance: the light's irradiance, a scalar or ``(C,)`` colour.
      albedo: the albedo of bounce hits, a scalar or ``(C,)``; ignored when ``vertex_albedo`` is given.
      vertex_albedo: optional ``(V,)`` or ``(V, C)`` per-vertex albedo, interpolated at bounce hits.
      sky: the radiance of escaping rays, a scalar or ``(C,)``.
      samples: bounce rays per point (static).
      valid: optional ``(...)`` bool; invalid points return 0 and trace no ray.

    Returns:
      ``(...)`` or ``(..., C)``: ``S(x)``. Differentiable with respect to every array argument; the hits,
      and so the visibility terms, hold the hit primitives fixed.

    Raises:
      TypeError, ValueError: ``structure`` is not a primitive structure of exactly one geometry.
    """
    if not isinstance(structure, PrimitiveAccelerationStructure):
        raise TypeError(f"one_bounce_diffuse: structure must be a primitive structure, got {type(structure).__name__}")
    if len(structure.geometry_info) != 1:
        raise ValueError(
            f"one_bounce_diffuse: structure must be built from one geometry (vertices, indices), got "
            f"{len(structure.geometry_info)}; concatenate the meshes into one geometry"
        )
    vertices, indices = jnp.asarray(vertices), jnp.asarray(indices)
    points, normals = jnp.asarray(points), jnp.asarray(normals)
    dtype = points.dtype
    irradiance, sky = jnp.asarray(light_irradiance, dtype), jnp.asarray(sky, dtype)
    surface_albedo = jnp.asarray(albedo if vertex_albedo is None else vertex_albedo, dtype)
    albedo_channels = surface_albedo.shape if vertex_albedo is None else surface_albedo.shape[1:]
    channels = np.broadcast_shapes(irradiance.shape, sky.shape, albedo_channels)
    if len(channels) > 1:
        raise ValueError(f"one_bounce_diffuse: colours must be scalars or (C,) arrays, got shape {channels}")
    enabled = jnp.ones(points.shape[:-1], bool) if valid is None else jnp.asarray(valid)
    # The work between the two traversals is jitted in three pieces, so that a call outside jax.jit compiles a
    # few programs (once per shape) instead of every operation.
    bounce = _bounce_rays(key, points, normals, enabled, samples)
    found = Intersector(tags.triangle_data).intersect(bounce, structure)
    shadow = _shadow_rays(found, bounce, vertices, indices, points, normals, enabled, light_direction)
    unoccluded = Intersector(accept_any_intersection=True).intersect(shadow, structure).type == 0
    per_vertex = vertex_albedo is not None
    return _combine(
        found,
        bounce,
        shadow,
        unoccluded,
        vertices,
        indices,
        normals,
        enabled,
        light_direction,
        irradiance,
        sky,
        surface_albedo,
        per_vertex,
    )


_ALL_RAYS = 0xFFFFFFFF


@functools.partial(jax.jit, static_argnames=("samples",))
def _bounce_rays(key, points, normals, enabled, samples):
    """``samples`` cosine-weighted rays per point (rows of a leading axis), masked off where not enabled."""
    keys = jax.random.split(key, samples)
    directions = jax.vmap(lambda k: cosine_hemisphere(k, normals))(keys)  # (K, ..., 3)
    start = jnp.broadcast_to(offset_ray_origin(points, normals), directions.shape)
    mask = jnp.broadcast_to(jnp.where(enabled, jnp.uint32(_ALL_RAYS), jnp.uint32(0)), directions.shape[:-1])
    return Ray(start, directions, mask=mask)


def _bounce_hits(found, bounce, vertices, indices):
    """Bounce hit points and their geometric normals facing the bounce rays."""
    n_y = face_forward(triangle_normals(vertices, indices, found.primitive_id), bounce.direction)
    return hit_points(bounce, found, miss_value=0.0), n_y


@jax.jit
def _shadow_rays(found, bounce, vertices, indices, points, normals, enabled, light_direction):
    """Rays towards the light from the points (row 0) and from the bounce hits (rows 1..K)."""
    light = _normalize(jnp.asarray(light_direction, points.dtype))
    y, n_y = _bounce_hits(found, bounce, vertices, indices)
    lit = jnp.concatenate([(enabled & (_dot(normals, light) > 0))[None], (found.type != 0) & (_dot(n_y, light) > 0)])
    origin = jnp.concatenate([offset_ray_origin(points, normals)[None], offset_ray_origin(y, n_y)], axis=0)
    mask = jnp.where(lit, jnp.uint32(_ALL_RAYS), jnp.uint32(0))
    return Ray(origin, jnp.broadcast_to(light, origin.shape), mask=mask)


@functools.partial(jax.jit, static_argnames=("per_vertex",))
def _combine(
    found,
    bounce,
    shadow,
    unoccluded,
    vertices,
    indices,
    normals,
    enabled,
    light_direction,
    irradiance,
    sky,
    surface_albedo,
    per_vertex,
):
    """The estimate of :func:`one_bounce_diffuse` from the traced bounce and shadow rays."""
    light = _normalize(jnp.asarray(light_direction, normals.dtype))
    _, n_y = _bounce_hits(found, bounce, vertices, indices)
    bounce_hit = found.type != 0
    channels = jnp.broadcast_shapes(
        irradiance.shape, sky.shape, surface_albedo.shape[1:] if per_vertex else surface_albedo.shape
    )
    expand = (lambda a: a[..., None]) if channels else (lambda a: a)
    if per_vertex:
        a_y = interpolate(surface_albedo, indices, found.primitive_id, found.triangle_barycentric_coord)
    else:
        a_y = jnp.broadcast_to(surface_albedo, (*bounce_hit.shape, *channels))
    visible = ((shadow.mask != 0) & unoccluded).astype(normals.dtype)
    direct_x = expand(visible[0] * jnp.maximum(_dot(normals, light), 0.0) / jnp.pi) * irradiance
    direct_y = a_y * expand(visible[1:] * jnp.maximum(_dot(n_y, light), 0.0) / jnp.pi) * irradiance
    incoming = jnp.where(expand(bounce_hit), direct_y, sky)
    total = direct_x + jnp.mean(incoming, axis=0)
    return jnp.where(expand(enabled), total, 0.0)
