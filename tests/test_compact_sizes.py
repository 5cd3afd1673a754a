"""Structure sizes before building, compaction (bit-for-bit traces), SAH cost, and refit against rebuild."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from lifecycle_scenes import (
    assert_same_results,
    box_case,
    box_geometry,
    curve_case,
    curve_geometry,
    instance_case,
    soup,
    trace,
    triangle_case,
    triangle_geometries,
)

import jaxrt as rt

# Curves are traced compacted in test_save_load.py (after a round trip), to share the compile time.
CASES = {
    "triangles": lambda: triangle_case(100),
    "triangles-high": lambda: triangle_case(100, quality="high"),
    "boxes-with-data": box_case,
    "instances": instance_case,
}


def built_bytes(structure) -> dict[str, int]:
    leaves = jax.tree_util.tree_flatten_with_path(structure)[0]
    return {jax.tree_util.keystr(path): np.asarray(leaf).nbytes for path, leaf in leaves}


# --- sizes ------------------------------------------------------------------------------------------------------


# Each primitive count compiles its own build, so a few counts rather than a random sweep.
@pytest.mark.parametrize(("count", "capacity"), [(1, None), (17, None), (17, 64)])
def test_sizes_equal_the_bytes_the_build_allocates(count, capacity):
    """(The clustering build has the same layout; its sizes are checked on the scenes below.)"""
    geometries = triangle_geometries(count, seed=count)
    sizes = rt.structure_sizes(geometries, capacity=capacity)
    built = rt.build_primitive_structure(geometries, capacity=capacity)
    assert dict(sizes.arrays) == built_bytes(built)
    assert sizes.total == sum(built_bytes(built).values())


def test_sizes_of_clustering_trees_curves_boxes_and_primitive_data():
    high = rt.structure_sizes(triangle_geometries(100), quality="high")
    assert dict(high.arrays) == built_bytes(triangle_case(100, quality="high").structure)
    curves, triangles = curve_geometry(), rt.TriangleGeometry(soup(20, 3).reshape(-1, 3))
    assert dict(rt.structure_sizes([curves, triangles]).arrays) == built_bytes(curve_case().structure)
    sizes = rt.structure_sizes(box_geometry())
    assert dict(sizes.arrays) == built_bytes(box_case().structure)
    assert any("leaf_primitive_data" in path for path in sizes.arrays)


def test_sizes_of_instance_structures_count_shared_components_once():
    blas = rt.build_primitive_structure(triangle_geometries(30, 7))
    instances = rt.Instances([0, 0, 0], np.tile(np.eye(3, 4, dtype=np.float32), (3, 1, 1)))
    sizes = rt.structure_sizes(instances, [blas], count=2)
    scene = rt.build_instance_structure([blas], instances, count=2)
    assert dict(sizes.arrays) == built_bytes(scene)
    # Two levels, a shared child reached twice: stored (and counted) once.
    top = rt.Instances([0, 1], np.tile(np.eye(3, 4, dtype=np.float32), (2, 1, 1)))
    assert dict(rt.structure_sizes(top, [scene, blas]).arrays) == built_bytes(
        rt.build_instance_structure([scene, blas], top)
    )
    # Children given abstractly (eval_shape of their build) work too.
    abstract = jax.eval_shape(lambda g: rt.build_primitive_structure(g), triangle_geometries(30, 7))
    assert rt.structure_sizes(instances, [abstract]).total == sizes.total


def test_sizes_reject_bad_arguments():
    geometry = rt.TriangleGeometry(soup(3).reshape(-1, 3))
    with pytest.raises(ValueError, match="structure_sizes: Instances need the structures"):
        rt.structure_sizes(rt.Instances([0], np.eye(3, 4, dtype=np.float32)[None]))
    with pytest.raises(ValueError, match="structure_sizes: structures is only for Instances"):
        rt.structure_sizes(geometry, [rt.build_primitive_structure(geometry)])
    with pytest.raises(ValueError, match="capacity=2 is below the primitive count 3"):
        rt.structure_sizes(geometry, capacity=2)


# --- compaction -------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(CASES))
def test_compact_traces_bit_for_bit(name):
    case = CASES[name]()
    compacted = rt.compact(case.structure)
    original, trimmed = rt.structure_sizes(case.structure), rt.structure_sizes(compacted)
    assert trimmed.total < original.total
    assert dict(trimmed.arrays) == built_bytes(compacted)
    result = trace(case)
    assert (result["type"] != 0).sum() >= 20  # the rays hit something
    assert_same_results(result, trace(case, compacted))
    assert rt.compact(compacted) is not None and rt.structure_sizes(rt.compact(compacted)).total == trimmed.total


def reachable_leaves(children: np.ndarray) -> list[int]:
    """Leaves reached from the root, in depth-first order (each node visited at most once)."""
    leaves, stack, seen = [], [0], set()
    while stack:
        node = stack.pop()
        assert node not in seen and 0 <= node < children.shape[0]
        seen.add(node)
        for child in children[node][::-1]:
            (stack.append(int(child)) if child >= 0 else leaves.append(int(-1 - child)))
    return leaves


@pytest.mark.parametrize("quality", ["fast", "high", "sah"])
@pytest.mark.parametrize("count", [1, 3, 17])
def test_compact_capacity_and_small_trees(count, quality):
    """The kept rows are the original's (the root's padding child excepted); every real leaf is reached once."""
    structure = triangle_case(count, seed=count, quality=quality).structure
    compacted = rt.compact(structure)
    padded = structure.capacity > max(count, 2)
    clustered = quality in ("high", "sah") and padded
    expected = count + 1 if clustered else max(count, 2)
    assert compacted.capacity == expected
    assert compacted.node_children.shape == (expected - 1, 2)
    for field in ("node_lower", "node_upper", "leaf_geometry", "leaf_primitive", "leaf_triangle"):
        assert np.array_equal(
            np.asarray(getattr(compacted, field)),
            np.asarray(getattr(structure, field))[: len(getattr(compacted, field))],
        )
    children = np.asarray(compacted.node_children)
    original = np.asarray(structure.node_children)[: expected - 1]
    if clustered:
        assert children[0, 1] == -1 - count and np.asarray(compacted.node_range)[0].tolist() == [0, count]
        children, original = children[1:], original[1:]
    assert np.array_equal(children, original)
    leaves = reachable_leaves(np.asarray(compacted.node_children))
    real = [k for k in leaves if np.asarray(compacted.leaf_geometry)[k] >= 0]
    assert sorted(real) == list(range(count))


def test_compact_keeps_sah_cost_and_refits_like_the_original():
    case = triangle_case(100, quality="high")
    compacted = rt.compact(case.structure)
    assert rt.sah_cost(compacted) == rt.sah_cost(case.structure)
    moved = [rt.TriangleGeometry(g.vertices * 1.5 + 0.25, opaque=g.opaque) for g in triangle_geometries(100)]
    a, b = rt.refit(case.structure, moved), rt.refit(compacted, moved)
    for field in ("node_lower", "node_upper", "leaf_triangle"):
        rows = getattr(b, field).shape[0]
        assert np.array_equal(np.asarray(getattr(a, field))[:rows], np.asarray(getattr(b, field))), field


def test_compact_instance_structure_compacts_primitive_components_keeps_tables():
    scene = instance_case().structure
    compacted = rt.compact(scene)
    assert compacted.instance_tables == scene.instance_tables  # the very same tables
    assert compacted.children == scene.children
    for before, after in zip(scene.primitive_structures, compacted.primitive_structures, strict=True):
        n = before.primitive_count
        assert after.capacity in (max(n, 2), n + 1) and after.capacity < before.capacity


def test_compact_rejects_what_it_cannot_compact():
    structure = triangle_case(5).structure
    with pytest.raises(TypeError, match="compact: structure must be a PrimitiveAccelerationStructure"):
        rt.compact(triangle_geometries(5))
    with pytest.raises(ValueError, match="compact: structure.leaf_geometry is traced"):
        jax.jit(rt.compact)(structure)
    batched = jax.tree_util.tree_map(lambda x: jnp.stack([x, x]), structure)
    with pytest.raises(ValueError, match="compact: structure is batched"):
        rt.compact(batched)
    # A node pointing past the real leaves is a layout neither build makes.
    children = np.asarray(structure.node_children).copy()
    children[1, 1] = -1 - 7
    broken = dataclasses.replace(structure, node_children=jnp.asarray(children))
    with pytest.raises(ValueError, match=r"capacity 8, 5 primitives\) references rows past its real leaves"):
        rt.compact(broken)


# --- SAH cost and refit against rebuild --------------------------------------------------------------------------


def twist(vertices: np.ndarray, angle: float) -> np.ndarray:
    """Rotate each vertex about the z axis by ``angle`` times its height (z in [-2, 2] -> [-1, 1])."""
    theta = angle * vertices[:, 2] / 2.0
    c, s = np.cos(theta), np.sin(theta)
    x, y = vertices[:, 0], vertices[:, 1]
    return np.stack([c * x - s * y, s * x + c * y, vertices[:, 2]], axis=1).astype(np.float32)


def test_sah_cost_bounds_and_errors():
    fast, high = triangle_case(100).structure, triangle_case(100, quality="high").structure
    assert rt.sah_cost(high) > 1.0 and rt.sah_cost(fast) > 1.0
    assert rt.sah_cost(instance_case().structure) >= 1.0
    with pytest.raises(TypeError, match="sah_cost: structure must be"):
        rt.sah_cost("tree")


def test_refit_traces_like_a_rebuild_and_drifts_in_sah():
    case = triangle_case(100)
    geometries = triangle_geometries(100)
    moved = [rt.TriangleGeometry(twist(np.asarray(g.vertices), 1.5), opaque=g.opaque) for g in geometries]
    refitted = rt.refit(case.structure, moved)
    rebuilt = rt.build_primitive_structure(moved)
    a, b = trace(case, refitted), trace(case, rebuilt)
    assert (a["type"] != 0).sum() >= 20
    assert_same_results(a, b)  # same triangles, the same watertight test: the same hits, bit for bit
    assert rt.sah_cost(refitted) > rt.sah_cost(rebuilt)
