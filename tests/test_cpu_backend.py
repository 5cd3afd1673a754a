"""The compiled CPU traversal (``backend="cpu"``, the default on the CPU) against the portable traversal and
the float64 brute force.

The CPU traversal must make the portable traversal's decisions exactly: the same hit or miss, the same
primitive, the same distance to the bit, the same instance chain and the same stats counters, on the hard cases
(closed meshes far from the origin hit through vertices and edges, exact axis-parallel rays, degenerate
triangles, disabled rays), on instanced scenes (two levels, masks, mirrored transforms, culling) and on random
scenes. Every test traces batches of one size through one scene capacity, so each intersector compiles once.
"""

from __future__ import annotations

import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from reference import (
    SMALL_CAPACITY,
    assert_matches_reference,
    brute_force,
    cube,
    edges,
    grid,
    icosphere,
    trace,
)
from scenes import far_exponents, random_rays, random_scene, scale_exponents, seeds
from test_instancing import aimed_rays, flatten
from test_instancing import random_scene as random_instanced_scene

import jaxrt as rt
from jaxrt._src import pipeline
from jaxrt._src.traversal import cpu

pytestmark = pytest.mark.skipif(cpu.unavailable_reason() is not None, reason=str(cpu.unavailable_reason()))

FAR = np.array([148376.0, 1234.0, -223423.0])
FIELDS = ("type", "distance", "primitive_id", "geometry_id", "triangle_barycentric_coord", "triangle_front_facing")
STATS = ("nodes_visited", "primitives_tested", "stack_overflow")


def _pair(*tags, **options) -> tuple[rt.Intersector, rt.Intersector]:
    """The same intersector on the portable traversal and on the CPU traversal."""
    return rt.Intersector(*tags, backend="portable", **options), rt.Intersector(*tags, backend="cpu", **options)


NEAREST = _pair(rt.tags.triangle_data, rt.tags.stats)
ANY_CULLED = _pair(
    rt.tags.triangle_data,
    rt.tags.stats,
    accept_any_intersection=True,
    triangle_cull_mode="front",
    front_facing_winding="counterclockwise",
)
INSTANCED = _pair(rt.tags.instancing, rt.tags.max_levels(2), rt.tags.triangle_data, rt.tags.stats)
INSTANCED_ANY = _pair(
    rt.tags.instancing, rt.tags.max_levels(2), rt.tags.triangle_data, accept_any_intersection=True,
    triangle_cull_mode="back",
)  # fmt: skip


def _assert_same(pair, structure, origin, direction, min_distance=0.0, max_distance=np.inf, mask=0xFFFFFFFF):
    """Trace with both backends (fixed batches, see ``reference.trace``) and require identical fields."""
    portable, compiled = (trace(i, structure, origin, direction, min_distance, max_distance, mask) for i in pair)
    names = [k for k in portable if k in FIELDS + STATS or k in ("instance_id", "instance_count")]
    assert names
    for name in names:
        np.testing.assert_array_equal(np.asarray(compiled[name]), np.asarray(portable[name]), err_msg=name)
    return compiled


def _build(vertices, indices=None):
    vertices = np.asarray(vertices, np.float32)
    return rt.build_primitive_structure(rt.TriangleGeometry(vertices, indices), capacity=SMALL_CAPACITY)


# --- hard cases -------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("pair", [NEAREST, ANY_CULLED], ids=["nearest", "any-culled"])
def test_closed_mesh_far_from_the_origin_through_vertices_and_edges(pair):
    v, f = icosphere(1)
    vertices = (v * [40.0, 25.0, 15.0] + FAR).astype(np.float32)
    structure = _build(vertices, f)
    v64 = vertices.astype(np.float64)
    targets = np.concatenate([v64, v64[edges(f)].mean(axis=1)])
    for origin in (FAR, FAR + [4.0, -5.0, 2.25], FAR + [90.0, 10.0, -60.0]):
        origin = origin.astype(np.float32)
        direction = (targets - origin.astype(np.float64)).astype(np.float32)
        result = _assert_same(pair, structure, origin, direction)
        if pair is NEAREST and np.array_equal(origin, FAR.astype(np.float32)):
            assert (np.asarray(result.type) != 0).all(), "a ray from inside leaked"


