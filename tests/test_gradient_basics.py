"""Gradients of the hit distance on a simple case against float64 central differences, and zero (never NaN)
gradients for rays that miss or are disabled."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

import jaxrt as rt

INTERSECTOR = rt.Intersector(rt.tags.triangle_data)
#: Two triangles sharing an edge, tilted; rays hit the first one well inside.
VERTICES = np.array([[0.1, -0.2, 0.3], [1.3, 0.1, -0.2], [0.2, 1.1, 0.4], [1.4, 1.2, 0.1]])
FACES = np.array([[0, 1, 2], [1, 3, 2]], np.int32)


def _distance(vertices, origin, direction):
    structure = rt.build_primitive_structure(rt.TriangleGeometry(vertices, FACES))
    result = INTERSECTOR.intersect(rt.Ray(origin, direction), structure)
    return jnp.where(jnp.isfinite(result.distance), result.distance, 0.0)


def _plane_distance(vertices, origin, direction):
    """The float64 truth: distance to the plane of the first triangle."""
    v0, v1, v2 = vertices[FACES[0]]
    n = np.cross(v1 - v0, v2 - v0)
    return np.dot(n, v0 - origin) / np.dot(n, direction)


def _central_difference(f, x, h=1e-6):
    grad = np.zeros_like(x)
    for index in np.ndindex(x.shape):
        step = np.zeros_like(x)
        step[index] = h
        grad[index] = (f(x + step) - f(x - step)) / (2 * h)
    return grad


def test_distance_gradient_matches_float64_central_differences():
    origin = np.array([0.4, 0.3, 2.0])
    direction = np.array([0.05, -0.1, -1.0])
    with jax.enable_x64(True):
        # One compiled program (eagerly, each operation of the build and its derivative compiles on its own).
        value, (g_vertices, g_origin, g_direction) = jax.jit(jax.value_and_grad(_distance, argnums=(0, 1, 2)))(
            jnp.asarray(VERTICES), jnp.asarray(origin), jnp.asarray(direction)
        )
        assert value.dtype == jnp.float64
    np.testing.assert_allclose(float(value), _plane_distance(VERTICES, origin, direction), rtol=1e-12)
    fd_vertices = _central_difference(lambda v: _plane_distance(v, origin, direction), VERTICES)
    fd_origin = _central_difference(lambda o: _plane_distance(VERTICES, o, direction), origin)
    fd_direction = _central_difference(lambda d: _plane_distance(VERTICES, origin, d), direction)
    np.testing.assert_allclose(np.asarray(g_vertices), fd_vertices, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(np.asarray(g_origin), fd_origin, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(np.asarray(g_direction), fd_direction, rtol=1e-6, atol=1e-9)
    assert np.abs(np.asarray(g_vertices)[3]).max() == 0  # vertex 3 is not on the hit triangle


def test_missed_and_disabled_rays_have_zero_gradients():
    """One batch: a hit, plain misses, a miss nearly parallel to every plane, a ray behind its interval, and
    disabled rays (zero or NaN direction, NaN origin). Only the hit contributes, and nothing is NaN."""
    origin = np.array(
        [[0.4, 0.3, 2.0], [5.0, 5.0, 2.0], [0.4, 0.3, 2.0], [-3.0, 5.0, 0.2], [0.4, 0.3, 2.0], [0.4, 0.3, 2.0],
         [0.4, 0.3, 2.0], [np.nan, 0.3, 2.0]],
        np.float32,
    )  # fmt: skip
    direction = np.array(
        [[0.05, -0.1, -1.0], [0.0, 0.0, -1.0], [0.0, 0.0, 1.0], [1.0, 0.0, 1e-20], [0.05, -0.1, -1.0],
         [0.0, 0.0, 0.0], [np.nan, 0.0, -1.0], [0.0, 0.0, -1.0]],
        np.float32,
    )  # fmt: skip
    max_distance = np.array([np.inf, np.inf, np.inf, np.inf, 1.0, np.inf, np.inf, np.inf], np.float32)
    vertices = VERTICES.astype(np.float32)

    def loss(vertices, origin, direction):
        structure = rt.build_primitive_structure(rt.TriangleGeometry(vertices, FACES))
        result = INTERSECTOR.intersect(rt.Ray(origin, direction, 0.0, max_distance), structure)
        hit = result.type == int(rt.IntersectionType.TRIANGLE)
        return jnp.sum(jnp.where(hit, result.distance + result.triangle_barycentric_coord.sum(-1), 0.0)), hit

    (_, hit), grads = jax.jit(jax.value_and_grad(loss, argnums=(0, 1, 2), has_aux=True))(vertices, origin, direction)
    np.testing.assert_array_equal(np.asarray(hit), [True, False, False, False, False, False, False, False])
    g_vertices, g_origin, g_direction = (np.asarray(g) for g in grads)
    for name, g in (("vertices", g_vertices), ("origin", g_origin), ("direction", g_direction)):
        assert not np.isnan(g).any(), f"NaN in the gradient with respect to {name}: {g}"
    np.testing.assert_array_equal(g_origin[1:], 0.0)
    np.testing.assert_array_equal(g_direction[1:], 0.0)
    assert np.abs(g_origin[0]).max() > 0 and np.abs(g_vertices[:3]).max() > 0
