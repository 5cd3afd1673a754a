"""Visibility-aware gradients by edge sampling: the boundary term of a pixel integral.

A pixel value is an integral ``I_p = int_pixel f(x, theta) dx`` over the image plane (``x`` in pixels).
Where ``f`` jumps along a curve ``C(theta)`` (a silhouette, an occlusion boundary, a shadow edge), Reynolds'
transport theorem gives

``dI_p/dtheta = int_pixel df/dtheta dx + int_{C in pixel} (f_- - f_+) (n . dx_C/dtheta) dl``

with ``n`` the unit normal of the curve pointing from its side ``-`` to its side ``+``. The first (area) term is
what plain autodiff of a Monte Carlo estimate gives (the hit primitive held fixed). This module estimates the
second (boundary) term by sampling points on the curves, after Li, Aittala, Durand and Lehtinen 2018:

- primary visibility: the silhouette edges of triangle meshes seen from the camera (an edge whose two triangles
  face opposite ways, or a boundary edge), projected to the image and clipped to it, sampled in proportion to
  their projected length (stratified);
- secondary visibility: the silhouette edges seen from a point or directional light, whose shadow on the first
  surface behind them (found by the library's traversal) is projected to the image.

``f_-`` and ``f_+`` come from the user's shading of two camera rays just either side of each sample point, so
an edge hidden behind another surface, or one that bounds no change of shading, contributes nothing. The
velocity ``dx_C/dtheta`` of the sample point is an ordinary JAX derivative: of the camera projection of an edge
point (vertices, instance transforms, camera), or of the projection of the shadow ray's hit (the traversal picks
the receiver; its hit is differentiable in the ray and the receiver's vertices).

References:
  Li, Aittala, Durand, Lehtinen, "Differentiable Monte Carlo Ray Tracing through Edge Sampling",
  SIGGRAPH Asia 2018.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from jaxrt._src.geometry import float_dtype
from jaxrt._src.ray import Ray
from jaxrt._src.transforms import apply_transform

__all__ = [
    "DirectionalLight",
    "EdgeSamples",
    "PinholeCamera",
    "PointLight",
    "SilhouetteMesh",
    "boundary_term",
    "edge_differences",
    "primary_edge_samples",
    "shadow_edge_samples",
]


def _normalize(v: jax.Array) -> jax.Array:
    # The epsilon keeps the gradient finite for zero vectors.
    return v / jnp.sqrt(jnp.sum(v * v, axis=-1, keepdims=True) + 1e-30)


def _positive_int(value: Any, name: str, owner: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0:
        raise ValueError(f"{owner}: {name} must be a positive int, got {value!r}")
    return int(value)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True, init=False)
class PinholeCamera:
    """A pinhole camera: image-plane positions in pixels to rays, and world points to image positions.

    Pixel ``(row, col)`` covers ``[col, col + 1] x [row, row + 1]`` of the image plane; row 0 is the top.
    The rays are those of :func:`jaxrt.shading.pinhole_rays` (same eye, target, up and field of view).

    Args:
      width, height: image size in pixels (static).
      eye, target, up: camera position, the point it looks at, and the up direction (differentiable).
      fov_degrees: vertical field of view.

    Raises:
      ValueError: a width or height that is not a positive int.

    Examples:
      >>> import jaxrt as rt
      >>> camera = rt.PinholeCamera(4, 3, eye=(0, 0, 5), target=(0, 0, 0))
      >>> [round(float(x), 3) for x in camera.project(jnp.array([0.0, 0.0, 0.0]))[0]]
      [2.0, 1.5]
    """

    eye: jax.Array
    target: jax.Array
    up: jax.Array
    fov_degrees: jax.Array
    width: int = dataclasses.field(metadata=dict(static=True))
    height: int = dataclasses.field(metadata=dict(static=True))

    def __init__(
        self, width: int, height: int, *, eye: Any, target: Any, up: Any = (0.0, 1.0, 0.0), fov_degrees: Any = 45.0
    ):
        dtype = float_dtype()
        object.__setattr__(self, "width", _positive_int(width, "width", "PinholeCamera"))
        object.__setattr__(self, "height", _positive_int(height, "height", "PinholeCamera"))
        for name, value in (("eye", eye), ("target", target), ("up", up)):
            value = jnp.asarray(value, dtype)
            if value.shape != (3,):
                raise ValueError(f"PinholeCamera: {name} must have shape (3,), got {value.shape}")
            object.__setattr__(self, name, value)
        object.__setattr__(self, "fov_degrees", jnp.asarray(fov_degrees, dtype))

    def _frame(self) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
        forward = _normalize(self.target - self.eye)
        right = _normalize(jnp.cross(forward, self.up))
        true_up = jnp.cross(right, forward)
        scale = jnp.tan(jnp.deg2rad(self.fov_degrees) * 0.5)
        return forward, right, true_up, scale

    def rays(self, positions: jax.Array) -> Ray:
        """Rays through image-plane ``positions`` ``(..., 2)`` (``(x, y)`` in pixels), unit directions."""
        forward, right, up, scale = self._frame()
        positions = jnp.asarray(positions, self.eye.dtype)
        px = (2.0 * positions[..., 0] / self.width - 1.0) * scale * (self.width / self.height)
        py = (1.0 - 2.0 * positions[..., 1] / self.height) * scale
        direction = _normalize(forward + px[..., None] * right + py[..., None] * up)
        return Ray(jnp.broadcast_to(self.eye, direction.shape), direction)

    def project(self, points: jax.Array) -> tuple[jax.Array, jax.Array]:
        """``(positions (..., 2), depth (...))``: image-plane positions in pixels of world ``points`` (..., 3)
        and their depth along the view direction (a point behind the camera has depth <= 0 and no meaning-
        ful position)."""
        forward, right, up, scale = self._frame()
        d = points - self.eye
        depth = jnp.sum(d * forward, axis=-1)
        safe = jnp.where(jnp.abs(depth) > 0, depth, 1.0)
        px = jnp.sum(d * right, axis=-1) / safe / (scale * (self.width / self.height))
        py = jnp.sum(d * up, axis=-1) / safe / scale
        return jnp.stack([(px + 1.0) * 0.5 * self.width, (1.0 - py) * 0.5 * self.height], axis=-1), depth

    def pixel_positions(self, key: jax.Array, samples_per_pixel: int) -> jax.Array:
        """``(samples_per_pixel, height, width, 2)`` positions inside each pixel: a jittered ``k x k`` grid
        when ``samples_per_pixel = k * k``, else independent uniform points."""
        spp = _positive_int(samples_per_pixel, "samples_per_pixel", "PinholeCamera.pixel_positions")
        dtype = self.eye.dtype
        jitter = jax.random.uniform(key, (spp, self.height, self.width, 2), dtype)
        k = int(round(np.sqrt(spp)))
        if k * k == spp:
            cell = jnp.stack(jnp.meshgrid(jnp.arange(k), jnp.arange(k), indexing="ij"), -1).reshape(spp, 1, 1, 2)
            jitter = (cell.astype(dtype) + jitter) / k
        rows, cols = jnp.meshgrid(
            jnp.arange(self.height, dtype=dtype), jnp.arange(self.width, dtype=dtype), indexing="ij"
        )
        return jnp.stack([cols, rows], -1) + jitter


def _mesh_edges(indices: np.ndarray, all_edges: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unique edges ``(E, 2)``, their first two triangles ``(E, 2)`` (-1: none) and whether each is always a
    candidate (a boundary or non-manifold edge, or every edge with ``all_edges``)."""
    t = len(indices)
    pairs = np.concatenate([indices[:, [0, 1]], indices[:, [1, 2]], indices[:, [2, 0]]])
    faces = np.tile(np.arange(t), 3)
    pairs = np.sort(pairs, axis=1)
    keep = pairs[:, 0] != pairs[:, 1]
    pairs, faces = pairs[keep], faces[keep]
    edges, inverse, counts = np.unique(pairs, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    order = np.argsort(inverse, kind="stable")
    first = np.searchsorted(inverse[order], np.arange(len(edges)))
    two = np.full((len(edges), 2), -1, np.int64)
    two[:, 0] = faces[order[first]]
    has_second = counts >= 2
    two[has_second, 1] = faces[order[first[has_second] + 1]]
    always = (counts != 2) | all_edges
    return edges.astype(np.int32), two.astype(np.int32), always


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True, init=False)
class SilhouetteMesh:
    """A triangle mesh whose edges may bound what a pixel sees: the edges the estimator samples.

    Args:
      vertices: ``(V, 3)`` vertex positions (object space when ``transform`` is given); differentiable.
      indices: ``(T, 3)`` vertex indices, concrete (the edge list is built on the host once).
      transform: optional ``(3, 4)`` object-to-world transform, or ``(N, 3, 4)`` for ``N`` instances of the
        mesh (as in :class:`~jaxrt.Instances`); differentiable, so gradients reach instance transforms.
      all_edges: sample every edge, not only silhouettes and boundary edges: for shading that is
        discontinuous across the mesh's own edges (flat normals, per-triangle colours).

    Raises:
      ValueError: bad shapes, non-concrete or out-of-range indices.

    Examples:
      >>> import jaxrt as rt
      >>> mesh = rt.SilhouetteMesh([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]])
      >>> mesh.edges.shape, int(mesh.always.sum())  # five edges, four on the boundary
      ((5, 2), 4)
    """

    vertices: jax.Array
    transform: jax.Array | None
    indices: jax.Array
    edges: jax.Array
    edge_faces: jax.Array
    always: jax.Array

    def __init__(self, vertices: Any, indices: Any, *, transform: Any = None, all_edges: bool = False):
        owner = "SilhouetteMesh"
        vertices = jnp.asarray(vertices, float_dtype())
        if vertices.ndim != 2 or vertices.shape[1] != 3:
            raise ValueError(f"{owner}: vertices must have shape (V, 3), got {vertices.shape}")
        if isinstance(indices, jax.core.Tracer):
            raise ValueError(f"{owner}: indices must be concrete (the edge list is built on the host), got a tracer")
        host = np.asarray(indices)
        if host.ndim != 2 or host.shape[1] != 3 or not np.issubdtype(host.dtype, np.integer):
            raise ValueError(f"{owner}: indices must be an int array of shape (T, 3), got {host.dtype} {host.shape}")
        if host.size and (host.min() < 0 or host.max() >= vertices.shape[0]):
            raise ValueError(f"{owner}: indices must be in [0, {vertices.shape[0]}), got {host.min()}..{host.max()}")
        if transform is not None:
            transform = jnp.asarray(transform, float_dtype())
            if transform.shape[-2:] != (3, 4) or transform.ndim not in (2, 3):
                raise ValueError(f"{owner}: transform must have shape (3, 4) or (N, 3, 4), got {transform.shape}")
        edges, faces, always = _mesh_edges(host.astype(np.int64), bool(all_edges))
        object.__setattr__(self, "vertices", vertices)
        object.__setattr__(self, "transform", transform)
        object.__setattr__(self, "indices", jnp.asarray(host, jnp.int32))
        object.__setattr__(self, "edges", jnp.asarray(edges))
        object.__setattr__(self, "edge_faces", jnp.asarray(faces))
        object.__setattr__(self, "always", jnp.asarray(always))

    def world_vertices(self) -> jax.Array:
        """``(N, V, 3)``: the vertices of each of the ``N`` instances in world space (``N = 1`` without one)."""
        if self.transform is None:
            return self.vertices[None]
        transform = self.transform.reshape(-1, 3, 4)
        return jax.vmap(apply_transform, in_axes=(0, None))(transform, self.vertices)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class DirectionalLight:
    """A light infinitely far away in ``direction`` (towards the light); its shadows have hard edges."""

    direction: jax.Array


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class PointLight:
    """A point light at ``position``; its shadows have hard edges."""

    position: jax.Array