@pytest.mark.parametrize("offset", [(0.0, 0.0, 0.0), (131072.0, 4096.0, -65536.0)])
def test_exact_axis_parallel_rays_through_grid_vertices_and_edges(offset):
    v, f = grid(8, 8)
    vertices = (v * 4 + offset).astype(np.float32)
    structure = _build(vertices, f)
    v64 = vertices.astype(np.float64)
    targets = np.concatenate([v64, v64[edges(f)].mean(axis=1)])
    for sign in (1.0, -1.0):
        direction = np.broadcast_to([0.0, 0.0, -sign], targets.shape)
        result = _assert_same(NEAREST, structure, targets + [0.0, 0.0, 5.0 * sign], direction)
        assert (np.asarray(result.type) != 0).all()
        _assert_same(ANY_CULLED, structure, targets + [0.0, 0.0, 5.0 * sign], direction)


def test_axis_parallel_rays_in_box_face_planes():
    s = 2.0
    v, f = cube((-s, -s, -s), (s, s, s))
    structure = _build((v + [65536.0, -32768.0, 1024.0]).astype(np.float32), f)
    points = np.array([-s, -s / 2, 0.0, s / 2, s])
    a, b = (x.ravel() for x in np.meshgrid(points, points))
    for axis in range(3):
        u, w = [i for i in range(3) if i != axis]
        origin = np.zeros((a.size, 3))
        origin[:, u], origin[:, w], origin[:, axis] = a, b, s + 3.0
        direction = np.zeros_like(origin)
        direction[:, axis] = -1.0
        result = _assert_same(NEAREST, structure, origin + [65536.0, -32768.0, 1024.0], direction)
        assert (np.asarray(result.type) != 0).all()


def test_degenerate_triangles_and_disabled_rays():
    point_like = np.array([[[1.0, 1, 1]] * 3, [[2.0, 0, 1], [2.0, 0, 1], [3.0, 1, 1]]])
    collinear = np.array([[[0.0, 0, 1], [1.0, 1, 1], [2.0, 2, 1]], [[0.0, 3, 2], [0.0, 4, 2], [0.0, 5, 2]]])
    wall = np.array([[[-9.0, -9, 5], [9, -9, 5], [0, 9, 5]]])
    triangles = np.concatenate([point_like, collinear, wall]).astype(np.float32)
    structure = _build(triangles.reshape(-1, 3))
    rng = np.random.default_rng(5)
    directions = np.concatenate([np.eye(3), -np.eye(3), rng.normal(size=(20, 3))])
    points = np.concatenate([triangles.mean(1), triangles[:, 0], 0.25 * triangles[:, 1] + 0.75 * triangles[:, 2]])
    origin = np.repeat(points, len(directions), 0) - 2 * np.tile(directions, (len(points), 1))
    direction = np.tile(directions, (len(points), 1))
    result = _assert_same(NEAREST, structure, origin, direction)
    assert not np.isin(np.asarray(result.primitive_id), np.arange(4)).any()

    nan, inf = np.nan, np.inf
    cases = [  # origin, direction, min, max, mask: all but the first and last are disabled
        ([0.25, 0.25, 1.0], [0.0, 0.0, 1.0], 0.0, inf, 1),
        ([0.25, 0.25, 1.0], [0.0, 0.0, 1.0], 2.0, 1.0, 1),
        ([0.25, 0.25, 1.0], [0.0, 0.0, 0.0], 0.0, inf, 1),
        ([nan, 0.25, 1.0], [0.0, 0.0, 1.0], 0.0, inf, 1),
        ([0.25, 0.25, 1.0], [0.0, nan, 1.0], 0.0, nan, 1),
        ([0.25, inf, 1.0], [0.0, 0.0, 1.0], 0.0, inf, 1),
        ([0.25, 0.25, 1.0], [0.0, 0.0, 1.0], 0.0, inf, 0),
        ([0.25, 0.25, 1.0], [0.0, 0.0, 1.0], 4.0, 4.0, 1),
    ]
    origin, direction, tmin, tmax, mask = (np.array(c) for c in zip(*cases, strict=True))
    for pair in (NEAREST, ANY_CULLED):
        result = _assert_same(pair, structure, origin, direction, tmin, tmax, mask)
        kind = np.asarray(result.type)
        assert (kind[1:-1] == 0).all() and np.isinf(np.asarray(result.distance)[1:-1]).all()
        assert (np.asarray(result.nodes_visited)[1:-1] == 0).all()
    assert (np.asarray(_assert_same(NEAREST, structure, origin, direction, tmin, tmax, mask).type)[[0, -1]] != 0).all()


