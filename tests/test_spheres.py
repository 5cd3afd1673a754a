"""Built-in spheres (``rt.SphereGeometry``) against a float64 brute force: nearest and any hit, intervals,
hits from inside, normals, primitive data, ``max_hits``, filters, instancing, keyframe motion, gradients
against central differences, the hard cases of Haines et al. (spheres 1e4 from the origin, radii 1e-3 to 1e3)
and bad input.

The reference takes the float32 inputs exactly (as float64) and solves the quadratic in float64; a ray counts
as ambiguous (and is not compared) where its nearest two sphere distances are within a relative 1e-4 of each
other, or where it passes within a relative 1e-4 of a sphere's silhouette (grazing).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from test_gpu_instanced import INTERPRETED, ON_GPU, kernel_launches_here, run_kernel_tests_in_interpreter

import jaxrt as rt
from jaxrt._src.traversal import cpu, gpu

RAYS = 256
CAPACITY = 64
AMBIGUOUS = 1e-4


# --- the float64 reference ---------------------------------------------------------------------------------------


def roots64(origin, direction, centers, radii):
    """``(near, far, grazing)`` ``(rays, spheres)`` in float64 (NaN where the ray misses) and the relative
    closeness of each ray to each silhouette."""
    o = np.asarray(origin, np.float64)[:, None, :]
    d = np.asarray(direction, np.float64)[:, None, :]
    c = np.asarray(centers, np.float64)[None]
    r = np.asarray(radii, np.float64)[None]
    f = o - c
    a = np.sum(d * d, -1)
    s = -np.sum(f * d, -1) / a
    g = f + s[..., None] * d
    miss2 = np.sum(g * g, -1)  # squared distance of the ray's line to the centre
    disc = r * r - miss2
    half = np.sqrt(np.maximum(disc, 0) / a)
    near = np.where(disc >= 0, s - half, np.nan)
    far = np.where(disc >= 0, s + half, np.nan)
    grazing = np.abs(np.sqrt(miss2) - r) <= AMBIGUOUS * np.maximum(r, 1e-30)
    return near, far, grazing


def reference(origin, direction, t_min, t_max, centers, radii):
    """Per ray: the nearest sphere, its distance, whether the ray enters there, and an ambiguity flag."""
    near, far, grazing = roots64(origin, direction, centers, radii)
    lo = np.asarray(t_min, np.float64)[:, None]
    hi = np.asarray(t_max, np.float64)[:, None]
    with np.errstate(invalid="ignore"):
        near_ok = (near >= lo) & (near <= hi)
        far_ok = (far >= lo) & (far <= hi)
        t = np.where(near_ok, near, np.where(far_ok, far, np.inf))
    order = np.argsort(t, axis=1)
    rows = np.arange(t.shape[0])
    best = order[:, 0]
    distance = t[rows, best]
    second = t[rows, order[:, 1]] if t.shape[1] > 1 else np.full_like(distance, np.inf)
    with np.errstate(invalid="ignore"):
        ambiguous = np.isfinite(distance) & (second - distance <= AMBIGUOUS * np.maximum(np.abs(distance), 1.0))
        # a root close to an interval end, or a grazing sphere, could fall either way in float32
        ends = np.concatenate([near, far], 1)
        scale = AMBIGUOUS * np.maximum(np.abs(ends), 1)
        edge = np.any((np.abs(ends - lo) <= scale) | (np.abs(ends - hi) <= scale), 1)
    ambiguous |= edge | np.any(grazing, 1)
    hit = np.isfinite(distance)
    front = hit & near_ok[rows, best]
    return hit, np.where(hit, best, -1), distance, front, ambiguous, t


def scene(seed: int, count: int = 40, spread: float = 4.0, inside: bool = True):
    """Random spheres and rays (some starting inside spheres, some with a finite interval)."""
    rng = np.random.default_rng(seed)
    centers = rng.uniform(-spread, spread, (count, 3)).astype(np.float32)
    radii = rng.uniform(0.2, 1.2, count).astype(np.float32)
    origin = rng.uniform(-2 * spread, 2 * spread, (RAYS, 3)).astype(np.float32)
    if inside:
        origin[:32] = centers[np.arange(32) % count] + rng.normal(size=(32, 3)).astype(np.float32) * 0.05
    targets = centers[rng.integers(0, count, RAYS)] + rng.normal(size=(RAYS, 3)).astype(np.float32)
    direction = (targets - origin).astype(np.float32)
    direction[:8] = rng.normal(size=(8, 3))
    t_min = np.zeros(RAYS, np.float32)
    t_max = np.full(RAYS, np.inf, np.float32)
    t_min[200:230] = rng.uniform(0.0, 0.8, 30)
    t_max[230:] = rng.uniform(0.3, 1.0, RAYS - 230)
    return centers, radii, origin, direction, t_min, t_max


def skip_unless_runs(backend: str) -> None:
    """Skip the test when ``backend`` is the CPU traversal and it cannot run here (e.g. on a GPU machine)."""
    if backend == "cpu" and cpu.unavailable_reason() is not None:
        pytest.skip(cpu.unavailable_reason())


def trace(intersector, structure, origin, direction, t_min, t_max, time=None):
    kw = {} if time is None else {"time": jnp.asarray(time, jnp.float32)}
    ray = rt.Ray(jnp.asarray(origin), jnp.asarray(direction), jnp.asarray(t_min), jnp.asarray(t_max), **kw)
    return jax.tree_util.tree_map(np.asarray, dict(intersector.intersect(ray, structure)))


NEAREST = rt.Intersector(rt.tags.normal, rt.tags.sphere_data, rt.tags.primitive_data)


def check_nearest(result, ref, origin, direction, centers, radii, rtol=1e-5):
    hit, best, distance, front, ambiguous, _ = ref
    clear = ~ambiguous
    assert clear.sum() > RAYS // 2
    sphere_type = int(rt.IntersectionType.SPHERE)
    np.testing.assert_array_equal(result["type"][clear], np.where(hit, sphere_type, 0)[clear])
    np.testing.assert_array_equal(result["primitive_id"][clear], best[clear])
    ok = clear & hit
    assert ok.sum() > 20
    np.testing.assert_allclose(result["distance"][ok], distance[ok], rtol=rtol, atol=1e-6)
    assert np.all(np.isinf(result["distance"][clear & ~hit]))
    np.testing.assert_array_equal(result["sphere_front_facing"][clear], front[clear])
    # the outward unit normal at the hit point
    point = origin[ok] + distance[ok, None] * direction[ok].astype(np.float64)
    outward = (point - centers[best[ok]]) / radii[best[ok], None]
    np.testing.assert_allclose(result["normal"][ok], outward, atol=2e-3)
    np.testing.assert_array_equal(result["primitive_data"][ok], best[ok] * 10)
    assert not np.isnan(result["distance"]).any() and not np.isnan(result["normal"]).any()


# --- nearest and any hit -----------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def random_scene():
    centers, radii, origin, direction, t_min, t_max = scene(1)
    geometry = rt.SphereGeometry(centers, radii, primitive_data=jnp.arange(len(radii)) * 10)
    structure = rt.build_primitive_structure(geometry, capacity=CAPACITY)
    ref = reference(origin, direction, t_min, t_max, centers, radii)
    return structure, (centers, radii, origin, direction, t_min, t_max), ref


def test_nearest_matches_float64(random_scene):
    structure, (centers, radii, origin, direction, t_min, t_max), ref = random_scene
    result = trace(NEAREST, structure, origin, direction, t_min, t_max)
    check_nearest(result, ref, origin, direction, centers, radii)
    # rays from inside report the exit hit, facing away
    hit, _, _, front, ambiguous, _ = ref
    assert np.sum(hit[:32] & ~front[:32] & ~ambiguous[:32]) >= 16
    # the interval cuts hits: some rays with a finite t_max miss a sphere they would hit without it
    _, _, unbounded, _, _, _ = reference(origin, direction, t_min, np.full(RAYS, np.inf), centers, radii)
    assert np.any(~hit[230:] & np.isfinite(unbounded[230:]))


def test_any_hit_accepts_a_real_hit(random_scene):
    structure, (centers, radii, origin, direction, t_min, t_max), ref = random_scene
    hit, _, _, _, ambiguous, t = ref
    result = trace(rt.Intersector(accept_any_intersection=True), structure, origin, direction, t_min, t_max)
    clear = ~ambiguous
    np.testing.assert_array_equal(result["type"][clear] != 0, hit[clear])
    ok = clear & hit
    chosen = t[ok, result["primitive_id"][ok]]
    np.testing.assert_allclose(result["distance"][ok], chosen, rtol=1e-5)


def test_max_hits_and_counting(random_scene):
    structure, (centers, radii, origin, direction, t_min, t_max), ref = random_scene
    _, _, _, _, ambiguous, t = ref
    k = 3
    result = trace(rt.Intersector(max_hits=k), structure, origin, direction, t_min, t_max)
    clear = ~ambiguous
    want = np.sort(t, axis=1)
    count = np.sum(np.isfinite(t), 1)
    np.testing.assert_array_equal(result["hit_count"][clear], np.minimum(count, k)[clear])
    np.testing.assert_array_equal(result["hit_overflow"][clear], (count > k)[clear])
    finite = np.isfinite(want[:, :k]) & clear[:, None]
    np.testing.assert_allclose(result["distance"][finite], want[:, :k][finite], rtol=1e-5)
    ray = rt.Ray(jnp.asarray(origin), jnp.asarray(direction), jnp.asarray(t_min), jnp.asarray(t_max))
    counted = np.asarray(rt.count_intersections(ray, structure))
    np.testing.assert_array_equal(counted[clear], count[clear])
    assert count.max() > k


def test_filter_on_non_opaque_spheres(random_scene):
    _, (centers, radii, origin, direction, t_min, t_max), _ = random_scene
    ids = jnp.arange(len(radii))
    geometry = rt.SphereGeometry(centers, radii, primitive_data=ids, opaque=False)
    structure = rt.build_primitive_structure(geometry, capacity=CAPACITY)
    even = rt.Intersector(filter=lambda c: c.primitive_data % 2 == 0)
    result = trace(even, structure, origin, direction, t_min, t_max)
    keep = np.arange(len(radii)) % 2 == 0
    hit, best, distance, _, ambiguous, _ = reference(origin, direction, t_min, t_max, centers[keep], radii[keep])
    clear = ~ambiguous
    np.testing.assert_array_equal(result["primitive_id"][clear], np.where(hit, np.flatnonzero(keep)[best], -1)[clear])
    np.testing.assert_allclose(result["distance"][clear & hit], distance[clear & hit], rtol=1e-5)


def test_mixed_with_triangles():
    """Spheres and triangles in one structure: each leaf takes its own test."""
    centers, radii, origin, direction, t_min, t_max = scene(2, count=8, inside=False)
    quad = np.array([[-1e3, -1e3], [1e3, -1e3], [1e3, 1e3], [-1e3, -1e3], [1e3, 1e3], [-1e3, 1e3]])
    ground = np.concatenate([quad, np.full((6, 1), -1.5)], 1).astype(np.float32)
    structure = rt.build_primitive_structure([rt.SphereGeometry(centers, radii), rt.TriangleGeometry(ground)])
    result = trace(rt.Intersector(rt.tags.normal), structure, origin, direction, t_min, t_max)
    hit, best, distance, _, ambiguous, _ = reference(origin, direction, t_min, t_max, centers, radii)
    with np.errstate(divide="ignore", invalid="ignore"):
        plane = (-1.5 - origin[:, 2].astype(np.float64)) / direction[:, 2]
        at = origin + plane[:, None] * direction
        plane_ok = (plane >= t_min) & (plane <= t_max) & np.all(np.abs(at[:, :2]) < 900, 1)
    plane = np.where(plane_ok, plane, np.inf)
    with np.errstate(invalid="ignore"):
        clear = ~ambiguous & (np.abs(plane - distance) > 1e-3)
    want_type = np.where(plane < distance, 1, np.where(hit, 4, 0))
    np.testing.assert_array_equal(result["type"][clear], want_type[clear])
    sphere_hits = clear & (want_type == 4)
    assert sphere_hits.sum() > 10 and (clear & (want_type == 1)).sum() > 10
    np.testing.assert_array_equal(result["geometry_id"][sphere_hits], 0)


@given(st.integers(0, 2**31 - 1), st.sampled_from([0.5, 4.0, 300.0]))
def test_random_scenes_match_float64(seed, spread):
    centers, radii, origin, direction, t_min, t_max = scene(seed, spread=spread)
    radii = (radii * spread / 4).astype(np.float32)
    geometry = rt.SphereGeometry(centers, radii, primitive_data=jnp.arange(len(radii)) * 10)
    structure = rt.build_primitive_structure(geometry, capacity=CAPACITY)
    ref = reference(origin, direction, t_min, t_max, centers, radii)
    check_nearest(trace(NEAREST, structure, origin, direction, t_min, t_max), ref, origin, direction, centers, radii)


# --- precision ----------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("backend", ["portable", "cpu"])
def test_far_small_and_large_spheres(backend):
    """Spheres about 1e4 from the origin with radii 1e-3 to 1e3: rays from the origin and from near each
    sphere, aimed at its centre or across it. Non-grazing hits have a relative distance error of at most 1e-6
    against float64 on the same float32 inputs, and no ray whose line passes within half a radius of the
    centre misses."""
    skip_unless_runs(backend)
    rng = np.random.default_rng(7)
    n = RAYS // 4
    direction_of = rng.normal(size=(n, 3))
    direction_of /= np.linalg.norm(direction_of, axis=1, keepdims=True)
    centers = (direction_of * 1e4 * rng.uniform(0.8, 1.2, (n, 1))).astype(np.float32)
    radii = (10.0 ** rng.uniform(-3, 3, n)).astype(np.float32)
    origins, directions, which = [], [], []
    for k in range(4):  # from the origin, from 3 to 100 radii away, aimed at the centre or off it
        if k == 0:
            o = np.zeros((n, 3))
        else:
            away = rng.normal(size=(n, 3))
            away /= np.linalg.norm(away, axis=1, keepdims=True)
            o = centers + away * (radii[:, None] * rng.uniform(3, 100, (n, 1)))
        o = o.astype(np.float32)
        offset = rng.normal(size=(n, 3)) * radii[:, None] * (0.0 if k < 2 else 0.4)
        origins.append(o)
        directions.append((centers + offset - o).astype(np.float32))
        which.append(np.arange(n))
    origin, direction, which = np.concatenate(origins), np.concatenate(directions), np.concatenate(which)
    for part in range(2):  # one structure of the far spheres; each ray is compared with its own sphere
        rows = slice(part * (RAYS // 2), (part + 1) * (RAYS // 2))
        structure = rt.build_primitive_structure(rt.SphereGeometry(centers, radii), capacity=CAPACITY)
        result = trace(rt.Intersector(backend=backend), structure, origin[rows], direction[rows], 0.0, np.inf)
        o, d, w = origin[rows], direction[rows], which[rows]
        near, far, _ = roots64(o, d, centers[w][:, None][:, 0], radii[w])
        near, far = np.diagonal(near), np.diagonal(far)
        f = o.astype(np.float64) - centers[w]
        dd = d.astype(np.float64)
        s = -np.sum(f * dd, 1) / np.sum(dd * dd, 1)
        miss = np.linalg.norm(f + s[:, None] * dd, axis=1)
        aimed = miss <= 0.5 * radii[w]
        assert aimed.sum() >= (RAYS // 2 - 8 if part == 0 else 16)  # the first half aims every ray exactly
        got = result["distance"]
        mine = result["primitive_id"] == w
        assert np.all(np.isfinite(got[aimed])), (
            f"missed rays aimed at centres: {np.flatnonzero(~np.isfinite(got) & aimed)}"
        )
        clean = aimed & mine & (miss <= 0.9 * radii[w])
        want = np.where(near >= 0, near, far)
        error = np.abs(got[clean] - want[clean]) / want[clean]
        assert error.max() <= 1e-6, f"relative distance error {error.max():.3g}"


# --- instancing, motion ------------------------------------------------------------------------------------------


def test_instanced_spheres():
    """Spheres below a rotated, uniformly scaled, translated instance match world-space spheres."""
    centers, radii, origin, direction, t_min, t_max = scene(3, count=16, inside=False)
    angle = 0.7
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    scale, shift = 1.5, np.array([0.5, -1.0, 2.0])
    transform = np.concatenate([rotation * scale, shift[:, None]], 1).astype(np.float32)
    inner = rt.build_primitive_structure(rt.SphereGeometry(centers, radii), capacity=CAPACITY)
    scene_structure = rt.build_instance_structure([inner], rt.Instances([0], transform[None]))
    intersector = rt.Intersector(rt.tags.instancing, rt.tags.normal, rt.tags.sphere_data)
    result = trace(intersector, scene_structure, origin, direction, t_min, t_max)
    world = (centers.astype(np.float64) @ rotation.T * scale + shift).astype(np.float32)
    world_radii = (radii * scale).astype(np.float32)
    hit, best, distance, front, ambiguous, _ = reference(origin, direction, t_min, t_max, world, world_radii)
    clear = ~ambiguous
    np.testing.assert_array_equal(result["primitive_id"][clear], best[clear])
    ok = clear & hit
    assert ok.sum() > 20
    np.testing.assert_allclose(result["distance"][ok], distance[ok], rtol=1e-4)
    point = origin[ok] + distance[ok, None] * direction[ok].astype(np.float64)
    outward = (point - world[best[ok]]) / world_radii[best[ok], None]
    np.testing.assert_allclose(result["normal"][ok], outward, atol=2e-3)
    np.testing.assert_array_equal(result["instance_id"][ok, 0], 0)


def test_keyframe_motion_of_centres_and_radii():
    centers, radii, origin, direction, t_min, t_max = scene(4, count=16, inside=False)
    rng = np.random.default_rng(4)
    moved = (centers + rng.normal(size=centers.shape)).astype(np.float32)
    radii1 = (radii * rng.uniform(0.3, 1.5, radii.shape)).astype(np.float32)
    geometry = rt.MotionSphereGeometry([centers, moved], [radii, radii1])
    structure = rt.build_primitive_structure(geometry, motion=rt.MotionSpec(0.0, 1.0), capacity=CAPACITY)
    time = rng.uniform(0, 1, RAYS).astype(np.float32)
    intersector = rt.Intersector(rt.tags.primitive_motion)
    result = trace(intersector, structure, origin, direction, t_min, t_max, time)
    checked = 0
    for w in (0.0, 0.25, 0.5, 0.75, 1.0):  # rays grouped by time: the reference blends per group
        rows = np.abs(time - w) < 0.125
        if not rows.any():
            continue
        w_rows = time[rows].astype(np.float64)[:, None]
        blended_c = centers[None] * (1 - w_rows[..., None]) + moved[None] * w_rows[..., None]  # (r, n, 3)
        blended_r = radii[None] * (1 - w_rows) + radii1[None] * w_rows
        for i, r in enumerate(np.flatnonzero(rows)):
            one = reference(
                origin[r : r + 1], direction[r : r + 1], t_min[r : r + 1], t_max[r : r + 1], blended_c[i], blended_r[i]
            )
            hit, best, distance, _, ambiguous, _ = one
            if ambiguous[0]:
                continue
            checked += 1
            assert result["primitive_id"][r] == best[0]
            if hit[0]:
                np.testing.assert_allclose(result["distance"][r], distance[0], rtol=1e-4)
    assert checked > RAYS // 2


# --- gradients ---------------------------------------------------------------------------------------------------


def test_gradients_match_central_differences():
    """d(distance), d(normal) with respect to centres, radii, ray origins and directions, in float64."""
    with jax.enable_x64(True):
        centers, radii, origin, direction, t_min, t_max = scene(5, count=12, inside=True)
        params = {
            "centers": jnp.asarray(centers, jnp.float64),
            "radii": jnp.asarray(radii, jnp.float64),
            "origin": jnp.asarray(origin, jnp.float64),
            "direction": jnp.asarray(direction, jnp.float64),
        }
        intersector = rt.Intersector(rt.tags.normal)

        def run(p):
            structure = rt.build_primitive_structure(rt.SphereGeometry(p["centers"], p["radii"]), capacity=16)
            ray = rt.Ray(p["origin"], p["direction"], jnp.zeros(RAYS), jnp.full(RAYS, jnp.inf))
            result = intersector.intersect(ray, structure)
            return result.distance, result.normal, result.primitive_id

        weights = jnp.asarray(np.random.default_rng(5).normal(size=(RAYS, 3)))

        def loss(p, mask):
            distance, normal, _ = run(p)
            distance = jnp.where(mask, distance, 0.0)
            normal = jnp.where(mask[:, None], normal, 0.0)
            return jnp.sum(distance) + jnp.sum(normal * weights)

        run_jit, loss_jit = jax.jit(run), jax.jit(loss)
        _, _, base_id = run_jit(params)
        base_id = np.asarray(base_id)
        rng = np.random.default_rng(6)
        tangent = {k: jnp.asarray(rng.normal(size=v.shape)) for k, v in params.items()}
        step = 1e-5
        ids, losses = [], []
        mask = jnp.asarray(base_id >= 0)
        for sign in (1, -1):
            moved = {k: v + sign * step * tangent[k] for k, v in params.items()}
            ids.append(np.asarray(run_jit(moved)[2]))
        stable = (ids[0] == base_id) & (ids[1] == base_id) & (base_id >= 0)
        assert stable.sum() > RAYS // 4
        mask = jnp.asarray(stable)
        for sign in (1, -1):
            moved = {k: v + sign * step * tangent[k] for k, v in params.items()}
            losses.append(float(loss_jit(moved, mask)))
        numeric = (losses[0] - losses[1]) / (2 * step)
        grad = jax.jit(jax.grad(loss))(params, mask)
        analytic = sum(float(jnp.sum(grad[k] * tangent[k])) for k in params)
        assert all(np.all(np.isfinite(np.asarray(g))) for g in grad.values())
        assert abs(analytic - numeric) <= 1e-5 * max(1.0, abs(numeric)), (analytic, numeric)
        for key in params:  # each parameter's gradient is non-zero
            assert float(jnp.max(jnp.abs(grad[key]))) > 0, key


# --- bad input -----------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("centers", "radii", "match"),
    [
        ([[0.0, np.nan, 0.0]], 1.0, r"SphereGeometry: centers has a non-finite value nan at index \(0, 1\)"),
        ([[0.0, 0.0, np.inf]], 1.0, r"centers has a non-finite value inf"),
        ([[0.0, 0.0, 0.0]], -1.0, r"SphereGeometry: radii\[0\] = -1.0 must be finite and >= 0"),
        ([[0.0, 0.0, 0.0], [1, 1, 1]], [1.0, np.nan], r"radii\[1\] = nan must be finite and >= 0"),
        ([[0.0, 0.0]], 1.0, r"SphereGeometry: centers must have shape \(N, 3\), got \(1, 2\)"),
        ([[0.0, 0.0, 0.0]], [1.0, 2.0], r"radii must be a scalar or have shape \(1,\)"),
        (np.zeros((0, 3), np.float32), 1.0, r"SphereGeometry: centers is empty"),
        (np.zeros((1, 3), np.int32), 1.0, r"SphereGeometry: centers must be float32 or float64, got dtype int32"),
        ([[0.0, 0.0, 0.0]], np.ones(1, np.int64), r"SphereGeometry: radii must be float32 or float64"),
    ],
)
def test_bad_input_is_a_named_value_error(centers, radii, match):
    with pytest.raises(ValueError, match=match):
        rt.SphereGeometry(np.asarray(centers) if isinstance(centers, np.ndarray) else centers, radii)


def test_bad_motion_input():
    with pytest.raises(ValueError, match=r"MotionSphereGeometry: keyframe 1: radii\[0\] = -2.0"):
        rt.MotionSphereGeometry([[[0.0, 0, 0]], [[1.0, 0, 0]]], [[1.0], [-2.0]])
    with pytest.raises(ValueError, match=r"MotionSphereGeometry: centers needs at least 2 keyframes"):
        rt.MotionSphereGeometry([[0.0, 0, 0]], 1.0)


def test_bad_spheres_inside_jit():
    """With checks a traced bad sphere is a BuildCheckError; without, it is never hit."""
    centers = jnp.array([[0.0, 0, 0], [0, 0, 3], [0, 0, 6], [0, 0, 9]], jnp.float32)
    radii = jnp.array([1.0, -1.0, jnp.nan, jnp.inf], jnp.float32)

    def build(c, r, checks):
        return rt.build_primitive_structure(rt.SphereGeometry(c, r), checks=checks, capacity=4)

    with pytest.raises(rt.BuildCheckError, match=r"radii\[1\] = -1\. is negative or not finite"):
        with rt.build_check_errors():
            jax.block_until_ready(jax.jit(lambda c, r: build(c, r, True))(centers, radii))
    bad_centre = centers.at[0, 1].set(jnp.nan)
    with pytest.raises(rt.BuildCheckError, match=r"centers\[0\] = \[ 0\., nan, 0\.\] is not finite"):
        with rt.build_check_errors():
            jax.block_until_ready(jax.jit(lambda c, r: build(c, r, True))(bad_centre, jnp.abs(radii)))
    structure = jax.jit(lambda c, r: build(c, r, False))(bad_centre, radii)
    origin = np.array([[0.0, 0, -5], [0, 0, 3], [0, 0, 6], [0, 0, 12]], np.float32)
    direction = np.array([[0.0, 0, 1], [1, 0, 0], [1, 0, 0], [0, 0, -1]], np.float32)
    result = rt.Intersector().intersect(rt.Ray(origin, direction), structure)
    assert np.all(np.asarray(result.type) == 0), np.asarray(result.primitive_id)


# --- every backend against the portable path --------------------------------------------------------------------

BACKEND_CASES = {
    "nearest": dict(),
    "any": dict(accept_any_intersection=True),
    "max_hits": dict(max_hits=3),
}


def _compare(got, want, ambiguous, fields=("type", "primitive_id", "geometry_id")):
    clear = ~ambiguous
    for name in fields:
        np.testing.assert_array_equal(got[name][clear], want[name][clear], err_msg=name)
    ok = clear & np.isfinite(want["distance"].reshape(len(clear), -1)[:, 0])
    np.testing.assert_allclose(got["distance"][ok], want["distance"][ok], rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(got["sphere_front_facing"][clear], want["sphere_front_facing"][clear])
    np.testing.assert_allclose(got["normal"][ok], want["normal"][ok], atol=1e-5)


@pytest.mark.parametrize("case", sorted(BACKEND_CASES))
def test_cpu_traversal_matches_portable(random_scene, case):
    skip_unless_runs("cpu")
    structure, (centers, radii, origin, direction, t_min, t_max), ref = random_scene
    tags = (rt.tags.normal, rt.tags.sphere_data)
    options = BACKEND_CASES[case]
    got = trace(rt.Intersector(*tags, backend="cpu", **options), structure, origin, direction, t_min, t_max)
    want = trace(rt.Intersector(*tags, backend="portable", **options), structure, origin, direction, t_min, t_max)
    _compare(got, want, ref[4] if case != "any" else np.zeros(RAYS, bool))


def test_cpu_traversal_instanced_matches_portable(random_scene):
    skip_unless_runs("cpu")
    structure, (centers, radii, origin, direction, t_min, t_max), ref = random_scene
    transform = np.array([[0.0, -1.2, 0, 0.5], [1.2, 0, 0, -1], [0, 0, 1.2, 2]], np.float32)
    scene_structure = rt.build_instance_structure([structure], rt.Instances([0], transform[None]))
    tags = (rt.tags.instancing, rt.tags.normal, rt.tags.sphere_data)
    got = trace(rt.Intersector(*tags, backend="cpu"), scene_structure, origin, direction, t_min, t_max)
    want = trace(rt.Intersector(*tags, backend="portable"), scene_structure, origin, direction, t_min, t_max)
    assert np.sum(want["type"] == 4) > 50
    _compare(got, want, np.zeros(RAYS, bool))


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_cpu_lean_loop_with_triangles(dtype, monkeypatch):
    """Spheres beside triangles in one structure take the CPU traversal's lean loop (``trace_flat``): nearest
    and any hit with back-face culling (triangles only), bit for bit the general loop's leaves, distances and
    stats counters (the same compiled sphere test), and the portable path's hits, in float32 and float64."""
    skip_unless_runs("cpu")
    from jaxrt._src import pipeline
    from jaxrt._src.traversal import cpu_kernel

    calls = []
    lean = cpu_kernel.trace_flat
    monkeypatch.setattr(cpu_kernel, "trace_flat", lambda *a: (calls.append(a[-2]), lean(*a))[1])
    centers, radii, origin, direction, t_min, t_max = scene(4, count=24)
    ground = np.array([[-9, -9, -1.5], [9, -9, -1.5], [0, 9, -1.5], [-9, 9, 1.0], [0, -9, 1.0], [9, 9, 1.0]])
    ambiguous = reference(origin, direction, t_min, t_max, centers, radii)[4]
    with jax.enable_x64(dtype == "float64"):
        cast = lambda a: jnp.asarray(a, dtype)  # noqa: E731
        geometries = [rt.SphereGeometry(cast(centers), cast(radii)), rt.TriangleGeometry(cast(ground))]
        structure = rt.build_primitive_structure(geometries, capacity=CAPACITY)
        assert structure.leaf_triangle.dtype == dtype
        ray = rt.Ray(*(cast(a) for a in (origin, direction, t_min, t_max)))
        tags = (rt.tags.normal, rt.tags.sphere_data)
        for options in ({}, {"accept_any_intersection": True, "triangle_cull_mode": "back"}):
            intersector, portable = (rt.Intersector(*tags, backend=b, **options) for b in ("cpu", "portable"))
            params, arrays = pipeline.cpu_kernel_arguments(structure, ray, intersector)
            assert params[9] == cpu._FORMULA_ROWS
            count = len(calls)
            lean_out = cpu._run(params, arrays)
            general_out = cpu._run((*params[:9], 1, *params[10:]), arrays)  # analytic code 1: the general loop
            assert len(calls) == count + 1
            for name, a, b in zip(("distance", "leaf", "chain", "visited", "tested", "overflow"), lean_out, general_out, strict=True):  # fmt: skip
                np.testing.assert_array_equal(a, b, err_msg=name)
            got, want = (jax.tree_util.tree_map(np.asarray, dict(i.intersect(ray, structure))) for i in (intersector, portable))  # fmt: skip
            assert np.sum(want["type"] == 4) > 50 and np.sum(want["type"] == 1) > 10
            _compare(got, want, np.zeros(RAYS, bool) if options else ambiguous)
    assert calls and all(calls)  # the lean loop traced them, with its sphere test


