"""The robustness helpers of ``jaxrt._src.numerics`` (internal) and the public ``offset_ray_origin``."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import given
from hypothesis import strategies as st

import jaxrt as rt
from jaxrt._src.numerics import RECIPROCAL_CLAMP, gamma, safe_reciprocal

F32 = np.finfo(np.float32)
_reciprocal = jax.jit(safe_reciprocal)
_offset = jax.jit(rt.offset_ray_origin)

SPECIAL = np.array(
    [0.0, -0.0, F32.smallest_subnormal, -F32.smallest_subnormal, F32.tiny, -F32.tiny, 1e-36, RECIPROCAL_CLAMP,
     2 * RECIPROCAL_CLAMP, 1e-20, 1.0, -1.0, 3.0, 1e20, 1e35, 1e36, 1e38, F32.max, -F32.max],
    np.float32,
)  # fmt: skip


def _check_reciprocal(x: np.ndarray) -> None:
    r = np.asarray(_reciprocal(x))
    assert np.isfinite(r).all(), x[~np.isfinite(r)]
    assert (r != 0).all(), x[r == 0]
    assert (np.abs(r) >= F32.tiny).all(), "subnormal reciprocal (flushed to zero on some backends)"
    np.testing.assert_array_equal(np.signbit(r), np.signbit(x))
    exact = (np.abs(x) >= 2 * RECIPROCAL_CLAMP) & (np.abs(x) <= 0.5 / RECIPROCAL_CLAMP)
    with np.errstate(divide="ignore", over="ignore"):
        np.testing.assert_array_equal(r[exact], (np.float32(1) / x)[exact])


def test_safe_reciprocal_of_special_values_is_finite_and_non_zero():
    _check_reciprocal(SPECIAL)


@given(st.lists(st.floats(width=32, allow_nan=False, allow_infinity=False), min_size=64, max_size=64))
def test_safe_reciprocal_is_finite_non_zero_and_exact_where_unclamped(values):
    _check_reciprocal(np.array(values, np.float32))


def test_safe_reciprocal_gradient_is_zero_where_clamped():
    x = jnp.array([0.0, -0.0, 1e-40, -1e-38, 2.0, -0.5, 1e37], jnp.float32)
    grad = np.asarray(jax.vmap(jax.grad(safe_reciprocal))(x))
    np.testing.assert_array_equal(grad[[0, 1, 2, 3, 6]], 0.0)
    np.testing.assert_allclose(grad[[4, 5]], [-0.25, -4.0])


def test_safe_reciprocal_keeps_float64_under_x64():
    with jax.enable_x64(True):
        r = safe_reciprocal(jnp.array([0.0, 1e-300, 4.0]))
        assert r.dtype == jnp.float64
        np.testing.assert_array_equal(np.asarray(r)[2], 0.25)
        assert np.isfinite(np.asarray(r)).all()


def test_gamma_matches_its_definition():
    for dtype, unit_roundoff in ((jnp.float32, 2.0**-24), (jnp.float64, 2.0**-53)):
        values = [gamma(n, dtype) for n in range(1, 20)]
        for n, value in enumerate(values, start=1):
            assert value == n * unit_roundoff / (1 - n * unit_roundoff)
            assert value > n * unit_roundoff
        assert all(a < b for a, b in zip(values, values[1:], strict=False))
    assert gamma(3) == gamma(3, jnp.float32)


_magnitudes = st.one_of(st.just(0.0), st.floats(-8.0, 5.0).map(lambda e: 10.0**e))
_points = st.lists(st.tuples(_magnitudes, st.sampled_from([-1.0, 1.0])), min_size=3, max_size=3)
_normals = st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3).filter(lambda n: np.linalg.norm(n) > 0.1)


@given(st.lists(st.tuples(_points, _normals), min_size=32, max_size=32))
def test_offset_ray_origin_moves_points_to_the_normal_side(cases):
    point = np.array([[m * s for m, s in p] for p, _ in cases], np.float32)
    normal = np.array([n for _, n in cases], np.float64)
    normal = (normal / np.linalg.norm(normal, axis=-1, keepdims=True)).astype(np.float32)
    moved = np.asarray(_offset(point, normal))
    assert moved.dtype == np.float32 and np.isfinite(moved).all()
    step = moved.astype(np.float64) - point.astype(np.float64)
    assert (np.sum(step * normal, axis=-1) > 0).all(), "an offset point did not move to the normal's side"
    # Each component moves along its normal component's sign, and by a bounded amount (256 ulp or 2**-16).
    moving = np.abs(normal) >= 1 / 256
    assert (np.sign(step[moving]) == np.sign(normal[moving])).all()
    ulp = np.spacing(np.maximum(np.abs(point), np.abs(moved)).astype(np.float32)).astype(np.float64)
    assert (np.abs(step) <= np.maximum(257 * ulp, 2.0**-16 * 1.01)).all()


def test_offset_ray_origin_batches_and_differentiates():
    point = jnp.ones((2, 5, 3), jnp.float32) * jnp.array([1e-3, 2.0, -3e4])
    normal = jnp.broadcast_to(jnp.array([0.0, 0.6, -0.8]), (2, 5, 3))
    assert rt.offset_ray_origin(point, normal).shape == (2, 5, 3)
    p, n = jnp.array([0.5, -2.0, 1e4]), jnp.array([0.0, 0.6, -0.8])
    np.testing.assert_array_equal(jax.jacobian(rt.offset_ray_origin)(p, n), np.eye(3))
    np.testing.assert_array_equal(jax.jacobian(rt.offset_ray_origin, argnums=1)(p, n), np.zeros((3, 3)))
