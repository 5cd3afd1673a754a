"""Intersection queries: the user's loop reproduces the intersector when it commits the same candidates.

Each test runs with both ways a query finds its candidates: stepping the portable traversal, and listing
them past a cursor as the GPU kernel does (on a GPU the kernel itself; elsewhere the brute-force lister of
``test_waves_driver.py``, the same listing computed over every leaf).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from jax import lax
from test_waves_driver import brute_force_lister

import jaxrt as rt
from jaxrt._src import query

FUNCTIONS = rt.intersection_functions
TRIANGLE = int(rt.IntersectionType.TRIANGLE)
BOX = int(rt.IntersectionType.BOUNDING_BOX)
RAYS = 256


@pytest.fixture(params=["traversal", "listing", "listing one at a time"])
def engine(request, monkeypatch):
    """How queries find candidates: the portable traversal, or listings past a cursor (the GPU kernel's where
    it runs, else the brute-force lister), of the default size or of one candidate (a listing per candidate)."""
    listing = request.param != "traversal"
    monkeypatch.setattr(query, "lists_with_the_kernel", lambda intersector, structure: listing)
    if request.param == "listing one at a time":
        monkeypatch.setattr(query, "KERNEL_CANDIDATES", 1)
    if listing and jax.default_backend() != "gpu":
        monkeypatch.setattr(query, "_lister", brute_force_lister)
    _loop.clear_cache()
    yield request.param
    _loop.clear_cache()


def _scene(seed: int):
    """Non-opaque and opaque triangle soups and spheres as boxes, all with one primitive-data layout."""
    rng = np.random.default_rng(seed)
    vertices = rng.uniform(-1, 1, (120, 3)).astype(np.float32)
    center = rng.uniform(-1, 1, (8, 3)).astype(np.float32)
    radius = rng.uniform(0.05, 0.25, 8).astype(np.float32)

    def data(alpha, c=None, r=None):
        n = alpha.shape[0]
        return {
            "alpha": alpha.astype(np.float32),
            "center": np.zeros((n, 3), np.float32) if c is None else c,
            "radius": np.zeros(n, np.float32) if r is None else r,
        }

    clear = rt.TriangleGeometry(vertices[:72], opaque=False, primitive_data=data(rng.uniform(0, 1, 24)))
    solid = rt.TriangleGeometry(vertices[72:], primitive_data=data(np.ones(16)))
    lower, upper = FUNCTIONS.sphere_bounds(center, radius)
    spheres = rt.BoundingBoxGeometry(lower, upper, primitive_data=data(rng.uniform(0, 1, 8), center, radius))
    structure = rt.build_primitive_structure([clear, solid, spheres])
    origin = rng.uniform(-1, 1, (RAYS, 3)).astype(np.float32)
    origin[:, 2] = -3
    direction = np.array([0, 0, 1.0]) + rng.normal(size=(RAYS, 3)) * 0.1
    return structure, rt.Ray(origin, direction.astype(np.float32), 0.0, rng.uniform(2, 6, RAYS).astype(np.float32))


def _filter(candidate):
    return candidate.primitive_data["alpha"] > 0.5


def _sphere_if_visible(ray, candidate):
    """Spheres whose alpha is above one half, by the analytic function."""
    accept, distance = FUNCTIONS.sphere(ray, candidate)
    return accept & (candidate.primitive_data["alpha"] > 0.5), distance


_INTERSECTOR = rt.Intersector(
    rt.tags.triangle_data,
    rt.tags.primitive_data,
    triangle_cull_mode="back",
    filter=_filter,
    intersection_functions={2: _sphere_if_visible},
)


@jax.jit
def _loop(structure, rays):
    """The alpha-test loop of Metal's intersection query, committing what the intersector's callbacks accept."""
    intersector = _INTERSECTOR

    def trace(ray):
        def body(q):
            alpha = q.candidate_primitive_data["alpha"]
            q = q.commit_triangle_intersection(alpha > 0.5)
            lower, upper = q.candidate_bounding_box
            box = rt.BoundingBoxCandidate(
                q.candidate_primitive_id, q.candidate_geometry_id, lower, upper, q.candidate_primitive_data
            )
            accept, distance = _sphere_if_visible(q.candidate_ray, box)
            return q.commit_bounding_box_intersection(distance, accept).next()

        q = rt.intersection_query(ray, structure, intersector)
        q = lax.while_loop(lambda q: q.has_candidate, body, q.next())
        return dict(
            type=q.committed_type,
            distance=q.committed_distance,
            primitive_id=q.committed_primitive_id,
            geometry_id=q.committed_geometry_id,
            barycentric=q.committed_triangle_barycentric_coord,
            front=q.committed_triangle_front_facing,
            alpha=q.committed_primitive_data["alpha"],
        )

    return jax.vmap(trace)(rays)


@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**31 - 1))
def test_query_loop_reproduces_the_intersector(engine, seed):
    structure, rays = _scene(seed)
    expected = _INTERSECTOR.intersect(rays, structure)
    got = _loop(structure, rays)
    np.testing.assert_array_equal(got["type"], expected.type)
    np.testing.assert_array_equal(got["primitive_id"], expected.primitive_id)
    np.testing.assert_array_equal(got["geometry_id"], expected.geometry_id)
    np.testing.assert_array_equal(got["alpha"], expected.primitive_data["alpha"])
    triangle = np.asarray(expected.type) == TRIANGLE
    # Triangles: the same watertight test, bit for bit in the traversal's loop; a listing computes the distance
    # in another compiled program (the kernel, or the brute-force lister, where XLA may contract products
    # into FMAs): the same primitive, its distance to an ulp or two (measured: at most 1 ulp).
    got_t, want_t = np.asarray(got["distance"])[triangle], np.asarray(expected.distance)[triangle]
    if engine == "traversal":
        np.testing.assert_array_equal(got_t, want_t)
    else:
        np.testing.assert_allclose(got_t, want_t, rtol=2.5e-7)
    np.testing.assert_array_equal(got["barycentric"], expected.triangle_barycentric_coord)
    np.testing.assert_array_equal(got["front"], expected.triangle_front_facing)
    # Boxes: the loop calls the sphere function in another compiled program, where XLA may contract other
    # products into FMAs: the distances agree to a few ulps (measured: at most 1 ulp).
    box = np.asarray(expected.type) == BOX
    np.testing.assert_allclose(np.asarray(got["distance"])[box], np.asarray(expected.distance)[box], rtol=4e-7)
    assert triangle.any() and box.any()


def test_query_candidates_are_the_non_opaque_hits_nearer_than_the_committed_one(engine):
    """A loop that commits nothing sees every non-opaque triangle the ray hits in front of the opaque hit, and
    no triangle the ray misses (the traversal presents candidates in its order, so some behind the opaque hit
    may come before it finds that hit, as in Metal; listings present them nearest first, so exactly those in
    front of it)."""
    structure, rays = _scene(7)
    intersector = rt.Intersector()

    def candidates(ray):
        def body(carry):
            q, seen = carry
            is_triangle = q.candidate_type == TRIANGLE
            seen = seen.at[jnp.where(is_triangle, q.candidate_primitive_id, 64)].set(True, mode="drop")
            return q.next(), seen

        q = rt.intersection_query(ray, structure, intersector)
        q, seen = lax.while_loop(lambda c: c[0].has_candidate, body, (q.next(), jnp.zeros(64, bool)))
        return seen, q.committed_distance

    seen, committed = jax.jit(jax.vmap(candidates))(rays)
    # The opaque triangles alone give the committed hit; count all hits of the clear geometry nearer than it.
    solid = rt.build_primitive_structure(_geometries_of(structure)[1])
    opaque = rt.Intersector(backend="portable").intersect(rays, solid)  # the same traversal code as the query
    if engine == "traversal":
        np.testing.assert_array_equal(committed, opaque.distance)
    else:  # listed distances come from another compiled program (see the test above)
        np.testing.assert_allclose(committed, opaque.distance, rtol=2.5e-7)
    clear = rt.build_primitive_structure(_geometries_of(structure)[0])
    multi = rt.Intersector(max_hits=24)

    def hit_set(max_distance):
        hits = multi.intersect(rt.Ray(rays.origin, rays.direction, rays.min_distance, max_distance), clear)
        ids = np.asarray(hits.primitive_id)
        out = np.zeros((RAYS, 64), bool)
        rows = np.nonzero(ids >= 0)
        out[rows[0], ids[rows]] = True
        return out

    seen = np.asarray(seen)
    nearer, anywhere = hit_set(np.minimum(rays.max_distance, committed)), hit_set(rays.max_distance)
    assert (seen >= nearer).all(), "a non-opaque hit in front of the committed one was not presented"
    assert (seen <= anywhere).all(), "a candidate was presented that the ray does not hit"
    assert seen.sum() > nearer.sum() // 2 > 0
    if engine != "traversal":
        np.testing.assert_array_equal(seen, nearer)
        assert (anywhere & ~nearer).any()  # hits behind the committed one exist, and were not presented


def _geometries_of(structure):
    """The clear and solid soups of :func:`_scene` as opaque geometries (rebuilt from the structure's leaves)."""
    leaves = np.asarray(structure.leaf_triangle)
    geometry = np.asarray(structure.leaf_geometry)
    primitive = np.asarray(structure.leaf_primitive)
    out = []
    for g in (0, 1):
        rows = np.nonzero(geometry == g)[0]
        triangles = leaves[rows[np.argsort(primitive[rows])]]
        out.append(rt.TriangleGeometry(triangles.reshape(-1, 3)))
    return out


def test_any_hit_query_stops_at_the_first_commit(engine):
    structure, rays = _scene(3)
    intersector = rt.Intersector(accept_any_intersection=True)

    def first(ray):
        def body(carry):
            q, triangles = carry
            triangles += (q.candidate_type == TRIANGLE).astype(jnp.int32)
            return q.commit_triangle_intersection().next(), triangles

        q = rt.intersection_query(ray, structure, intersector)
        q, steps = lax.while_loop(lambda c: c[0].has_candidate, body, (q.next(), 0))
        return q.committed_type, steps

    kind, triangles = jax.jit(jax.vmap(first))(rays)
    assert int(jnp.max(triangles)) == 1  # the first committed candidate ends the traversal
    blocked = rt.count_intersections(rays, rt.build_primitive_structure(_geometries_of(structure)))
    np.testing.assert_array_equal(np.asarray(kind) != 0, np.asarray(blocked) > 0)


def test_query_validates_its_inputs():
    structure, rays = _scene(1)
    with pytest.raises(ValueError, match="one ray"):
        rt.intersection_query(rays, structure, rt.Intersector())
    with pytest.raises(TypeError, match="Intersector"):
        rt.intersection_query(rt.Ray([0.0, 0, -3], [0.0, 0, 1]), structure, None)


def test_disabled_ray_has_no_candidate(engine):
    structure, _ = _scene(2)
    q = rt.intersection_query(rt.Ray([0.0, 0, -3], [0.0, 0, 0]), structure, rt.Intersector()).next()
    assert not bool(q.has_candidate)
    assert int(q.committed_type) == 0 and float(q.committed_distance) == np.inf
