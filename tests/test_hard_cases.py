"""Hard cases: shared edges and vertices, axis-parallel and grazing rays, degenerate and duplicate triangles,
pathological trees, tiny triangles far away, rays that start on a surface, and disabled rays."""

from __future__ import annotations

import numpy as np
import pytest
from reference import (
    assert_matches_reference,
    assert_valid_tree,
    brute_force,
    capacity_for,
    cube,
    edges,
    grid,
    icosphere,
    octahedron,
    same_box_triangles,
    trace,
)

import jaxrt as rt

#: The far-away centre used in the watertightness findings.
FAR = np.array([148376.0, 1234.0, -223423.0])
FULL = rt.Intersector(rt.tags.triangle_data, rt.tags.stats)
ANY = rt.Intersector(accept_any_intersection=True)
NONE = int(rt.IntersectionType.NONE)
TRIANGLE = int(rt.IntersectionType.TRIANGLE)


def _build(vertices, indices=None):
    vertices = np.asarray(vertices, np.float32)
    count = len(vertices) // 3 if indices is None else len(indices)
    return rt.build_primitive_structure(rt.TriangleGeometry(vertices, indices), capacity=capacity_for(count))


def _trace(structure, origin, direction, min_distance=0.0, max_distance=np.inf, intersector=FULL):
    return trace(intersector, structure, origin, np.asarray(direction), min_distance, max_distance)


def _flat_reference(origin, direction, triangles, min_distance=0.0, max_distance=np.inf, **kw):
    direction = np.asarray(direction, np.float32)
    n = direction.shape[0]
    origin = np.broadcast_to(np.asarray(origin, np.float32), direction.shape)
    tmin = np.broadcast_to(np.asarray(min_distance, np.float32), (n,))
    tmax = np.broadcast_to(np.asarray(max_distance, np.float32), (n,))
    return brute_force(origin, direction, tmin, tmax, triangles, **kw)


# --- closed meshes: no leaks through shared edges and vertices ----------------------------------------------------

CLOSED = {
    "octahedron": (octahedron, np.zeros(3), np.ones(3)),
    "cube": (cube, np.zeros(3), np.ones(3)),
    "icosphere": (lambda: icosphere(3), np.zeros(3), np.ones(3)),
    "ellipsoid far from the origin": (lambda: icosphere(4), FAR, np.array([40.0, 25.0, 15.0])),
}


@pytest.mark.parametrize("name", list(CLOSED))
def test_rays_from_inside_through_vertices_and_edge_midpoints_do_not_leak(name):
    mesh, center, radii = CLOSED[name]
    v, f = mesh()
    vertices = (v * radii + center).astype(np.float32)
    structure = _build(vertices, f)
    e = edges(f)
    v64 = vertices.astype(np.float64)
    targets = np.concatenate([v64, v64[e].mean(axis=1)])
    # Faces around each target: those holding the vertex, or both ends of the edge.
    holds = np.zeros((targets.shape[0], f.shape[0]), bool)
    holds[: len(v64)] = (f[None, :, :] == np.arange(len(v64))[:, None, None]).any(-1)
    holds[len(v64) :] = (f[None, :, :] == e[:, 0, None, None]).any(-1) & (f[None, :, :] == e[:, 1, None, None]).any(-1)
    for origin in (center, center + radii * np.array([0.1, -0.2, 0.15])):
        origin = origin.astype(np.float32)
        direction = (targets - origin.astype(np.float64)).astype(np.float32)
        result = _trace(structure, origin, direction)
        kind = np.asarray(result.type)
        assert (kind == NONE).sum() == 0, f"{(kind == NONE).sum()} of {len(kind)} rays leaked"
        k = np.asarray(result.primitive_id)
        assert holds[np.arange(len(k)), k].all(), "a ray through a vertex or edge hit a face not around it"
        ref = brute_force(
            np.broadcast_to(origin, direction.shape), direction, np.zeros(len(k)), np.full(len(k), np.inf),
            vertices[f[k]], pairs=True,
        )  # fmt: skip
        assert ref.possible[:, 0].all()
        err = np.abs(np.asarray(result.distance, np.float64) - ref.distance[:, 0])
        assert (err <= ref.tolerance[:, 0]).all(), err.max()


