"""The K nearest hits (``max_hits``) and ``rt.count_intersections`` on the compiled CPU traversal, against the
portable traversal (exactly: the same hits in the same order, the same distances to the bit, instance chains,
counts, overflow flags and stats counters) and against a float64 brute force.

Scenes are stacks of large, overlapping triangles, so that most rays cross more than K of them: with exact
duplicates (equal distances: the order of ties) and a coplanar grid (rays through shared edges and vertices),
and ray intervals that end exactly at hit distances. Instanced scenes at one and two levels with instance and
ray masks. Every batch has one size and every structure one capacity, so each intersector compiles once.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from reference import SMALL_CAPACITY, brute_force, grid, random_rotation
from test_instancing import aimed_rays, flatten, oracle
from test_instancing import random_scene as random_instanced_scene

import jaxrt as rt
from jaxrt._src import pipeline
from jaxrt._src.traversal import cpu

pytestmark = pytest.mark.skipif(cpu.unavailable_reason() is not None, reason=str(cpu.unavailable_reason()))

K = 4
RAYS = 256
#: Triangles of a stack scene: random layers, exact duplicates of some of them, and a coplanar grid patch.
LAYERS, DUPLICATES = 32, 8


def _pair(*tags, **options) -> tuple[rt.Intersector, rt.Intersector]:
    """The same intersector on the portable traversal and on the CPU traversal."""
    return rt.Intersector(*tags, backend="portable", **options), rt.Intersector(*tags, backend="cpu", **options)


K_NEAREST = _pair(rt.tags.triangle_data, rt.tags.stats, max_hits=K)
NEAREST_ONLY = _pair(rt.tags.triangle_data, max_hits=1)
COUNTING = _pair()
INSTANCING = (rt.tags.instancing, rt.tags.max_levels(2), rt.tags.triangle_data)
K_INSTANCED = _pair(*INSTANCING, rt.tags.stats, max_hits=K)
COUNTING_INSTANCED = _pair(*INSTANCING)


def _assert_same(pair, structure, rays):
    """Both backends on the same rays: every field identical (bit for bit). Returns the CPU result."""
    portable, compiled = pair
    assert pipeline.resolve_backend(compiled) == "cpu"
    assert pipeline.kernel_declines(compiled, pipeline.scene_view(structure).geometry_info, "cpu") is None
    a, b = portable.intersect(rays, structure), compiled.intersect(rays, structure)
    assert set(a) == set(b)
    for name in a:
        np.testing.assert_array_equal(np.asarray(b[name]), np.asarray(a[name]), err_msg=name)
    return b


def _assert_same_counts(pair, structure, rays) -> np.ndarray:
    portable, compiled = (rt.count_intersections(rays, structure, i) for i in pair)
    np.testing.assert_array_equal(np.asarray(compiled), np.asarray(portable))
    return np.asarray(compiled)


# --- stack scenes --------------------------------------------------------------------------------------------


def stack_scene(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(triangles (T, 3, 3), origin, direction)`` in float32: tilted layers over the unit square, exact
    duplicates, and a coplanar 2x2 grid of quads; rays from below, some through grid vertices and edges; all
    rotated, scaled and moved away from the origin."""
    rng = np.random.default_rng(seed)
    corners = np.array([[-4.0, -4.0], [8.0, -4.0], [-4.0, 8.0]]) + rng.uniform(-1, 1, (LAYERS, 3, 2))
    heights = rng.uniform(0, 8, (LAYERS, 1)) + rng.uniform(-0.5, 0.5, (LAYERS, 3))
    layers = np.concatenate([corners, heights[..., None]], axis=-1)
    duplicates = layers[rng.choice(LAYERS, DUPLICATES, replace=False)]
    v, f = grid(2, 2)  # vertices in [0, 1]^2, z = 0
    patch = (v[f] - [0.5, 0.5, 0.0]) * [2.0, 2.0, 1.0] + [0.0, 0.0, 4.0]
    local = np.concatenate([layers, duplicates, patch])
    n = RAYS
    # Starting heights from below every layer to above most of them: from 0 to all layers ahead.
    height = np.where(rng.uniform(size=(n, 1)) < 0.4, rng.uniform(6.5, 8.6, (n, 1)), rng.uniform(-2, 9, (n, 1)))
    start = np.concatenate([rng.uniform(-1.5, 1.5, (n, 2)), height], axis=-1)
    target = start + [0.0, 0.0, 14.0] + np.concatenate([rng.normal(0, 0.3, (n, 2)), np.zeros((n, 1))], axis=-1)
    # A quarter of the rays go straight up through grid vertices and edge midpoints of the patch.
    nodes = np.array([[x, y] for x in (-1.0, -0.5, 0.0, 0.5, 1.0) for y in (-1.0, -0.25, 0.0, 1.0)])
    aimed = rng.uniform(size=n) < 0.25
    start[aimed, :2] = nodes[rng.integers(0, len(nodes), aimed.sum())]
    target[aimed, :2] = start[aimed, :2]
    rotation = random_rotation(rng)
    scale = 10.0 ** rng.uniform(-1, 1)
    center = rng.normal(size=3) * 10.0 ** rng.uniform(0, 3)
    world = lambda p: (p @ rotation.T) * scale + center  # noqa: E731
    triangles = world(local).astype(np.float32)
    origin = world(start).astype(np.float32)
    direction = (world(target) - world(start)).astype(np.float32) / np.float32(rng.uniform(1, 14))
    return triangles, origin, direction


