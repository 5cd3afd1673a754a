"""Small scenes of every structure kind for the lifecycle tests (sizes, compaction, save and load)."""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import numpy as np

import jaxrt as rt


class Case(NamedTuple):
    """A structure, an intersector that reads every field it can report, and rays aimed at it."""

    structure: object
    intersector: rt.Intersector
    rays: rt.Ray


def soup(count: int, seed: int = 0) -> np.ndarray:
    """``(count, 3, 3)`` float32 triangles scattered in a cube of side 4."""
    rng = np.random.default_rng(seed)
    centre = rng.uniform(-2.0, 2.0, (count, 1, 3))
    return (centre + rng.normal(scale=0.3, size=(count, 3, 3))).astype(np.float32)


def rays_at(points: np.ndarray, count: int = 256, seed: int = 1, spread: float = 0.05) -> rt.Ray:
    """Rays from a sphere of radius 10 at random points within about ``spread`` of ``points`` (``(P, 3)``)."""
    rng = np.random.default_rng(seed)
    target = points[rng.integers(0, len(points), count)] + rng.normal(scale=spread, size=(count, 3))
    origin = rng.normal(size=(count, 3))
    origin = 10.0 * origin / np.linalg.norm(origin, axis=1, keepdims=True)
    return rt.Ray(origin.astype(np.float32), (target - origin).astype(np.float32))