@pytest.mark.parametrize("offset", [(0.0, 0.0, 0.0), (131072.0, 4096.0, -65536.0)])
def test_axis_parallel_rays_exactly_through_grid_vertices_and_edges_hit(offset):
    """Exact arithmetic: coordinates are multiples of 1/4, so an axis-parallel ray passes exactly through each
    vertex and edge midpoint, its edge functions are exact, and zero edge functions count as inside."""
    v, f = grid(8, 8)
    vertices = (v * 4 + offset).astype(np.float32)
    assert np.array_equal(vertices, v * 4 + offset)  # exactly representable
    v64 = vertices.astype(np.float64)
    targets = np.concatenate([v64, v64[edges(f)].mean(axis=1)])
    structure = _build(vertices, f)
    for sign in (1.0, -1.0):
        direction = np.broadcast_to([0.0, 0.0, -sign], targets.shape)
        origin = targets + [0.0, 0.0, 5.0 * sign]
        result = _trace(structure, origin, direction)
        assert (np.asarray(result.type) == TRIANGLE).all()
        np.testing.assert_allclose(np.asarray(result.distance), 5.0, rtol=2**-22)
        # Oblique rays aimed exactly at interior features cannot leak either.
        slope = np.array([3.0, -2.0, 5.0 * sign])
        inside = targets[:, :2] - np.asarray(offset[:2])
        interior = np.all((inside > 0) & (inside < 4), axis=1)
        result = _trace(structure, targets[interior] + slope, np.broadcast_to(-slope, targets[interior].shape))
        assert (np.asarray(result.type) == TRIANGLE).all()
        np.testing.assert_allclose(np.asarray(result.distance), 1.0, rtol=1e-5)


@pytest.mark.parametrize("offset", [(0.0, 0.0, 0.0), (65536.0, -32768.0, 1024.0)])
def test_axis_parallel_rays_onto_box_faces_edges_and_corners(offset):
    """Rays along each axis onto face interiors, face diagonals (shared edges), box edges and corners, including
    rays that run inside a side face's plane (their origin on a slab plane of the box)."""
    s = 2.0
    v, f = cube((-s, -s, -s), (s, s, s))
    vertices = (v + offset).astype(np.float32)
    structure = _build(vertices, f)
    grid_points = np.array([-s, -s / 2, 0.0, s / 2, s])
    a, b = (x.ravel() for x in np.meshgrid(grid_points, grid_points))
    for axis in range(3):
        for sign in (1.0, -1.0):
            u, w = [i for i in range(3) if i != axis]
            origin = np.zeros((a.size, 3))
            origin[:, u], origin[:, w], origin[:, axis] = a, b, sign * (s + 3.0)
            direction = np.zeros_like(origin)
            direction[:, axis] = -sign
            result = _trace(structure, origin + offset, direction)
            assert (np.asarray(result.type) == TRIANGLE).all(), (axis, sign)
            np.testing.assert_allclose(np.asarray(result.distance), 3.0, rtol=2**-22)
            hit_faces = vertices[f[np.asarray(result.primitive_id)]]
            np.testing.assert_array_equal(hit_faces[..., axis], offset[axis] + sign * s)  # the facing side


def test_rays_in_a_triangle_plane_miss_it_without_nan():
    v, f = grid(4, 4)
    structure = _build(v, f)
    y = np.linspace(-0.25, 1.25, 13)  # through vertices, edges, cell interiors and outside
    origin = np.stack([np.full_like(y, -1.0), y, np.zeros_like(y)], -1)
    for direction in ([1.0, 0.0, 0.0], [1.0, 0.5, 0.0], [0.0, 1.0, 0.0]):
        result = _trace(structure, origin, np.broadcast_to(direction, origin.shape))
        assert (np.asarray(result.type) == NONE).all()