class EdgeSamples(NamedTuple):
    """Points on the image's discontinuity curves, with what the boundary term needs of them.

    Attributes:
      position: ``(N, 2)`` image-plane positions in pixels, differentiable (their derivative is the curve's
        velocity).
      normal: ``(N, 2)`` unit normals of the curve there (no gradient).
      weight: ``(N,)`` length element over sampling density, divided by ``N`` (0 for an invalid sample).
    """

    position: jax.Array
    normal: jax.Array
    weight: jax.Array


def _edges_seen_from(meshes: Sequence[SilhouetteMesh], facing: Callable) -> tuple[jax.Array, jax.Array, jax.Array]:
    """``(a, b, candidate)``: world endpoints ``(E, 3)`` of every edge of every instance and whether it is a
    silhouette as seen by ``facing(normals, centres) -> bool`` (or always a candidate)."""
    starts, ends, candidates = [], [], []
    for mesh in meshes:
        world = mesh.world_vertices()  # (N, V, 3)
        triangles = world[:, mesh.indices]  # (N, T, 3, 3)
        normals = jnp.cross(triangles[..., 1, :] - triangles[..., 0, :], triangles[..., 2, :] - triangles[..., 0, :])
        front = facing(normals, jnp.mean(triangles, axis=-2))  # (N, T)
        f0, f1 = mesh.edge_faces[:, 0], jnp.maximum(mesh.edge_faces[:, 1], 0)
        silhouette = mesh.always[None] | (front[:, f0] != front[:, f1])
        starts.append(world[:, mesh.edges[:, 0]].reshape(-1, 3))
        ends.append(world[:, mesh.edges[:, 1]].reshape(-1, 3))
        candidates.append(silhouette.reshape(-1))
    return jnp.concatenate(starts), jnp.concatenate(ends), jnp.concatenate(candidates)


