"""Benchmark ray sets: primary (camera), diffuse (cosine-weighted from surface points) and shadow rays.

Rays are NumPy float32 arrays in a :class:`RayBatch`, so that every tracer gets identical bits. Directions
are unit length; distances are in scene units. Secondary rays start at random points on the surface, moved
off it with :func:`jaxrt.offset_ray_origin` (Wächter & Binder 2019), and use ``min_distance = 0``.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

import jaxrt as rt

__all__ = ["RayBatch", "primary_rays", "diffuse_rays", "shadow_rays", "surface_points"]


class RayBatch(NamedTuple):
    """``N`` rays as host arrays."""

    origin: np.ndarray
    """``(N, 3)`` float32."""
    direction: np.ndarray
    """``(N, 3)`` float32, unit length."""
    max_distance: np.ndarray
    """``(N,)`` float32; ``inf`` for unbounded rays."""

    def __len__(self) -> int:
        return int(self.origin.shape[0])

    def take(self, index: np.ndarray) -> RayBatch:
        """The rays at ``index``."""
        return RayBatch(self.origin[index], self.direction[index], self.max_distance[index])

    def to_jaxrt(self) -> rt.Ray:
        """The batch as a :class:`jaxrt.Ray` (``min_distance = 0``), on the default device."""
        return rt.Ray(self.origin, self.direction, 0.0, self.max_distance)


def _normalized(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _bounds(vertices: np.ndarray) -> tuple[np.ndarray, float]:
    """The bounding-box centre and the radius of the sphere about it that holds every vertex."""
    points = vertices.astype(np.float64)
    centre = (points.min(axis=0) + points.max(axis=0)) / 2.0
    return centre, float(np.linalg.norm(points - centre, axis=1).max())


def primary_rays(
    vertices: np.ndarray,
    n_rays: int,
    *,
    eye: tuple[float, float, float] | np.ndarray | None = None,
    target: tuple[float, float, float] | np.ndarray | None = None,
    up: tuple[float, float, float] = (0.0, 1.0, 0.0),
    fov_degrees: float = 40.0,
) -> RayBatch:
    """Pinhole-camera rays through pixel centres, in scanline order (row by row from the top left).

    The image has ``floor(sqrt(n_rays))`` rows and enough columns for ``n_rays`` pixels; the last row is
    partial when ``n_rays`` is not a product of the two (powers of 4 give square images).

    Args:
      vertices: ``(V, 3)`` scene vertices; they set the default framing.
      n_rays: number of rays.
      eye: camera position; default: in front of the bounding-box centre and slightly above and to the
        right, at the distance where the sphere about the centre that holds every vertex just fills the
        vertical field of view.
      target: the point at the image centre; default: the bounding-box centre.
      up: the camera's up direction (need not be orthogonal to the view direction).
      fov_degrees: vertical field of view.

    Returns:
      A :class:`RayBatch` of unbounded rays from ``eye``.
    """
    centre, radius = _bounds(vertices)
    target = centre if target is None else np.asarray(target, np.float64)
    if eye is None:
        distance = radius / np.sin(np.radians(fov_degrees) / 2.0)
        eye = target + distance * _normalized(np.array([0.35, 0.25, 1.0]))
    eye = np.asarray(eye, np.float64)
    forward = _normalized(target - eye)
    right = np.cross(forward, np.asarray(up, np.float64))
    if np.linalg.norm(right) < 1e-9:
        right = np.cross(forward, np.array([1.0, 0.0, 0.0]))
    right = _normalized(right)
    true_up = np.cross(right, forward)
    height = max(1, int(np.sqrt(n_rays)))
    width = -(-n_rays // height)
    pixel = np.arange(n_rays)
    row, col = pixel // width, pixel % width
    half = np.tan(np.radians(fov_degrees) / 2.0)
    x = ((col + 0.5) / width * 2.0 - 1.0) * half * width / height
    y = (1.0 - (row + 0.5) / height * 2.0) * half
    direction = _normalized(forward + x[:, None] * right + y[:, None] * true_up)
    origin = np.broadcast_to(eye, direction.shape)
    return RayBatch(origin.astype(np.float32), direction.astype(np.float32), np.full(n_rays, np.inf, np.float32))


def surface_points(
    vertices: np.ndarray, indices: np.ndarray, n_points: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Area-uniform random points on the mesh.

    Returns:
      ``(points, normals, triangle)``: float64 points ``(N, 3)``, unit geometric normals ``(N, 3)``
      (the winding's side) and the triangle index of each point.
    """
    tri = vertices[indices].astype(np.float64)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = np.linalg.norm(normal, axis=1)
    if not area.sum() > 0:
        raise ValueError("surface_points: every triangle of the mesh has zero area")
    triangle = rng.choice(len(tri), size=n_points, p=area / area.sum())
    r1, r2 = rng.random(n_points), rng.random(n_points)
    s = np.sqrt(r1)
    b0, b1, b2 = 1.0 - s, s * (1.0 - r2), s * r2
    t = tri[triangle]
    points = b0[:, None] * t[:, 0] + b1[:, None] * t[:, 1] + b2[:, None] * t[:, 2]
    return points, normal[triangle] / area[triangle, None], triangle