def _structure(triangles):
    return rt.build_primitive_structure(rt.TriangleGeometry(triangles.reshape(-1, 3)), capacity=SMALL_CAPACITY)


def check_against_float64(result, ref, triangles, k: int | None) -> tuple[list[str], int]:
    """Failures of a ``max_hits=k`` result (``k=None``: a ``hit_count`` array of counts) against the float64
    brute force over ``triangles``, and the number of rays whose answer float64 cannot decide (a possible but
    uncertain hit, or two of the first ``k + 1`` hits closer than their tolerances, unless they are exact
    duplicates); those are checked for consistency only."""
    failures, ambiguous = [], 0
    same = (triangles[:, None] == triangles[None]).all(axis=(-1, -2))
    canonical = np.argmax(same, axis=1)  # exact duplicates are one triangle to float64
    certain, possible = ref.certain.sum(axis=1), ref.possible.sum(axis=1)
    if k is None:
        count = np.asarray(result)
        wrong = np.flatnonzero((count < certain) | (count > possible))
        return [f"ray {r}: {count[r]} hits, {certain[r]} certain, {possible[r]} possible" for r in wrong], int(
            np.sum(certain != possible)
        )
    ids = np.asarray(result.primitive_id)
    distance = np.asarray(result.distance, np.float64)
    count, overflow = np.asarray(result.hit_count), np.asarray(result.hit_overflow)
    for r in range(ids.shape[0]):
        n = int(count[r])
        got, at = ids[r, :n], distance[r, :n]
        if np.any(ids[r, n:] != -1) or not np.all(np.isposinf(distance[r, n:])):
            failures.append(f"ray {r}: entries past hit_count {n}: {ids[r]}")
        if len(set(got.tolist())) != n or np.any(np.diff(at) < 0):
            failures.append(f"ray {r}: hits {got} at {at} repeat or are unsorted")
        real = [ref.possible[r, i] and abs(t - ref.distance[r, i]) <= ref.tolerance[r, i] for i, t in zip(got, at, strict=True)]  # fmt: skip
        if not all(real):
            failures.append(f"ray {r}: hits {got} at {at} are not all real")
        if not min(certain[r], k) <= n <= min(possible[r], k):
            failures.append(f"ray {r}: hit_count {n}, {certain[r]} certain and {possible[r]} possible hits")
        if (certain[r] > k and not overflow[r]) or (possible[r] <= k and overflow[r]):
            failures.append(f"ray {r}: hit_overflow {overflow[r]}, {certain[r]} certain, {possible[r]} possible")
        hits = np.flatnonzero(ref.certain[r])
        hits = hits[np.argsort(ref.distance[r, hits], kind="stable")][: k + 1]
        low, high = ref.distance[r, hits] - ref.tolerance[r, hits], ref.distance[r, hits] + ref.tolerance[r, hits]
        close = (low[1:] <= high[:-1]) & (canonical[hits[1:]] != canonical[hits[:-1]])
        if certain[r] != possible[r] or np.any(close):
            ambiguous += 1
        elif not np.array_equal(canonical[got], canonical[hits[:k]]):
            failures.append(f"ray {r}: hits {got} at {at}, expected {hits[:k]}")
    return failures, ambiguous


