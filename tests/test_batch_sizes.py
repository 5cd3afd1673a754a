"""Every leaf kind traced in one call with batches below, at and above the traversal's internal sizes.

The portable traversal keeps ``REFILL_LANES`` (2048) rays in flight and takes the rest from a queue; batches
over ``CPU_CHUNK`` (65,536) rays run in sequential chunks; batches are padded to a power of two. A batch of
1000 rays (padded to 1024) fits one window, 2048 fills it exactly, 2049 (padded to 4096) refills lanes, and
65,537 (padded to 131,072) runs two chunks. XLA also compiles a batch of 4096 rows or more differently
(jaxlib 0.11's CPU YNNPACK fusion returned ``1 / |direction| = inf`` there, and every curve missed).

Each scene has a few hundred base rays checked against a float64 oracle once; a batch of ``n`` rays draws
its rays from the base rays in a random order, so that every lane, window and chunk holds different rays.
Triangles (``tests/reference.py``'s brute force), instances (Möller-Trumbore on the world-space triangles,
as in ``test_instancing``) and spheres (bounding boxes with ``rt.intersection_functions.sphere``, against the
analytic float64 roots) and linear round curves (``jaxrt.bench.curves``' float64 reference, on the pairs whose
ray comes near the segment) are checked at every size: about 45 s on two CPU cores.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np
import pytest
from reference import brute_force
from test_instancing import oracle

import jaxrt as rt
from jaxrt._src import pipeline
from jaxrt.bench.curves import host_segments, reference_hits

BASE_RAYS = 400
BELOW, AT, ABOVE, CHUNKS = 1000, 2048, 2049, 65_537
NONE = int(rt.IntersectionType.NONE)
#: Barycentric margin of the instance oracle (as in test_instancing) and relative margin of the sphere oracle.
MARGIN = 2e-4
SPHERE_MARGIN = 1e-3


def test_the_sizes_straddle_the_traversal_constants():
    assert BELOW < pipeline.REFILL_LANES == AT < ABOVE
    assert pipeline.CPU_CHUNK < CHUNKS <= 2 * pipeline.CPU_CHUNK


class Expected(NamedTuple):
    """The oracle's answer per base ray."""

    certain: np.ndarray  # (B,) some hit is certain: a miss is wrong
    possible: np.ndarray  # (B,) some hit is possible: otherwise a hit is wrong
    nearest: np.ndarray  # (B,) global id of the nearest certain hit when it is clear of every other, else -1
    distance: np.ndarray  # (B,) its float64 distance
    tolerance: np.ndarray  # (B,) allowed distance error


class Case(NamedTuple):
    intersector: rt.Intersector
    structure: object
    origin: np.ndarray  # (B, 3) float32
    direction: np.ndarray
    expected: Expected
    offsets: np.ndarray  # first global id of each geometry


def _expected(certain, possible, t, tolerance) -> Expected:
    """Reduce per-pair ``(B, P)`` oracle arrays to per-ray answers."""
    t_certain = np.where(certain, t, np.inf)
    j = np.argmin(t_certain, axis=1)
    rows = np.arange(t.shape[0])
    t_j, tol_j = t[rows, j], tolerance[rows, j]
    others = possible.copy()
    others[rows, j] = False
    clear = ~np.any(others & (t - tolerance <= t_j[:, None] + tol_j[:, None]), axis=1)
    has = certain.any(axis=1)
    nearest = np.where(has & clear, j, -1)
    return Expected(has, possible.any(axis=1), nearest, np.where(has, t_j, np.inf), np.where(has, tol_j, 0.0))