kernel_here = pytest.fixture(kernel_launches_here, name="kernel_here")
kernel_test = pytest.mark.skipif(not (INTERPRETED or ON_GPU), reason="runs in the interpreter process or on a GPU")


def test_kernel_in_interpreter():
    """Runs this module's GPU kernel tests in Triton's interpreter, in a fresh process."""
    run_kernel_tests_in_interpreter(__file__, "gpu_kernel")


@kernel_test
@pytest.mark.parametrize("case", ["nearest", "any", "triangles"])
def test_gpu_kernel_matches_portable(case, kernel_here, monkeypatch):
    """The Triton kernel (the interpreter on a CPU) on a tiny scene: spheres alone, any hit, and spheres with
    triangles in one structure, under an instance for the last."""
    if not ON_GPU:
        monkeypatch.setattr(gpu, "unavailable_reason", lambda intersector: None)
    centers, radii, origin, direction, t_min, t_max = scene(9, count=12)
    n = 64
    origin, direction, t_min, t_max = origin[:n], direction[:n], t_min[:n], t_max[:n]
    geometry = rt.SphereGeometry(centers, radii)
    tags = (rt.tags.normal, rt.tags.sphere_data)
    options = dict(accept_any_intersection=True) if case == "any" else {}
    structure = rt.build_primitive_structure(geometry)
    if case == "triangles":
        ground = np.array([[-9, -9, -1.5], [9, -9, -1.5], [0, 9, -1.5]], np.float32)
        inner = rt.build_primitive_structure([geometry, rt.TriangleGeometry(ground)])
        structure = rt.build_instance_structure([inner], rt.Instances([0], np.eye(3, 4, dtype=np.float32)[None]))
        tags = (*tags, rt.tags.instancing)
    ray = rt.Ray(origin, direction, t_min, t_max)
    got = jax.tree_util.tree_map(
        np.asarray, dict(rt.Intersector(*tags, backend="gpu", **options).intersect(ray, structure))
    )
    want = jax.tree_util.tree_map(
        np.asarray, dict(rt.Intersector(*tags, backend="portable", **options).intersect(ray, structure))
    )
    assert np.sum(want["type"] == 4) > 10
    if case == "any":  # any hit: a real hit of the chosen sphere
        np.testing.assert_array_equal(got["type"] != 0, want["type"] != 0)
        return
    np.testing.assert_array_equal(got["primitive_id"], want["primitive_id"])
    np.testing.assert_array_equal(got["type"], want["type"])
    np.testing.assert_allclose(got["distance"], want["distance"], rtol=1e-6)