def _stratified_choice(key: jax.Array, lengths: jax.Array, count: int) -> tuple[jax.Array, jax.Array, jax.Array]:
    """``(index, fraction, total)``: ``count`` stratified samples of the concatenated ``lengths``: the
    segment each falls in and where along it (in ``[0, 1)``), and the total length."""
    cumulative = jnp.cumsum(lengths)
    total = cumulative[-1]
    u = (jnp.arange(count, dtype=lengths.dtype) + jax.random.uniform(key, (count,), lengths.dtype)) / count
    target = u * total
    index = jnp.clip(jnp.searchsorted(cumulative, target, side="right"), 0, lengths.shape[0] - 1)
    start = cumulative[index] - lengths[index]
    fraction = jnp.clip((target - start) / jnp.where(lengths[index] > 0, lengths[index], 1.0), 0.0, 1.0)
    return index, fraction, total


def _clip_to_image(xa: jax.Array, xb: jax.Array, width: int, height: int) -> tuple[jax.Array, jax.Array]:
    """The parameter range ``[s0, s1]`` of the segments ``xa + s (xb - xa)`` inside the image (Liang-Barsky);
    ``s0 >= s1`` where a segment misses it."""
    d = xb - xa
    s0, s1 = jnp.zeros(xa.shape[:-1], xa.dtype), jnp.ones(xa.shape[:-1], xa.dtype)
    for axis, size in ((0, width), (1, height)):
        for p, q in ((-d[..., axis], xa[..., axis]), (d[..., axis], size - xa[..., axis])):
            parallel = p == 0
            r = q / jnp.where(parallel, 1.0, p)
            s0 = jnp.where(~parallel & (p < 0), jnp.maximum(s0, r), s0)
            s1 = jnp.where(~parallel & (p > 0), jnp.minimum(s1, r), s1)
            s1 = jnp.where(parallel & (q < 0), -1.0, s1)
    return s0, s1


