"""Gradients of instanced hits with respect to instance transforms, at two levels, against finite differences."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

import jaxrt as rt

TRIANGLES = np.array(
    [[[-2.0, -2.0, 0.1], [3.0, -1.0, -0.2], [-1.0, 3.0, 0.3]], [[-2.0, -2.0, 1.1], [3.0, -1.0, 0.8], [-1.0, 3.0, 1.3]]],
    np.float32,
)
INTERSECTOR = rt.Intersector(rt.tags.instancing, rt.tags.max_levels(2), rt.tags.triangle_data, rt.tags.world_space_data)


def _rotation(angle: float, axis: int) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    r = np.eye(3)
    i, j = [k for k in range(3) if k != axis]
    r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
    return r


INNER = np.concatenate([_rotation(0.3, 0) @ np.diag([1.2, 0.8, 1.0]), [[0.2], [-0.1], [0.3]]], axis=1).astype(
    np.float32
)
OUTER = np.concatenate([_rotation(-0.2, 1) @ np.diag([1.0, 1.1, -0.9]), [[0.1], [0.2], [-0.4]]], axis=1).astype(
    np.float32
)
ORIGIN = np.array([[0.1, 0.2, 5.0], [0.5, -0.4, 6.0], [-0.3, 0.1, -5.0]], np.float32)
DIRECTION = np.array([[0.05, 0.02, -1.0], [-0.1, 0.05, -1.2], [0.02, 0.03, 1.0]], np.float32)


def _loss(inner: jax.Array, outer: jax.Array) -> jax.Array:
    blas = rt.build_primitive_structure(rt.TriangleGeometry(TRIANGLES.reshape(-1, 3)))
    level1 = rt.build_instance_structure([blas], rt.Instances([0], inner[None]))
    level2 = rt.build_instance_structure([level1], rt.Instances([0], outer[None]))
    hit = INTERSECTOR.intersect(rt.Ray(ORIGIN, DIRECTION), level2)
    bary = hit.triangle_barycentric_coord
    weights = jnp.arange(1.0, 4.0)
    return (
        jnp.sum(weights * hit.distance)
        + jnp.sum(bary[:, 0] * weights)
        - jnp.sum(bary[:, 1])
        + 0.1 * jnp.sum(hit.object_to_world_transform * jnp.arange(12.0).reshape(3, 4))
        + 0.1 * jnp.sum(hit.world_to_object_transform)
    )


def _finite_difference(fn, x: np.ndarray, step: float) -> np.ndarray:
    grad = np.zeros(x.shape)
    for index in np.ndindex(*x.shape):
        up, down = x.copy(), x.copy()
        up[index] += step
        down[index] -= step
        grad[index] = (float(fn(up)) - float(fn(down))) / (2 * step)
    return grad


def test_gradients_with_respect_to_both_levels_match_finite_differences():
    hit = INTERSECTOR.intersect(
        rt.Ray(ORIGIN, DIRECTION),
        rt.build_instance_structure(
            [
                rt.build_instance_structure(
                    [rt.build_primitive_structure(rt.TriangleGeometry(TRIANGLES.reshape(-1, 3)))],
                    rt.Instances([0], INNER[None]),
                )
            ],
            rt.Instances([0], OUTER[None]),
        ),
    )
    assert (np.asarray(hit.type) != 0).all(), "every ray must hit for the gradient check"
    loss = jax.jit(_loss)
    grad_inner, grad_outer = jax.jit(jax.grad(_loss, argnums=(0, 1)))(INNER, OUTER)
    assert np.isfinite(np.asarray(grad_inner)).all() and np.isfinite(np.asarray(grad_outer)).all()
    fd_inner = _finite_difference(lambda m: loss(m.astype(np.float32), OUTER), INNER.astype(np.float64), 1e-2)
    fd_outer = _finite_difference(lambda m: loss(INNER, m.astype(np.float32)), OUTER.astype(np.float64), 1e-2)
    np.testing.assert_allclose(np.asarray(grad_inner), fd_inner, rtol=2e-2, atol=2e-2)
    np.testing.assert_allclose(np.asarray(grad_outer), fd_outer, rtol=2e-2, atol=2e-2)


def test_distance_gradient_of_a_translation_is_exact():
    # A ray straight down onto a horizontal triangle lifted by t_z: distance = o_z - t_z, so d/dt_z = -1.
    triangle = np.array([[-1, -1, 0], [2, -1, 0], [-1, 2, 0]], np.float32)
    blas = rt.build_primitive_structure(rt.TriangleGeometry(triangle))
    ray = rt.Ray(np.array([0.1, 0.1, 3.0], np.float32), np.array([0, 0, -1], np.float32))

    def distance(transform):
        scene = rt.build_instance_structure([blas], rt.Instances([0], transform[None]))
        return rt.Intersector(rt.tags.instancing).intersect(ray, scene).distance

    transform = np.array([[1, 0, 0, 0.3], [0, 1, 0, -0.2], [0, 0, 1, 0.5]], np.float32)
    grad = np.asarray(jax.grad(distance)(transform))
    assert abs(float(distance(transform)) - 2.5) < 1e-6
    np.testing.assert_allclose(grad[:, 3], [0, 0, -1], atol=1e-6)