def triangle_geometries(count: int = 100, seed: int = 0) -> list[rt.TriangleGeometry]:
    """Two triangle geometries (the second non-opaque) over ``count`` triangles in all."""
    triangles = soup(count, seed)
    first = max(1, count // 3)
    out = [rt.TriangleGeometry(triangles[:first].reshape(-1, 3))]
    if count > first:
        out.append(rt.TriangleGeometry(triangles[first:].reshape(-1, 3), opaque=False))
    return out


def triangle_case(count: int = 100, seed: int = 0, quality: str = "fast") -> Case:
    geometries = triangle_geometries(count, seed)
    structure = rt.build_primitive_structure(geometries, quality=quality)
    points = np.concatenate([np.asarray(g.vertices) for g in geometries])
    return Case(structure, rt.Intersector(rt.tags.triangle_data), rays_at(points, seed=seed + 1))


def curve_geometry(strands: int = 12, seed: int = 2) -> rt.CurveGeometry:
    """Catmull-Rom strands of four segments each."""
    rng = np.random.default_rng(seed)
    points, radii, indices = [], [], []
    for s in range(strands):
        p = rng.uniform(-2.0, 2.0, 3) + np.cumsum(rng.normal(scale=0.4, size=(7, 3)), axis=0)
        indices.append(np.arange(4) + 7 * s)
        points.append(p)
        radii.append(rng.uniform(0.03, 0.08, 7))
    return rt.CurveGeometry(
        np.concatenate(points).astype(np.float32),
        np.concatenate(radii).astype(np.float32),
        np.concatenate(indices),
        basis="catmull_rom",
        control_point_count=4,
        end_caps="sphere",
    )


@functools.cache
def curve_case() -> Case:
    """Curves and triangles in one structure."""
    curves = curve_geometry()
    triangles = rt.TriangleGeometry(soup(20, 3).reshape(-1, 3))
    structure = rt.build_primitive_structure([curves, triangles])
    points = np.concatenate([np.asarray(curves.control_points), np.asarray(triangles.vertices)])
    return Case(structure, rt.Intersector(rt.tags.curve_data, rt.tags.triangle_data), rays_at(points, seed=4))


@functools.cache
def linear_curve_case() -> Case:
    """Round linear segments only, with an intersector specialised to them (the cheapest curve code to compile)."""
    rng = np.random.default_rng(12)
    points = rng.uniform(-2.0, 2.0, (60, 3)).astype(np.float32)
    geometry = rt.CurveGeometry(
        points, np.full(60, 0.05, np.float32), np.arange(0, 58, 2), basis="linear", control_point_count=2
    )
    intersector = rt.Intersector(rt.tags.curve_data, curve_basis="linear", curve_control_point_count=2)
    return Case(rt.build_primitive_structure(geometry), intersector, rays_at(points, seed=13))


def box_geometry(count: int = 40, seed: int = 5) -> rt.BoundingBoxGeometry:
    """Spheres as boxes with their centre and radius (and a nested tuple) as primitive data."""
    rng = np.random.default_rng(seed)
    centre = rng.uniform(-3.0, 3.0, (count, 3)).astype(np.float32)
    radius = rng.uniform(0.1, 0.4, count).astype(np.float32)
    lower, upper = rt.intersection_functions.sphere_bounds(centre, radius)
    data = {"center": centre, "radius": radius, "extra": (np.arange(count, dtype=np.int32), [radius * 2])}
    return rt.BoundingBoxGeometry(lower, upper, primitive_data=data)


@functools.cache
def box_case() -> Case:
    geometry = box_geometry()
    structure = rt.build_primitive_structure(geometry)
    intersector = rt.Intersector(rt.tags.primitive_data, intersection_functions={0: rt.intersection_functions.sphere})
    return Case(structure, intersector, rays_at(np.asarray(geometry.primitive_data["center"]), seed=6))


def _transforms(count: int, seed: int, spread: float) -> np.ndarray:
    rng = np.random.default_rng(seed)
    angle = rng.uniform(0, 2 * np.pi, count)
    c, s = np.cos(angle), np.sin(angle)
    rotation = np.zeros((count, 3, 3))
    rotation[:, 0, 0], rotation[:, 0, 1], rotation[:, 1, 0], rotation[:, 1, 1] = c, -s, s, c
    rotation[:, 2, 2] = 1.0
    translation = rng.uniform(-spread, spread, (count, 3))
    return np.concatenate([rotation, translation[..., None]], axis=-1).astype(np.float32)


@functools.cache
def instance_case() -> Case:
    """Two levels: groups of two triangle structures, placed several times (with masks and a count)."""
    blas = rt.build_primitive_structure(triangle_geometries(30, 7))
    other = rt.build_primitive_structure(triangle_geometries(12, 8), quality="high")
    group = rt.build_instance_structure(
        [blas, other], rt.Instances([0, 1, 0], _transforms(3, 9, 3.0), user_id=[5, 6, 7]), count=3
    )
    scene = rt.build_instance_structure(
        [group, blas],
        rt.Instances([0, 0, 1, 0, 1], _transforms(5, 10, 8.0), mask=[1, 3, 0xFF, 2, 0xFF], user_id=[1, 2, 3, 4, 5]),
        count=4,
    )
    points = _transforms(5, 10, 8.0)[:, :, 3]
    intersector = rt.Intersector(rt.tags.instancing, rt.tags.max_levels(2), rt.tags.triangle_data)
    return Case(scene, intersector, rays_at(points, 512, seed=11, spread=1.0))


def trace(case: Case, structure=None) -> dict:
    """Every field of the result, on the host."""
    result = case.intersector.intersect(case.rays, case.structure if structure is None else structure)
    return jax.tree_util.tree_map(np.asarray, dict(result))


def assert_same_results(a: dict, b: dict) -> None:
    """Bit-for-bit equal result fields (NaN equal to NaN)."""
    assert a.keys() == b.keys()
    for key in a:
        x, y = jax.tree_util.tree_leaves(a[key]), jax.tree_util.tree_leaves(b[key])
        assert len(x) == len(y), key
        for u, v in zip(x, y, strict=True):
            assert u.dtype == v.dtype and u.shape == v.shape, key
            assert np.array_equal(u.reshape(-1).view(np.uint8), v.reshape(-1).view(np.uint8)), f"{key} differs"


def assert_same_structure(a, b) -> None:
    """Same pytree (static data included) and bit-identical arrays."""
    la, ta = jax.tree_util.tree_flatten(a)
    lb, tb = jax.tree_util.tree_flatten(b)
    assert ta == tb
    for x, y in zip(la, lb, strict=True):
        x, y = np.asarray(x), np.asarray(y)
        assert x.dtype == y.dtype and x.shape == y.shape
        assert np.array_equal(x.reshape(-1).view(np.uint8), y.reshape(-1).view(np.uint8))
