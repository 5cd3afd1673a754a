"""Property tests: the BVH traversal against the float64 brute-force oracle on random scenes and rays.

Scenes have a fixed triangle count over three geometries and ray batches a fixed size (see ``scenes.py``), so
each test compiles its build and traversal once and hypothesis examples only run them.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from reference import (
    LARGE_BATCH,
    LARGE_CAPACITY,
    SMALL_CAPACITY,
    assert_matches_reference,
    brute_force,
    check_nearest,
    check_watertight,
    crosses_loop,
    global_index,
)
from scenes import GEOMETRY_COUNTS, RAYS, far_exponents, random_rays, random_scene, scale_exponents, seeds

import jaxrt as rt

NEAREST = rt.Intersector(rt.tags.triangle_data, rt.tags.stats)
ANY = rt.Intersector(accept_any_intersection=True)


def _scene_and_rays(seed, far_exp, scale_exp, **kw):
    scene = random_scene(seed, far_exp, scale_exp)
    rays = random_rays(seed ^ 0x5EED, scene, **kw)
    return scene, rays


def _reference(scene, rays, **kw):
    return brute_force(rays.origin, rays.direction, rays.min_distance, rays.max_distance, scene.triangles, **kw)


@given(seeds, far_exponents, scale_exponents)
def test_nearest_hit_matches_brute_force(seed, far_exp, scale_exp):
    scene, rays = _scene_and_rays(seed, far_exp, scale_exp)
    structure = rt.build_primitive_structure(scene.geometries, capacity=SMALL_CAPACITY)
    result = NEAREST.intersect(rays.ray(), structure)
    ref = _reference(scene, rays)
    assert_matches_reference(result, ref, scene.counts)

    # Winding of the hit triangle against the float64 sign of dot(cross(v1 - v0, v2 - v0), d).
    hit = np.asarray(result.type) == int(rt.IntersectionType.TRIANGLE)
    k = global_index(result.geometry_id, result.primitive_id, scene.counts)
    rows = np.flatnonzero(hit)
    clockwise = ref.clockwise[rows, k[rows]]
    front = np.asarray(result.triangle_front_facing)[rows]
    decided = clockwise != 0
    np.testing.assert_array_equal(front[decided], clockwise[decided] > 0)
    assert not np.asarray(result.triangle_front_facing)[~hit].any()

    # Watertightness inside the connected grid patch (geometry 0).
    crossing = crosses_loop(rays.origin, rays.direction, rays.min_distance, rays.max_distance, scene.patch_loop)
    failures = check_watertight(result, ref, crossing, np.arange(GEOMETRY_COUNTS[0]))
    assert not failures, failures


@given(seeds, far_exponents, scale_exponents)
def test_any_hit_agrees_with_nearest_hit_on_occlusion(seed, far_exp, scale_exp):
    scene, rays = _scene_and_rays(seed, far_exp, scale_exp)
    structure = rt.build_primitive_structure(scene.geometries, capacity=SMALL_CAPACITY)
    nearest = NEAREST.intersect(rays.ray(), structure)
    occluded = ANY.intersect(rays.ray(), structure)
    np.testing.assert_array_equal(np.asarray(occluded.type), np.asarray(nearest.type))
    # The reported hit is a genuine one (not necessarily the nearest) with the right distance.
    assert_matches_reference(occluded, _reference(scene, rays), scene.counts, any_hit=True)
    assert set(occluded) == {"type", "distance", "primitive_id", "geometry_id"}


@given(seeds, far_exponents, scale_exponents)
def test_build_inside_jit_equals_build_outside(seed, far_exp, scale_exp):
    scene = random_scene(seed, far_exp, scale_exp)
    outside = rt.build_primitive_structure(scene.geometries, capacity=SMALL_CAPACITY)
    leaves = [(g.vertices, g.indices) for g in scene.geometries]
    inside = _jitted_build(leaves)
    assert jax.tree_util.tree_structure(inside) == jax.tree_util.tree_structure(outside)
    for a, b in zip(jax.tree_util.tree_leaves(inside), jax.tree_util.tree_leaves(outside), strict=True):
        assert a.dtype == b.dtype and a.shape == b.shape
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@jax.jit
def _jitted_build(leaves):
    return rt.build_primitive_structure([rt.TriangleGeometry(v, i) for v, i in leaves], capacity=SMALL_CAPACITY)


def test_structure_built_and_traced_inside_one_jit():
    scene, rays = _scene_and_rays(7, 3.0, 1.0)

    @jax.jit
    def trace(leaves, origin, direction):
        structure = rt.build_primitive_structure(
            [rt.TriangleGeometry(v, i) for v, i in leaves], capacity=SMALL_CAPACITY
        )
        return NEAREST.intersect(rt.Ray(origin, direction, rays.min_distance, rays.max_distance), structure)

    result = trace(
        [(g.vertices, g.indices) for g in scene.geometries], jnp.asarray(rays.origin), jnp.asarray(rays.direction)
    )
    assert_matches_reference(result, _reference(scene, rays), scene.counts)
    eager = NEAREST.intersect(rays.ray(), rt.build_primitive_structure(scene.geometries, capacity=SMALL_CAPACITY))
    for name in result:
        np.testing.assert_array_equal(np.asarray(result[name]), np.asarray(eager[name]), err_msg=name)


@settings(max_examples=6)
@given(seeds, far_exponents, scale_exponents)
def test_result_independent_of_batch_size_and_shape(seed, far_exp, scale_exp):
    scene, rays = _scene_and_rays(seed, far_exp, scale_exp)
    structure = rt.build_primitive_structure(scene.geometries, capacity=SMALL_CAPACITY)
    flat = NEAREST.intersect(rays.ray(), structure)
    square = NEAREST.intersect(rays.ray().reshape(16, 16), structure)
    part = 137  # not a power of two
    partial = NEAREST.intersect(
        rt.Ray(rays.origin[:part], rays.direction[:part], rays.min_distance[:part], rays.max_distance[:part]),
        structure,
    )
    for name in flat:
        expected = np.asarray(flat[name])
        assert square[name].shape == (16, 16, *expected.shape[1:])
        np.testing.assert_array_equal(np.asarray(square[name]).reshape(expected.shape), expected, err_msg=name)
        assert partial[name].shape == (part, *expected.shape[1:])
        np.testing.assert_array_equal(np.asarray(partial[name]), expected[:part], err_msg=name)
    for r in (0, 5, RAYS - 1):
        single = NEAREST.intersect(
            rt.Ray(rays.origin[r], rays.direction[r], rays.min_distance[r], rays.max_distance[r]), structure
        )
        for name in flat:
            assert single[name].shape == flat[name].shape[1:]
            np.testing.assert_array_equal(np.asarray(single[name]), np.asarray(flat[name])[r], err_msg=name)


def test_batch_larger_than_the_traversal_window_gives_the_same_results():
    """Thousands of rays in one call (more than the traversal keeps in flight) trace like 256 at a time, and a
    structure with more padding gives the same results (the radix tree of the real keys does not change)."""
    scene = random_scene(11, 4.5, 2.0)
    rays = random_rays(12, scene, count=LARGE_BATCH)
    small = rt.build_primitive_structure(scene.geometries, capacity=SMALL_CAPACITY)
    large = rt.build_primitive_structure(scene.geometries, capacity=LARGE_CAPACITY)
    big = NEAREST.intersect(rays.ray(), large)
    for i in range(0, LARGE_BATCH, RAYS):
        s = slice(i, i + RAYS)
        part = NEAREST.intersect(
            rt.Ray(rays.origin[s], rays.direction[s], rays.min_distance[s], rays.max_distance[s]), small
        )
        for name in part:
            np.testing.assert_array_equal(np.asarray(big[name])[s], np.asarray(part[name]), err_msg=name)
    ref = brute_force(rays.origin, rays.direction, rays.min_distance, rays.max_distance, scene.triangles)
    assert_matches_reference(big, ref, scene.counts)


@settings(max_examples=6)
@pytest.mark.parametrize(
    "cull, winding",
    [("front", "clockwise"), ("back", "clockwise"), ("front", "counterclockwise")],
)
@given(seed=seeds, far_exp=far_exponents, scale_exp=scale_exponents)
def test_cull_mode_and_winding_match_float64_orientation(cull, winding, seed, far_exp, scale_exp):
    scene, rays = _scene_and_rays(seed, far_exp, scale_exp)
    structure = rt.build_primitive_structure(scene.geometries, capacity=SMALL_CAPACITY)
    intersector = rt.Intersector(rt.tags.triangle_data, triangle_cull_mode=cull, front_facing_winding=winding)
    result = intersector.intersect(rays.ray(), structure)
    ref = _reference(scene, rays, cull=cull, front_facing_winding=winding)
    assert_matches_reference(result, ref, scene.counts)
    hit = np.asarray(result.type) == int(rt.IntersectionType.TRIANGLE)
    # Every surviving hit faces the side that is not culled.
    np.testing.assert_array_equal(np.asarray(result.triangle_front_facing)[hit], cull == "back")


@given(seeds, far_exponents, scale_exponents)
def test_min_and_max_distance_are_honoured(seed, far_exp, scale_exp):
    """Every ray gets an interval around its target: hits lie inside it, and nearer hits are skipped."""
    scene = random_scene(seed, far_exp, scale_exp)
    rays = random_rays(seed ^ 0xD15, scene, intervals=False)
    structure = rt.build_primitive_structure(scene.geometries, capacity=SMALL_CAPACITY)
    unbounded = NEAREST.intersect(rays.ray(), structure)
    first = np.asarray(unbounded.distance)
    # Start just past the first hit (where there is one) and stop at three times that distance.
    rng = np.random.default_rng(seed)
    tmin = np.where(np.isfinite(first), first * np.float32(1.0001), rng.uniform(0, 10, RAYS)).astype(np.float32)
    tmax = np.where(np.isfinite(first), first * 3, np.inf).astype(np.float32)
    bounded = rt.Ray(rays.origin, rays.direction, tmin, tmax)
    result = NEAREST.intersect(bounded, structure)
    distance = np.asarray(result.distance)
    hit = np.isfinite(distance)
    assert np.all(distance[hit] >= tmin[hit]) and np.all(distance[hit] <= tmax[hit])
    ref = brute_force(rays.origin, rays.direction, tmin, tmax, scene.triangles)
    assert_matches_reference(result, ref, scene.counts)
    failures = check_nearest(ANY.intersect(bounded, structure), ref, scene.counts, any_hit=True)
    assert not failures, failures