# --- point queries -------------------------------------------------------------------------------------------------


def test_closest_point_and_signed_distance():
    """The nearest sphere surface to each point, and the signed distance to the set (negative inside a sphere),
    against float64; differentiable in the points, centres and radii."""
    rng = np.random.default_rng(11)
    centers = rng.uniform(-4, 4, (30, 3)).astype(np.float32)
    radii = rng.uniform(0.1, 0.8, 30).astype(np.float32)
    points = np.concatenate([rng.uniform(-6, 6, (100, 3)), centers[:28] + rng.normal(size=(28, 3)) * 0.05])
    points = points.astype(np.float32)
    structure = rt.build_primitive_structure(rt.SphereGeometry(centers, radii), capacity=CAPACITY)
    result = rt.closest_point(points, structure)
    gap = np.linalg.norm(points[:, None].astype(np.float64) - centers[None], axis=-1) - radii[None]
    surface = np.abs(gap)
    best = np.argmin(surface, 1)
    rows = np.arange(len(points))
    clear = np.sort(surface, 1)[:, 1] - surface[rows, best] > 1e-4
    np.testing.assert_array_equal(np.asarray(result.primitive_id)[clear], best[clear])
    np.testing.assert_allclose(np.asarray(result.distance), surface[rows, best], atol=2e-6)
    on_surface = np.linalg.norm(np.asarray(result.point) - centers[np.asarray(result.primitive_id)], axis=1)
    np.testing.assert_allclose(on_surface, radii[np.asarray(result.primitive_id)], rtol=1e-5)
    inside = np.any(gap < 0, 1)
    assert inside.sum() >= 28
    signed = np.asarray(rt.signed_distance(points, structure))
    np.testing.assert_allclose(signed, np.where(inside, -1, 1) * surface[rows, best], atol=2e-6)
    np.testing.assert_array_equal(np.asarray(rt.contains(points, structure)), inside)

    def total(c, r, p):
        s = rt.build_primitive_structure(rt.SphereGeometry(c, r), capacity=CAPACITY)
        return jnp.sum(rt.closest_point(p, s).distance)

    grads = jax.grad(total, argnums=(0, 1, 2))(jnp.asarray(centers), jnp.asarray(radii), jnp.asarray(points))
    # d|p - q|/dp is the unit vector from the surface point; the chosen sphere's radius moves the surface by 1
    direction = points - np.asarray(result.point)
    unit = direction / np.linalg.norm(direction, axis=1, keepdims=True)
    np.testing.assert_allclose(np.asarray(grads[2])[clear], unit[clear], atol=1e-4)
    chosen = np.asarray(result.primitive_id)
    sign = np.where(gap[rows, chosen] < 0, 1.0, -1.0)  # d|(|p - c| - r)|/dr
    want_r = np.zeros(30)
    np.add.at(want_r, chosen, sign)
    np.testing.assert_allclose(np.asarray(grads[1]), want_r, atol=1e-4)
    want_c = np.zeros((30, 3))
    np.add.at(want_c, chosen, -unit)  # the centre moves the surface point with it
    np.testing.assert_allclose(np.asarray(grads[0]), want_c, atol=1e-3)