def primary_edge_samples(
    key: jax.Array, camera: PinholeCamera, meshes: Sequence[SilhouetteMesh], count: int
) -> EdgeSamples:
    """``count`` stratified samples on the meshes' silhouette edges as the camera sees them.

    Edges are clipped to the part in front of the camera and to the image, and sampled in proportion to
    their projected length. Whether a sample is really on a visible silhouette is decided later by the
    shading on its two sides (:func:`edge_differences`).
    """
    count = _positive_int(count, "count", "primary_edge_samples")
    eye = camera.eye
    a, b, candidate = _edges_seen_from(meshes, lambda n, c: jnp.sum(n * (c - eye), axis=-1) > 0)
    detached = lax.stop_gradient
    a_d, b_d = detached(a), detached(b)
    # The part of each edge in front of the camera: depth >= near (a small fraction of the edge's depth).
    _, za = camera.project(a_d)
    _, zb = camera.project(b_d)
    near = 1e-6 * jnp.maximum(jnp.abs(za), jnp.abs(zb)) + 1e-12
    dz = zb - za
    cross = (near - za) / jnp.where(dz != 0, dz, 1.0)
    t0 = jnp.where(za < near, jnp.clip(cross, 0.0, 1.0), 0.0)
    t1 = jnp.where(zb < near, jnp.clip(cross, 0.0, 1.0), 1.0)
    in_front = (za >= near) | (zb >= near)
    pa, pb = a_d + t0[:, None] * (b_d - a_d), a_d + t1[:, None] * (b_d - a_d)
    xa, _ = camera.project(pa)
    xb, _ = camera.project(pb)
    za, zb = za + t0 * dz, za + t1 * dz
    s0, s1 = _clip_to_image(xa, xb, camera.width, camera.height)
    screen_length = jnp.linalg.norm(xb - xa, axis=-1)
    lengths = jnp.where(candidate & in_front & (s1 > s0), screen_length * (s1 - s0), 0.0)
    index, fraction, total = _stratified_choice(key, lengths, count)
    s = s0[index] + fraction * (s1[index] - s0[index])
    # Screen parameter s to the world parameter along [pa, pb] (perspective: t = s za / ((1 - s) zb + s za)).
    za_i, zb_i = za[index], zb[index]
    valid = (total > 0) & (lengths[index] > 0)
    denominator = (1.0 - s) * zb_i + s * za_i
    t = s * za_i / jnp.where(valid & (denominator > 0), denominator, 1.0)
    # Invalid samples (nothing to sample) take an edge's midpoint: finite, with zero weight and gradient.
    t = jnp.where(valid, jnp.clip(t, 0.0, 1.0), 0.5)
    tau = detached(t0[index] + t * (t1[index] - t0[index]))
    point = a[index] + tau[:, None] * (b[index] - a[index])  # attached: moves with the vertices
    position, _ = camera.project(point)
    tangent = detached(xb[index] - xa[index])
    normal = _normalize(jnp.stack([-tangent[:, 1], tangent[:, 0]], axis=-1))
    weight = jnp.where(valid, total / count, 0.0)
    return EdgeSamples(position, normal, detached(weight))


