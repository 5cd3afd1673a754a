"""Boxes with intersection functions, alpha filters, primitive data, K nearest hits and counting below instances:
tracing an instance structure equals tracing the same scene flattened into one primitive structure, and the
flattened scene is checked against a float64 brute force for the triangles."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import jaxrt as rt

SPHERES = 6
#: The flattened scenes of one and two levels (3 and 6 copies: 138 and 276 primitives) in one capacity bucket,
#: so that their reference traces share one compiled program per intersector.
FLAT_CAPACITY = 512


def _rotation(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def _object(rng):
    """Triangles (non-opaque, with alpha and a label as primitive data) and spheres as cubic boxes."""
    triangles = rng.uniform(-1.0, 1.0, size=(40, 3, 3)) * np.array([1.0, 1.0, 0.3])
    triangles += rng.uniform(-1.0, 1.0, size=(40, 1, 3))
    centers = rng.uniform(-1.0, 1.0, size=(SPHERES, 3))
    radius = rng.uniform(0.1, 0.3, size=(SPHERES, 1))
    return triangles.astype(np.float32), centers.astype(np.float32), radius.astype(np.float32)


def _geometries(triangles, centers, radius, alpha, label):
    vertices = triangles.reshape(-1, 3)
    mesh = rt.TriangleGeometry(
        vertices,
        np.arange(len(vertices)).reshape(-1, 3),
        opaque=False,
        primitive_data={
            "alpha": alpha,
            "label": label,
            "center": np.zeros((len(label), 3), np.float32),
            "radius": np.zeros(len(label), np.float32),
        },
    )
    n = centers.shape[0]
    boxes = rt.BoundingBoxGeometry(
        centers - radius,
        centers + radius,
        primitive_data={
            "alpha": np.ones(n, np.float32),
            "label": 1000 + np.arange(n, dtype=np.int32) % SPHERES,
            "center": centers,
            "radius": radius[:, 0],
        },
    )
    return [mesh, boxes]


def _scene(seed: int, levels: int):
    """An instance structure of ``levels`` levels over one object structure, and its flattened twin."""
    rng = np.random.default_rng(seed)
    triangles, centers, radius = _object(rng)
    alpha = rng.uniform(0.0, 1.0, size=len(triangles)).astype(np.float32)
    label = np.arange(len(triangles), dtype=np.int32)
    blas = rt.build_primitive_structure(_geometries(triangles, centers, radius, alpha, label))
    transforms = []
    for level in range(levels):
        placed = []
        for i in range(2 if level else 3):
            m = np.zeros((3, 4))
            m[:, :3] = _rotation(rng)
            m[:, 3] = rng.uniform(-3.0, 3.0, size=3) * (1 + level) + np.array([4.0 * i, 0, 0])
            placed.append(m)
        transforms.append(np.stack(placed))
    structure, world = blas, [np.eye(3, 4)]
    for placed in transforms:
        instances = rt.Instances(np.zeros(len(placed), np.int32), placed.astype(np.float32))
        structure = rt.build_instance_structure([structure], instances)
        world = [_compose(m, w) for m in placed for w in world]
    flat_triangles, flat_centers = [], []
    for w in world:
        flat_triangles.append(np.einsum("ij,tvj->tvi", w[:, :3], triangles) + w[:, 3])
        flat_centers.append(centers @ w[:, :3].T + w[:, 3])
    copies = len(world)
    flat = rt.build_primitive_structure(
        _geometries(
            np.concatenate(flat_triangles).astype(np.float32),
            np.concatenate(flat_centers).astype(np.float32),
            np.tile(radius, (copies, 1)),
            np.tile(alpha, copies),
            np.tile(label, copies),
        ),
        capacity=FLAT_CAPACITY,
    )
    return structure, flat, copies


def _compose(outer: np.ndarray, inner: np.ndarray) -> np.ndarray:
    return np.concatenate([outer[:, :3] @ inner[:, :3], (outer[:, :3] @ inner[:, 3] + outer[:, 3])[:, None]], axis=1)


def _rays(seed: int, n: int = 256, flat=None) -> rt.Ray:
    """Rays from a box around the scene, most aimed at its primitives (the flattened scene's leaves)."""
    rng = np.random.default_rng(seed + 100)
    origin = rng.uniform(-12.0, 12.0, size=(n, 3)) + np.array([4.0, 0.0, 0.0])
    target = rng.uniform(-4.0, 4.0, size=(n, 3)) + np.array([4.0, 0.0, 0.0])
    if flat is not None:
        real = np.asarray(flat.leaf_geometry) >= 0
        centres = np.asarray(flat.leaf_triangle).mean(axis=1)
        boxes = np.asarray(flat.leaf_box)
        is_box = np.asarray(flat.leaf_geometry) == 1
        centres[is_box] = boxes[is_box].mean(axis=1)
        centres = centres[real]
        aimed = rng.uniform(size=n) < 0.8
        picks = centres[rng.integers(0, len(centres), size=n)] + rng.normal(scale=0.05, size=(n, 3))
        target = np.where(aimed[:, None], picks, target)
    return rt.Ray(origin.astype(np.float32), (target - origin).astype(np.float32), max_distance=50.0)


def _alpha_filter(candidate):
    return candidate.primitive_data["alpha"] > 0.5


def _intersector(levels: int, **options) -> rt.Intersector:
    tags = (rt.tags.triangle_data, rt.tags.primitive_data)
    if levels:
        tags += (rt.tags.instancing, rt.tags.max_levels(levels))
    return rt.Intersector(
        *tags,
        intersection_functions={1: rt.intersection_functions.sphere},
        filter=_alpha_filter,
        backend="portable",
        **options,
    )


def _assert_same(got, want, copies: int):
    np.testing.assert_array_equal(got.type, want.type)
    hit = np.asarray(want.type) != int(rt.IntersectionType.NONE)
    np.testing.assert_allclose(np.asarray(got.distance)[hit], np.asarray(want.distance)[hit], rtol=2e-4, atol=1e-5)
    assert np.all(np.isinf(np.asarray(got.distance)[~hit]))
    np.testing.assert_array_equal(got.geometry_id, want.geometry_id)
    # The flattened scene numbers each copy's primitives one copy after another: compare the labels.
    np.testing.assert_array_equal(got.primitive_data["label"], want.primitive_data["label"])
    np.testing.assert_array_equal(np.asarray(got.primitive_id) >= 0, np.asarray(want.primitive_id) >= 0)


@pytest.mark.parametrize("levels", [1, 2])
def test_boxes_filters_and_data_below_instances_equal_the_flattened_scene(levels):
    structure, flat, copies = _scene(levels, levels)
    rays = _rays(levels, flat=flat)
    got = _intersector(levels).intersect(rays, structure)
    want = _intersector(0).intersect(rays, flat)
    kinds = set(np.asarray(want.type).tolist())
    assert (np.asarray(want.type) != 0).sum() > 100, "weak test scene"
    assert {int(rt.IntersectionType.TRIANGLE), int(rt.IntersectionType.BOUNDING_BOX)} <= kinds, "weak test scene"
    _assert_same(got, want, copies)
    assert np.all(np.asarray(got.instance_count)[np.asarray(got.type) != 0] == levels)


def test_filter_rejections_change_the_answer_below_instances():
    """The filter is really called below instances: accepting everything gives other hits."""
    structure, flat, _ = _scene(3, 1)
    rays = _rays(3, flat=flat)
    filtered = _intersector(1).intersect(rays, structure)
    everything = rt.Intersector(
        rt.tags.instancing, intersection_functions={1: rt.intersection_functions.sphere}, backend="portable"
    ).intersect(rays, structure)
    assert np.any(np.asarray(filtered.distance) != np.asarray(everything.distance))
    assert np.all(np.asarray(filtered.distance) >= np.asarray(everything.distance))


@pytest.mark.parametrize("levels", [1, 2])
def test_max_hits_and_counting_below_instances_equal_the_flattened_scene(levels):
    structure, flat, copies = _scene(10 + levels, levels)
    rays = _rays(10 + levels, flat=flat)
    got = _intersector(levels, max_hits=3).intersect(rays, structure)
    want = _intersector(0, max_hits=3).intersect(rays, flat)
    np.testing.assert_array_equal(got.hit_count, want.hit_count)
    np.testing.assert_array_equal(got.hit_overflow, want.hit_overflow)
    assert np.asarray(want.hit_count).max() >= 2, "weak test scene"
    for k in range(3):
        pick = lambda r, k=k: type(r)(
            {
                name: np.asarray(v)[:, k] if name not in ("hit_count", "hit_overflow", "primitive_data") else v
                for name, v in r.items()
            }
        )  # noqa: E731
        g, w = pick(got), pick(want)
        np.testing.assert_array_equal(g.type, w.type)
        hit = np.asarray(w.type) != 0
        np.testing.assert_allclose(np.asarray(g.distance)[hit], np.asarray(w.distance)[hit], rtol=2e-4, atol=1e-5)
        np.testing.assert_array_equal(
            np.asarray(got.primitive_data["label"])[:, k], np.asarray(want.primitive_data["label"])[:, k]
        )
    options = dict(intersection_functions={1: rt.intersection_functions.sphere}, filter=_alpha_filter)
    deep = rt.Intersector(rt.tags.instancing, rt.tags.max_levels(levels), **options)
    counted = rt.count_intersections(rays, structure, deep)
    reference = rt.count_intersections(rays, flat, rt.Intersector(**options))
    np.testing.assert_array_equal(counted, reference)
    assert np.asarray(reference).max() >= 3


def test_flattened_triangles_match_a_float64_brute_force():
    """The reference itself: the flattened scene's triangle hits against an exact float64 ray cast."""
    _, flat, _ = _scene(5, 1)
    rays = _rays(5, flat=flat)
    opaque = rt.Intersector(backend="portable")
    tris = np.asarray(flat.leaf_triangle, np.float64)
    real = np.asarray(flat.leaf_geometry) == 0
    tris = tris[real]
    # The boxes need their function: trace the flattened triangles alone.
    mesh_only = rt.build_primitive_structure(rt.TriangleGeometry(tris.reshape(-1, 3).astype(np.float32)))
    result = opaque.intersect(rays, mesh_only)
    o = np.asarray(rays.origin, np.float64)
    d = np.asarray(rays.direction, np.float64)
    e1, e2 = tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]
    p = np.cross(d[:, None], e2[None])
    det = np.einsum("tj,rtj->rt", e1, p)
    s = o[:, None] - tris[None, :, 0]
    u = np.einsum("rtj,rtj->rt", s, p) / det
    q = np.cross(s, e1[None])
    v = np.einsum("rj,rtj->rt", d, q) / det
    t = np.einsum("tj,rtj->rt", e2, q) / det
    ok = (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0) & (t <= 50.0)
    nearest = np.where(ok, t, np.inf).min(axis=1)
    np.testing.assert_allclose(np.asarray(result.distance), nearest, rtol=1e-4)
    assert np.isfinite(nearest).sum() > 20


