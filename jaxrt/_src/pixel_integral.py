"""Pixel integrals of a user's shading function, with visibility-aware gradients (opt-in edge sampling)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxrt._src.ray import Ray
from jaxrt._src.visibility import (
    DirectionalLight,
    PinholeCamera,
    PointLight,
    SilhouetteMesh,
    boundary_term,
    edge_differences,
    primary_edge_samples,
    shadow_edge_samples,
)

__all__ = ["pixel_integral"]


def pixel_integral(
    shade: Callable[[Ray], jax.Array],
    camera: PinholeCamera,
    key: jax.Array,
    *,
    samples_per_pixel: int = 4,
    meshes: Sequence[SilhouetteMesh] = (),
    edge_samples: int = 0,
    lights: Sequence[DirectionalLight | PointLight] = (),
    shadow_edge_samples_per_light: int = 0,
    trace: Callable[[Ray], Any] | None = None,
    edge_offset: float | None = None,
) -> jax.Array:
    """The image ``(height, width, ...)``: each pixel's mean of ``shade`` over its area, with the boundary term.

    ``shade(rays) -> values`` is the user's whole integrand for a flat batch of camera rays ``(n,)``: it
    traces, shades (shadow rays, textures, anything) and returns ``(n,)`` or ``(n, C)`` values. The area term
    is a Monte Carlo estimate with ``samples_per_pixel`` jittered rays per pixel (stratified when it is a
    square), differentiated by JAX as usual (hits held fixed). With ``meshes`` and ``edge_samples``, the
    derivative also gets the boundary term where the visible surface changes (silhouettes and occlusion
    boundaries of those meshes); with ``lights`` and ``shadow_edge_samples_per_light``, where a point or
    directional light's shadow edge cast by those meshes falls (``trace`` finds the surface it falls on).
    The value is the area estimate alone: the edge work only runs when something differentiates the image
    (under ``jax.jit``).

    Args:
      shade: ``rays -> values``, pure JAX; the same function is called on the pixel rays and on the edge rays.
      camera: the :class:`PinholeCamera` (static size, differentiable pose).
      key: ``jax.random`` key: a fixed key gives a fixed sampling pattern.
      samples_per_pixel: camera rays per pixel for the area term (static).
      meshes: the :class:`SilhouetteMesh` es whose edges can bound what a pixel sees (the moving ones, and any
        that can hide them).
      edge_samples: samples on the meshes' silhouette edges seen from the camera (static; 0: none).
      lights: lights whose hard shadow edges move with the parameters.
      shadow_edge_samples_per_light: samples on each light's shadow edges (static).
      trace: ``rays -> rt.IntersectionResult`` on the scene (e.g. ``lambda r: intersector.intersect(r, s)``),
        needed with ``lights``.
      edge_offset: how far either side of an edge, in pixels, its two shading rays go (``None``: 1e-3 in
        float32, 1e-5 in float64; see :func:`~jaxrt.visibility.edge_differences`).

    Returns:
      ``(height, width)`` or ``(height, width, C)`` pixel values.

    Raises:
      ValueError: a negative or non-int sample count, lights without ``trace``, or edge samples without meshes.

    Examples:
      >>> import jaxrt as rt
      >>> v = jnp.array([[-1., -1, 0], [1, -1, 0], [0, 1, 0]]); f = jnp.array([[0, 1, 2]])
      >>> camera = rt.PinholeCamera(8, 8, eye=(0, 0, 3), target=(0, 0, 0))
      >>> def render(x):
      ...     s = rt.build_primitive_structure(rt.TriangleGeometry(v + x, f))
      ...     shade = lambda rays: (rt.Intersector().intersect(rays, s).type != 0).astype(v.dtype)
      ...     mesh = rt.SilhouetteMesh(v + x, f)
      ...     return rt.pixel_integral(shade, camera, jax.random.key(0), meshes=[mesh], edge_samples=256)
      >>> g = jax.grad(lambda x: render(x)[:, :4].sum())(jnp.zeros(3))
      >>> bool(g[0] < 0)  # moving right takes coverage out of the left half
      True
    """
    for name, value in (
        ("edge_samples", edge_samples),
        ("shadow_edge_samples_per_light", shadow_edge_samples_per_light),
    ):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
            raise ValueError(f"pixel_integral: {name} must be an int >= 0, got {value!r}")
    if lights and trace is None:
        raise ValueError("pixel_integral: lights were given but no trace function to find where shadows fall")
    if (edge_samples or (lights and shadow_edge_samples_per_light)) and not meshes:
        raise ValueError("pixel_integral: edge samples were asked for but meshes is empty")
    key_pixels, key_edges, key_shadows = jax.random.split(key, 3)
    positions = camera.pixel_positions(key_pixels, samples_per_pixel)
    rays = camera.rays(positions.reshape(-1, 2))
    values = shade(rays)
    values = values.reshape(samples_per_pixel, camera.height, camera.width, *values.shape[1:])
    image = jnp.mean(values, axis=0)
    if edge_samples:
        samples = primary_edge_samples(key_edges, camera, meshes, edge_samples)
        image = image + boundary_term(camera, samples, edge_differences(shade, camera, samples, offset=edge_offset))
    if shadow_edge_samples_per_light:
        for light, light_key in zip(lights, jax.random.split(key_shadows, max(len(lights), 1)), strict=False):
            samples = shadow_edge_samples(light_key, camera, meshes, light, shadow_edge_samples_per_light, trace)
            differences = edge_differences(shade, camera, samples, offset=edge_offset)
            image = image + boundary_term(camera, samples, differences)
    return image