@pytest.mark.parametrize("offset", [(0.0, 0.0, 0.0), tuple(FAR)])
def test_grazing_rays_match_the_reference(offset):
    v, f = grid(4, 4)
    vertices = (v * 8 + offset).astype(np.float32)
    triangles = vertices[f]
    structure = _build(vertices, f)
    rng = np.random.default_rng(3)
    n = 256
    slope = 10.0 ** rng.uniform(-7, -1, n)
    target = np.concatenate([rng.uniform(0, 8, (n, 2)), np.zeros((n, 1))], -1) + offset
    heading = rng.normal(size=(n, 2))
    heading /= np.linalg.norm(heading, axis=-1, keepdims=True)
    direction = np.concatenate([heading, -slope[:, None]], -1)
    origin = (target - 4.0 * direction).astype(np.float32)
    result = _trace(structure, origin, direction)
    ref = _flat_reference(origin, direction, triangles)
    assert_matches_reference(result, ref, (len(f),))


# --- degenerate, duplicate and coincident primitives --------------------------------------------------------------


#: Exactly degenerate triangles (as float32): repeated vertices, single points, exactly collinear vertices.
_P = np.array([0.5, 0.25, -1.0])
_Q = _P + np.array([0.5, 1.0, 1.5])
POINT_LIKE = np.array(
    [
        [_P, _P, _Q],
        [_Q, _P, _Q],
        [_P, _P, _P],
        [[1.0, 0, 0], [1, 0, 0], [1, 0, 0]],
        [FAR, FAR, FAR + 0.5],
    ]
)
COLLINEAR = np.array([[_P, _Q, 2 * _Q - _P], [[0.0, 0, 0], [1, 1, 1], [2, 2, 2]], [[0.0, 0, 0], [3, 0, 0], [1, 0, 0]]])


def _rays_through(triangles, directions):
    points = np.concatenate([triangles.mean(1), triangles[:, 0], 0.25 * triangles[:, 1] + 0.75 * triangles[:, 2]])
    origin = np.repeat(points, len(directions), 0) - 2 * np.tile(directions, (len(points), 1))
    return origin.astype(np.float32), np.tile(directions, (len(points), 1)).astype(np.float32)


def _degenerate_scene(degenerate):
    wall = np.array([[[-9.0, -9, 5], [9, -9, 5], [0, 9, 5]]])  # behind everything, seen from z < 5
    triangles = np.concatenate([degenerate, wall]).astype(np.float32)
    assert np.array_equal(triangles[:-1], degenerate)  # exactly representable: exactly zero area
    return triangles, _build(triangles.reshape(-1, 3))


AXES = np.concatenate([np.eye(3), -np.eye(3)])
OBLIQUE = np.random.default_rng(5).normal(size=(64, 3))


@pytest.mark.parametrize("directions", [AXES, OBLIQUE], ids=["axis-parallel", "oblique"])
def test_triangles_with_coincident_vertices_are_never_hit(directions):
    triangles, structure = _degenerate_scene(POINT_LIKE)
    origin, direction = _rays_through(POINT_LIKE, directions)
    result = _trace(structure, origin, direction)
    assert not np.isin(np.asarray(result.primitive_id), np.arange(len(POINT_LIKE))).any()
    assert_matches_reference(result, _flat_reference(origin, direction, triangles), (len(triangles),))


def test_collinear_triangles_are_never_hit_by_axis_parallel_rays():
    """Axis-parallel rays see the vertices unsheared (exact), so the zero area is exact too."""
    triangles, structure = _degenerate_scene(COLLINEAR)
    origin, direction = _rays_through(COLLINEAR, AXES)
    result = _trace(structure, origin, direction)
    assert not np.isin(np.asarray(result.primitive_id), np.arange(len(COLLINEAR))).any()


