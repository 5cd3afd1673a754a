"""Curves in acceleration structures, through the public API: the BVH against brute force, mixed triangle and
curve structures against separate ones merged by distance, result fields, gradients, specialisation."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_curves_primitive import aimed_rays, run, strand

import jaxrt as rt
from jaxrt._src.curves import pack_segments
from jaxrt._src.primitives import curve as primitive

CURVE = int(rt.IntersectionType.CURVE)
TRIANGLE = int(rt.IntersectionType.TRIANGLE)
NONE = int(rt.IntersectionType.NONE)
FULL = rt.Intersector(rt.tags.curve_data, rt.tags.triangle_data)


def hair(seed=0, strands=6, basis="catmull_rom", count=4, curve_type="round", end_caps="none", radius=0.05):
    """A few strands of 3 segments, offset from each other, as one geometry."""
    rng = np.random.default_rng(seed)
    points, radii, indices = [], [], []
    for _ in range(strands):
        p, r, i = strand(rng, basis, count, 3, radius=radius, turn=0.3, offset=rng.normal(scale=0.6, size=3))
        indices.append(i + sum(len(q) for q in points))
        points.append(p)
        radii.append(r)
    return rt.CurveGeometry(
        np.concatenate(points),
        np.concatenate(radii),
        np.concatenate(indices),
        basis=basis,
        control_point_count=count,
        curve_type=curve_type,
        end_caps=end_caps,
    )


def trace(intersector, structure, origin, direction):
    result = intersector.intersect(rt.Ray(jnp.asarray(origin), jnp.asarray(direction)), structure)
    return jax.tree_util.tree_map(np.asarray, dict(result))


def pair(seed):
    """Round strands with sphere caps and flat ones without: the two curve geometries most tests share (same
    static structure description, so the traversal compiles once for all of them)."""
    return hair(seed=seed, end_caps="sphere"), hair(seed=seed + 100, curve_type="flat")


def test_structure_equals_brute_force():
    geometries = pair(0)
    rng = np.random.default_rng(1)
    origin, direction = np.concatenate([np.stack(aimed_rays(rng, g, 32)) for g in geometries], axis=1)
    got = trace(FULL, rt.build_primitive_structure(geometries), origin, direction)
    brute = [run(g, origin, direction) for g in geometries]  # every segment, the same primitive test
    distance = np.concatenate([np.where(b.hit, b.distance, np.inf) for b in brute], axis=1)
    u = np.concatenate([b.u for b in brute], axis=1)
    part = np.concatenate([b.part for b in brute], axis=1)
    nearest = distance.min(axis=1)
    hit = np.isfinite(nearest)
    np.testing.assert_array_equal(got["type"], np.where(hit, CURVE, NONE))
    # The brute-force nearest hit, polished to its root as the intersector reports it (smooth_hit).
    best = np.argmin(distance, axis=1)
    rows = np.arange(len(origin))
    packed = np.concatenate([np.asarray(pack_segments(g)[0]) for g in geometries])
    polish = jax.jit(jax.vmap(primitive.smooth_hit))
    args = (origin, direction, packed[best], part[rows, best], u[rows, best], np.where(hit, nearest, 1.0))
    polished_t, polished_u = (np.asarray(a) for a in polish(*(jnp.asarray(a) for a in args)))
    # The same primitive test compiled in another program: a few float32 ulps apart where XLA contracts
    # multiply-adds differently (seen with jax 0.12); misses exactly.
    np.testing.assert_allclose(got["distance"], np.where(hit, polished_t, np.inf).astype(np.float32), rtol=5e-7)
    single = hit & ((distance == nearest[:, None]).sum(axis=1) == 1)
    segments = geometries[0].primitive_count
    np.testing.assert_array_equal(got["geometry_id"][single], (best >= segments)[single])
    np.testing.assert_array_equal(got["primitive_id"][single], (best % segments)[single])
    np.testing.assert_allclose(got["curve_parameter"][single], polished_u[single], atol=1e-6)
    # The polish moves a hit by less than the test's tolerance (1e-3 of the radius, here at most 0.05).
    np.testing.assert_allclose(polished_t[hit], nearest[hit], rtol=0, atol=1e-3 * 0.05 + 1e-6)
    assert (got["primitive_id"][~hit] == -1).all() and (got["curve_parameter"][~hit] == 0).all()
    assert hit.sum() > 32


def test_mixed_structure_equals_separate_structures_merged_by_distance():
    curves = pair(2)
    rng = np.random.default_rng(4)
    triangles = rt.TriangleGeometry(rng.uniform(-2, 2, (30, 3)).astype(np.float32))
    origin, direction = aimed_rays(rng, curves[0], 64)
    mixed = trace(FULL, rt.build_primitive_structure([triangles, *curves]), origin, direction)
    separate = [trace(FULL, rt.build_primitive_structure(g), origin, direction) for g in (triangles, curves)]
    distance = np.stack([r["distance"] for r in separate])
    best = np.argmin(distance, axis=0)
    rows = np.arange(64)
    np.testing.assert_array_equal(mixed["distance"], distance[best, rows])
    hit = np.isfinite(distance[best, rows])
    geometry_id = np.stack([separate[0]["geometry_id"], separate[1]["geometry_id"] + 1])[best, rows]
    np.testing.assert_array_equal(mixed["geometry_id"][hit], geometry_id[hit])
    for field in ("type", "primitive_id", "curve_parameter", "triangle_barycentric_coord"):
        expected = np.stack([r[field] for r in separate])[best, rows]
        np.testing.assert_array_equal(mixed[field][hit], expected[hit], err_msg=field)
    assert {TRIANGLE, CURVE} <= set(mixed["type"][hit].tolist())


def test_linear_curves_and_any_hit():
    geometry = hair(seed=5, basis="linear", count=2, end_caps="sphere")
    origin, direction = aimed_rays(np.random.default_rng(6), geometry, 64)
    structure = rt.build_primitive_structure(geometry)
    occluded = trace(rt.Intersector(accept_any_intersection=True), structure, origin, direction)
    brute = run(geometry, origin, direction)
    np.testing.assert_array_equal(np.isfinite(occluded["distance"]), brute.hit.any(axis=1))
    assert (occluded["type"][np.isfinite(occluded["distance"])] == CURVE).all()


def test_gradients_through_build_and_traversal():
    geometries = pair(7)
    origin, direction = aimed_rays(np.random.default_rng(8), geometries[0], 64, spread=0.5)
    intersector = rt.Intersector(rt.tags.curve_data)

    @jax.jit
    @jax.value_and_grad
    def loss(args):
        points, radii, ray_origin = args
        g = rt.CurveGeometry(
            points, radii, geometries[0].indices, basis="catmull_rom", control_point_count=4, end_caps="sphere"
        )
        result = intersector.intersect(
            rt.Ray(ray_origin, jnp.asarray(direction)), rt.build_primitive_structure([g, geometries[1]])
        )
        hit = result.type == CURVE
        return jnp.sum(jnp.where(hit, result.distance + result.curve_parameter, 0.0))

    args = (geometries[0].control_points, geometries[0].radii, jnp.asarray(origin))
    _, grads = loss(args)
    assert all(np.isfinite(np.asarray(g)).all() for g in grads)
    rng = np.random.default_rng(9)
    for index in range(3):
        tangent = rng.normal(size=np.shape(args[index])).astype(np.float32)
        step = 1e-3
        plus, minus = list(args), list(args)
        plus[index] = args[index] + step * tangent
        minus[index] = args[index] - step * tangent
        numeric = (float(loss(tuple(plus))[0]) - float(loss(tuple(minus))[0])) / (2 * step)
        analytic = float(jnp.sum(grads[index] * tangent))
        np.testing.assert_allclose(analytic, numeric, rtol=5e-2, atol=5e-2, err_msg=f"argument {index}")


def test_refit_equals_rebuild():
    geometries = pair(10)
    structure = rt.build_primitive_structure(geometries)
    moved = [jax.tree_util.tree_map(lambda a: a, g) for g in geometries]
    moved[0].control_points = moved[0].control_points + jnp.array([0.1, -0.05, 0.02])
    moved[1].radii = moved[1].radii * 1.5
    origin, direction = aimed_rays(np.random.default_rng(11), moved[0], 64)
    refit = trace(FULL, rt.refit(structure, moved), origin, direction)
    rebuilt = trace(FULL, rt.build_primitive_structure(moved), origin, direction)
    np.testing.assert_array_equal(refit["distance"], rebuilt["distance"])


def test_specialisation_is_checked():
    curves = rt.build_primitive_structure(hair(seed=12))
    triangles = rt.build_primitive_structure(rt.TriangleGeometry(np.eye(3, dtype=np.float32)))
    ray = rt.Ray(jnp.zeros((1, 3)), jnp.array([[0.0, 0.0, 1.0]]))
    with pytest.raises(ValueError, match=r"holds geometry kinds \['curve'\].*geometry_types=\['triangle'\]"):
        rt.Intersector(geometry_types="triangle").intersect(ray, curves)
    with pytest.raises(ValueError, match="curve_type='round', but the intersector declares curve_type='flat'"):
        rt.Intersector(curve_type=rt.CurveType.FLAT).intersect(ray, curves)
    with pytest.raises(ValueError, match="curve_basis='catmull_rom', but"):
        rt.Intersector(curve_basis="bezier").intersect(ray, curves)
    with pytest.raises(ValueError, match="geometry_types must name kinds"):
        rt.Intersector(geometry_types=["disk"])
    # A specialised intersector accepts the structure it describes (checked before anything compiles).
    specialised = rt.Intersector(
        geometry_types=[rt.IntersectionType.CURVE],
        curve_basis="catmull_rom",
        curve_type="round",
        curve_control_point_count=4,
    )
    from jaxrt._src.intersector import _check_geometry

    _check_geometry(specialised, curves)
    # The curve_data tag on a triangle-only structure: the field, all zeros.
    result = rt.Intersector(rt.tags.curve_data).intersect(ray, triangles)
    assert float(result.curve_parameter[0]) == 0.0


def test_triangle_only_structures_compile_no_curve_code(monkeypatch):
    from jaxrt._src.primitives import curve as primitive

    def forbidden(*args, **kwargs):
        raise AssertionError("curve code traced for a triangle-only structure")

    monkeypatch.setattr(primitive, "intersect", forbidden)
    monkeypatch.setattr(primitive, "smooth_hit", forbidden)
    triangles = rt.build_primitive_structure(rt.TriangleGeometry(np.eye(3, dtype=np.float32) + 0.5))
    ray = rt.Ray(jnp.zeros((3, 3)), jnp.ones((3, 3)))
    rt.Intersector(rt.tags.triangle_data, rt.tags.curve_data, rt.tags.stats).intersect(ray, triangles)


def test_hair_file_to_structure(tmp_path):
    from jaxrt._src.io.hair import load_hair, write_hair

    rng = np.random.default_rng(13)
    counts = np.array([5, 7, 6])
    points = np.cumsum(rng.normal(scale=0.3, size=(counts.sum(), 3)), axis=0)
    write_hair(tmp_path / "three.hair", points, counts, thickness=0.1)
    curves = load_hair(tmp_path / "three.hair")
    structure = rt.build_primitive_structure(curves.geometry(end_caps="sphere"))
    assert structure.primitive_count == (5 - 1) + (7 - 1) + (6 - 1)
    assert structure.geometry_info[0].curve.basis == rt.CurveBasis.CATMULL_ROM