# --- random scenes: the portable path, and the float64 brute force -----------------------------------------------


@settings(max_examples=6)
@given(seeds, far_exponents, scale_exponents)
def test_random_scenes_equal_the_portable_path_and_match_brute_force(seed, far_exp, scale_exp):
    scene = random_scene(seed, far_exp, scale_exp)
    rays = random_rays(seed ^ 0x5EED, scene)
    structure = rt.build_primitive_structure(scene.geometries, capacity=SMALL_CAPACITY)
    args = (rays.origin, rays.direction, rays.min_distance, rays.max_distance)
    result = _assert_same(NEAREST, structure, *args)
    reference = brute_force(*args, scene.triangles)
    assert_matches_reference(result, reference, scene.counts)
    any_hit = _assert_same(ANY_CULLED, structure, *args)
    culled = brute_force(*args, scene.triangles, cull="front", front_facing_winding="counterclockwise")
    hit = np.asarray(any_hit.type) != 0
    assert not (hit & ~culled.possible.any(axis=1)).any(), "an any-hit answer where no hit is possible"
    assert not (~hit & culled.certain.any(axis=1)).any(), "an any-hit miss where a hit is certain"


# --- instances --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["rigid", "mirrored"])
def test_two_level_instances_with_masks_equal_the_portable_path(kind):
    scene = random_instanced_scene(11, 2, kind, masks=True)
    flat = flatten(scene)
    origin, direction = aimed_rays(3, flat)
    ray_mask = np.random.default_rng(4).choice([1, 2, 4, 8, 6, 0xFF, 0x100], len(origin)).astype(np.uint32)
    result = _assert_same(INSTANCED, scene.structure, origin, direction, mask=ray_mask)
    assert (np.asarray(result.type) != 0).any() and (np.asarray(result.instance_count) == 2).any()
    _assert_same(INSTANCED, scene.structure, origin, direction)


def test_culling_below_mirrored_instances_and_instance_options():
    triangle = np.array([[0, 0, 0], [0, 1, 0], [1, 0, 0]], np.float32)
    blas = rt.build_primitive_structure(rt.TriangleGeometry(triangle))
    place = lambda x, mirror: np.array([[mirror, 0, 0, x], [0, 1, 0, 0], [0, 0, 1, 0]], np.float32)  # noqa: E731
    transforms = np.stack([place(0, 1), place(10, -1), place(20, -1), place(30, 1)])
    options = [
        rt.InstanceOptions.NONE,
        rt.InstanceOptions.NONE,
        rt.InstanceOptions.DISABLE_TRIANGLE_CULLING,
        rt.InstanceOptions.TRIANGLE_FRONT_FACING_WINDING_COUNTERCLOCKWISE,
    ]
    inner = rt.build_instance_structure([blas], rt.Instances([0, 0, 0, 0], transforms, options=options))
    outer = rt.build_instance_structure([inner], rt.Instances([0, 0], np.stack([place(0, 1), place(0, -1)])))
    xs = np.array([0.2, 9.8, 19.8, 30.2, -0.2, -9.8, -19.8, -30.2], np.float32)
    origin = np.stack([xs, np.full(8, 0.2), np.full(8, 1.0)], -1)
    for sign in (1.0, -1.0):
        origin[:, 2] = sign
        direction = np.broadcast_to(np.array([0, 0, -sign], np.float32), origin.shape)
        result = _assert_same(INSTANCED_ANY, outer, origin, direction)
        assert (np.asarray(result.type) != 0).any() and (np.asarray(result.type) == 0).any()