def test_vmapped_scenes_with_boxes_below_instances():
    """``jax.vmap`` over (rays, instance structure) pairs with boxes and filters below the instances."""
    import jax

    scenes = [_scene(20 + i, 1)[0] for i in range(2)]
    stacked = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *scenes)
    rays = _rays(20, 64)
    batch = jax.tree_util.tree_map(lambda a: jnp.stack([a, a]), rays)
    intersector = _intersector(1)
    together = jax.vmap(intersector.intersect)(batch, stacked)
    for i, s in enumerate(scenes):
        alone = intersector.intersect(rays, s)
        np.testing.assert_array_equal(np.asarray(together.type)[i], alone.type)
        np.testing.assert_array_equal(np.asarray(together.primitive_data["label"])[i], alone.primitive_data["label"])


@pytest.mark.parametrize("levels", [1, 2])
def test_intersection_query_below_instances_reproduces_the_intersector(levels):
    """A query loop that applies the filter and the sphere function itself gives the intersector's hits."""
    import jax
    from jax import lax

    structure, flat, _ = _scene(30 + levels, levels)
    rays = _rays(30 + levels, 128, flat)
    tags = (rt.tags.triangle_data, rt.tags.instancing, rt.tags.max_levels(levels))
    plain = rt.Intersector(*tags, backend="portable")

    def trace(ray):
        def body(q):
            data = q.candidate_primitive_data
            box = rt.BoundingBoxCandidate(
                q.candidate_primitive_id, q.candidate_geometry_id, *q.candidate_bounding_box, data
            )
            ok, t = rt.intersection_functions.sphere(q.candidate_ray, box)
            q = q.commit_triangle_intersection(data["alpha"] > 0.5)
            return q.commit_bounding_box_intersection(t, ok).next()

        q = rt.intersection_query(ray, structure, plain)
        q = lax.while_loop(lambda q: q.has_candidate, body, q.next())
        return (
            q.committed_type,
            q.committed_distance,
            q.committed_primitive_data["label"],
            q.committed_instance_id,
            q.committed_triangle_barycentric_coord,
        )

    kind, distance, label, instance_id, uv = jax.jit(jax.vmap(trace))(rays)
    # The intersector traces the rays twice over: 256 rays, the shapes of the tests above (one compiled trace).
    twice = jax.tree_util.tree_map(lambda a: jnp.concatenate([a, a]), rays)
    want = jax.tree_util.tree_map(lambda a: a[: len(kind)], _intersector(levels).intersect(twice, structure))
    np.testing.assert_array_equal(kind, want.type)
    np.testing.assert_array_equal(label, want.primitive_data["label"])
    np.testing.assert_array_equal(instance_id, want.instance_id)
    hit = np.asarray(want.type) != 0
    assert hit.sum() > 40
    np.testing.assert_allclose(np.asarray(distance)[hit], np.asarray(want.distance)[hit], rtol=1e-5)
    triangles = np.asarray(want.type) == int(rt.IntersectionType.TRIANGLE)
    np.testing.assert_allclose(
        np.asarray(uv)[triangles], np.asarray(want.triangle_barycentric_coord)[triangles], atol=1e-5
    )
