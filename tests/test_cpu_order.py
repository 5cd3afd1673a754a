"""The order the CPU traversal traces a batch in (``jaxrt._src.traversal.cpu_order``): a permutation of the rays,
kept as given for a coherent batch, and never a different result.

An incoherent batch of at least ``cpu.SORT_MIN`` rays is traced sorted along a Morton curve of origin and
direction, its results put back at each ray's index: every field (stats counters included) equals the portable
traversal's and the unsorted CPU traversal's, for the lean loop and for the general one (instances, hit lists).
"""

from __future__ import annotations

import numpy as np
import pytest
from reference import icosphere

import jaxrt as rt
from jaxrt._src.traversal import cpu, cpu_order

pytestmark = pytest.mark.skipif(cpu.unavailable_reason() is not None, reason=str(cpu.unavailable_reason()))

N = 2048
FIELDS = ("type", "distance", "primitive_id", "triangle_barycentric_coord", "nodes_visited", "primitives_tested")
BOX = (np.full(3, -4.0, np.float32), np.full(3, 4.0, np.float32))


def _rays(n=N, seed=0):
    """Incoherent rays around a unit icosphere: random origins and directions, some NaN (disabled), some
    parallel to an axis."""
    rng = np.random.default_rng(seed)
    origin = (rng.normal(size=(n, 3)) * 3).astype(np.float32)
    direction = (rng.normal(size=(n, 3)) * 0.3 - origin).astype(np.float32)
    direction[::5] = rng.normal(size=direction[::5].shape)
    direction[1::97] = [0.0, 0.0, -1.0]
    origin[3::101] = np.nan
    return origin, direction