# --- composition: jit, vmap, grad, float64, buckets ---------------------------------------------------------------


def _mesh_and_rays(n=64, seed=0):
    v, f = icosphere(2)
    rng = np.random.default_rng(seed)
    origin = rng.normal(size=(n, 3)) * 3
    direction = rng.normal(size=(n, 3)) * 0.3 - origin
    direction[::4] = rng.normal(size=direction[::4].shape)  # some rays miss
    return v.astype(np.float32), f, origin.astype(np.float32), direction.astype(np.float32)


def test_jit_and_vmap_over_rays_and_scenes_equal_unbatched_calls():
    """Under ``vmap`` the callback gets the batch axes: one call for rays over one scene, a loop over scenes."""
    v, f, origin, direction = _mesh_and_rays()
    intersector = rt.Intersector(rt.tags.triangle_data, backend="cpu")
    scales = (1.0, 1.5)
    structures = [rt.build_primitive_structure(rt.TriangleGeometry(v * s, f)) for s in scales]
    halves = [rt.Ray(origin[i * 32 : (i + 1) * 32], direction[i * 32 : (i + 1) * 32]) for i in range(2)]
    expected = np.stack(
        [np.asarray(intersector.intersect(r, s).primitive_id) for r, s in zip(halves, structures, strict=True)]
    )
    assert (expected >= 0).any() and (expected < 0).any()
    rays = rt.Ray(origin.reshape(2, 32, 3), direction.reshape(2, 32, 3))
    jitted = jax.jit(lambda r: intersector.intersect(r, structures[0]).primitive_id)(halves[0])
    np.testing.assert_array_equal(np.asarray(jitted), expected[0])
    over_rays = jax.vmap(lambda r: intersector.intersect(r, structures[0]).primitive_id)(rays)
    np.testing.assert_array_equal(np.asarray(over_rays)[0], expected[0])
    np.testing.assert_array_equal(
        np.asarray(over_rays)[1], np.asarray(intersector.intersect(halves[1], structures[0]).primitive_id)
    )
    stacked = jax.vmap(lambda s: rt.build_primitive_structure(rt.TriangleGeometry(v * s, f)))(jnp.array(scales))
    over_scenes = jax.vmap(lambda r, s: intersector.intersect(r, s).primitive_id)(rays, stacked)
    np.testing.assert_array_equal(np.asarray(over_scenes), expected)


def test_gradients_equal_the_portable_path():
    v, f, origin, direction = _mesh_and_rays(32)

    def loss(intersector, vertices, o):
        structure = rt.build_primitive_structure(rt.TriangleGeometry(vertices, f))
        hit = intersector.intersect(rt.Ray(o, direction), structure)
        return jnp.sum(jnp.where(hit.type != 0, hit.distance, 0.0)) + jnp.sum(hit.triangle_barycentric_coord)

    portable, compiled = _pair(rt.tags.triangle_data)
    expected = jax.grad(loss, argnums=(1, 2))(portable, jnp.asarray(v), jnp.asarray(origin))
    got = jax.grad(loss, argnums=(1, 2))(compiled, jnp.asarray(v), jnp.asarray(origin))
    for a, b in zip(got, expected, strict=True):
        assert np.abs(np.asarray(b)).max() > 0
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_float64_equals_the_portable_path():
    with jax.enable_x64(True):
        v, f, origin, direction = _mesh_and_rays()
        structure = rt.build_primitive_structure(rt.TriangleGeometry(v.astype(np.float64), f))
        assert structure.leaf_triangle.dtype == jnp.float64
        rays = rt.Ray(origin.astype(np.float64), direction.astype(np.float64))
        portable, compiled = _pair(rt.tags.triangle_data, rt.tags.stats)
        a, b = portable.intersect(rays, structure), compiled.intersect(rays, structure)
        assert b.distance.dtype == jnp.float64
        for name in ("distance", "primitive_id", "nodes_visited", "triangle_barycentric_coord"):
            np.testing.assert_array_equal(np.asarray(b[name]), np.asarray(a[name]), err_msg=name)