def _aimed(rng, targets: np.ndarray, count: int, spread: float) -> tuple[np.ndarray, np.ndarray]:
    """Rays from 6-10 units away at random targets (jittered by ``spread``), plus a quarter of random rays."""
    aimed = targets[rng.integers(0, len(targets), count)] + rng.normal(scale=spread, size=(count, 3))
    direction = rng.normal(size=(count, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    origin = aimed - direction * rng.uniform(6.0, 10.0, (count, 1))
    wild = rng.random(count) < 0.25
    origin[wild] = rng.uniform(-8.0, 8.0, (int(wild.sum()), 3))
    direction *= rng.uniform(0.5, 2.0, (count, 1))  # not unit length: distances are in direction units
    return origin.astype(np.float32), direction.astype(np.float32)


def _random_triangles(rng, count: int) -> np.ndarray:
    centre = rng.uniform(-5.0, 5.0, (count, 1, 3))
    return (centre + rng.normal(scale=0.5, size=(count, 3, 3))).astype(np.float32)


@functools.cache
def triangle_case() -> Case:
    rng = np.random.default_rng(1)
    triangles = _random_triangles(rng, 300)
    origin, direction = _aimed(rng, triangles.mean(axis=1), BASE_RAYS, 0.2)
    structure = rt.build_primitive_structure(rt.TriangleGeometry(triangles.reshape(-1, 3)))
    ref = brute_force(origin, direction, np.zeros(BASE_RAYS), np.full(BASE_RAYS, np.inf), triangles)
    expected = _expected(ref.certain, ref.possible, ref.distance, ref.tolerance)
    return Case(rt.Intersector(), structure, origin, direction, expected, np.zeros(1, np.int64))


@functools.cache
def instance_case() -> Case:
    rng = np.random.default_rng(2)
    triangles = _random_triangles(rng, 60) * np.float32(0.4)
    inner = rt.build_primitive_structure(rt.TriangleGeometry(triangles.reshape(-1, 3)))
    count = 8
    transforms = np.zeros((count, 3, 4), np.float32)
    for i in range(count):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        transforms[i, :, :3] = q * rng.uniform(0.5, 1.5)
        transforms[i, :, 3] = rng.uniform(-4.0, 4.0, 3)
    structure = rt.build_instance_structure([inner], rt.Instances(np.zeros(count, np.int32), transforms))
    m = transforms.astype(np.float64)
    world = np.einsum("kij,tvj->ktvi", m[:, :, :3], triangles.astype(np.float64)) + m[:, None, None, :, 3]
    world = world.reshape(-1, 3, 3)  # global id: instance * 60 + primitive
    origin, direction = _aimed(rng, world.mean(axis=1), BASE_RAYS, 0.1)
    t, bary_min, _, _ = oracle(origin, direction, world)
    ahead = np.isfinite(t) & (t > 0)
    certain, possible = ahead & (bary_min > MARGIN), ahead & (bary_min >= -MARGIN)
    expected = _expected(certain, possible, t, 1e-4 * (1.0 + np.where(np.isfinite(t), np.abs(t), 0.0)))
    intersector = rt.Intersector(rt.tags.instancing)
    return Case(intersector, structure, origin, direction, expected, np.arange(count) * len(triangles))


@functools.cache
def sphere_case() -> Case:
    rng = np.random.default_rng(3)
    count = 64
    centre = rng.uniform(-5.0, 5.0, (count, 3)).astype(np.float32)
    radius = rng.uniform(0.2, 0.8, count).astype(np.float32)
    lower, upper = rt.intersection_functions.sphere_bounds(centre, radius)
    geometry = rt.BoundingBoxGeometry(lower, upper, primitive_data={"center": centre, "radius": radius})
    structure = rt.build_primitive_structure(geometry)
    origin, direction = _aimed(rng, centre, BASE_RAYS, 0.4)
    o, d = origin.astype(np.float64)[:, None], direction.astype(np.float64)[:, None]
    c, r = centre.astype(np.float64)[None], radius.astype(np.float64)[None]
    a = np.sum(d * d, axis=-1)
    along = np.sum((c - o) * d, axis=-1) / a  # ray parameter of the closest approach
    miss = np.linalg.norm(o + along[..., None] * d - c, axis=-1)  # closest-approach distance
    half = np.sqrt(np.maximum(r * r - miss * miss, 0.0) / a)
    near, far = along - half, along + half
    t = np.where(near >= 0, near, far)
    ahead = far >= 0
    certain = ahead & (miss < r * (1 - SPHERE_MARGIN)) & (np.abs(near) > SPHERE_MARGIN)
    possible = ahead & (miss <= r * (1 + SPHERE_MARGIN))
    t = np.where(possible, t, np.inf)
    expected = _expected(certain, possible, t, 1e-3 * (1.0 + np.abs(np.where(possible, t, 0.0))))
    functions = {0: rt.intersection_functions.sphere}
    return Case(rt.Intersector(intersection_functions=functions), structure, origin, direction, expected, np.zeros(1))


@functools.cache
def curve_case() -> Case:
    rng = np.random.default_rng(4)
    count = 64
    middle = rng.uniform(-5.0, 5.0, (count, 3))
    axis = rng.normal(size=(count, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    half = rng.uniform(0.5, 1.5, (count, 1)) * axis
    points = np.stack([middle - half, middle + half], axis=1).reshape(-1, 3).astype(np.float32)
    radii = np.repeat(rng.uniform(0.05, 0.3, count), 2).astype(np.float32)
    geometry = rt.CurveGeometry(points, radii, np.arange(count) * 2, basis="linear", control_point_count=2)
    structure = rt.build_primitive_structure(geometry)
    origin, direction = _aimed(rng, middle, BASE_RAYS, 0.15)
    # Only pairs whose ray line passes within reach of the segment's bounding sphere go to the reference.
    o, d = origin.astype(np.float64), direction.astype(np.float64)
    unit = d / np.linalg.norm(d, axis=1, keepdims=True)
    to_middle = middle[None] - o[:, None]
    gap = np.linalg.norm(to_middle - np.sum(to_middle * unit[:, None], axis=-1, keepdims=True) * unit[:, None], axis=-1)
    near = gap <= np.linalg.norm(half, axis=1)[None] + radii[::2][None] + 0.1
    ray_index, segment_index = np.nonzero(near)
    # Bands as in test_curves_primitive: 1e-2 radii, plus float32 rounding of ray-space coordinates.
    scale = np.linalg.norm(origin, axis=1) + 10.0
    rounding = 32 * float(np.finfo(np.float32).eps) * scale
    ref = reference_hits(
        origin,
        direction,
        np.zeros(BASE_RAYS),
        np.full(BASE_RAYS, np.inf),
        host_segments(geometry),
        ray_index,
        segment_index,
        band=1e-2 * radii.max() + rounding[ray_index],
    )
    shape = (BASE_RAYS, count)
    ambiguous, hit, t = np.zeros(shape, bool), np.zeros(shape, bool), np.full(shape, np.inf)
    ambiguous[ray_index, segment_index] = ref.ambiguous
    hit[ray_index, segment_index] = ref.hit
    t[ray_index, segment_index] = ref.distance
    length = np.linalg.norm(direction, axis=1)
    tolerance = np.broadcast_to(((1e-2 * radii.max() + rounding) / length)[:, None], shape)
    expected = _expected(hit & ~ambiguous, hit | ambiguous, np.where(hit, t, np.inf), tolerance)
    return Case(rt.Intersector(rt.tags.curve_data), structure, origin, direction, expected, np.zeros(1))


CASES = {"triangles": triangle_case, "instances": instance_case, "spheres": sphere_case, "curves": curve_case}


def check(case: Case, n: int) -> None:
    """Trace ``n`` rays drawn from the base rays in one call and compare every one with the oracle."""
    rng = np.random.default_rng(n)
    pick = rng.permutation(np.resize(np.arange(BASE_RAYS), n))
    result = case.intersector.intersect(rt.Ray(case.origin[pick], case.direction[pick]), case.structure)
    kind = np.asarray(result.type)
    distance = np.asarray(result.distance, np.float64)
    if "instance_id" in result:  # one level: the instance is the geometry's offset
        offset = case.offsets[np.maximum(np.asarray(result.instance_id)[:, 0], 0)]
    else:
        offset = case.offsets[np.maximum(np.asarray(result.geometry_id), 0)]
    got = np.where(kind != NONE, offset + np.asarray(result.primitive_id), -1)
    e = Expected(*(a[pick] for a in case.expected))
    hit = kind != NONE
    with np.errstate(invalid="ignore"):  # inf - inf on misses
        error = np.abs(distance - e.distance)
    problems = {
        "missed a certain hit": e.certain & ~hit,
        "hit where the oracle has no possible hit": hit & ~e.possible,
        "another primitive than the clear nearest": (e.nearest >= 0) & (got != e.nearest),
        "distance off": (e.nearest >= 0) & (got == e.nearest) & ~(error <= e.tolerance),
    }
    report = [
        f"{name}: {int(bad.sum())} rays, first {np.flatnonzero(bad)[:5]}" for name, bad in problems.items() if bad.any()
    ]
    assert not report, f"{n} rays: " + "; ".join(report)
    # The check has teeth: most rays have a clear answer and many of them hit.
    assert np.mean(e.nearest >= 0) > 0.2 and np.mean(e.certain | ~e.possible) > 0.8


@pytest.mark.parametrize("n", [BELOW, AT, ABOVE, CHUNKS])
@pytest.mark.parametrize("kind", list(CASES))
def test_batch_against_the_float64_oracle(kind, n):
    check(CASES[kind](), n)