# --- lifecycle, jit and vmap ---------------------------------------------------------------------------------------


def test_refit_save_load_compact_and_vmap(tmp_path):
    """A refit moves the spheres; saving, loading and compaction keep the hits; ``vmap`` over structures."""
    rng = np.random.default_rng(12)
    centers = rng.uniform(-2, 2, (20, 3)).astype(np.float32)
    moved = (centers + 0.3).astype(np.float32)
    origin = np.concatenate([moved[:, :2], np.full((20, 1), -9.0)], 1).astype(np.float32)
    ray = rt.Ray(origin, np.tile(np.float32([[0, 0, 1]]), (20, 1)))
    data = jnp.arange(20)
    structure = rt.build_primitive_structure(rt.SphereGeometry(centers, 0.15, primitive_data=data))
    refit = rt.refit(structure, rt.SphereGeometry(moved, 0.2, primitive_data=data))
    fresh = rt.build_primitive_structure(rt.SphereGeometry(moved, 0.2, primitive_data=data))
    intersector = rt.Intersector(rt.tags.primitive_data)
    want = intersector.intersect(ray, fresh)
    for other in (refit, rt.compact(refit)):
        got = intersector.intersect(ray, other)
        np.testing.assert_array_equal(np.asarray(got.distance), np.asarray(want.distance))
    assert np.all(np.isfinite(np.asarray(want.distance)))
    rt.save(tmp_path / "spheres.jaxrt", refit)
    loaded = rt.load(tmp_path / "spheres.jaxrt")
    np.testing.assert_array_equal(np.asarray(intersector.intersect(ray, loaded).distance), np.asarray(want.distance))
    pair = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), structure, fresh)
    both = jax.jit(jax.vmap(lambda s: rt.Intersector().intersect(ray, s).distance))(pair)
    np.testing.assert_array_equal(np.asarray(both[1]), np.asarray(want.distance))
    np.testing.assert_array_equal(np.asarray(both[0]), np.asarray(rt.Intersector().intersect(ray, structure).distance))