def test_collinear_triangles_are_never_hit_by_oblique_rays():
    triangles, structure = _degenerate_scene(COLLINEAR)
    origin, direction = _rays_through(COLLINEAR, OBLIQUE)
    result = _trace(structure, origin, direction)
    hits = np.isin(np.asarray(result.primitive_id), np.arange(len(COLLINEAR)))
    assert not hits.any(), f"{hits.sum()} of {hits.size} rays hit a zero-area triangle"


def test_duplicate_triangles_report_one_of_them():
    rng = np.random.default_rng(6)
    tri = rng.normal(size=(3, 3))
    others = rng.normal(size=(5, 3, 3)) + [0, 0, 6]
    first = np.concatenate([np.repeat(tri[None], 4, 0), others]).astype(np.float32)  # ids 0..3 are the same
    second = np.concatenate([others[:2], tri[None]]).astype(np.float32)  # id 2 is the same again
    geometries = [rt.TriangleGeometry(first.reshape(-1, 3)), rt.TriangleGeometry(second.reshape(-1, 3))]
    structure = rt.build_primitive_structure(geometries, capacity=capacity_for(len(first) + len(second)))
    bary = rng.dirichlet(np.ones(3), 64)
    origin = bary @ tri - rng.normal(size=(64, 3)) * 3
    direction = bary @ tri - origin
    triangles = np.concatenate([first, second])
    for intersector in (FULL, ANY):
        result = _trace(structure, origin, direction, intersector=intersector)
        ref = _flat_reference(origin, direction, triangles)
        assert_matches_reference(result, ref, (len(first), len(second)), any_hit=intersector.accept_any_intersection)
        ids = list(zip(np.asarray(result.geometry_id).tolist(), np.asarray(result.primitive_id).tolist(), strict=True))
        near = np.asarray(result.distance) <= 1.0 + 1e-5
        assert all(i in {(0, 0), (0, 1), (0, 2), (0, 3), (1, 2)} for i, n in zip(ids, near, strict=True) if n)


def test_triangles_sharing_one_bounding_box_trace_correctly():
    """All primitives have one Morton code: the build's pathological case."""
    triangles = same_box_triangles(200, center=(3.0, -1.0, 2.0))
    structure = _build(triangles.reshape(-1, 3))
    assert_valid_tree(structure, triangles, (200,))
    rng = np.random.default_rng(8)
    target = rng.uniform(-1, 1, (256, 3)) + (3.0, -1.0, 2.0)
    origin = target + rng.normal(size=(256, 3)) * 4
    result = _trace(structure, origin, target - origin)
    assert (np.asarray(result.type) == TRIANGLE).mean() > 0.5
    assert_matches_reference(result, _flat_reference(origin, target - origin, triangles), (200,))


def test_all_triangles_at_one_point():
    triangles = np.full((256, 3, 3), [1.0, 2.0, 3.0], np.float32)
    structure = _build(triangles.reshape(-1, 3))
    assert_valid_tree(structure, triangles, (256,))
    directions = np.concatenate([np.eye(3), -np.eye(3), np.random.default_rng(9).normal(size=(58, 3))])
    result = _trace(structure, np.array([1.0, 2.0, 3.0]) - 2 * directions, directions)
    assert (np.asarray(result.type) == NONE).all()


def test_deepest_tree_the_builder_makes_does_not_overflow_the_stack():
    """Centroids whose Morton codes are 0, every single bit, and all ones (a chain 30 levels deep), with four
    primitives per centroid for the index tie-break below that."""
    centers = [np.zeros(3), np.full(3, 1024.0)]
    for m in range(10):
        for axis in range(3):
            c = np.zeros(3)
            c[axis] = 2.0**m + 0.5  # quantises to exactly 2**m (scene extent 1024 in each axis)
            centers.append(c)
    triangles = np.concatenate([same_box_triangles(4, center=c, half=0.25, seed=i) for i, c in enumerate(centers)])
    structure = _build(triangles.reshape(-1, 3))
    depth = assert_valid_tree(structure, triangles, (len(triangles),))
    assert depth >= 30, depth
    rng = np.random.default_rng(10)
    target = np.asarray(centers)[rng.integers(0, len(centers), 256)] + rng.uniform(-0.25, 0.25, (256, 3))
    origin = target + rng.normal(size=(256, 3)) * 2
    origin[:64] = [-1.0, -1.0, -1.0]  # long rays along the chain
    result = _trace(structure, origin, target - origin)
    assert_matches_reference(result, _flat_reference(origin, target - origin, triangles), (len(triangles),))