MOTION_SPECS = (
    rt.MotionSpec(0.5, 2.5, start_border="vanish", end_border="clamp"),
    rt.MotionSpec(0.5, 2.5, start_border="clamp", end_border="vanish"),
)


#: Position of the motion flag among the lean loop's arguments (``cpu_kernel.trace_flat``).
MOVING = 23


@pytest.mark.parametrize("spec", MOTION_SPECS, ids=("vanish-start", "vanish-end"))
def test_keyframe_motion_equals_the_portable_path(spec, monkeypatch):
    """Moving triangles (three keyframes) with a static floor in one structure, rays at random times (before,
    inside and after the range, and exactly at the keyframes): nearest and any hit, bit for bit."""
    from jaxrt._src.traversal import cpu_kernel

    rng = np.random.default_rng(11)
    base = rng.uniform(-1.0, 1.0, size=(40, 1, 3)) + rng.uniform(-0.6, 0.6, size=(40, 3, 3))
    keys = np.stack([base * (1.0 + 0.3 * k) + [0.4 * k, -0.3 * k, 0.2 * k] for k in range(3)]).astype(np.float32)
    floor = rt.TriangleGeometry(np.array([[-4.0, -4, -3], [4, -4, -3], [-4, 4, -3]], np.float32))
    structure = rt.build_primitive_structure(
        [rt.MotionTriangleGeometry(keys.reshape(3, -1, 3)), floor], motion=spec, capacity=SMALL_CAPACITY
    )
    n = 192
    origin = np.concatenate([rng.uniform(-2.5, 2.5, (n, 2)), np.full((n, 1), 6.0)], axis=-1).astype(np.float32)
    direction = (np.array([0.0, 0.0, -1.0]) + rng.normal(scale=0.25, size=(n, 3))).astype(np.float32)
    time = rng.uniform(-0.5, 3.5, n).astype(np.float32)
    time[:8] = [0.5, 1.5, 2.5, 0.0, 3.0, np.nextafter(np.float32(0.5), 0), np.nextafter(np.float32(2.5), 9), 1.0]
    rays = rt.Ray(origin, direction, time=time)
    calls = []
    traced = cpu_kernel.trace_flat
    monkeypatch.setattr(cpu_kernel, "trace_flat", lambda *a: (calls.append(a[MOVING]), traced(*a))[1])
    for options in ({}, {"accept_any_intersection": True, "triangle_cull_mode": "back"}):
        tags = (rt.tags.primitive_motion, rt.tags.triangle_data, rt.tags.stats)
        portable, compiled = (rt.Intersector(*tags, backend=b, **options).intersect(rays, structure) for b in ("portable", "cpu"))  # fmt: skip
        hit = np.asarray(portable.type) != 0
        assert 0 < hit.sum() < n
        for name in ("type", "distance", "primitive_id", "geometry_id", "triangle_front_facing", *STATS):
            np.testing.assert_array_equal(np.asarray(compiled[name]), np.asarray(portable[name]), err_msg=name)
        # The barycentrics are not the traversal's: both paths re-intersect the same leaf at the same distance in
        # JAX, and XLA fuses that blend and re-intersection differently inside the portable program (a separate
        # program gives the CPU path's values), a few ulps apart.
        bary = (np.asarray(r.triangle_barycentric_coord) for r in (compiled, portable))
        np.testing.assert_allclose(*bary, rtol=0, atol=1e-6)
    assert calls and all(calls)  # the compiled loop traced them, with motion