def shadow_edge_samples(
    key: jax.Array,
    camera: PinholeCamera,
    meshes: Sequence[SilhouetteMesh],
    light: DirectionalLight | PointLight,
    count: int,
    trace: Callable[[Ray], Any],
    *,
    min_distance: float = 1e-4,
) -> EdgeSamples:
    """``count`` samples on the image of the shadow edges that ``light`` casts from the meshes.

    Silhouette edges as the light sees them are sampled in proportion to their world length; a ray from each
    sample point away from the light finds the surface the shadow edge falls on (``trace(rays)``, an
    :class:`~jaxrt.IntersectionResult` with a differentiable ``distance``), and that point is projected to the
    image. The curve's image-plane tangent is the derivative of that chain along the edge (``jax.jvp``).

    Args:
      min_distance: where the shadow rays start, as a fraction of the edge's length (past the edge's own
        triangles).
    """
    count = _positive_int(count, "count", "shadow_edge_samples")
    if isinstance(light, DirectionalLight):
        towards = _normalize(jnp.asarray(light.direction, camera.eye.dtype))

        def facing(n, c):
            return jnp.sum(n * towards, axis=-1) > 0

        def away(q):
            return jnp.broadcast_to(-towards, q.shape)

    elif isinstance(light, PointLight):
        light_position = jnp.asarray(light.position, camera.eye.dtype)

        def facing(n, c):
            return jnp.sum(n * (c - light_position), axis=-1) > 0

        def away(q):
            return _normalize(q - light_position)

    else:
        raise TypeError(
            f"shadow_edge_samples: light must be a DirectionalLight or PointLight, got {type(light).__name__}"
        )
    a, b, candidate = _edges_seen_from(meshes, facing)
    detached = lax.stop_gradient
    world_length = jnp.linalg.norm(detached(b - a), axis=-1)
    lengths = jnp.where(candidate, world_length, 0.0)
    index, tau, total = _stratified_choice(key, lengths, count)
    tau = detached(tau)
    a_i, b_i = a[index], b[index]
    start = min_distance * world_length[index]

    def receiver(t):
        q = a_i + t[:, None] * (b_i - a_i)
        d = away(q)
        hits = trace(Ray(q, d, start, jnp.inf))
        hit = hits.type != 0
        y = q + jnp.where(hit, hits.distance, 0.0)[:, None] * d
        x, depth = camera.project(y)
        return x, (hit, depth)

    # The tangent along the edge by forward mode; the attached position by a plain call: the outer derivative
    # of a primal computed inside jax.jvp would miss the hit's custom derivative rule.
    position, (hit, depth) = receiver(tau)
    _, tangent, _ = jax.jvp(receiver, (tau,), (jnp.ones_like(tau),), has_aux=True)
    tangent = detached(tangent)
    speed = jnp.linalg.norm(tangent, axis=-1)
    normal = jnp.stack([-tangent[:, 1], tangent[:, 0]], axis=-1) / jnp.where(speed > 0, speed, 1.0)[:, None]
    inside = (
        (position[:, 0] >= 0)
        & (position[:, 0] < camera.width)
        & (position[:, 1] >= 0)
        & (position[:, 1] < camera.height)
    )
    valid = (total > 0) & (lengths[index] > 0) & hit & (depth > 0) & detached(inside) & jnp.isfinite(speed)
    safe_length = jnp.where(lengths[index] > 0, lengths[index], 1.0)
    weight = jnp.where(valid, speed * total / (safe_length * count), 0.0)
    position = jnp.where(valid[:, None], position, 0.0)
    return EdgeSamples(position, normal, detached(weight))