@pytest.mark.parametrize("size", [0.1, 1.0])
def test_tiny_triangles_far_from_the_origin(size):
    rng = np.random.default_rng(11)
    n = 64
    anchors = FAR + rng.uniform(-20, 20, (n, 1, 3))
    triangles = (anchors + size * rng.normal(size=(n, 3, 3))).astype(np.float32)
    structure = _build(triangles.reshape(-1, 3))
    k = rng.integers(0, n, 192)
    bary = np.where(
        rng.uniform(size=(192, 1)) < 0.3, np.eye(3)[rng.integers(0, 3, 192)], rng.dirichlet(np.ones(3), 192)
    )
    target = np.einsum("rv,rvk->rk", bary, triangles[k].astype(np.float64))
    origin = target + rng.normal(size=(192, 3)) * 10.0 ** rng.uniform(0, 1.7, (192, 1))
    origin[-32:] = 0.0  # from the coordinate origin, about 2.7e5 away
    direction = (target - origin).astype(np.float32)
    result = _trace(structure, origin, direction)
    assert (np.asarray(result.type) == TRIANGLE).mean() > 0.5
    assert_matches_reference(result, _flat_reference(origin, direction, triangles), (n,))


# --- rays that start on a surface -------------------------------------------------------------------------------


@pytest.mark.parametrize("center, radius", [((0.0, 0.0, 0.0), 2.0), (tuple(FAR), 400.0)])
def test_rays_starting_on_a_surface(center, radius):
    """Secondary rays from hit points of a closed convex mesh.

    Without an offset, a ray may re-hit its own surface at distance about 0 (documented), and nothing else
    wrong happens. With ``offset_ray_origin`` along the normal on the side the ray leaves from, outgoing rays
    escape the convex mesh entirely and ingoing rays reach its far side.
    """
    v, f = icosphere(3)
    vertices = (v * radius + center).astype(np.float32)
    triangles = vertices[f].astype(np.float64)
    structure = _build(vertices, f)
    rng = np.random.default_rng(12)
    n = 256
    aim = rng.normal(size=(n, 3))
    aim /= np.linalg.norm(aim, axis=-1, keepdims=True)
    origin = (np.asarray(center) + aim * radius * 3).astype(np.float32)
    direction = (np.asarray(center) + aim * radius * rng.uniform(0, 0.9, (n, 1)) - origin).astype(np.float32)
    primary = _trace(structure, origin, direction)
    assert (np.asarray(primary.type) == TRIANGLE).all()
    point = origin + np.asarray(primary.distance)[:, None] * direction  # float32, as a renderer computes it
    k = np.asarray(primary.primitive_id)
    normal = np.cross(triangles[k, 1] - triangles[k, 0], triangles[k, 2] - triangles[k, 0])
    normal = (normal / np.linalg.norm(normal, axis=-1, keepdims=True)).astype(np.float32)  # outward

    def hemisphere(sign):
        d = rng.normal(size=(n, 3))
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        d = np.where((np.sum(d * normal, -1) * sign < 0.2)[:, None], d + 2 * sign * normal, d)
        return d.astype(np.float32)

    outward, inward = hemisphere(1.0), hemisphere(-1.0)
    self_hit = 1e-4 * radius

    out = _trace(structure, point, outward)
    escaped = np.asarray(out.type) == NONE
    assert (escaped | (np.asarray(out.distance) <= self_hit)).all()

    out = _trace(structure, rt.offset_ray_origin(point, normal), outward)
    assert (np.asarray(out.type) == NONE).all(), "an offset outgoing ray re-hit the surface"

    into = _trace(structure, point, inward)
    assert (np.asarray(into.type) == TRIANGLE).all()
    far_side = np.asarray(into.distance) > 0.1 * radius
    assert (far_side | (np.asarray(into.distance) <= self_hit)).all()

    offset = np.asarray(rt.offset_ray_origin(point, -normal))
    into = _trace(structure, offset, inward)
    assert (np.asarray(into.type) == TRIANGLE).all()
    assert (np.asarray(into.distance) > 0.1 * radius).all(), "an offset ingoing ray re-hit its own surface"
    assert (np.asarray(into.primitive_id) != k).all()


