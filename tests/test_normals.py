"""``rt.tags.normal`` against float64 references: triangles (and their winding), every curve basis and type,
instances with rotations, non-uniform scales and mirroring, bounding boxes, misses, and finite gradients."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from reference import icosphere, random_rotation

import jaxrt as rt
from jaxrt._src.curves import bezier_matrix

NONE = int(rt.IntersectionType.NONE)
TRIANGLE = int(rt.IntersectionType.TRIANGLE)
CURVE = int(rt.IntersectionType.CURVE)
#: Angle (as the length of the difference of unit vectors) allowed between a float32 normal and float64.
TRIANGLE_TOL = 2e-5
#: Curves: the hit point is within the test's tolerance (1e-3 of the radius) of the surface.
CURVE_TOL = 1e-2


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _trace(intersector, structure, origin, direction):
    rays = rt.Ray(jnp.asarray(origin, jnp.float32), jnp.asarray(direction, jnp.float32))
    return jax.tree_util.tree_map(np.asarray, dict(intersector.intersect(rays, structure)))


def _rays_at(rng, points, spread):
    """Rays from random directions aimed near ``points`` ``(n, 3)``."""
    direction = _unit(rng.normal(size=points.shape))
    target = points + rng.normal(scale=spread, size=points.shape)
    return target - 4.0 * direction, direction


def test_triangle_normals_and_winding():
    vertices, faces = icosphere(2)
    rng = np.random.default_rng(0)
    triangles = vertices[faces].astype(np.float64)
    structure = rt.build_primitive_structure(rt.TriangleGeometry(vertices, faces))
    origin, direction = _rays_at(rng, rng.normal(size=(256, 3)) * 0.7, 0.3)
    origin[:20] = [5.0, 5.0, 5.0]  # misses
    hit = _trace(rt.Intersector(rt.tags.normal, rt.tags.triangle_data), structure, origin, direction)
    found = hit["type"] == TRIANGLE
    assert 100 < found.sum() < 236 and (hit["type"][:20] == NONE).all()
    tri = triangles[hit["primitive_id"][found]]
    expected = _unit(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]))
    np.testing.assert_allclose(hit["normal"][found], expected, atol=TRIANGLE_TOL)
    assert np.isfinite(hit["normal"]).all() and (hit["normal"][~found] == 0).all()
    # Not flipped towards the ray: along the ray exactly where the triangle is seen clockwise (front facing
    # with the default winding), and outward on this counterclockwise-outward sphere.
    along = np.sum(hit["normal"][found] * direction[found], axis=1) > 0
    np.testing.assert_array_equal(along, hit["triangle_front_facing"][found])
    point = origin[found] + hit["distance"][found, None] * direction[found]
    assert (np.sum(hit["normal"][found] * point, axis=1) > 0).all()


# One geometry per basis and control point count, round and flat, in one structure (one compiled trace).
CURVE_CONFIGS = [("bezier", 3), ("bezier", 4), ("bspline", 3), ("bspline", 4), ("catmull_rom", 4), ("linear", 2)]


def _curve_scene():
    rng = np.random.default_rng(7)
    geometries, segments = [], []
    for k, curve_type in enumerate(("round", "flat")):
        for j, (basis, count) in enumerate(CURVE_CONFIGS):
            base = np.array([3.0 * j, 3.0 * k, 0.0])
            points = base + np.cumsum(rng.normal(scale=0.5, size=(count, 3)), axis=0)
            radii = rng.uniform(0.15, 0.25, count)
            geometries.append(
                rt.CurveGeometry(points, radii, [0], basis=basis, control_point_count=count, curve_type=curve_type)
            )
            bezier = bezier_matrix(basis, count) @ np.concatenate([points, radii[:, None]], axis=1)
            segments.append(bezier)  # (4, 4) float64 x, y, z, radius
    return rt.build_primitive_structure(geometries), segments


def _bezier(b, u):
    """Point and tangent of cubic Bezier control points ``b`` ``(4, k)`` at parameters ``u`` ``(m,)``."""
    u = u[:, None]
    point = (1 - u) ** 3 * b[0] + 3 * u * (1 - u) ** 2 * b[1] + 3 * u**2 * (1 - u) * b[2] + u**3 * b[3]
    tangent = 3 * ((1 - u) ** 2 * (b[1] - b[0]) + 2 * u * (1 - u) * (b[2] - b[1]) + u**2 * (b[3] - b[2]))
    return point, tangent


def _argmin(f, lo=0.0, hi=1.0):
    """The minimiser of ``f`` over ``[lo, hi]``: a dense grid, then ternary refinement around the best."""
    grid = np.linspace(lo, hi, 4001)
    best = grid[np.argmin(f(grid))]
    step = (hi - lo) / 4000
    a, b = max(lo, best - step), min(hi, best + step)
    for _ in range(80):
        m1, m2 = a + (b - a) / 3, b - (b - a) / 3
        if f(np.array([m1]))[0] < f(np.array([m2]))[0]:
            b = m2
        else:
            a = m1
    return 0.5 * (a + b)


def _ribbon_crossing(b, o, d):
    """The parameter of the nearest crossing of a ray with the ray-facing ribbon of Bezier segment ``b``: the
    local minima of the centre line's distance to the ray, within the radius, nearest along the ray."""

    def across(u):
        rel = _bezier(b, u)[0][:, :3] - o
        return np.linalg.norm(rel - (rel @ d)[:, None] * d, axis=1)

    grid = np.linspace(0.0, 1.0, 4001)
    a = across(grid)
    minima = np.flatnonzero((a[1:-1] <= a[:-2]) & (a[1:-1] <= a[2:])) + 1
    best_u, best_t = np.nan, np.inf
    for i in minima[(minima > 0) & (minima < len(grid) - 1)]:
        u = _argmin(across, grid[i - 1], grid[i + 1])
        point = _bezier(b, np.array([u]))[0][0]
        depth = (point[:3] - o) @ d
        if across(np.array([u]))[0] <= abs(point[3]) and 0 < depth < best_t:
            best_u, best_t = u, depth
    return best_u, best_t