def test_keyframe_motion_in_float64_equals_the_portable_path(monkeypatch):
    from jaxrt._src.traversal import cpu_kernel

    calls = []
    traced = cpu_kernel.trace_flat
    monkeypatch.setattr(cpu_kernel, "trace_flat", lambda *a: (calls.append(a[MOVING]), traced(*a))[1])
    with jax.enable_x64(True):
        rng = np.random.default_rng(12)
        keys = rng.uniform(-1.0, 1.0, size=(1, 30, 1, 3)) + rng.uniform(-0.6, 0.6, size=(2, 30, 3, 3))
        spec = rt.MotionSpec(0.5, 2.5, end_border="vanish")
        structure = rt.build_primitive_structure(
            rt.MotionTriangleGeometry(keys.reshape(2, -1, 3)), motion=spec, capacity=SMALL_CAPACITY
        )
        assert structure.leaf_triangle.dtype == jnp.float64
        n = 128
        origin = np.concatenate([rng.uniform(-1.5, 1.5, (n, 2)), np.full((n, 1), 6.0)], axis=-1)
        direction = np.array([0.0, 0.0, -1.0]) + rng.normal(scale=0.1, size=(n, 3))
        rays = rt.Ray(origin, direction, time=rng.uniform(0.0, 3.0, n))
        tags = (rt.tags.primitive_motion, rt.tags.stats)
        portable, compiled = (rt.Intersector(*tags, backend=b).intersect(rays, structure) for b in ("portable", "cpu"))  # fmt: skip
        assert compiled.distance.dtype == jnp.float64 and (np.asarray(portable.type) != 0).any()
        for name in ("type", "distance", "primitive_id", *STATS):
            np.testing.assert_array_equal(np.asarray(compiled[name]), np.asarray(portable[name]), err_msg=name)
    assert calls and all(calls)


