"""The candidate-wave loop (``jaxrt._src.traversal.waves``) on the CPU, with a brute-force lister in JAX.

The GPU kernel lists each ray's ``K`` first candidates past its cursor (``test_gpu_waves.py`` runs it, in
Triton's interpreter or on a GPU). Here the same listing is computed by brute force over every leaf (the
watertight triangle test without the filter, each box at its slab entry distance, sorted by ``(distance,
leaf)``), so the loop itself (deciding the candidates with the portable leaf tests, merging, moving cursors,
ending rays) is checked on any machine: against the float64 reference of ``test_custom_geometry.py`` and the
portable traversal, for nearest and any hit, ``max_hits`` and counting, with 1 to 3 candidates per wave (few
candidates: many waves; the default counts run in ``test_gpu_waves.py``).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_custom_geometry import (
    CYLINDERS,
    DISKS,
    SPHERES,
    alpha_filter,
    assert_nearest,
    build,
    check_any,
    expected,
    random_rays,
    random_scene,
)

import jaxrt as rt
from jaxrt._src import leaves as leaf_tests
from jaxrt._src import pipeline
from jaxrt._src.numerics import safe_reciprocal
from jaxrt._src.primitives import box
from jaxrt._src.scene_view import scene_view
from jaxrt._src.traversal import waves
from jaxrt._src.traversal.scene import TraversalResult
from jaxrt._src.traversal.step import HitList

RAYS = 96


def _wrap(fn):
    """A user function (not recognised as built-in) calling ``fn``."""

    def user(ray, candidate):
        return fn(ray, candidate)

    return user


FUNCTIONS = {
    SPHERES: _wrap(rt.intersection_functions.sphere),
    DISKS: _wrap(rt.intersection_functions.disk),
    CYLINDERS: _wrap(rt.intersection_functions.capped_cylinder),
}


def brute_force_lister(intersector, view, rays):
    """``(K, t_max, enabled, cursor_t, cursor_leaf) -> TraversalResult``: each ray's ``K`` first candidates past
    its cursor, in ``(distance, leaf)`` order, over every leaf (the kernel's wave, by brute force)."""
    triangles = leaf_tests.TriangleLeaves(view.leaves.triangle, intersector.cull)
    is_box = view.leaf_flag(view.slot_table(leaf_tests.box_slots(view)), jnp.arange(view.leaves.geometry.shape[0]))
    real = view.leaves.geometry >= 0
    leaves = jnp.arange(view.leaves.geometry.shape[0], dtype=jnp.int32)

    def one(k, origin, direction, t_min, t_max, enabled, cursor_t, cursor_leaf):
        context = triangles.prepare(origin, direction, None)
        hit, t = triangles(context, leaves, t_min, t_max)
        if view.leaves.box is not None:
            inside, entry = box.ray_box(
                origin, safe_reciprocal(direction), t_min, t_max, view.leaves.box[:, 0], view.leaves.box[:, 1]
            )
            hit, t = jnp.where(is_box, inside, hit & ~is_box), jnp.where(is_box, entry, t)
        past = hit & real & enabled & ((t > cursor_t) | ((t == cursor_t) & (leaves > cursor_leaf)))
        key = jnp.where(past, t, jnp.inf)
        order = jnp.lexsort((leaves, key))[:k]
        listed = past[order]
        return jnp.where(listed, key[order], jnp.inf), jnp.where(listed, leaves[order], -1), jnp.sum(past)

    def list_candidates(k, t_max, enabled, cursor_t, cursor_leaf):
        args = (rays.origin, rays.direction, rays.t_min, t_max, enabled, cursor_t, cursor_leaf)
        distance, leaf, total = jax.vmap(functools.partial(one, k))(*args)
        n = total.shape[0]
        zeros = jnp.zeros((n,), jnp.int32)
        return TraversalResult(distance[:, 0], leaf[:, 0], jnp.zeros((n, 0), jnp.int32), zeros, zeros,
                               jnp.zeros((n,), bool), HitList(distance, leaf, total.astype(jnp.int32)))  # fmt: skip

    return list_candidates


@functools.partial(jax.jit, static_argnums=(0, 3, 4))
def trace_in_waves(intersector, structure, ray, first: int, later: int):
    """The intersector's result with the traversal in waves of the brute-force lister."""
    view = scene_view(structure)
    rays = pipeline.sanitized_rays(ray)
    tester = leaf_tests.leaf_tester(intersector, view)
    found = waves.trace_waves(intersector, tester, rays, brute_force_lister(intersector, view, rays),
                              candidates=first, later=later)  # fmt: skip
    return found


@functools.partial(jax.jit, static_argnums=0)
def _portable(intersector, structure, ray):
    """The portable traversal's result: one compiled program per intersector, shared by the parametrizations
    (the structure and rays are arguments, not constants folded into each call's program)."""
    return pipeline._trace_portable(intersector, scene_view(structure), pipeline.sanitized_rays(ray))


def _intersector(**kw):
    return rt.Intersector(intersection_functions=FUNCTIONS, filter=alpha_filter, backend="portable", **kw)


def _as_result(found, intersector, structure, ray):
    """The public result fields for a traversal result (as ``Intersector.intersect`` assembles them)."""
    from jaxrt._src import fields as result_fields

    view = scene_view(structure)
    rays = pipeline.sanitized_rays(ray)
    geometry = (rays.origin, rays.direction, rays.t_min, rays.t_max)
    fields = result_fields.hit_fields(intersector, view, *geometry, found.leaf, found.distance, found.instances)
    return rt.IntersectionResult(fields)


@pytest.mark.parametrize("first, later", [(1, 1), (2, 3)])
def test_nearest_in_waves(first, later):
    scene = random_scene(21)
    structure = build(scene)
    rays = random_rays(22, scene, RAYS)
    inter = _intersector()
    found = trace_in_waves(inter, structure, rays.ray(), first, later)
    want = _portable(inter, structure, rays.ray())
    np.testing.assert_array_equal(np.asarray(found.leaf), np.asarray(want.leaf))
    hit = np.asarray(want.leaf) >= 0
    np.testing.assert_allclose(np.asarray(found.distance)[hit], np.asarray(want.distance)[hit], rtol=1e-6)
    assert hit.sum() > 20
    assert_nearest(_as_result(found, inter, structure, rays.ray()), expected(scene, rays))


@pytest.mark.parametrize("first, later", [(1, 2)])
def test_any_hit_in_waves(first, later):
    scene = random_scene(23)
    structure = build(scene)
    rays = random_rays(24, scene, RAYS)
    options = dict(accept_any_intersection=True, triangle_cull_mode="front", front_facing_winding="counterclockwise")
    inter = _intersector(**options)
    found = trace_in_waves(inter, structure, rays.ray(), first, later)
    want = _portable(inter, structure, rays.ray())
    np.testing.assert_array_equal(np.asarray(found.leaf) >= 0, np.asarray(want.leaf) >= 0)
    failures, _ = check_any(
        _as_result(found, inter, structure, rays.ray()),
        expected(scene, rays, cull="front", front_facing_winding="counterclockwise"),
    )
    assert not failures, "\n".join(failures[:20])


@pytest.mark.parametrize("first, later", [(1, 2)])
def test_hit_lists_and_counts_in_waves(first, later):
    scene = random_scene(25)
    structure = build(scene)
    ray = random_rays(26, scene, RAYS).ray()
    listing = _intersector(max_hits=3)
    found = trace_in_waves(listing, structure, ray, first, later)
    want = _portable(listing, structure, ray)
    np.testing.assert_array_equal(np.asarray(found.hits.leaf), np.asarray(want.hits.leaf))
    np.testing.assert_array_equal(np.minimum(found.hits.total, 4), np.minimum(want.hits.total, 4))
    np.testing.assert_allclose(np.asarray(found.hits.distance), np.asarray(want.hits.distance), rtol=1e-6)
    assert (np.asarray(want.hits.total) >= 2).sum() > 5
    from jaxrt._src.intersector import _CountingIntersector

    counting = _CountingIntersector(intersection_functions=FUNCTIONS, filter=alpha_filter, backend="portable")
    got = trace_in_waves(counting, structure, ray, first, later).hits.total
    np.testing.assert_array_equal(np.asarray(got), np.asarray(_portable(counting, structure, ray).hits.total))
    assert np.asarray(got).max() >= 3