def _camera(n=N):
    """A camera's rays, pixel after pixel: one origin, neighbouring directions."""
    side = int(np.sqrt(n))
    u, v = np.meshgrid(np.linspace(-0.5, 0.5, side), np.linspace(-0.5, 0.5, n // side))
    direction = np.stack([u.ravel(), v.ravel(), -np.ones(u.size)], axis=1).astype(np.float32)
    return np.broadcast_to(np.float32([0, 0, 5]), direction.shape).copy(), direction


def test_ray_order_is_a_stable_permutation_by_key():
    origin, direction = _rays()
    direction[7] = [0.0, 0.0, 0.0]
    direction[8] = [np.inf, 1.0, 0.0]
    order = cpu_order.ray_order(origin, direction, *BOX)
    assert order.dtype == np.int32
    np.testing.assert_array_equal(np.sort(order), np.arange(N))
    frame = cpu_order._frame(*BOX)
    keys = np.array([cpu_order._key(origin, direction, i, frame) for i in range(N)])
    np.testing.assert_array_equal(order, np.argsort(keys, kind="stable"))


def test_coherent_batches_are_kept_and_random_ones_sorted():
    assert cpu_order.coherent(*_camera(), *BOX)
    assert not cpu_order.coherent(*_rays(), *BOX)
    assert cpu_order.coherent(*(a[:1] for a in _rays()), *BOX)


def _unsorted(monkeypatch, trace):
    """``trace()`` with the ordering switched off (every batch traced as given)."""
    with monkeypatch.context() as m:
        m.setattr(cpu, "SORT_MIN", 1 << 62)
        return trace()


@pytest.mark.parametrize("options", [{}, {"accept_any_intersection": True, "triangle_cull_mode": "back"}])
def test_sorted_batch_equals_portable_and_unsorted(monkeypatch, options):
    v, f = icosphere(2)
    structure = rt.build_primitive_structure(rt.TriangleGeometry(v.astype(np.float32), f))
    origin, direction = _rays()
    assert not cpu_order.coherent(origin, direction, *BOX)
    rays = rt.Ray(origin, direction)
    tags = (rt.tags.triangle_data, rt.tags.stats)
    portable = rt.Intersector(*tags, backend="portable", **options).intersect(rays, structure)
    compiled = rt.Intersector(*tags, backend="cpu", **options)
    sorted_ = compiled.intersect(rays, structure)
    unsorted = _unsorted(monkeypatch, lambda: compiled.intersect(rays, structure))
    assert (np.asarray(sorted_.type) != 0).any() and (np.asarray(sorted_.type) == 0).any()
    for name in FIELDS:
        np.testing.assert_array_equal(np.asarray(sorted_[name]), np.asarray(portable[name]), err_msg=name)
        np.testing.assert_array_equal(np.asarray(sorted_[name]), np.asarray(unsorted[name]), err_msg=name)


def test_sorted_batch_in_the_general_loop_equals_unsorted(monkeypatch):
    """Instances and a hit list (the general loop): every output, the instance chains and the hits included."""
    v, f = icosphere(1)
    blas = rt.build_primitive_structure(rt.TriangleGeometry(v.astype(np.float32), f))
    transforms = np.tile(np.eye(4, dtype=np.float32)[:3], (3, 1, 1))
    transforms[:, :, 3] = [[-2.0, 0, 0], [0, 0, 0], [2.0, 0.5, 0]]
    scene = rt.build_instance_structure([blas], rt.Instances(np.zeros(3, np.int32), transforms))
    origin, direction = _rays(seed=1)
    rays = rt.Ray(origin, direction)
    intersector = rt.Intersector(rt.tags.instancing, rt.tags.triangle_data, rt.tags.stats, backend="cpu", max_hits=3)
    sorted_ = intersector.intersect(rays, scene)
    unsorted = _unsorted(monkeypatch, lambda: intersector.intersect(rays, scene))
    assert (np.asarray(sorted_.type) != 0).any()
    assert set(sorted_) == set(unsorted) and "hit_count" in sorted_
    for name in sorted_:
        np.testing.assert_array_equal(np.asarray(sorted_[name]), np.asarray(unsorted[name]), err_msg=name)


def test_box_rows_are_laid_out_once_per_structure_and_dropped_with_it():
    """The box rows of a structure traced at top level are made on its first call, reused while its node arrays
    live, never handed to other arrays, and dropped with them."""
    import gc

    v, f = icosphere(2)
    first = rt.build_primitive_structure(rt.TriangleGeometry(v.astype(np.float32), f))
    second = rt.build_primitive_structure(rt.TriangleGeometry(v.astype(np.float32) * 2, f))
    rays = rt.Ray(*(np.asarray(a) for a in _rays(64)))
    rows = cpu.host_scene(first, rays)[1]
    assert cpu.host_scene(first, rays)[1] is rows
    expected = cpu.box_rows(np.asarray(first.node_lower), np.asarray(first.node_upper))
    np.testing.assert_array_equal(np.asarray(rows).view(np.float32), expected)
    other = cpu.host_scene(second, rays)[1]
    assert other is not rows and not np.array_equal(np.asarray(other), np.asarray(rows))
    key = id(first.node_lower)
    assert key in cpu._BOX_ROWS
    del first
    gc.collect()
    assert key not in cpu._BOX_ROWS


def test_box_rows_inside_jit_are_laid_out_once_per_structure_and_dropped_with_it():
    """Inside ``jit`` the callback receives a structure passed as an argument in place: its box rows are laid
    out on the first call, found again by the buffers' addresses while the arrays that own them live, kept
    apart per structure, and dropped with the structure; the results equal the top-level call's."""
    import gc

    import jax

    v, f = icosphere(2)
    first = rt.build_primitive_structure(rt.TriangleGeometry(v.astype(np.float32), f))
    second = rt.build_primitive_structure(rt.TriangleGeometry(v.astype(np.float32) * 2, f))
    rays = rt.Ray(*(np.asarray(a) for a in _rays(64)))
    intersector = rt.Intersector(rt.tags.triangle_data, rt.tags.stats, backend="cpu")
    traced = jax.jit(intersector.intersect)
    key = (first.node_lower.unsafe_buffer_pointer(), first.node_upper.unsafe_buffer_pointer())
    result = traced(rays, first)
    rows = cpu._TRACED_ROWS[key][2]
    np.testing.assert_array_equal(rows, cpu.box_rows(np.asarray(first.node_lower), np.asarray(first.node_upper)))
    traced(rays, first)
    assert cpu._TRACED_ROWS[key][2] is rows  # not laid out again
    expected = intersector.intersect(rays, first)
    for name in FIELDS:
        np.testing.assert_array_equal(np.asarray(result[name]), np.asarray(expected[name]), err_msg=name)
    other = traced(rays, second)
    other_key = (second.node_lower.unsafe_buffer_pointer(), second.node_upper.unsafe_buffer_pointer())
    assert other_key in cpu._TRACED_ROWS and cpu._TRACED_ROWS[other_key][2] is not rows
    assert not np.array_equal(np.asarray(other["distance"]), np.asarray(result["distance"]))
    del first, result, expected
    gc.collect()
    assert key not in cpu._TRACED_ROWS and other_key in cpu._TRACED_ROWS


@pytest.mark.parametrize(
    "shape,dtype", [((N,), np.bool_), ((N, 3), np.float32), ((N, 0), np.int32), ((N, 2, 3), np.float64)]
)
def test_permuted_and_unpermuted_are_the_fancy_indexing(shape, dtype):
    rng = np.random.default_rng(3)
    a = (rng.normal(size=shape) * 100).astype(dtype)
    order = rng.permutation(N).astype(np.int32)
    np.testing.assert_array_equal(cpu_order.permuted(a, order), a[order])
    expected = np.empty_like(a)
    expected[order] = a
    np.testing.assert_array_equal(cpu_order.unpermuted(a, order), expected)