@pytest.mark.parametrize("backend", ["portable", "cpu"])
def test_ray_masks_select_instances_of_spheres(backend):
    """Two instances of one sphere structure with masks 1 and 2: each ray sees the instances its mask names."""
    skip_unless_runs(backend)
    inner = rt.build_primitive_structure(rt.SphereGeometry([[0.0, 0.0, 0.0]], 1.0))
    transforms = np.stack([np.eye(3, 4), np.eye(3, 4)]).astype(np.float32)
    transforms[1, :, 3] = [0.0, 0.0, -4.0]  # behind the first
    scene_structure = rt.build_instance_structure([inner], rt.Instances([0, 0], transforms, mask=[1, 2]))
    masks = np.array([1, 2, 3, 4], np.uint32)
    origin = np.tile(np.float32([[0, 0, 5]]), (4, 1))
    direction = np.tile(np.float32([[0, 0, -1]]), (4, 1))
    intersector = rt.Intersector(rt.tags.instancing, backend=backend)
    result = intersector.intersect(rt.Ray(origin, direction, mask=masks), scene_structure)
    np.testing.assert_array_equal(np.asarray(result.distance), np.float32([4, 8, 4, np.inf]))
    np.testing.assert_array_equal(np.asarray(result.instance_id)[:, 0], [0, 1, 0, -1])
