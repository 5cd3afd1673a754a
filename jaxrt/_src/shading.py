"""Small, differentiable shading helpers: camera rays, hit points, normals, Lambert shading, ambient occlusion.

All are plain JAX functions (jit/vmap/grad friendly); randomness comes from an explicit ``jax.random`` key.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxrt._src.intersector import Intersector
from jaxrt._src.numerics import offset_ray_origin
from jaxrt._src.ray import Ray
from jaxrt._src.result import IntersectionResult

__all__ = [
    "pinhole_rays",
    "hit_points",
    "triangle_normals",
    "lambert",
    "cosine_hemisphere",
    "ambient_occlusion",
]


def _normalize(v: jax.Array) -> jax.Array:
    # The epsilon keeps the gradient finite for zero vectors.
    return v / jnp.sqrt(jnp.sum(v * v, axis=-1, keepdims=True) + 1e-30)


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
      A :class:`~jaxrt.Ray` batch with unit directions; row 0 is the top of the image.
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


def hit_points(rays: Ray, result: IntersectionResult) -> jax.Array:
    """``origin + distance * direction`` for hits, 0 for misses (no NaN, differentiable)."""
    hit = result.type != 0
    distance = jnp.where(hit, result.distance, 0.0)
    return jnp.where(hit[..., None], rays.origin + distance[..., None] * rays.direction, 0.0)


def triangle_normals(vertices: jax.Array, indices: jax.Array, primitive_id: jax.Array) -> jax.Array:
    """Unit geometric normals ``normalize(cross(v1 - v0, v2 - v0))`` of triangles ``primitive_id`` (-1 gives 0)."""
    tri = vertices[indices[jnp.maximum(primitive_id, 0)]]
    n = _normalize(jnp.cross(tri[..., 1, :] - tri[..., 0, :], tri[..., 2, :] - tri[..., 0, :]))
    return jnp.where((primitive_id >= 0)[..., None], n, 0.0)


def lambert(normals: jax.Array, light_direction: jax.Array, albedo=1.0) -> jax.Array:
    """Lambertian shading ``albedo * max(0, dot(n, l))`` for unit normals and a direction towards the light."""
    l = _normalize(jnp.asarray(light_direction, normals.dtype))  # noqa: E741
    return albedo * jnp.maximum(jnp.sum(normals * l, axis=-1), 0.0)


def cosine_hemisphere(key: jax.Array, normals: jax.Array) -> jax.Array:
    """One cosine-weighted direction per normal on the hemisphere around it (Malley's method)."""
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
      ``(...)`` visibility in [0, 1] (1: unoccluded).
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