def _square(m):
    return np.vstack([np.asarray(m, np.float64), [0, 0, 0, 1]])


def _affine(linear, translation):
    return np.concatenate([linear, np.asarray(translation, np.float64)[:, None]], axis=1).astype(np.float32)


def _instanced_scene():
    """Instances of an icosphere (a rotation, a non-uniform scale, a mirror with a non-uniform scale, below
    a shearing, mirroring top-level transform) and of the curve structure (as is, and non-uniformly scaled and
    mirrored): chains of one and two levels, traced by one intersector (one compiled trace and gradient)."""
    rng = np.random.default_rng(3)
    vertices, faces = icosphere(1)
    mesh = rt.build_primitive_structure(rt.TriangleGeometry(vertices, faces))
    curves, segments = _curve_scene()
    inner_linear = [
        random_rotation(rng),
        random_rotation(rng) @ np.diag([0.4, 1.5, 0.8]) @ random_rotation(rng),
        np.diag([-1.0, 1.0, 1.0]) @ random_rotation(rng) @ np.diag([1.0, 0.5, 1.2]),
    ]
    inner = np.stack([_affine(a, [3.0 * k - 3.0, 0, 0]) for k, a in enumerate(inner_linear)])
    spheres = rt.build_instance_structure([mesh], rt.Instances(np.zeros(3, np.int32), inner))
    top = np.stack(
        [
            _affine(np.diag([1.0, -0.7, 1.3]) @ random_rotation(rng) + 0.2 * rng.normal(size=(3, 3)), [0, -6, 0]),
            _affine(np.eye(3), [0, 0, 0]),
            _affine(np.diag([0.6, 1.4, -1.0]) @ random_rotation(rng), [0, 0, 12]),
        ]
    )
    chains = [_square(top[0]) @ _square(m) for m in inner] + [_square(top[1]), _square(top[2])]
    return spheres, curves, top, chains, vertices[faces].astype(np.float64), segments


def _aim(rng, chains, segments):
    """Rays at the three spheres' centres and at points of every curve under both curve instances."""
    points = [np.repeat(chain[None, :3, 3], 48, axis=0) for chain in chains[:3]]
    for chain in chains[3:]:
        for b in segments:
            p = _bezier(b, rng.uniform(0.1, 0.9, 10))[0][:, :3]
            points.append(p @ chain[:3, :3].T + chain[:3, 3])
    return _rays_at(rng, np.concatenate(points), 0.05)


def _curve_reference(b, round_curve, o, d, distance):
    """The float64 object-space normal of a curve hit at ``distance`` (None where it cannot be checked)."""
    point = o + distance * d
    if round_curve:  # the sphere of the swept family that touches the hit point
        u = _argmin(lambda u: np.linalg.norm(point - _bezier(b, u)[0][:, :3], axis=1) - _bezier(b, u)[0][:, 3])
        normal = point - _bezier(b, np.array([u]))[0][0, :3]
    else:  # the ribbon across the ray at its nearest crossing
        u, depth = _ribbon_crossing(b, o, d / np.linalg.norm(d))
        if not abs(depth / np.linalg.norm(d) - distance) < 1e-3:
            return None  # a grazing hit the float32 test places elsewhere (its accuracy is tested elsewhere)
        tangent = _bezier(b, np.array([u]))[1][0, :3]
        normal = -(d - (d @ tangent) / (tangent @ tangent) * tangent)
    return normal if 1e-3 < u < 1 - 1e-3 else None  # (segment ends without caps: no hit to check)