def test_one_moving_triangle_beside_an_empty_leaf_equals_the_portable_path_and_float64(monkeypatch):
    """A structure of one moving triangle: the tree links it beside an empty padding leaf, whose blended box
    the compiled loop must reject as the portable step does (the counters would show a tested padding leaf).
    Nearest hits equal the portable path bit for bit and match a float64 brute force on each ray's triangle
    blended at its time."""
    from jaxrt._src.traversal import cpu_kernel

    calls = []
    traced = cpu_kernel.trace_flat
    monkeypatch.setattr(cpu_kernel, "trace_flat", lambda *a: (calls.append(a[MOVING]), traced(*a))[1])
    keys = np.array(
        [
            [[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [0.0, 1.0, 0.0]],
            [[-0.5, -1.0, 0.5], [1.5, -1.0, 0.5], [0.5, 1.2, 0.5]],
        ],
        np.float32,
    )
    structure = rt.build_primitive_structure(
        rt.MotionTriangleGeometry(keys), motion=rt.MotionSpec(0.0, 1.0), capacity=SMALL_CAPACITY
    )
    rng = np.random.default_rng(21)
    n = 256
    origin = np.concatenate([rng.uniform(-1.5, 1.5, (n, 2)), np.full((n, 1), 5.0)], axis=-1).astype(np.float32)
    direction = (np.array([0.0, 0.0, -1.0]) + rng.normal(scale=0.05, size=(n, 3))).astype(np.float32)
    time = rng.uniform(0.0, 1.0, n).astype(np.float32)
    rays = rt.Ray(origin, direction, time=time)
    tags = (rt.tags.primitive_motion, rt.tags.triangle_data, rt.tags.stats)
    portable, compiled = (rt.Intersector(*tags, backend=b).intersect(rays, structure) for b in ("portable", "cpu"))
    hit = np.asarray(portable.type) != 0
    assert 0 < hit.sum() < n
    for name in ("type", "distance", "primitive_id", *STATS):
        np.testing.assert_array_equal(np.asarray(compiled[name]), np.asarray(portable[name]), err_msg=name)
    assert calls and all(calls)  # the compiled loop traced them, with motion
    w = time.astype(np.float64)[:, None, None]  # keyframes at times 0 and 1
    blended = (1.0 - w) * keys[0].astype(np.float64) + w * keys[1].astype(np.float64)
    ref = brute_force(origin, direction, np.zeros(n), np.full(n, np.inf), blended, pairs=True)
    assert_matches_reference(compiled, ref, [1])


def test_no_recompile_within_a_bucket():
    v, f, origin, direction = _mesh_and_rays(200)
    structure = rt.build_primitive_structure(rt.TriangleGeometry(v, f))
    intersector = rt.Intersector(backend="cpu")
    intersector.intersect(rt.Ray(origin[:130], direction[:130]), structure).distance.block_until_ready()
    from jaxrt._src.traversal import cpu_kernel

    compiled, kernels = pipeline._intersect_jit._cache_size(), len(cpu_kernel.trace_rays.signatures)
    for n in (131, 170, 200):  # the bucket of 256
        hit = intersector.intersect(rt.Ray(origin[:n], direction[:n]), structure)
        assert hit.distance.shape == (n,)
    assert pipeline._intersect_jit._cache_size() == compiled
    assert len(cpu_kernel.trace_rays.signatures) == kernels


def test_threads_claiming_chunks_equal_one_thread(monkeypatch):
    """Several threads claim chunks of rays from one counter: every ray is traced once, as by one thread."""
    v, f, origin, direction = _mesh_and_rays(5000, seed=3)
    structure = rt.build_primitive_structure(rt.TriangleGeometry(v, f))
    intersector = rt.Intersector(rt.tags.triangle_data, rt.tags.stats, backend="cpu")
    rays = rt.Ray(origin, direction)
    results = []
    for count in ("1", "3"):
        monkeypatch.setenv("JAXRT_CPU_THREADS", count)
        assert cpu.threads() == int(count)
        results.append(intersector.intersect(rays, structure))
    one, several = results
    assert (np.asarray(one.type) != 0).any() and (np.asarray(one.type) == 0).any()
    for name in FIELDS + STATS:
        np.testing.assert_array_equal(np.asarray(several[name]), np.asarray(one[name]), err_msg=name)


def test_scene_read_in_place_equals_the_scene_passed_through_the_callback():
    """At top level the traversal reads the structure's and the rays' buffers in place; under ``jit`` (a trace)
    it receives them through the callback. Both give the same result, disabled rays included."""
    v, f, origin, direction = _mesh_and_rays(300, seed=2)
    structure = rt.build_primitive_structure(rt.TriangleGeometry(v, f))
    origin[::7] = np.nan  # disabled rays: their own values are in the buffers read in place
    rays = rt.Ray(origin, direction, 0.0, np.where(np.arange(300) % 5 == 0, 1.5, np.inf).astype(np.float32))
    assert cpu.host_scene(structure, rays)[0].shape == (8, 2)
    assert cpu.host_scene(structure, rays, with_rays=False)[0].shape == (4, 2)
    intersector = rt.Intersector(rt.tags.triangle_data, rt.tags.stats, backend="cpu")
    in_place = intersector.intersect(rays, structure)
    passed = jax.jit(intersector.intersect)(rays, structure)
    assert (np.asarray(in_place.type) != 0).any() and (np.asarray(in_place.nodes_visited)[::7] == 0).all()
    for name in FIELDS + STATS:
        np.testing.assert_array_equal(np.asarray(in_place[name]), np.asarray(passed[name]), err_msg=name)
    instanced = rt.build_instance_structure([structure], rt.Instances([0], np.eye(3, 4, dtype=np.float32)[None]))
    assert cpu.host_scene(instanced, rays) is None


def test_buffers_read_in_place_are_held_while_the_call_runs():
    """A structure dropped by the caller right after ``intersect`` returns (the call runs asynchronously) is
    still read correctly: the program keeps every buffer the traversal reads in place."""
    v, f, origin, direction = _mesh_and_rays(256, seed=4)
    rays = rt.Ray(origin, direction)
    build = lambda: rt.build_primitive_structure(rt.TriangleGeometry(v, f))  # noqa: E731
    expected = np.asarray(rt.Intersector(backend="portable").intersect(rays, build()).primitive_id)
    assert (expected >= 0).any()
    intersector = rt.Intersector(backend="cpu")
    for _ in range(3):
        results = [intersector.intersect(rays, build()).primitive_id for _ in range(6)]
        clutter = [jnp.full((1 << 16,), -1.0) + i for i in range(8)]  # reuses freed memory, if any was freed
        for result in results:
            np.testing.assert_array_equal(np.asarray(result), expected)
        del clutter


_ONE_CORE_SCRIPT = """
import os
os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})  # before jax starts its threads: all share one core
import numpy as np
import jaxrt as rt
rng = np.random.default_rng(5)
v = rng.normal(size=(200, 3)).astype(np.float32)
f = rng.integers(0, 200, size=(300, 3)).astype(np.int32)
origin = (rng.normal(size=(256, 3)) * 3).astype(np.float32)
rays = rt.Ray(origin, (rng.normal(size=(256, 3)) * 0.3 - origin).astype(np.float32))
intersector = rt.Intersector(backend="cpu")
for _ in range(8):
    results = [intersector.intersect(rays, rt.build_primitive_structure(rt.TriangleGeometry(v, f))) for _ in range(6)]
    for result in results:
        np.asarray(result.primitive_id)
print("done")
"""


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="needs os.sched_setaffinity (Linux)")
def test_calls_queued_behind_running_traversals_do_not_deadlock_on_one_core():
    """Calls made while earlier ones still run (their structures still being built) finish: taking a buffer's
    address waits for it without holding the GIL that a running traversal's callback needs. On one core the
    deadlock this guards against showed in about half of such runs."""
    try:
        done = subprocess.run(
            [sys.executable, "-c", _ONE_CORE_SCRIPT], capture_output=True, text=True, timeout=180, check=False
        )
    except subprocess.TimeoutExpired:
        pytest.fail("intersect calls queued behind running CPU traversals deadlocked (no progress in 180 s)")
    assert done.returncode == 0 and done.stdout.strip() == "done", done.stderr[-2000:]


