"""The trees of instance structures: the full-sweep SAH build and the tightened world boxes of instances.

Layout contract of :func:`sweep_sah_tree` on random boxes, its depth bound on boxes that drive a greedy SAH
build into a chain, its SAH cost against the LBVH's, instance boxes against the float64 transformed vertices,
and traces of both qualities against the float64 brute force over the flattened scene.
"""

from __future__ import annotations

import functools

import hypothesis
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import strategies as st
from test_instancing import INTERSECTOR, aimed_rays, check_against_oracle, flatten, instance_node, random_mesh

import jaxrt as rt
from jaxrt._src.bvh.boxes import child_boxes, range_boxes
from jaxrt._src.bvh.radix_tree import tree_depth_bound
from jaxrt._src.bvh.sah import tree_cost
from jaxrt._src.bvh.sweep_sah import sweep_sah_tree
from jaxrt._src.instances import _top_boxes, refit_instances

CAPACITY = 32


@functools.partial(jax.jit, static_argnums=3)
def _tree(lower, upper, valid, max_depth):
    children, node_range, order = sweep_sah_tree(lower, upper, valid, max_depth)
    leaf_lower, leaf_upper = lower[order], upper[order]
    range_lower, range_upper = range_boxes(leaf_lower, leaf_upper, node_range[:, 0], node_range[:, 1])
    node_lower, node_upper = child_boxes(children, range_lower, range_upper, leaf_lower, leaf_upper)
    return children, node_range, order, node_lower, node_upper


def _check_layout(children, node_range, order, node_lower, node_upper, lower, upper, valid, max_depth) -> int:
    """The structure layout: root 0, parents before children, contiguous halves, every leaf once, child boxes
    the union of their leaves, the valid leaves first; returns the deepest leaf's depth."""
    capacity = lower.shape[0]
    np.testing.assert_array_equal(np.sort(order), np.arange(capacity))
    assert valid[order[: valid.sum()]].all(), "the valid leaves come first"
    leaf_lo, leaf_hi = lower[order], upper[order]
    assert tuple(node_range[0]) == (0, capacity - 1)
    seen = np.zeros(capacity, int)
    deepest = 0
    stack = [(0, 1)]
    visited = 0
    while stack:
        node, depth = stack.pop()
        visited += 1
        spans = []
        for side in range(2):
            child = children[node, side]
            if child < 0:
                seen[-1 - child] += 1
                spans.append((-1 - child, -1 - child))
                deepest = max(deepest, depth + 1)
            else:
                assert child > node, "pre-order: a child follows its parent"
                spans.append(tuple(node_range[child]))
                stack.append((child, depth + 1))
            a, b = spans[-1]
            np.testing.assert_array_equal(node_lower[node, side], leaf_lo[a : b + 1].min(axis=0))
            np.testing.assert_array_equal(node_upper[node, side], leaf_hi[a : b + 1].max(axis=0))
        first, last = node_range[node]
        assert spans[0][0] == first and spans[0][1] + 1 == spans[1][0] and spans[1][1] == last, (node, spans)
    assert visited == capacity - 1
    np.testing.assert_array_equal(seen, 1)
    assert deepest <= max_depth, (deepest, max_depth)
    return deepest


@hypothesis.settings(max_examples=12, deadline=None)
@hypothesis.given(
    seed=st.integers(0, 2**20),
    count=st.integers(0, CAPACITY),
    spread=st.sampled_from([0.0, 1e-3, 1.0, 1e4]),
)
def test_sweep_sah_tree_layout(seed, count, spread):
    rng = np.random.default_rng(seed)
    centre = rng.uniform(-spread, spread, (CAPACITY, 3)) + rng.choice([0.0, 50.0], (CAPACITY, 1))
    half = rng.uniform(0, 1, (CAPACITY, 3)) * rng.choice([0.0, 0.01, 1.0], (CAPACITY, 1))
    lower, upper = (centre - half).astype(np.float32), (centre + half).astype(np.float32)
    valid = np.zeros(CAPACITY, bool)
    valid[rng.permutation(CAPACITY)[:count]] = True
    lower[~valid], upper[~valid] = np.inf, -np.inf
    depth = tree_depth_bound(CAPACITY)
    out = [np.asarray(a) for a in _tree(lower, upper, valid, depth)]
    _check_layout(*out, lower, upper, valid, depth)