def edge_differences(
    shade: Callable[[Ray], jax.Array], camera: PinholeCamera, samples: EdgeSamples, *, offset: float | None = None
) -> jax.Array:
    """``f(x - offset n) - f(x + offset n)`` for each sample ``(N, ...)``: the jump of the shading across the
    curve, from two camera rays ``offset`` pixels either side of it (no gradient).

    ``offset=None``: 1e-3 pixels in float32 (some 16 float32 steps of a pixel coordinate at 512 pixels, so the
    two rays stay on their sides of the edge), 1e-5 in float64. A sample within ``offset`` of another
    discontinuity (a corner) can see the wrong side: a bias that shrinks with the offset.
    """
    detached = lax.stop_gradient
    x, n = detached(samples.position), detached(samples.normal)
    if offset is None:
        offset = 1e-3 if x.dtype == jnp.float32 else 1e-5
    rays = camera.rays(jnp.concatenate([x - offset * n, x + offset * n]))
    values = jnp.asarray(shade(jax.tree_util.tree_map(detached, rays)))
    if not jnp.issubdtype(values.dtype, jnp.inexact):  # a mask: differences need a signed type
        values = values.astype(x.dtype)
    count = x.shape[0]
    return detached(values[:count] - values[count:])


@functools.partial(jax.custom_jvp, nondiff_argnums=(3,))
def _attach(position: jax.Array, coefficient: jax.Array, pixel: jax.Array, pixels: int) -> jax.Array:
    """Zeros ``(pixels, C)`` whose derivative is ``sum_s [pixel_s = p] coefficient_s . d(position_s)``."""
    return jnp.zeros((pixels, coefficient.shape[1]), coefficient.dtype)


@_attach.defjvp
def _attach_jvp(pixels, primals, tangents):
    position, coefficient, pixel = primals
    d_position = tangents[0]
    rate = jnp.einsum("sck,sk->sc", coefficient, d_position)
    out = jnp.zeros((pixels, coefficient.shape[1]), coefficient.dtype)
    return out, jax.ops.segment_sum(rate, pixel, num_segments=pixels)


def boundary_term(camera: PinholeCamera, samples: EdgeSamples, differences: jax.Array) -> jax.Array:
    """An image of zeros ``(height, width, ...)`` whose derivative is the boundary term of the pixel integrals.

    Add it to a pixel-integral estimate: ``jax.grad`` of any loss of the sum then has the visibility term.
    Its value is exactly 0 and, when nothing differentiates it, XLA drops the edge work behind it (under
    ``jax.jit``).
    """
    detached = lax.stop_gradient
    channels = differences.shape[1:]
    flat = differences.reshape(differences.shape[0], -1)
    x = detached(samples.position)
    col = jnp.clip(jnp.floor(x[:, 0]).astype(jnp.int32), 0, camera.width - 1)
    row = jnp.clip(jnp.floor(x[:, 1]).astype(jnp.int32), 0, camera.height - 1)
    coefficient = (samples.weight[:, None] * flat)[:, :, None] * samples.normal[:, None, :]
    coefficient = detached(jnp.where(jnp.isfinite(coefficient), coefficient, 0.0))
    image = _attach(samples.position, coefficient, row * camera.width + col, camera.width * camera.height)
    return image.reshape(camera.height, camera.width, *channels)
