"""The LBVH itself: the Karras radix tree (an internal helper), the node layout of built structures, refit."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from reference import (
    SMALL_CAPACITY,
    assert_matches_reference,
    assert_valid_tree,
    brute_force,
    global_index,
    same_box_triangles,
)
from scenes import far_exponents, random_rays, random_scene, scale_exponents, seeds

import jaxrt as rt
from jaxrt._src.bvh.morton import MORTON_BITS, PADDING_CODE
from jaxrt._src.bvh.radix_tree import build_radix_tree

_radix_tree = jax.jit(build_radix_tree)
#: Fixed key counts (each compiles once): the smallest tree, odd and power-of-two sizes.
SIZES = (2, 3, 64, 100)


def _check_radix_tree(codes: np.ndarray) -> int:
    """The tree over ``codes`` (sorted) is the binary radix tree of the 64-bit keys ``code << 32 | index``."""
    n = codes.shape[0]
    children, first, last = (np.asarray(a) for a in _radix_tree(codes.astype(np.uint32)))
    assert children.shape == (n - 1, 2) and first.shape == last.shape == (n - 1,)
    keys = [(int(c) << 32) | i for i, c in enumerate(codes)]
    assert (first[0], last[0]) == (0, n - 1)
    seen_leaf, seen_node = np.zeros(n, int), np.zeros(n - 1, int)
    deepest = 0
    stack = [(0, 1)]
    while stack:
        node, depth = stack.pop()
        seen_node[node] += 1
        deepest = max(deepest, depth)
        lo, hi = int(first[node]), int(last[node])
        # Karras: the split is where the first differing bit of the range's end keys flips from 0 to 1.
        bit = (keys[lo] ^ keys[hi]).bit_length() - 1
        assert bit >= 0, f"node {node} covers equal keys"
        split = next(i for i in range(lo, hi + 1) if (keys[i] >> bit) & 1)
        spans = []
        for child in children[node]:
            if child < 0:
                seen_leaf[-1 - child] += 1
                spans.append((-1 - child, -1 - child))
            else:
                stack.append((int(child), depth + 1))
                spans.append((int(first[child]), int(last[child])))
        assert spans == [(lo, split - 1), (split, hi)], (node, spans, lo, split, hi)
    np.testing.assert_array_equal(seen_leaf, 1, err_msg="every leaf reachable exactly once")
    np.testing.assert_array_equal(seen_node, 1, err_msg="every internal node reachable exactly once")
    return deepest


@given(st.sampled_from(SIZES), st.data())
def test_radix_tree_of_random_codes(n, data):
    codes = data.draw(st.lists(st.integers(0, 2**MORTON_BITS - 1), min_size=n, max_size=n))
    _check_radix_tree(np.sort(np.array(codes, np.uint32)))


@given(st.sampled_from(SIZES), st.data())
def test_radix_tree_with_equal_codes_uses_the_index_tie_break(n, data):
    distinct = data.draw(st.lists(st.integers(0, 2**MORTON_BITS - 1), min_size=1, max_size=3))
    codes = data.draw(st.lists(st.sampled_from(distinct), min_size=n, max_size=n))
    padding = data.draw(st.integers(0, n - 1))  # trailing padding codes, as the builder sorts them
    codes = np.sort(np.array(codes, np.uint32))
    codes[n - padding :] = PADDING_CODE
    _check_radix_tree(codes)


@pytest.mark.parametrize("n", SIZES)
def test_radix_tree_all_codes_equal_is_balanced(n):
    depth = _check_radix_tree(np.full(n, 12345, np.uint32))
    assert depth == max(1, (n - 1).bit_length())


@given(seeds, far_exponents, scale_exponents)
def test_built_structure_satisfies_the_node_layout(seed, far_exp, scale_exp):
    scene = random_scene(seed, far_exp, scale_exp)
    structure = rt.build_primitive_structure(scene.geometries)
    assert structure.capacity == 64 and structure.primitive_count == scene.triangles.shape[0]
    assert_valid_tree(structure, scene.triangles, scene.counts)
    np.testing.assert_array_equal(np.asarray(structure.leaf_triangle)[np.asarray(structure.leaf_geometry) < 0], 0)


@pytest.mark.parametrize("count, capacity", [(1, None), (2, None), (5, 64), (33, None)])
def test_small_and_padded_structures_are_valid(count, capacity):
    rng = np.random.default_rng(count)
    triangles = rng.normal(size=(count, 3, 3)).astype(np.float32)
    structure = rt.build_primitive_structure(rt.TriangleGeometry(triangles.reshape(-1, 3)), capacity=capacity)
    expected = max(2, 1 << (max(count, capacity or 0) - 1).bit_length())
    assert structure.capacity == expected
    assert_valid_tree(structure, triangles, (count,))


def test_structure_with_all_centroids_equal_is_valid():
    """Equal Morton codes everywhere: the tree falls back to the index tie-break and stays balanced."""
    triangles = same_box_triangles(100)
    structure = rt.build_primitive_structure(rt.TriangleGeometry(triangles.reshape(-1, 3)))
    depth = assert_valid_tree(structure, triangles, (100,))
    assert depth <= 1 + (structure.capacity - 1).bit_length()


@given(seeds, far_exponents, scale_exponents, st.floats(-3.0, 0.0))
def test_refit_after_moving_vertices_equals_a_rebuild(seed, far_exp, scale_exp, move_exp):
    scene = random_scene(seed, far_exp, scale_exp)
    structure = rt.build_primitive_structure(scene.geometries, capacity=SMALL_CAPACITY)
    rng = np.random.default_rng(seed)
    moved = [
        rt.TriangleGeometry(
            (
                np.asarray(g.vertices, np.float64) + rng.normal(size=g.vertices.shape) * scene.scale * 10**move_exp
            ).astype(np.float32),
            g.indices,
        )
        for g in scene.geometries
    ]
    moved_triangles = np.concatenate([np.asarray(g.vertices)[np.asarray(g.indices)] for g in moved])
    refitted = rt.refit(structure, moved)
    assert_valid_tree(refitted, moved_triangles, scene.counts)
    np.testing.assert_array_equal(np.asarray(refitted.node_children), np.asarray(structure.node_children))
    np.testing.assert_array_equal(np.asarray(refitted.leaf_primitive), np.asarray(structure.leaf_primitive))

    rebuilt = rt.build_primitive_structure(moved, capacity=SMALL_CAPACITY)
    rays = random_rays(seed ^ 0xF17, scene)
    intersector = rt.Intersector(rt.tags.triangle_data, rt.tags.stats)
    a = intersector.intersect(rays.ray(), refitted)
    b = intersector.intersect(rays.ray(), rebuilt)
    # Same triangles, same per-triangle test: the nearest distance is bitwise the same; ids differ only on ties.
    np.testing.assert_array_equal(np.asarray(a.type), np.asarray(b.type))
    np.testing.assert_array_equal(np.asarray(a.distance), np.asarray(b.distance))
    ref = brute_force(rays.origin, rays.direction, rays.min_distance, rays.max_distance, moved_triangles)
    assert_matches_reference(a, ref, scene.counts)
    ka = global_index(a.geometry_id, a.primitive_id, scene.counts)
    kb = global_index(b.geometry_id, b.primitive_id, scene.counts)
    differ = np.flatnonzero(ka != kb)
    for r in differ:  # a tie: both triangles at the same float64 distance within tolerance
        assert abs(ref.distance[r, ka[r]] - ref.distance[r, kb[r]]) <= ref.tolerance[r, ka[r]] + ref.tolerance[r, kb[r]]


def test_refit_rejects_other_geometry_counts():
    v = np.random.default_rng(0).normal(size=(9, 3)).astype(np.float32)
    structure = rt.build_primitive_structure(rt.TriangleGeometry(v))
    with pytest.raises(ValueError, match="refit"):
        rt.refit(structure, rt.TriangleGeometry(v[:6]))
    with pytest.raises(ValueError, match="refit"):
        rt.refit(structure, [rt.TriangleGeometry(v), rt.TriangleGeometry(v)])