@settings(max_examples=5, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_stack_scenes_equal_the_portable_path_and_match_float64(seed):
    triangles, origin, direction = stack_scene(seed)
    structure = _structure(triangles)
    rng = np.random.default_rng(seed ^ 0x51)
    tmin = np.where(rng.uniform(size=RAYS) < 0.3, rng.uniform(0, 2, RAYS), 0.0).astype(np.float32)
    tmax = np.where(rng.uniform(size=RAYS) < 0.3, tmin + rng.uniform(-0.2, 4, RAYS), np.inf).astype(np.float32)
    rays = rt.Ray(origin, direction, tmin, tmax)
    ref = brute_force(origin, direction, tmin, tmax, triangles)
    for pair, k in ((K_NEAREST, K), (NEAREST_ONLY, 1)):
        result = _assert_same(pair, structure, rays)
        failures, ambiguous = check_against_float64(result, ref, triangles, k)
        assert not failures, f"{len(failures)} rays disagree with float64:\n" + "\n".join(failures[:12])
        assert ambiguous < RAYS // 4
    count = _assert_same_counts(COUNTING, structure, rays)
    failures, ambiguous = check_against_float64(count, ref, triangles, None)
    assert not failures, "\n".join(failures[:12])
    assert ambiguous < RAYS // 4 and count.max() > 2 * K
    # The scene is dense: overflowing rays, rays with 1 to K hits, and disabled rays (empty intervals).
    result = K_NEAREST[1].intersect(rays, structure)
    hit_count, overflow = np.asarray(result.hit_count), np.asarray(result.hit_overflow)
    assert overflow.sum() >= 10 and ((hit_count > 0) & (hit_count < K)).sum() >= 10
    assert not hit_count[tmin > tmax].any() and (tmin > tmax).any()


def test_ties_and_hits_at_the_interval_ends_equal_the_portable_path():
    """Duplicates give hits at equal distances (kept in the portable path's order: after the hits at the same
    distance, in traversal order); intervals that end exactly at hit distances keep both end hits."""
    triangles, origin, direction = stack_scene(5)
    structure = _structure(triangles)
    found = _assert_same(K_NEAREST, structure, rt.Ray(origin, direction))
    distance, ids = np.asarray(found.distance), np.asarray(found.primitive_id)
    tied = (distance[:, 1:] == distance[:, :-1]) & np.isfinite(distance[:, 1:])
    rows, at = np.nonzero(tied)
    duplicates = (triangles[ids[rows, at]] == triangles[ids[rows, at + 1]]).all(axis=(-1, -2))
    assert duplicates.sum() >= 5
    # [t_min, t_max] from the second to the third hit: both ends are hit distances.
    ends = np.asarray(found.hit_count) >= 3
    assert ends.sum() >= 50
    tmin = np.where(ends, distance[:, 1], 0.0).astype(np.float32)
    tmax = np.where(ends, distance[:, 2], np.inf).astype(np.float32)
    rays = rt.Ray(origin, direction, tmin, tmax)
    closed = _assert_same(K_NEAREST, structure, rays)
    got, count = np.asarray(closed.distance), np.asarray(closed.hit_count)
    assert np.all(got[ends, 0] == tmin[ends])
    last = np.take_along_axis(got, np.maximum(count - 1, 0)[:, None], axis=1)[:, 0]
    whole = ends & ~np.asarray(closed.hit_overflow)
    assert whole.sum() >= 50 and np.all(last[whole] == tmax[whole])
    counts = _assert_same_counts(COUNTING, structure, rays)
    np.testing.assert_array_equal(np.minimum(counts, K), count)
    np.testing.assert_array_equal(counts[whole], count[whole])
    _assert_same(NEAREST_ONLY, structure, rays)


# --- instances -------------------------------------------------------------------------------------------------


def test_instances_with_masks_equal_the_portable_path_and_match_float64():
    """Two levels of instances over meshes, and one level over a mesh (hits at depths 1 and 2)."""
    levels = 2
    scene = random_instanced_scene(23, levels, "mirrored", masks=True)
    flat = flatten(scene)
    origin, direction = aimed_rays(levels, flat)
    n = origin.shape[0]
    ray_mask = np.random.default_rng(levels).choice([1, 2, 4, 8, 6, 0xFF, 0x100], n).astype(np.uint32)
    ray_mask[: n // 2] = 0xFFFFFFFF
    rays = rt.Ray(origin, direction, mask=ray_mask)
    result = _assert_same(K_INSTANCED, scene.structure, rays)
    counts = _assert_same_counts(COUNTING_INSTANCED, scene.structure, rays)
    depth = np.asarray(result.instance_count)[np.asarray(result.type) != 0]
    assert (depth == 1).any() and (depth == 2).any() and counts.max() > 1
    # float64: each returned hit is a visible world-space triangle at its distance; counts between the
    # certain and the possible hits (the margins of test_instancing's oracle).
    t, bary_min, facing, _ = oracle(origin, direction, flat.triangles)
    visible = ((flat.masks[None] & ray_mask[:, None, None]) != 0).all(axis=2) & (t > 0)
    cosine = np.maximum(np.abs(facing), 1e-3)
    scale = np.abs(origin).max(axis=1, keepdims=True) / np.linalg.norm(direction, axis=1, keepdims=True)
    tol = 2e-5 * (np.abs(t) + scale + 1.0) / cosine
    certain = visible & (bary_min > 2e-4 / cosine)
    possible = visible & (bary_min > -2e-4 / cosine)
    assert np.all(counts >= certain.sum(axis=1)) and np.all(counts <= possible.sum(axis=1))
    chains, primitive = np.asarray(result.instance_id), np.asarray(result.primitive_id)
    distance = np.asarray(result.distance, np.float64)
    returned = 0
    for r in range(n):
        for h in range(int(result.hit_count[r])):
            match = np.flatnonzero(
                (flat.chains[:, : chains.shape[-1]] == chains[r, h]).all(axis=1) & (flat.primitive == primitive[r, h])
            )
            assert match.size == 1, (r, h)
            i = int(match[0])
            assert possible[r, i] and abs(distance[r, h] - t[r, i]) <= tol[r, i], (r, h)
            returned += 1
    assert returned > n // 2 and (np.asarray(result.hit_count) >= 2).sum() >= 3, (
        returned,
        np.asarray(result.hit_count),
    )


# --- composition -------------------------------------------------------------------------------------------------


def test_jit_and_vmap_over_rays_and_scenes_equal_unbatched_calls():
    triangles, origin, direction = stack_scene(9)
    _, compiled = K_NEAREST
    structure = _structure(triangles)
    halves = [rt.Ray(origin[i * 128 : (i + 1) * 128], direction[i * 128 : (i + 1) * 128]) for i in range(2)]
    fields = lambda h: (h.primitive_id, h.distance, h.hit_count, h.hit_overflow)  # noqa: E731
    expected = [fields(compiled.intersect(r, structure)) for r in halves]
    jitted = jax.jit(lambda r: fields(compiled.intersect(r, structure)))(halves[0])
    rays = rt.Ray(origin.reshape(2, 128, 3), direction.reshape(2, 128, 3))
    over_rays = jax.vmap(lambda r: fields(compiled.intersect(r, structure)))(rays)
    moved = triangles + np.float32(0.25) * (triangles[:, 1:2] - triangles[:, 0:1])
    stacked = jax.vmap(lambda t: _structure(t))(jnp.stack([triangles, moved]))
    over_scenes = jax.vmap(lambda r, s: fields(compiled.intersect(r, s)))(rays, stacked)
    second = fields(compiled.intersect(halves[1], _structure(moved)))
    counts = jax.vmap(lambda r: rt.count_intersections(r, structure, COUNTING[1]))(rays)
    for i, name in enumerate(("primitive_id", "distance", "hit_count", "hit_overflow")):
        np.testing.assert_array_equal(np.asarray(jitted[i]), np.asarray(expected[0][i]), err_msg=name)
        for half in range(2):
            np.testing.assert_array_equal(np.asarray(over_rays[i][half]), np.asarray(expected[half][i]), err_msg=name)
        np.testing.assert_array_equal(np.asarray(over_scenes[i][0]), np.asarray(expected[0][i]), err_msg=name)
        np.testing.assert_array_equal(np.asarray(over_scenes[i][1]), np.asarray(second[i]), err_msg=name)
    assert np.asarray(over_rays[2]).max() == K and not np.array_equal(np.asarray(second[1]), np.asarray(expected[1][1]))
    portable = rt.count_intersections(rt.Ray(origin, direction), structure, COUNTING[0])
    np.testing.assert_array_equal(np.asarray(counts).reshape(-1), np.asarray(portable))


def test_float64_equals_the_portable_path():
    with jax.enable_x64(True):
        triangles, origin, direction = stack_scene(3)
        structure = _structure(triangles.astype(np.float64))
        rays = rt.Ray(origin.astype(np.float64), direction.astype(np.float64))
        result = _assert_same(K_NEAREST, structure, rays)
        assert result.distance.dtype == jnp.float64 and result.distance.shape == (RAYS, K)
        assert np.asarray(result.hit_overflow).any()
        _assert_same_counts(COUNTING, structure, rays)


def test_the_cpu_traversal_runs_and_hit_lists_refuse_any_hit(monkeypatch):
    """No portable traversal runs for a covered intersector; the kernel's own checks name the bad options."""
    triangles, origin, direction = stack_scene(2)
    structure = _structure(triangles)

    def portable(*args, **kwargs):
        raise AssertionError("the portable traversal ran")

    monkeypatch.setattr(pipeline, "_trace_portable", portable)
    compiled = rt.Intersector(rt.tags.triangle_data, max_hits=3, backend="cpu")
    assert np.asarray(compiled.intersect(rt.Ray(origin, direction), structure).hit_count).max() == 3
    assert rt.count_intersections(rt.Ray(origin, direction), structure, rt.Intersector(backend="auto")).shape == (RAYS,)
    with pytest.raises(ValueError, match="hit lists need max_hits >= 1"):
        cpu._params(pipeline.scene_view(structure).layout, True, 0, 2, False)
    with pytest.raises(ValueError, match="hit lists need max_hits >= 1"):
        cpu._params(pipeline.scene_view(structure).layout, False, 0, 0, False)
