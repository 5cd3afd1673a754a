"""Gradients through box primitives (intersection functions) and per-primitive data, against float64
finite differences."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

import jaxrt as rt

FUNCTIONS = rt.intersection_functions


def _spheres(center, radius):
    lower, upper = FUNCTIONS.sphere_bounds(jax.lax.stop_gradient(center), jax.lax.stop_gradient(radius) * 1.001)
    geometry = rt.BoundingBoxGeometry(lower, upper, primitive_data={"center": center, "radius": radius})
    return rt.build_primitive_structure(geometry)


def _rays(rng, center, radius, count):
    """Rays from outside aimed at random points of the spheres' front halves (no grazing rays)."""
    pick = rng.integers(0, len(center), count)
    direction = rng.normal(size=(count, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    lateral = rng.normal(size=(count, 3))
    lateral -= (lateral * direction).sum(1, keepdims=True) * direction
    lateral /= np.linalg.norm(lateral, axis=1, keepdims=True)
    offset = lateral * radius[pick, None] * rng.uniform(0, 0.7, (count, 1))
    origin = center[pick] + offset - 4 * direction
    return origin, direction


def test_sphere_distance_gradients_match_float64_finite_differences():
    with jax.enable_x64(True):
        rng = np.random.default_rng(0)
        center = rng.uniform(-3, 3, (6, 3)) * np.array([1.0, 1.0, 1.0])
        center[:, 0] = np.arange(6) * 2.5  # apart: each ray hits the sphere it aims at
        radius = rng.uniform(0.4, 1.0, 6)
        origin, direction = _rays(rng, center, radius, 32)
        intersector = rt.Intersector(intersection_functions={0: FUNCTIONS.sphere})

        def total(c, r, o, d):
            hit = intersector.intersect(rt.Ray(o, d), _spheres(c, r))
            return jnp.sum(jnp.where(jnp.isfinite(hit.distance), hit.distance, 0.0)), hit

        args = [jnp.asarray(a) for a in (center, radius, origin, direction)]
        # The gradient and the shifted values as compiled programs, one each (eagerly, each operation of the
        # build and its derivative compiles on its own).
        (_, hit), grads = jax.jit(jax.value_and_grad(total, argnums=(0, 1, 2, 3), has_aux=True))(*args)
        shifted_total = jax.jit(total)
        assert np.all(np.asarray(hit.type) == int(rt.IntersectionType.BOUNDING_BOX))
        step = 1e-5
        for index, grad in enumerate(grads):
            base = np.asarray(args[index])
            rng_dir = np.random.default_rng(index).normal(size=base.shape)
            shifted = [list(args) for _ in range(4)]
            for k, s in enumerate((-2, -1, 1, 2)):
                shifted[k][index] = jnp.asarray(base + s * step * rng_dir)
            f = [float(shifted_total(*a)[0]) for a in shifted]
            numeric = (f[0] - 8 * f[1] + 8 * f[2] - f[3]) / (12 * step)
            analytic = float(np.sum(np.asarray(grad) * rng_dir))
            # Five-point differences of a smooth function in float64 agree to about 1e-8 relative.
            assert abs(numeric - analytic) <= 1e-6 * max(1.0, abs(numeric)), (index, numeric, analytic)


def test_misses_have_zero_gradients_and_no_nan():
    rng = np.random.default_rng(1)
    center = jnp.asarray(rng.uniform(-1, 1, (4, 3)), jnp.float32)
    radius = jnp.full((4,), 0.2, jnp.float32)
    intersector = rt.Intersector(intersection_functions={0: FUNCTIONS.sphere})
    origin = jnp.asarray([[50.0, 50, 50], [0, 0, -5], [1e30, 0, 0]], jnp.float32)
    direction = jnp.asarray([[0.0, 0, 1], [0, 0, 0], [1, 0, 0]], jnp.float32)  # a miss, disabled, far away

    def total(c, r):
        hit = intersector.intersect(rt.Ray(origin, direction), _spheres(c, r))
        return jnp.sum(jnp.where(jnp.isfinite(hit.distance), hit.distance, 0.0))

    grads = jax.jit(jax.grad(total, argnums=(0, 1)))(center, radius)
    for grad in grads:
        assert np.all(np.asarray(grad) == 0.0)


def test_primitive_data_gradient_is_the_hit_indicator():
    """d(sum of the hit primitives' data)/d(data) counts how often each primitive is hit."""
    rng = np.random.default_rng(2)
    vertices = rng.uniform(-1, 1, (60, 3)).astype(np.float32)
    weight = jnp.asarray(rng.uniform(0, 1, 20), jnp.float32)
    origin = rng.uniform(-1, 1, (128, 3)).astype(np.float32)
    origin[:, 2] = -3
    rays = rt.Ray(origin, np.tile(np.float32([0, 0, 1]), (128, 1)))
    intersector = rt.Intersector(rt.tags.primitive_data)

    def total(w):
        structure = rt.build_primitive_structure(rt.TriangleGeometry(vertices, primitive_data={"w": w}))
        return jnp.sum(intersector.intersect(rays, structure).primitive_data["w"]), intersector.intersect(
            rays, structure
        )

    grad, hit = jax.jit(jax.grad(total, has_aux=True))(weight)
    ids = np.asarray(hit.primitive_id)
    expected = np.bincount(ids[ids >= 0], minlength=20).astype(np.float32)
    np.testing.assert_array_equal(np.asarray(grad), expected)
    assert expected.sum() > 0