# --- backend choice ---------------------------------------------------------------------------------------------


def test_auto_picks_the_cpu_traversal_and_forced_backends_explain_themselves(monkeypatch):
    assert pipeline.resolve_backend(rt.Intersector()) == "cpu"
    assert pipeline.resolve_backend(rt.Intersector(backend="portable")) == "portable"
    structure = _build([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    rays = rt.Ray([0.2, 0.2, 1.0], [0.0, 0.0, -1.0])
    assert pipeline.kernel_declines(rt.Intersector(max_hits=2), structure.geometry_info, "cpu") is None
    clipped = rt.build_primitive_structure(rt.TriangleGeometry([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], opaque=False))
    keep_all = lambda candidate: jnp.bool_(True)  # noqa: E731
    with pytest.raises(ValueError, match="backend='cpu' cannot run: filters on non-opaque geometry"):
        rt.Intersector(backend="cpu", filter=keep_all).intersect(rays, clipped)
    # Declined cases under "auto" take the portable traversal (they are traced in test_custom_geometry.py).
    assert pipeline.kernel_declines(rt.Intersector(filter=keep_all), clipped.geometry_info, "cpu") is not None
    monkeypatch.setattr(jax, "default_backend", lambda: "tpu")
    with pytest.raises(ValueError, match="backend='cpu' cannot run: the default JAX backend is 'tpu'"):
        rt.Intersector(backend="cpu").intersect(rays, structure)
    assert pipeline.resolve_backend(rt.Intersector()) == "portable"
