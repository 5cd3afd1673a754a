"""The high-quality builds (agglomerative clustering, ``quality="high"``; the full-sweep SAH tree, ``"sah"``):
valid layout, same hits, lower SAH cost."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from reference import assert_matches_reference, assert_valid_tree, brute_force, global_index
from scenes import random_rays, random_scene

import jaxrt as rt
from jaxrt._src.bvh import ploc
from jaxrt._src.bvh.radix_tree import build_radix_tree


def _sah(structure) -> float:
    """Sum of node and leaf box areas over the root's (the bench's SAH cost, cost 1 per node and per leaf)."""
    lower = np.asarray(structure.node_lower, np.float64)
    upper = np.asarray(structure.node_upper, np.float64)
    extent = np.where(lower <= upper, upper - lower, 0.0)
    area = 2.0 * (extent[..., 0] * extent[..., 1] + extent[..., 1] * extent[..., 2] + extent[..., 2] * extent[..., 0])
    root_extent = upper[0].max(axis=0) - lower[0].min(axis=0)
    root = 2.0 * (root_extent[0] * root_extent[1] + root_extent[1] * root_extent[2] + root_extent[2] * root_extent[0])
    return float((area.sum() + root) / root)


def _bumpy_grid(nx: int = 8, ny: int = 4, seed: int = 0) -> np.ndarray:
    """``2 nx ny`` triangles of a bumpy height field, as ``(T, 3, 3)`` float32."""
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), indexing="ij")
    z = rng.normal(size=x.shape) * 0.3
    p = np.stack([x, y, z], -1).reshape(-1, 3)
    cell = (np.arange(nx)[:, None] * (ny + 1) + np.arange(ny)[None, :]).ravel()
    faces = np.concatenate(
        [np.stack([cell, cell + ny + 1, cell + 1], 1), np.stack([cell + 1, cell + ny + 1, cell + ny + 2], 1)]
    )
    return p[faces].astype(np.float32)


@pytest.mark.parametrize("quality", ["high", "sah"])
@pytest.mark.parametrize("count", [1, 3, 100])
def test_high_quality_tree_is_valid(count, quality):
    """Every leaf and node reachable once, contiguous ranges, exact boxes, depth within the stack bound
    (1: no clustering; 3: one padding leaf; 100: a padding subtree; the grid below has no padding)."""
    triangles = np.random.default_rng(count).normal(size=(count, 3, 3)).astype(np.float32)
    structure = rt.build_primitive_structure(rt.TriangleGeometry(triangles.reshape(-1, 3)), quality=quality)
    assert_valid_tree(structure, triangles, (count,))


@pytest.mark.parametrize("quality", ["high", "sah"])
def test_high_quality_traces_like_brute_force_and_the_fast_tree(quality):
    scene = random_scene(3, 4.0, 0.0)  # three geometries, far from the origin
    high = rt.build_primitive_structure(scene.geometries, quality=quality)
    fast = rt.build_primitive_structure(scene.geometries)
    assert_valid_tree(high, scene.triangles, scene.counts)
    assert not np.array_equal(np.asarray(high.node_children), np.asarray(fast.node_children))
    rays = random_rays(7, scene)
    intersector = rt.Intersector(rt.tags.triangle_data)
    a = intersector.intersect(rays.ray(), high)
    b = intersector.intersect(rays.ray(), fast)
    ref = brute_force(rays.origin, rays.direction, rays.min_distance, rays.max_distance, scene.triangles)
    assert_matches_reference(a, ref, scene.counts)
    # Same triangles and the same per-triangle test: the nearest distance is bitwise the same.
    np.testing.assert_array_equal(np.asarray(a.type), np.asarray(b.type))
    np.testing.assert_array_equal(np.asarray(a.distance), np.asarray(b.distance))
    ka = global_index(a.geometry_id, a.primitive_id, scene.counts)
    kb = global_index(b.geometry_id, b.primitive_id, scene.counts)
    for r in np.flatnonzero(ka != kb):  # only ties may pick another triangle
        assert abs(ref.distance[r, ka[r]] - ref.distance[r, kb[r]]) <= ref.tolerance[r, ka[r]] + ref.tolerance[r, kb[r]]


@pytest.mark.parametrize("quality", ["high", "sah"])
def test_high_quality_lowers_the_sah_cost_and_refits(quality):
    triangles = _bumpy_grid()
    geometry = rt.TriangleGeometry(triangles.reshape(-1, 3))
    high = rt.build_primitive_structure(geometry, quality=quality)
    fast = rt.build_primitive_structure(geometry)
    assert high.capacity == len(triangles) == 64  # no padding leaves
    assert_valid_tree(high, triangles, (64,))
    assert _sah(high) < _sah(fast)
    moved = triangles + np.float32(0.1) * np.sin(triangles[..., ::-1]).astype(np.float32)
    refitted = rt.refit(high, rt.TriangleGeometry(moved.reshape(-1, 3)))
    assert_valid_tree(refitted, moved, (len(moved),))
    np.testing.assert_array_equal(np.asarray(refitted.node_children), np.asarray(high.node_children))


def test_too_deep_a_clustering_tree_falls_back_to_the_radix_tree():
    rng = np.random.default_rng(0)
    lower = np.sort(rng.uniform(size=(6, 3)), axis=0).astype(np.float32)
    lower = jnp.asarray(np.concatenate([lower, np.full((2, 3), np.inf, np.float32)]))
    upper = jnp.asarray(np.concatenate([np.asarray(lower[:6]) + 0.1, np.full((2, 3), -np.inf, np.float32)]))
    radix_children, first, last = build_radix_tree(jnp.arange(8, dtype=jnp.uint32))
    radix_range = jnp.stack([first, last], axis=-1)
    restructure = jax.jit(ploc.restructure, static_argnums=(2, 5))
    children, node_range, order = restructure(lower, upper, 6, radix_children, radix_range, 2)
    np.testing.assert_array_equal(children, radix_children)
    np.testing.assert_array_equal(node_range, radix_range)
    np.testing.assert_array_equal(order, np.arange(8))


def test_quality_is_validated():
    with pytest.raises(ValueError, match="quality"):
        rt.build_primitive_structure(rt.TriangleGeometry(np.eye(3, dtype=np.float32)), quality="best")
