"""Compiled code is reused: checked through JAX's compilation events, not timers.

``jax.monitoring`` reports ``/jax/core/compile/jaxpr_to_mlir_module_duration`` each time a computation is
lowered for compilation (an in-memory cache miss, whether or not a persistent cache then serves it) and
``/jax/core/compile/backend_compile_duration`` each time XLA compiles. Shapes here are unique to this module,
so the first calls compile and the assertions on the later ones are meaningful.
"""

from __future__ import annotations

import contextlib

import jax
import numpy as np
import pytest

import jaxrt as rt

_EVENTS = ("/jax/core/compile/jaxpr_to_mlir_module_duration", "/jax/core/compile/backend_compile_duration")
INTERSECTOR = rt.Intersector(rt.tags.triangle_data, accept_any_intersection=True)


@contextlib.contextmanager
def compilations():
    """Collect the names of the functions lowered or compiled inside the block."""
    names: list[str] = []

    def listener(event, duration, **kwargs):
        if event in _EVENTS:
            names.append(f"{event.rsplit('/', 1)[-1]}:{kwargs.get('fun_name', '?')}")

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        yield names
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)


def _geometry(count, seed):
    rng = np.random.default_rng(seed)
    return rt.TriangleGeometry(rng.normal(size=(count * 3, 3)).astype(np.float32))


def _rays(count, seed):
    rng = np.random.default_rng(seed)
    return rt.Ray(rng.normal(size=(count, 3)).astype(np.float32), rng.normal(size=(count, 3)).astype(np.float32))


def test_second_call_with_the_same_shapes_does_not_recompile():
    with compilations() as first:
        structure = rt.build_primitive_structure(_geometry(37, 0), capacity=1024)
        jax.block_until_ready(INTERSECTOR.intersect(_rays(300, 1), structure).distance)
    assert first, "the listener saw no compilation: the check below would be vacuous"
    with compilations() as second:
        structure = rt.build_primitive_structure(_geometry(37, 2), capacity=1024)  # new values, same shapes
        jax.block_until_ready(INTERSECTOR.intersect(_rays(300, 3), structure).distance)
        equal = rt.Intersector(rt.tags.triangle_data, accept_any_intersection=True)  # an equal, new intersector
        jax.block_until_ready(equal.intersect(_rays(300, 4), structure).distance)
    assert second == [], f"recompiled: {second}"


def test_ray_counts_in_one_power_of_two_bucket_share_compiled_code():
    structure = rt.build_primitive_structure(_geometry(41, 5), capacity=1024)
    other = rt.build_primitive_structure(_geometry(41, 6), capacity=2048)
    with compilations() as first:
        jax.block_until_ready(INTERSECTOR.intersect(_rays(520, 7), structure).distance)  # bucket 1024
    assert first
    # The eager padding and slicing of a 700-ray batch compile once, here on another structure.
    jax.block_until_ready(INTERSECTOR.intersect(_rays(700, 8), other).distance)
    with compilations() as second:
        result = INTERSECTOR.intersect(_rays(700, 9), structure)  # same bucket as 520 rays
        jax.block_until_ready(result.distance)
    assert second == [], f"recompiled: {second}"
    assert result.distance.shape == (700,)


def test_new_structure_of_the_same_capacity_does_not_recompile_the_traversal():
    rays = _rays(300, 10)
    first = rt.build_primitive_structure(_geometry(37, 11), capacity=1024)  # the shapes of the first test
    jax.block_until_ready(INTERSECTOR.intersect(rays, first).distance)
    second = rt.build_primitive_structure(_geometry(38, 12), capacity=1024)  # another count, same capacity
    with compilations() as names:
        jax.block_until_ready(INTERSECTOR.intersect(rays, second).distance)
    assert names == [], f"recompiled: {names}"


def test_build_inside_jit_with_same_shapes_does_not_recompile():
    @jax.jit
    def build(vertices):
        return rt.build_primitive_structure(rt.TriangleGeometry(vertices), capacity=1024).node_lower

    rng = np.random.default_rng(13)
    jax.block_until_ready(build(rng.normal(size=(45 * 3, 3)).astype(np.float32)))
    with compilations() as names:
        jax.block_until_ready(build(rng.normal(size=(45 * 3, 3)).astype(np.float32)))
    assert names == []


def test_closed_over_rays_are_named_inside_jit_only(monkeypatch):
    """Large concrete rays or structure arrays reaching ``intersect`` inside ``jax.jit`` (closed over, so folded
    into the program as constants) give a warning; the same call with them as arguments, or eagerly, does not."""
    import warnings

    from jaxrt._src import intersector as module

    monkeypatch.setattr(module, "CLOSED_OVER_BYTES", 1024)
    structure = rt.build_primitive_structure(_geometry(16, 0))
    rays = _rays(64, 1)
    intersector = rt.Intersector()
    with pytest.warns(module.ClosedOverConstantsWarning, match="as arguments"):
        jax.jit(lambda: intersector.intersect(rays, structure).distance)()
    with warnings.catch_warnings():
        warnings.simplefilter("error", module.ClosedOverConstantsWarning)
        jax.jit(lambda r, s: intersector.intersect(r, s).distance)(rays, structure)
        intersector.intersect(rays, structure)
