"""``max_hits`` (the K nearest hits of each ray) and ``rt.count_intersections`` against float64 brute force.

Scenes, rays and the reference come from ``test_custom_geometry.py`` (one layout of opaque and alpha-tested
triangle soups, spheres, disks and capped cylinders, so both modules share its build): the reference says, for
every ray and primitive, whether a correct float32 implementation must hit it, may hit it, or must not, and
within which distances. A primitive is hit at most once along a ray (an intersection function reports its
nearest accepted root), so the sorted list of all hits is the list of primitives that are hit, by distance.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from reference import icosphere, octahedron, random_rotation
from test_custom_geometry import (
    AMBIGUOUS_LIMIT,
    CAPACITY,
    COUNTS,
    CUTOFFS,
    FUNCTIONS,
    OPAQUE,
    RAYS,
    Expected,
    alpha_filter,
    assert_data_round_trip,
    build,
    expected,
    far_exponents,
    global_index,
    random_rays,
    random_scene,
    scale_exponents,
    seeds,
)

import jaxrt as rt

K = 4
K_NEAREST = rt.Intersector(
    rt.tags.primitive_data, rt.tags.triangle_data, intersection_functions=FUNCTIONS, filter=alpha_filter, max_hits=K
)
COUNTING = rt.Intersector(intersection_functions=FUNCTIONS, filter=alpha_filter)
#: Triangles four times their usual size: many rays cross more than K primitives.
SPREAD = 4.0


def _scene_and_rays(seed, far_exp, scale_exp):
    scene = random_scene(seed, far_exp, scale_exp, spread=SPREAD)
    return scene, random_rays(seed ^ 0x3417, scene)


def check_k_nearest(result, exp: Expected) -> tuple[list[str], int]:
    """Failures of a ``max_hits=K`` result against the reference, and the number of ambiguous rays.

    A ray is ambiguous when a primitive it may or may not hit could change its first K hits, its hit count
    or its overflow flag, or when two of its first K + 1 hits are closer than their tolerances (their order
    is undecided). Ambiguous rays are still checked: only real hits, sorted, distinct, and counts between
    what the certain hits and all possible hits allow.
    """
    kind = np.asarray(result.type)
    distance = np.asarray(result.distance, np.float64)
    k_all = global_index(result.geometry_id, result.primitive_id, exp.offsets)
    count, overflow = np.asarray(result.hit_count), np.asarray(result.hit_overflow)
    failures, ambiguous = [], 0
    for r in range(kind.shape[0]):
        hits = np.flatnonzero(exp.hit[r])
        hits = hits[np.argsort(exp.lo[r, hits], kind="stable")]
        maybes = np.flatnonzero(exp.maybe[r])
        n = len(hits)
        first = hits[: K + 1]
        unordered = np.any(exp.lo[r, first[1:]] <= exp.hi[r, first[:-1]])
        if n > K:
            unsure = np.any(exp.lo[r, maybes] <= exp.hi[r, hits[K - 1]])
        else:
            unsure = len(maybes) > 0
        returned = int(count[r])
        empty = slice(returned, K)
        if np.any(kind[r, empty] != 0) or np.any(k_all[r, empty] != -1) or not np.all(np.isposinf(distance[r, empty])):
            failures.append(f"ray {r}: entries past hit_count {returned} are not empty: {k_all[r]}, {distance[r]}")
        if unordered or unsure:
            ambiguous += 1
            real = [
                exp.possible[r, k] and exp.lo[r, k] <= t <= exp.hi[r, k] and kind[r, i] == exp.kind[k]
                for i, (k, t) in enumerate(zip(k_all[r, :returned], distance[r, :returned], strict=True))
            ]
            if not all(real):
                failures.append(f"ray {r}: hits {k_all[r, :returned]} at {distance[r, :returned]} are not all real")
            if len(set(k_all[r, :returned].tolist())) != returned or np.any(np.diff(distance[r, :returned]) < 0):
                failures.append(
                    f"ray {r}: hits {k_all[r, :returned]} at {distance[r, :returned]} repeat or are unsorted"
                )
            if not min(n, K) <= returned <= min(n + len(maybes), K):
                failures.append(f"ray {r}: hit_count {returned}, but {n} certain and {len(maybes)} possible hits")
            if (n > K and not overflow[r]) or (n + len(maybes) <= K and overflow[r]):
                failures.append(f"ray {r}: hit_overflow {overflow[r]}, but {n} certain and {len(maybes)} possible hits")
            continue
        want = hits[:K]
        if returned != len(want) or overflow[r] != (n > K):
            failures.append(
                f"ray {r}: hit_count {returned} and overflow {overflow[r]}, expected {len(want)} of {n} hits"
            )
            continue
        if not np.array_equal(k_all[r, :returned], want):
            failures.append(f"ray {r}: hits {k_all[r, :returned]} at {distance[r, :returned]}, expected {want}")
            continue
        outside = (distance[r, :returned] < exp.lo[r, want]) | (distance[r, :returned] > exp.hi[r, want])
        if np.any(outside) or np.any(kind[r, :returned] != exp.kind[want]):
            failures.append(
                f"ray {r}: hits {want} at {distance[r, :returned]} (types {kind[r, :returned]}), "
                f"expected in [{exp.lo[r, want]}, {exp.hi[r, want]}]"
            )
        triangles = want < exp.barycentric.shape[1]
        bary = np.asarray(result.triangle_barycentric_coord[r, :returned], np.float64)[triangles]
        error = np.abs(bary - exp.barycentric[r, want[triangles]]).max(axis=-1, initial=0)
        if np.any(error > exp.barycentric_tolerance[r, want[triangles]]):
            failures.append(f"ray {r}: barycentrics of hits {want} off by {error}")
        if np.any(np.asarray(result.triangle_barycentric_coord[r, :returned])[~triangles] != 0):
            failures.append(f"ray {r}: analytic hits {want[~triangles]} with barycentrics")
    return failures, ambiguous


def check_counts(count, exp: Expected) -> tuple[list[str], int]:
    """Failures of ``count_intersections`` (exact where no primitive is in doubt), and the rays in doubt."""
    count = np.asarray(count)
    certain, doubtful = exp.hit.sum(axis=1), exp.maybe.sum(axis=1)
    wrong = (count < certain) | (count > certain + doubtful)
    failures = [
        f"ray {r}: {count[r]} hits, expected {certain[r]} (+ up to {doubtful[r]})" for r in np.flatnonzero(wrong)
    ]
    return failures, int(np.sum(doubtful > 0))


@settings(max_examples=6, deadline=None)
@given(seeds, far_exponents, scale_exponents)
def test_k_nearest_hits_match_float64(seed, far_exp, scale_exp):
    """The K nearest hits on triangle soups (alpha-tested ones through the filter) and analytic shapes, with
    random ray intervals and disabled rays: sorted, with the right primitives, counts and overflow flags."""
    scene, rays = _scene_and_rays(seed, far_exp, scale_exp)
    structure = build(scene)
    result = K_NEAREST.intersect(rays.ray(), structure)
    assert result.distance.shape == (RAYS, K) and result.triangle_barycentric_coord.shape == (RAYS, K, 2)
    assert result.hit_count.shape == result.hit_overflow.shape == (RAYS,)
    exp = expected(scene, rays)
    failures, ambiguous = check_k_nearest(result, exp)
    assert not failures, f"{len(failures)} rays disagree with the float64 reference:\n" + "\n".join(failures[:20])
    assert ambiguous <= AMBIGUOUS_LIMIT * RAYS, ambiguous
    assert_data_round_trip(result, scene)
    # Every returned hit lies in its ray's interval; disabled rays return nothing.
    distance = np.asarray(result.distance)
    found = np.isfinite(distance)
    assert np.all((distance >= rays.min_distance[:, None]) | ~found)
    assert np.all((distance <= rays.max_distance[:, None]) | ~found)
    disabled = ~rays.enabled
    assert disabled.any() and not np.asarray(result.hit_count)[disabled].any()
    assert not np.asarray(result.hit_overflow)[disabled].any() and not found[disabled].any()
    # The scene is dense enough for overflowing rays, and rays with 1 to K hits.
    count = np.asarray(result.hit_count)
    assert np.asarray(result.hit_overflow).sum() >= 10 and ((count > 0) & (count < K)).sum() >= 10
    # A batch of shape (16, 16): the K axis (and the barycentrics' axis) follow the batch axes.
    square = K_NEAREST.intersect(rays.ray().reshape(16, 16), structure)
    for name, value in result.items():
        if name != "primitive_data":
            assert square[name].shape == (16, 16, *value.shape[1:]), name
            np.testing.assert_array_equal(np.asarray(square[name]).reshape(value.shape), np.asarray(value))
    assert square.primitive_data["extra"][1]["code"].shape == (16, 16, K, 2, 2)


@settings(max_examples=6, deadline=None)
@given(seeds, far_exponents, scale_exponents)
def test_count_intersections_matches_float64(seed, far_exp, scale_exp):
    scene, rays = _scene_and_rays(seed, far_exp, scale_exp)
    structure = build(scene)
    count = rt.count_intersections(rays.ray(), structure, COUNTING)
    assert count.dtype == np.int32 and count.shape == (RAYS,)
    square = rt.count_intersections(rays.ray().reshape(16, 16), structure, COUNTING)
    np.testing.assert_array_equal(np.asarray(square), np.asarray(count).reshape(16, 16))
    exp = expected(scene, rays)
    failures, doubtful = check_counts(count, exp)
    assert not failures, f"{len(failures)} rays disagree with the float64 reference:\n" + "\n".join(failures[:20])
    assert doubtful <= AMBIGUOUS_LIMIT * RAYS, doubtful
    assert not np.asarray(count)[~rays.enabled].any()
    assert np.asarray(count).max() > K


def _convex(vertices, faces):
    """Outward face planes ``(normal, offset)`` of a closed convex mesh."""
    tri = vertices[faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    return normal, np.sum(normal * tri[:, 0], axis=-1)


@settings(max_examples=4, deadline=None)
@given(seeds)
def test_parity_of_counts_tells_inside_from_outside(seed):
    """Rays from random points away from the surfaces of a closed icosphere and two alpha-tested octahedra:
    the count is odd iff the point is inside an odd number of the visible meshes, with the second octahedron
    rejected by the filter (invisible) or accepted. The analytic shapes are out of the rays' reach."""
    rng = np.random.default_rng(seed)
    scene = random_scene(seed)  # for its layout, primitive data and far-away shapes
    scale = 10.0 ** rng.uniform(-1, 2)
    center = rng.normal(size=3) * scale * 10.0 ** rng.uniform(-1, 2)
    sphere_v, sphere_f = icosphere(1)
    assert len(sphere_f) == COUNTS[OPAQUE]
    meshes = [(sphere_v @ random_rotation(rng).T * scale + center, sphere_f)]
    octa_v, octa_f = octahedron()
    for _ in range(2):
        size = scale * rng.uniform(0.3, 0.8)
        meshes.append((octa_v @ random_rotation(rng).T * size + center + rng.uniform(-1, 1, 3) * scale * 0.8, octa_f))
    triangles = [(v[f]).astype(np.float32) for v, f in meshes]
    away_from_rays = center + 1e3 * scale
    data = [dict(d) for d in scene.data]
    for geometry, keys in ((2, ("center",)), (3, ("center",)), (4, ("p0", "p1"))):
        data[geometry].update({key: (data[geometry][key] + away_from_rays).astype(np.float32) for key in keys})

    def structure(cutoffs):
        alpha = dict(data[1], cutoff=np.repeat(cutoffs, 8).astype(np.float32))
        geometries = [
            rt.TriangleGeometry(triangles[0].reshape(-1, 3), primitive_data=data[0]),
            rt.TriangleGeometry(np.concatenate(triangles[1:]).reshape(-1, 3), primitive_data=alpha, opaque=False),
        ] + [
            rt.BoundingBoxGeometry(g.lower + away_from_rays, g.upper + away_from_rays, primitive_data=d)
            for g, d in zip(scene.geometries[2:], data[2:], strict=True)
        ]
        return rt.build_primitive_structure(geometries, capacity=CAPACITY)

    # Points in two boxes around the meshes, at least 1e-3 * scale from every surface.
    points = center + rng.uniform(-1, 1, (RAYS, 3)) * scale * np.where(np.arange(RAYS) % 2, 1.0, 2.5)[:, None]
    inside = []
    margin = np.full(RAYS, np.inf)
    for v, f in meshes:
        normal, offset = _convex(v, f)
        signed = (points @ normal.T - offset).max(axis=-1)  # the distance to the surface inside, a bound outside
        inside.append(signed < 0)
        margin = np.minimum(margin, np.abs(signed))
    direction = rng.normal(size=(RAYS, 3))
    direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
    # Every ray ends outside all meshes (they lie within 2.2 * scale of the centre) and far from the shapes.
    ray = rt.Ray(points.astype(np.float32), direction.astype(np.float32), 0.0, np.float32(8 * scale))
    away = margin > 1e-3 * scale
    assert away.sum() > RAYS * 0.9
    for cutoffs, visible in (([CUTOFFS[0], CUTOFFS[2]], inside[:2]), ([CUTOFFS[0], CUTOFFS[0]], inside)):
        count = np.asarray(rt.count_intersections(ray, structure(cutoffs), COUNTING))
        odd = np.logical_xor.reduce(visible)
        assert odd[away].sum() >= 10 and (~odd[away]).sum() >= 10
        np.testing.assert_array_equal(count[away] % 2 == 1, odd[away])


def test_count_intersections_refuses_multi_hit_and_any_hit_intersectors():
    scene = random_scene(1)
    ray = rt.Ray(np.zeros(3, np.float32), np.ones(3, np.float32))
    structure = build(scene)
    with pytest.raises(ValueError, match=r"count_intersections: the intersector must not set max_hits or accept_any"):
        rt.count_intersections(ray, structure, K_NEAREST)
    with pytest.raises(ValueError, match=r"must not set max_hits or accept_any_intersection"):
        rt.count_intersections(
            ray, structure, rt.Intersector(accept_any_intersection=True, intersection_functions=FUNCTIONS)
        )
    with pytest.raises(TypeError, match=r"count_intersections: intersector must be an rt.Intersector, got dict"):
        rt.count_intersections(ray, structure, {"max_hits": 2})
