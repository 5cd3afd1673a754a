"""Analytic intersection functions (sphere, disk, capped cylinder) against float64 closed forms."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import jaxrt as rt
from jaxrt._src.candidate import BoundingBoxCandidate

FUNCTIONS = rt.intersection_functions


def _candidate(data, lower=(0.0, 0.0, 0.0), upper=(1.0, 1.0, 1.0)):
    dtype = jnp.float64 if jax.config.jax_enable_x64 else jnp.float32
    data = None if data is None else {k: v if isinstance(v, jax.Array) else jnp.asarray(v, dtype) for k, v in data.items()}
    return BoundingBoxCandidate(jnp.int32(0), jnp.int32(0), jnp.asarray(lower, dtype), jnp.asarray(upper, dtype), data)


def _ray(o, d, t_max=np.inf):
    return rt.Ray(np.asarray(o, np.float32), np.asarray(d, np.float32), 0.0, t_max)


def _roots(a, b, c):
    disc = b * b - 4 * a * c
    if disc < 0 or a == 0:
        return []
    s = np.sqrt(disc)
    return [(-b - s) / (2 * a), (-b + s) / (2 * a)]


def sphere_reference(o, d, center, radius):
    f = o - center
    return [t for t in _roots(d @ d, 2 * f @ d, f @ f - radius * radius) if t >= 0]


def disk_reference(o, d, center, normal, radius):
    denom = d @ normal
    if denom == 0:
        return []
    t = (center - o) @ normal / denom
    p = o + t * d - center
    return [t] if t >= 0 and p @ p <= radius * radius else []


def cylinder_reference(o, d, p0, p1, radius, t_min=0.0):
    axis = (p1 - p0) / np.linalg.norm(p1 - p0)
    length = np.linalg.norm(p1 - p0)
    oc = o - p0
    dp, op = d - axis * (d @ axis), oc - axis * (oc @ axis)
    hits = [t for t in _roots(dp @ dp, 2 * op @ dp, op @ op - radius * radius)
            if t >= t_min and 0 <= (oc + t * d) @ axis <= length]
    if d @ axis != 0:
        for plane in (0.0, length):
            t = (plane - oc @ axis) / (d @ axis)
            q = oc + t * d
            q = q - axis * (q @ axis)
            if t >= t_min and q @ q <= radius * radius:
                hits.append(t)
    return hits


vec = st.tuples(*[st.floats(-3, 3)] * 3).map(np.array)


def _direction(v):
    n = np.linalg.norm(v)
    return v / n if n > 0.1 else np.array([0.0, 0.0, 1.0])


def _check(accept, distance, reference, scale):
    if not reference:
        assert not bool(accept)
        assert np.isinf(float(distance))
    else:
        assert bool(accept)
        assert abs(float(distance) - min(reference)) <= 1e-4 * scale


def _well_conditioned(values, margin):
    return all(abs(v) > margin for v in values)


@settings(max_examples=150)
@given(o=vec, d=vec, center=vec, radius=st.floats(0.1, 2.0))
def test_sphere_matches_float64(o, d, center, radius):
    d = _direction(d)
    f = o - center
    closest = f - d * (f @ d)
    # Skip near-tangent rays and origins near the surface, where float32 and float64 may disagree on hit/miss.
    if not _well_conditioned([closest @ closest - radius**2, f @ f - radius**2], 1e-3):
        return
    accept, distance = FUNCTIONS.sphere(_ray(o, d), _candidate({"center": center, "radius": radius}))
    _check(accept, distance, sphere_reference(o, d, center, radius), 1 + np.linalg.norm(f))


@settings(max_examples=150)
@given(o=vec, d=vec, center=vec, normal=vec, radius=st.floats(0.1, 2.0))
def test_disk_matches_float64(o, d, center, normal, radius):
    d, normal = _direction(d), _direction(normal)
    denom = d @ normal
    if abs(denom) < 1e-3:
        return
    t = (center - o) @ normal / denom
    p = o + t * d - center
    if not _well_conditioned([p @ p - radius**2, t], 1e-3):
        return
    data = {"center": center, "normal": normal, "radius": radius}
    accept, distance = FUNCTIONS.disk(_ray(o, d), _candidate(data))
    _check(accept, distance, disk_reference(o, d, center, normal, radius), 1 + abs(t))


@settings(max_examples=150)
@given(o=vec, d=vec, p0=vec, p1=vec, radius=st.floats(0.1, 1.5))
def test_capped_cylinder_matches_float64(o, d, p0, p1, radius):
    d = _direction(d)
    if np.linalg.norm(p1 - p0) < 0.2:
        return
    hits = cylinder_reference(o, d, p0, p1, radius)
    # Skip rays that graze an edge or the wall: perturbing the radius must not change the hit count.
    if len(cylinder_reference(o, d, p0, p1, radius * 1.001)) != len(hits) or len(
        cylinder_reference(o, d, p0, p1, radius * 0.999)
    ) != len(hits):
        return
    near = cylinder_reference(o, d, p0, p1, radius, t_min=-1e-3)
    if near and min(near) < 1e-3:  # the origin lies on the surface
        return
    data = {"p0": p0, "p1": p1, "radius": radius}
    accept, distance = FUNCTIONS.capped_cylinder(_ray(o, d), _candidate(data))
    _check(accept, distance, hits, 1 + np.linalg.norm(o - p0) + np.linalg.norm(p1 - p0))


def test_sphere_without_data_is_inscribed_in_the_box():
    accept, distance = FUNCTIONS.sphere(_ray([0.5, 0.5, -2], [0, 0, 1]), _candidate(None, [0, 0, 0], [1, 1, 1]))
    assert bool(accept) and float(distance) == pytest.approx(2.0, abs=1e-6)


def test_origin_inside_sphere_returns_the_far_root_and_max_distance_is_respected():
    candidate = _candidate({"center": [0, 0, 0], "radius": 1.0})
    accept, distance = FUNCTIONS.sphere(_ray([0, 0, 0], [0, 0, 1]), candidate)
    assert bool(accept) and float(distance) == pytest.approx(1.0, abs=1e-6)
    accept, distance = FUNCTIONS.sphere(_ray([0, 0, -3], [0, 0, 1], t_max=1.5), candidate)
    assert not bool(accept) and np.isinf(float(distance))


def test_parallel_ray_misses_disk_without_nan():
    candidate = _candidate({"center": [0, 0, 0], "normal": [0, 0, 1], "radius": 1.0})

    def distance(o):
        accept, t = FUNCTIONS.disk(rt.Ray(o, jnp.array([1.0, 0, 0])), candidate)
        return jnp.where(accept, t, 0.0)

    grad = jax.grad(distance)(jnp.array([-2.0, 0.0, 0.0]))
    assert float(distance(jnp.array([-2.0, 0.0, 0.0]))) == 0.0
    assert np.all(np.isfinite(np.asarray(grad)))


@pytest.mark.parametrize("name", ["sphere", "capped_cylinder"])
def test_gradients_match_central_differences(name):
    data = {"sphere": {"center": [0.1, -0.2, 0.0], "radius": 0.8},
            "capped_cylinder": {"p0": [0, -1, 0.2], "p1": [0, 1, 0.2], "radius": 0.7}}[name]
    fn = getattr(FUNCTIONS, name)

    def distance(origin, radius):
        params = dict(data, radius=radius)
        return fn(rt.Ray(origin, jnp.array([0.1, 0.05, 1.0])), _candidate(params))[1]

    with jax.enable_x64(True):
        origin, radius = jnp.array([0.05, 0.1, -3.0], jnp.float64), jnp.float64(data["radius"])
        grad_o, grad_r = jax.grad(distance, argnums=(0, 1))(origin, radius)
        eps = 1e-6
        for k in range(3):
            step = jnp.zeros(3).at[k].set(eps)
            fd = (distance(origin + step, radius) - distance(origin - step, radius)) / (2 * eps)
            assert float(grad_o[k]) == pytest.approx(float(fd), rel=1e-4, abs=1e-6)
        fd = (distance(origin, radius + eps) - distance(origin, radius - eps)) / (2 * eps)
        assert float(grad_r) == pytest.approx(float(fd), rel=1e-4, abs=1e-6)


def test_bounds_contain_the_shapes():
    lower, upper = FUNCTIONS.disk_bounds([[0.0, 0, 0]], [[0.0, 0, 1]], [2.0])
    np.testing.assert_allclose(np.asarray(lower), [[-2, -2, 0]], atol=1e-6)
    np.testing.assert_allclose(np.asarray(upper), [[2, 2, 0]], atol=1e-6)
    lower, upper = FUNCTIONS.capped_cylinder_bounds([[0.0, 0, 0]], [[0.0, 3, 0]], [1.0])
    np.testing.assert_allclose(np.asarray(lower), [[-1, 0, -1]], atol=1e-6)
    np.testing.assert_allclose(np.asarray(upper), [[1, 3, 1]], atol=1e-6)


def test_bounding_box_geometry_validation():
    with pytest.raises(ValueError, match="inverted on axis 1"):
        rt.BoundingBoxGeometry([[0.0, 1, 0]], [[1.0, 0, 1]])
    with pytest.raises(ValueError, match="non-finite"):
        rt.BoundingBoxGeometry([[0.0, np.nan, 0]], [[1.0, 1, 1]])
    with pytest.raises(ValueError, match="empty"):
        rt.BoundingBoxGeometry(np.zeros((0, 3)), np.zeros((0, 3)))
    with pytest.raises(TypeError, match="float32 or float64"):
        rt.BoundingBoxGeometry(np.zeros((1, 3), int), np.ones((1, 3), int))
    with pytest.raises(ValueError, match="leading dimension"):
        rt.BoundingBoxGeometry(np.zeros((2, 3)), np.ones((2, 3)), primitive_data={"r": np.ones(3)})