def test_normals_through_instances_every_curve_basis_and_type_with_gradients():
    spheres, curves, top, chains, triangles, segments = _instanced_scene()
    rng = np.random.default_rng(4)
    origin, direction = _aim(rng, chains, segments)
    origin[:8] = [50.0, 50.0, 50.0]  # misses
    intersector = rt.Intersector(rt.tags.normal, rt.tags.instancing, rt.tags.max_levels(2))
    rays = rt.Ray(jnp.asarray(origin, jnp.float32), jnp.asarray(direction, jnp.float32))
    weights = jnp.asarray(rng.normal(size=origin.shape), jnp.float32)

    def traced(top_transforms, spheres, curves, rays, weights):
        index = jnp.array([0, 1, 1], jnp.int32)
        structure = rt.build_instance_structure([spheres, curves], rt.Instances(index, top_transforms))
        hit = intersector.intersect(rays, structure)
        return jnp.sum(hit.normal * weights), hit

    # One compiled program for the build, the trace and the gradient (the scene passed as arguments, not
    # folded in as constants): eagerly, each operation of the build and its derivative compiles on its own.
    value_and_grad = jax.jit(jax.value_and_grad(traced, has_aux=True))
    (_, hit), grad = value_and_grad(jnp.asarray(top), spheres, curves, rays, weights)
    hit = jax.tree_util.tree_map(np.asarray, dict(hit))
    grad = np.asarray(grad)
    assert np.isfinite(grad).all() and (np.abs(grad).sum(axis=(1, 2)) > 0).all()
    kind = hit["type"]
    assert (kind[:8] == NONE).all() and (hit["normal"][kind == NONE] == 0).all()
    assert np.isfinite(hit["normal"]).all()
    checked = np.zeros((2, len(segments)), int)
    for ray in np.flatnonzero(kind != NONE):
        ids = hit["instance_id"][ray]
        chain = chains[ids[1]] if ids[0] == 0 else chains[2 + ids[0]]
        linear, shift = chain[:3, :3], chain[:3, 3]
        o = np.linalg.solve(linear, origin[ray] - shift)
        d = np.linalg.solve(linear, direction[ray].astype(np.float64))
        g = hit["geometry_id"][ray]
        if kind[ray] == TRIANGLE:
            tri = triangles[hit["primitive_id"][ray]]
            n_object = np.cross(tri[1] - tri[0], tri[2] - tri[0])
            tolerance = 1e-4
            # Outward on every (convex) ellipsoid, mirrored or not.
            point = origin[ray] + hit["distance"][ray] * direction[ray]
            assert np.dot(hit["normal"][ray], point - shift) > 0
        else:
            n_object = _curve_reference(segments[g], g < len(CURVE_CONFIGS), o, d, hit["distance"][ray])
            if n_object is None:
                continue
            tolerance = CURVE_TOL
            checked[ids[0] - 1, g] += 1
        expected = _unit(np.linalg.inv(linear).T @ n_object)
        np.testing.assert_allclose(hit["normal"][ray], expected, atol=tolerance, err_msg=f"ray {ray}, geometry {g}")
    assert (checked >= 3).all(), checked
    assert (kind == TRIANGLE).sum() > 80


def test_box_and_miss_normals_are_zero():
    boxes = rt.BoundingBoxGeometry([[-1.0, -1, -1]], [[1.0, 1, 1]])
    structure = rt.build_primitive_structure(boxes)
    intersector = rt.Intersector(rt.tags.normal, intersection_functions={0: rt.intersection_functions.sphere})
    hit = _trace(intersector, structure, [[0.0, 0, 5], [3.0, 3, 5]], [[0.0, 0, -1], [0, 0, -1]])
    assert hit["type"].tolist() == [int(rt.IntersectionType.BOUNDING_BOX), NONE]
    assert hit["normal"].tolist() == [[0.0, 0, 0], [0.0, 0, 0]]


def test_absent_normal_names_the_tag():
    structure = rt.build_primitive_structure(rt.TriangleGeometry([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]]))
    result = rt.Intersector().intersect(rt.Ray(jnp.array([0.2, 0.2, 1]), jnp.array([0.0, 0, -1])), structure)
    with pytest.raises(AttributeError, match=r"rt\.tags\.normal"):
        _ = result.normal
    with pytest.raises(KeyError, match=r"rt\.tags\.normal"):
        _ = result["normal"]
    with pytest.raises(AttributeError, match="no field 'nonsense'"):
        _ = result.nonsense


def test_normal_gradients_are_finite_and_match_the_formula():
    vertices = jnp.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0.2], [2, 2, 2]])
    faces = jnp.array([[0, 1, 2]])
    rays = rt.Ray(jnp.array([[0.2, 0.2, 1.0], [5, 5, 1]]), jnp.array([[0.0, 0, -1], [0, 0, -1]]))
    weights = jnp.array([[0.3, -0.5, 0.7], [1.0, 1.0, 1.0]])
    intersector = rt.Intersector(rt.tags.normal)

    def traced(v):
        structure = rt.build_primitive_structure(rt.TriangleGeometry(v, faces))
        return jnp.sum(intersector.intersect(rays, structure).normal * weights)

    def formula(v):
        t = v[faces[0]]
        n = jnp.cross(t[1] - t[0], t[2] - t[0])
        return jnp.sum(n / jnp.linalg.norm(n) * weights[0])

    grad = jax.jit(jax.grad(traced))(vertices)  # one program (eagerly, each operation compiles on its own)
    assert np.isfinite(np.asarray(grad)).all()
    np.testing.assert_allclose(grad, jax.grad(formula)(vertices), atol=1e-5)