@pytest.mark.parametrize("max_depth", [7, 9, tree_depth_bound(64)])
def test_depth_bound_holds_where_the_sah_would_make_a_chain(max_depth):
    # Nested boxes of doubling size: the cheapest split always peels off the largest box.
    size = 2.0 ** np.arange(64, dtype=np.float64)[:, None] / 2**40
    lower = np.zeros((64, 3), np.float32)
    upper = np.broadcast_to(size, (64, 3)).astype(np.float32)
    valid = np.ones(64, bool)
    out = [np.asarray(a) for a in _tree(lower, upper, valid, max_depth)]
    deepest = _check_layout(*out, lower, upper, valid, max_depth)
    if max_depth > 20:
        assert deepest > 20, "unconstrained, the SAH peels the boxes off one by one"


def _table_cost(structure) -> float:
    table = structure.root
    return tree_cost(table.node_lower, table.node_upper, table.node_children)


def _clustered_instances(rng, n):
    centres = rng.uniform(-50, 50, (8, 3))
    position = centres[rng.integers(0, 8, n)] + rng.normal(0, 3, (n, 3))
    position[: n // 8] = rng.uniform(-60, 60, (n // 8, 3))  # and a few scattered ones
    rotation = np.stack([np.linalg.qr(rng.normal(size=(3, 3)))[0] for _ in range(n)])
    rotation *= np.sign(np.linalg.det(rotation))[:, None, None]
    return np.concatenate([rotation, position[:, :, None]], axis=2).astype(np.float32)


def test_sah_tree_costs_less_than_the_lbvh_and_traces_the_same():
    rng = np.random.default_rng(3)
    mesh = random_mesh(rng)
    transform = _clustered_instances(rng, 200)
    instances = rt.Instances(np.zeros(200, np.int32), transform)
    high = rt.build_instance_structure([mesh.structure], instances)
    fast = rt.build_instance_structure([mesh.structure], instances, quality="fast")
    assert _table_cost(high) < 0.9 * _table_cost(fast), (_table_cost(high), _table_cost(fast))
    origin = rng.uniform(-80, 80, (256, 3)).astype(np.float32)
    target = transform[rng.integers(0, 200, 256), :, 3] + rng.normal(0, 0.5, (256, 3))
    direction = (target - origin).astype(np.float32)
    rays = rt.Ray(origin, direction)
    a, b = INTERSECTOR.intersect(rays, high), INTERSECTOR.intersect(rays, fast)
    assert (np.asarray(a.type) != 0).sum() > 50
    for field in ("type", "distance", "primitive_id", "instance_id"):
        np.testing.assert_array_equal(np.asarray(a[field]), np.asarray(b[field]), err_msg=field)


def _world_boxes(structure) -> tuple[np.ndarray, np.ndarray]:
    """Each instance's box as stored in its leaf's parent (float64)."""
    table = structure.root
    children = np.asarray(table.node_children)
    instance = np.asarray(table.leaf_instance)
    lower, upper = np.asarray(table.node_lower, np.float64), np.asarray(table.node_upper, np.float64)
    n = table.instance_slots
    out_lo, out_hi = np.full((n, 3), np.inf), np.full((n, 3), -np.inf)
    for node, side in zip(*np.nonzero(children < 0), strict=True):
        i = instance[-1 - children[node, side]]
        if i >= 0:
            out_lo[i], out_hi[i] = lower[node, side], upper[node, side]
    return out_lo, out_hi


def test_instance_boxes_bound_their_vertices_and_are_tighter_than_the_root_box():
    rng = np.random.default_rng(5)
    # A long thin L-shaped mesh: its rotated root box is far looser than its rotated parts.
    bar = np.array([[[0, 0, 0], [10, 0, 0], [10, 0.2, 0]], [[0, 0, 0], [10, 0.2, 0], [0, 0.2, 0]]], np.float64)
    leg = bar[:, :, [1, 0, 2]]
    parts = [bar + [0, 0, z] for z in np.linspace(0, 1, 4)] + [leg + [0, 0, z] for z in np.linspace(0, 1, 4)]
    triangles = np.concatenate(parts).astype(np.float32)
    blas = rt.build_primitive_structure(rt.TriangleGeometry(triangles.reshape(-1, 3)))
    transform = _clustered_instances(rng, 24)
    scene = rt.build_instance_structure([blas], rt.Instances(np.zeros(24, np.int32), transform))
    lo, hi = _world_boxes(scene)
    t = transform.astype(np.float64)
    world = np.einsum("nij,kj->nki", t[:, :, :3], triangles.reshape(-1, 3).astype(np.float64)) + t[:, None, :, 3]
    assert (world >= lo[:, None]).all() and (world <= hi[:, None]).all()
    # Against the transformed root box (its eight corners).
    root_lo = np.asarray(blas.node_lower[0], np.float64).min(0)
    root_hi = np.asarray(blas.node_upper[0], np.float64).max(0)
    corners = np.array([[root_hi[i] if (k >> i) & 1 else root_lo[i] for i in range(3)] for k in range(8)])
    loose = np.einsum("nij,kj->nki", t[:, :, :3], corners) + t[:, None, :, 3]
    area = lambda lo, hi: np.sum(np.prod(hi - lo, axis=-1)[..., None] / (hi - lo), axis=-1)  # noqa: E731
    assert (area(lo, hi) <= area(loose.min(1), loose.max(1)) * (1 + 1e-4)).all()
    assert area(lo, hi).sum() < 0.8 * area(loose.min(1), loose.max(1)).sum()
    # The top boxes cover the root box exactly.
    top_lo, top_hi = (np.asarray(a) for a in _top_boxes(blas))
    assert top_lo.shape == (16, 3)
    np.testing.assert_array_equal(top_lo.min(0), root_lo.astype(np.float32))
    np.testing.assert_array_equal(top_hi.max(0), root_hi.astype(np.float32))


@hypothesis.settings(
    max_examples=4, deadline=None, phases=[hypothesis.Phase.explicit, hypothesis.Phase.reuse, hypothesis.Phase.generate]
)
@hypothesis.given(
    seed=st.integers(0, 2**20),
    count=st.integers(1, 12),
    quality=st.sampled_from(["high", "fast"]),
    spread=st.sampled_from([0.5, 6.0]),
)
def test_instance_trees_against_brute_force(seed, count, quality, spread):
    rng = np.random.default_rng(seed)
    meshes = [random_mesh(rng), random_mesh(rng)]
    node = instance_node(rng, meshes, 12, "scaled", spread, count=count)
    if quality == "fast":  # the same instances under the LBVH
        node.structure = rt.build_instance_structure(
            [m.structure for m in meshes], rt.Instances(node.index, node.transform), count=count, quality="fast"
        )
    flat = flatten(node, count)
    origin, direction = aimed_rays(seed, flatten(node))  # also aimed at instances past the count
    result = INTERSECTOR.intersect(rt.Ray(origin, direction), node.structure)
    check_against_oracle(result, origin, direction, flat)


def test_instance_quality_is_checked():
    blas = rt.build_primitive_structure(rt.TriangleGeometry(np.eye(3, dtype=np.float32)))
    instances = rt.Instances([0], np.eye(3, 4, dtype=np.float32)[None])
    with pytest.raises(ValueError, match="quality must be one of"):
        rt.build_instance_structure([blas], instances, quality="best")
    scene = rt.build_instance_structure([blas], instances)
    with pytest.raises(ValueError, match="quality must be one of"):
        refit_instances(scene, instances, quality="sah")


def test_sah_tree_under_vmap_equals_a_loop():
    rng = np.random.default_rng(9)
    boxes = rng.uniform(-5, 5, (3, CAPACITY, 3)).astype(np.float32)
    lower, upper = boxes - 0.5, boxes + 0.5
    valid = np.arange(CAPACITY)[None] < np.array([[CAPACITY], [20], [3]])
    batched = jax.vmap(lambda lo, hi, ok: _tree(lo, hi, ok, 12))(jnp.asarray(lower), jnp.asarray(upper), valid)
    for b in range(3):
        one = _tree(lower[b], upper[b], valid[b], 12)
        for x, y in zip(batched, one, strict=True):
            np.testing.assert_array_equal(np.asarray(x[b]), np.asarray(y))