def _offset_origin(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    return np.asarray(rt.offset_ray_origin(points.astype(np.float32), normals.astype(np.float32)))


def diffuse_rays(vertices: np.ndarray, indices: np.ndarray, n_rays: int, *, seed: int = 0) -> RayBatch:
    """Cosine-weighted hemisphere rays from area-uniform random surface points.

    Each ray leaves a random side of its triangle (surfaces are two-sided), so on a closed mesh half the
    rays cross the interior and half leave into the open. Origins are offset along the chosen side's
    normal with :func:`jaxrt.offset_ray_origin`.

    Args:
      vertices, indices: the mesh, ``(V, 3)`` and ``(T, 3)``.
      n_rays: number of rays.
      seed: random seed.

    Returns:
      A :class:`RayBatch` of unbounded rays.
    """
    rng = np.random.default_rng(seed)
    points, normals, _ = surface_points(vertices, indices, n_rays, rng)
    normals *= np.where(rng.random(n_rays) < 0.5, -1.0, 1.0)[:, None]
    # Malley's method: a uniform point on the unit disc lifted onto the hemisphere.
    r, phi = np.sqrt(rng.random(n_rays)), 2.0 * np.pi * rng.random(n_rays)
    local = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(0.0, 1.0 - r * r))], axis=1)
    # Orthonormal basis around the normal (Duff et al., "Building an Orthonormal Basis, Revisited", 2017).
    nx, ny, nz = normals.T
    sign = np.where(nz >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + nz)
    b = nx * ny * a
    tangent = np.stack([1.0 + sign * nx * nx * a, sign * b, -sign * nx], axis=1)
    bitangent = np.stack([b, sign + ny * ny * a, -ny], axis=1)
    direction = _normalized(local[:, :1] * tangent + local[:, 1:2] * bitangent + local[:, 2:] * normals)
    origin = _offset_origin(points, normals)
    return RayBatch(origin, direction.astype(np.float32), np.full(n_rays, np.inf, np.float32))


def shadow_rays(
    vertices: np.ndarray,
    indices: np.ndarray,
    n_rays: int,
    *,
    light: tuple[float, float, float] | np.ndarray | None = None,
    seed: int = 0,
) -> RayBatch:
    """Segments from area-uniform random surface points to a point light (for any-hit/occlusion tests).

    Origins are offset towards the light's side of their triangle; ``max_distance`` is the distance to the
    light, so a hit means the point is in shadow.

    Args:
      vertices, indices: the mesh.
      n_rays: number of rays.
      light: light position; default: above and to the side of the bounding box (``+y`` is up).
      seed: random seed.

    Returns:
      A :class:`RayBatch` with finite ``max_distance``.
    """
    rng = np.random.default_rng(seed)
    centre, radius = _bounds(vertices)
    light = centre + radius * np.array([0.6, 1.5, 0.4]) if light is None else np.asarray(light, np.float64)
    points, normals, _ = surface_points(vertices, indices, n_rays, rng)
    to_light = light - points
    normals *= np.where(np.einsum("ij,ij->i", normals, to_light) < 0.0, -1.0, 1.0)[:, None]
    origin = _offset_origin(points, normals)
    to_light = light - origin.astype(np.float64)
    distance = np.linalg.norm(to_light, axis=1)
    return RayBatch(origin, (to_light / distance[:, None]).astype(np.float32), distance.astype(np.float32))