# --- disabled rays ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("intersector", [FULL, ANY], ids=["triangle_data+stats", "any_hit"])
def test_disabled_rays_miss_without_nan(intersector):
    structure = _build([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    nan, inf = np.nan, np.inf
    #                 origin              direction          min  max  mask
    cases = [
        ([0.25, 0.25, 1.0], [0.0, 0.0, -1.0], 0.0, inf, 1),  # enabled: hits at 1
        ([0.25, 0.25, 1.0], [0.0, 0.0, -1.0], 2.0, 1.0, 1),  # max < min
        ([0.25, 0.25, 1.0], [0.0, 0.0, 0.0], 0.0, inf, 1),  # zero direction
        ([nan, 0.25, 1.0], [0.0, 0.0, -1.0], 0.0, inf, 1),
        ([0.25, 0.25, 1.0], [0.0, nan, -1.0], 0.0, inf, 1),
        ([0.25, 0.25, 1.0], [0.0, 0.0, -1.0], nan, inf, 1),
        ([0.25, 0.25, 1.0], [0.0, 0.0, -1.0], 0.0, nan, 1),
        ([0.25, inf, 1.0], [0.0, 0.0, -1.0], 0.0, inf, 1),
        ([0.25, 0.25, 1.0], [0.0, 0.0, -inf], 0.0, inf, 1),
        ([0.25, 0.25, 1.0], [0.0, 0.0, -1.0], 0.0, inf, 0),  # mask 0
        ([0.25, 0.25, 1.0], [0.0, 0.0, -1.0], 1.0, 1.0, 1),  # enabled: the interval is inclusive
    ]
    origin, direction, tmin, tmax, mask = (np.array(c) for c in zip(*cases, strict=True))
    result = trace(intersector, structure, origin, direction, tmin, tmax, mask)
    enabled = np.zeros(len(cases), bool)
    enabled[[0, -1]] = True
    # Seen along -z, (0,0,0), (1,0,0), (0,1,0) is counterclockwise (n . d < 0): back-facing.
    expected_type = np.where(enabled, TRIANGLE, NONE)
    np.testing.assert_array_equal(np.asarray(result.type), expected_type)
    off = ~enabled
    np.testing.assert_array_equal(np.asarray(result.distance)[off], np.inf)
    np.testing.assert_array_equal(np.asarray(result.primitive_id)[off], -1)
    np.testing.assert_array_equal(np.asarray(result.geometry_id)[off], -1)
    np.testing.assert_array_equal(np.asarray(result.distance)[enabled], 1.0)
    if "triangle_barycentric_coord" in result:
        np.testing.assert_array_equal(np.asarray(result.triangle_barycentric_coord)[off], 0.0)
        np.testing.assert_array_equal(np.asarray(result.triangle_front_facing)[off], False)
        np.testing.assert_array_equal(np.asarray(result.triangle_front_facing)[enabled], False)
    if "nodes_visited" in result:
        np.testing.assert_array_equal(np.asarray(result.nodes_visited)[off], 0)
        np.testing.assert_array_equal(np.asarray(result.primitives_tested)[off], 0)
        assert not np.asarray(result.stack_overflow).any()
