"""The GPU kernel's hit lists (``max_hits``) and counting, against the portable traversal and float64.

As in ``test_gpu_instanced.py``: the kernel runs in Triton's interpreter on the CPU (in a fresh process) or on
a CUDA GPU, launched through the same :class:`gpu.KernelCall`. The reference is the portable traversal of the
same scene view with the intersector's leaf tests (``drivers.traverse`` with ``max_hits`` / ``count_all``):
both test the same leaves against the same bounds step for step, so the hit leaves (in the same order, ties
included), the hit counts and the traversal counters are equal, and distances agree to rounding (rtol 1e-6,
as in ``test_gpu_instanced.py``). Scenes are stacks of tilted layers (many hits per ray) with a random soup
around them; one layer is there twice, so its two copies are hit at exactly equal distances by both paths
and their order is the tie order. Rays along the shared diagonal of each quad hit two different triangles at
distances equal only up to rounding: the order of such a pair follows each path's rounding (XLA may contract
multiply-adds, the kernel never does), so they are used where order does not matter, in the counts.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from reference import brute_force
from test_gpu_instanced import (
    INTERPRETED,
    LAUNCHES,
    ON_GPU,
    assert_same_fields,
    kernel_launches_here,
    kernel_test,
    run_kernel_tests_in_interpreter,
    scene_of_levels,
)
from test_gpu_instanced import rays as instanced_rays

import jaxrt as rt
from jaxrt._src import leaves as leaf_tests
from jaxrt._src import pipeline
from jaxrt._src.intersector import _CountingIntersector
from jaxrt._src.scene_view import scene_view
from jaxrt._src.traversal import drivers, gpu

ALL_RAYS = np.uint32(0xFFFFFFFF)
LAYERS = 6


def layer_triangles(seed: int, layers: int = LAYERS, soup: int = 12) -> np.ndarray:
    """``(T, 3, 3)``: ``layers`` tilted quads (two triangles each, sharing the diagonal x = y; every other layer
    wound the other way) stacked along z, the nearest one twice (equal distances), and a soup of random
    triangles around them."""
    rng = np.random.default_rng(seed)
    corners = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
    out = []
    for i in range(layers):
        tilt = rng.uniform(-0.08, 0.08, 2)
        z = 0.3 * i + corners @ tilt
        quad = np.concatenate([corners, z[:, None]], axis=1)
        pair = [quad[[0, 1, 2]], quad[[0, 2, 3]]] if i % 2 == 0 else [quad[[0, 2, 1]], quad[[0, 3, 2]]]
        out += pair * (2 if i == 0 else 1)
    centre = rng.uniform(-1.2, 1.2, (soup, 1, 3)) * np.array([1.0, 1.0, 1.5]) + np.array([0, 0, 0.8])
    out += list(centre + 0.5 * rng.standard_normal((soup, 3, 3)))
    return np.asarray(out, np.float32)


def structure_of(triangles: np.ndarray) -> rt.PrimitiveAccelerationStructure:
    return rt.build_primitive_structure(rt.TriangleGeometry(triangles.reshape(-1, 3)))


def layer_rays(n: int, seed: int, *, diagonal: bool = False):
    """Rays from below the stack, up through it: some missing the quads, short intervals (fewer hits than K),
    raised starts, and two disabled rays; with ``diagonal``, a fifth go straight up the quads' shared diagonal
    (both triangles of a quad are hit, at distances equal up to rounding)."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-1.3, 1.3, (n, 2))
    diagonal = (rng.random(n) < 0.2) & diagonal
    xy[diagonal, 1] = xy[diagonal, 0]
    origin = np.concatenate([xy, np.full((n, 1), -0.7)], axis=1)
    direction = np.concatenate([rng.normal(0.0, 0.15, (n, 2)), rng.uniform(0.5, 1.5, (n, 1))], axis=1)
    direction[diagonal, :2] = 0.0
    t_min = np.where(rng.random(n) < 0.2, rng.uniform(0.0, 1.0, n), 0.0)
    t_max = np.where(rng.random(n) < 0.3, rng.uniform(0.5, 1.5, n), np.inf)
    enabled = np.ones(n, bool)
    enabled[-2:] = False
    arrays = (origin, direction, t_min, t_max)
    return tuple(jnp.asarray(np.asarray(a, np.float32)) for a in arrays) + (
        jnp.asarray(enabled),
        jnp.full(n, ALL_RAYS),
    )


def portable(structure, ray_args, intersector: rt.Intersector, *, max_hits: int, count_all: bool = False):
    view = scene_view(structure)
    tester = leaf_tests.leaf_tester(intersector, view)
    fn = functools.partial(
        drivers.traverse, view.traversal, view.layout, tester, any_hit=False, max_hits=max_hits, count_all=count_all
    )
    return jax.jit(jax.vmap(fn))(*ray_args)


def kernel(structure, ray_args, intersector: rt.Intersector, *, max_hits: int | None, count_all: bool = False):
    view = scene_view(structure)
    return gpu.trace_scene(
        view.traversal,
        view.layout,
        *ray_args,
        any_hit=False,
        cull=intersector.cull,
        max_hits=max_hits,
        count_all=count_all,
    )


def assert_same(got, want) -> None:
    """The same hit list (leaves, order, count), the same decisions (counters, result leaf), distances to
    rounding."""
    for name in ("leaf", "instances", "nodes_visited", "primitives_tested"):
        np.testing.assert_array_equal(np.asarray(getattr(got, name)), np.asarray(getattr(want, name)), err_msg=name)
    np.testing.assert_allclose(np.asarray(got.distance), np.asarray(want.distance), rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(np.asarray(got.hits.leaf), np.asarray(want.hits.leaf), err_msg="hit leaves")
    np.testing.assert_array_equal(np.asarray(got.hits.total), np.asarray(want.hits.total), err_msg="hit totals")
    np.testing.assert_allclose(np.asarray(got.hits.distance), np.asarray(want.hits.distance), rtol=1e-6, atol=1e-7)
    if want.hits.instances is None:
        assert got.hits.instances is None
    else:
        np.testing.assert_array_equal(np.asarray(got.hits.instances), np.asarray(want.hits.instances), "chains")
    assert not np.asarray(got.stack_overflow).any()


# --- running the kernel in Triton's interpreter -----------------------------------------------------------------


kernel_here = pytest.fixture(kernel_launches_here, name="kernel_here")


def test_kernel_in_interpreter():
    """Runs this module's kernel tests in Triton's interpreter, in a fresh process."""
    # The IR test compiles outside the interpreter.
    run_kernel_tests_in_interpreter(__file__, "not interpreter and not kernel_ir")


# --- the kernel's tests -------------------------------------------------------------------------------------------


@kernel_test
@pytest.mark.parametrize("k", [1, 2, 4])
def test_k_nearest_equal_the_portable_hit_list(k, kernel_here):
    """K = 1, 2, 4 through a stack of layers: rays with fewer hits than K (short intervals, misses) and with
    more (overflow), equal distances (a duplicated layer, rays on the shared diagonal) in the same order."""
    structure = structure_of(layer_triangles(k))
    ray_args = layer_rays(64, seed=10 + k)
    intersector = rt.Intersector(max_hits=k)
    got = kernel(structure, ray_args, intersector, max_hits=k)
    if not ON_GPU:
        assert [name for name, _ in LAUNCHES] == ["trace_kernel"], LAUNCHES
    assert_same(got, portable(structure, ray_args, intersector, max_hits=k))
    total = np.asarray(got.hits.total)
    assert (total > k).sum() > 10 and ((total > 0) & (total <= k)).sum() >= 2, total
    leaves = np.asarray(got.hits.leaf)
    distance = np.asarray(got.hits.distance)
    with np.errstate(invalid="ignore"):  # inf - inf past the last hit
        steps = np.diff(distance, axis=1)
    assert not np.any(steps < 0)
    if k > 1:  # equal distances kept side by side (the duplicated layer)
        assert (steps == 0).sum() > 3
    assert np.all((leaves >= 0) == np.isfinite(distance))


@kernel_test
@pytest.mark.parametrize("cull_mode", ["back", "front"])
def test_k_nearest_with_culling(cull_mode, kernel_here):
    structure = structure_of(layer_triangles(7))
    ray_args = layer_rays(64, seed=8)
    intersector = rt.Intersector(max_hits=2, triangle_cull_mode=cull_mode)
    got = kernel(structure, ray_args, intersector, max_hits=2)
    assert_same(got, portable(structure, ray_args, intersector, max_hits=2))
    total = np.asarray(got.hits.total)
    assert (total > 0).sum() > 10 and (total > 2).sum() > 5


@kernel_test
def test_counts_equal_the_portable_count_and_float64(kernel_here):
    """``count_all``: every accepted hit counted, no culling; equal to the portable count, and within the
    float64 brute force's certain and possible hits (equal where no triangle is in doubt)."""
    triangles = layer_triangles(3)
    structure = structure_of(triangles)
    ray_args = layer_rays(64, seed=21, diagonal=True)
    intersector = rt.Intersector()
    got = kernel(structure, ray_args, intersector, max_hits=0, count_all=True)
    assert_same(got, portable(structure, ray_args, intersector, max_hits=0, count_all=True))
    count = np.asarray(got.hits.total)
    origin, direction, t_min, t_max, enabled, _ = (np.asarray(a) for a in ray_args)
    t_max = np.where(enabled, t_max, -1.0)  # disabled rays: an empty interval
    ref = brute_force(origin, direction, t_min, t_max, triangles)
    certain, possible = ref.certain.sum(axis=1), ref.possible.sum(axis=1)
    assert np.all((certain <= count) & (count <= possible)), np.flatnonzero((count < certain) | (count > possible))
    sure = certain == possible
    assert sure.sum() > 40 and count.max() > LAYERS
    np.testing.assert_array_equal(count[sure], certain[sure])
    assert np.all(count[~np.asarray(enabled)] == 0)


INSTANCED = rt.Intersector(rt.tags.instancing, rt.tags.max_levels(2), triangle_cull_mode="back")


@kernel_test
@pytest.mark.parametrize("k", [0, 2])
def test_below_instances(k, kernel_here):
    """Two instance levels (masks, mirrors, per-instance culling options, chains of both lengths): counting
    (``k = 0``) and the K nearest hits with each hit's instance chain, as the portable path finds them."""
    structure = scene_of_levels(2, seed=4)
    ray_args = instanced_rays(64, seed=5)
    count_all = k == 0
    got = kernel(structure, ray_args, INSTANCED, max_hits=k, count_all=count_all)
    assert_same(got, portable(structure, ray_args, INSTANCED, max_hits=k, count_all=count_all))
    total = np.asarray(got.hits.total)
    assert (total > 1).sum() > 5
    if k:
        chains = np.asarray(got.hits.instances)
        lengths = (chains >= 0).sum(axis=-1)[np.asarray(got.hits.leaf) >= 0]
        assert set(lengths.tolist()) == {1, 2}, lengths
        assert (total > k).sum() > 3


@kernel_test
@pytest.mark.parametrize("levels", [0, 2])
def test_vmap_over_scenes_maps_hit_leaves(levels, kernel_here):
    """``jax.vmap`` over (rays, scene) pairs: one launch, each scene's hit leaves and chains in its own
    numbering."""
    if levels:
        structures = [scene_of_levels(levels, seed=30 + s) for s in range(2)]
        per_scene = [instanced_rays(40, seed=40 + s, spread=3.0) for s in range(2)]
        intersector = rt.Intersector(rt.tags.instancing, rt.tags.max_levels(2), max_hits=3)
    else:
        structures = [structure_of(layer_triangles(30 + s)) for s in range(2)]
        per_scene = [layer_rays(40, seed=40 + s) for s in range(2)]
        intersector = rt.Intersector(max_hits=3)
    views = [scene_view(s) for s in structures]
    layout = views[0].layout
    assert views[1].layout == layout
    stack = lambda *xs: jax.tree.map(lambda *a: jnp.stack(a), *xs)  # noqa: E731
    fn = lambda scene, *r: gpu.trace_scene(scene, layout, *r, any_hit=False, cull=0, max_hits=3)  # noqa: E731
    got = jax.jit(jax.vmap(fn))(stack(*[v.traversal for v in views]), *stack(*per_scene))
    if not ON_GPU:
        assert [n for _, n in LAUNCHES] == [96], LAUNCHES  # 2 x 40 rays in one launch (padded to 3 x 32)
    for s, structure in enumerate(structures):
        one = jax.tree.map(lambda a, s=s: a[s], got)
        assert_same(one, portable(structure, per_scene[s], intersector, max_hits=3))
        assert (np.asarray(one.hits.total) > 1).sum() > 3


@kernel_test
@pytest.mark.parametrize("k", [None, 3])
def test_intersector_takes_the_kernel(k, kernel_here, monkeypatch):
    """``Intersector(max_hits=K, backend="gpu")`` and ``count_intersections``: the kernel runs (a launch with
    the hit-list constants) and every field equals the portable path's."""
    if not ON_GPU:
        monkeypatch.setattr(gpu, "unavailable_reason", lambda intersector: None)
    # With the kernel rows packed at build time (the flat static case the intersector traces prepacked).
    structure = rt.build_primitive_structure(
        rt.TriangleGeometry(layer_triangles(50).reshape(-1, 3)), kernel_layout=True
    )
    origin, direction, t_min, t_max, _, _ = layer_rays(64, seed=51, diagonal=k is None)
    ray = rt.Ray(origin, direction, t_min, t_max)
    calls = []
    kernel_call = gpu.kernel_call
    monkeypatch.setattr(gpu, "kernel_call", lambda *a, **kw: calls.append(a[4]) or kernel_call(*a, **kw))
    if k is None:
        got = {"hit_count": rt.count_intersections(ray, structure, rt.Intersector(backend="gpu"))}
        want = {"hit_count": rt.count_intersections(ray, structure, rt.Intersector(backend="portable"))}
        assert calls and calls[0].count and not calls[0].max_hits and calls[0].prepacked, calls
        assert np.asarray(want["hit_count"]).max() > LAYERS
    else:
        tags = (rt.tags.triangle_data, rt.tags.stats)
        got = rt.Intersector(*tags, max_hits=k, backend="gpu").intersect(ray, structure)
        want = rt.Intersector(*tags, max_hits=k, backend="portable").intersect(ray, structure)
        assert calls and calls[0].max_hits == k and not calls[0].count and calls[0].prepacked, calls
        assert np.asarray(want.hit_overflow).sum() > 10
    if not ON_GPU:
        assert LAUNCHES, "the kernel did not run"
    assert_same_fields(got, want, rtol=1e-5)


# --- coverage (no kernel run) -------------------------------------------------------------------------------------


def test_coverage_of_hit_lists():
    """The GPU kernel and the CPU traversal take ``max_hits`` and counting; filters on non-opaque geometry
    decline on the CPU, and on the GPU below instances (the kernel takes them in candidate waves in a
    primitive structure: ``test_gpu_waves.py``)."""
    opaque = structure_of(layer_triangles(60)).geometry_info
    clear = rt.build_primitive_structure(
        rt.TriangleGeometry(layer_triangles(60).reshape(-1, 3), opaque=False)
    ).geometry_info
    k4, counting = rt.Intersector(max_hits=4), _CountingIntersector()  # what count_intersections builds
    assert pipeline.kernel_declines(k4, opaque, "gpu") is None
    assert pipeline.kernel_declines(counting, opaque, "gpu", True) is None
    alpha = rt.Intersector(max_hits=4, filter=lambda c: jnp.asarray(True))
    assert pipeline.kernel_declines(alpha, clear, "gpu") is None
    assert "filters on non-opaque" in pipeline.kernel_declines(alpha, clear, "gpu", levels=1)
    assert pipeline.kernel_declines(k4, opaque, "cpu") is None
    assert pipeline.kernel_declines(counting, opaque, "cpu") is None
    assert "filters on non-opaque" in pipeline.kernel_declines(alpha, clear, "cpu")


def test_static_kernels_compile_no_hit_list_code():
    """Without a hit list the constants are 0 / False (the kernel generated without hit-list code) and only
    the traversal result is read back."""
    view = scene_view(structure_of(layer_triangles(61)))
    config = gpu._Config(False, 0, 8, 0, int(view.layout.primitive_leaves), gpu.DEFAULT_OPTIONS, False)
    args = (jnp.zeros((1, 16)), jnp.zeros((1, 12)), jnp.zeros((1, 16)), jnp.zeros((16, 32)))
    call = gpu.kernel_call(*args, config)
    assert (call.params["MAX_HITS"], call.params["COUNT"], gpu.returned(call)) == (0, False, 6)
    call = gpu.kernel_call(*args, dataclasses.replace(config, max_hits=4))
    assert (call.params["MAX_HITS"], gpu.returned(call)) == (4, 10)
    assert call.out_shape[6].shape == call.out_shape[7].shape == (4 * 32,)


def test_bad_hit_list_arguments_raise():
    view = scene_view(structure_of(layer_triangles(62)))
    ray_args = layer_rays(4, seed=1)
    with pytest.raises(ValueError, match="hit lists need"):
        gpu.trace_scene(view.traversal, view.layout, *ray_args, any_hit=True, cull=0, max_hits=2)
    with pytest.raises(ValueError, match="hit lists need"):
        gpu.trace_scene(view.traversal, view.layout, *ray_args, any_hit=False, cull=0, max_hits=0)


def _kernel_ir(levels: int, max_hits: int, count: bool) -> str:
    """Triton IR of ``trace_kernel`` for a CUDA target (the front end only: no GPU needed)."""
    from kernel_binaries import compile_trace_kernel

    config = gpu._Config(False, 0, 24, levels, 8, gpu.DEFAULT_OPTIONS, levels > 0, max_hits=max_hits, count=count)
    return compile_trace_kernel(config, stage="ttir")


@pytest.mark.skipif(INTERPRETED, reason="compiles the kernel's IR (outside the interpreter)")
@pytest.mark.parametrize("levels", [0, 2])
def test_static_kernel_ir_reads_no_hit_list(levels):
    """Without a hit list the hit buffers are parameters that no instruction reads or writes (the code is the
    kernel's without hit lists); with one they are used."""
    pytest.importorskip("triton")
    names = ("%hit_distance_ptr", "%hit_leaf_ptr", "%hit_total_ptr", "%hit_chain_ptr")
    body = lambda text: text.split("tt.func public @trace_kernel", 1)[1].split("\n", 1)[1]  # noqa: E731
    static = body(_kernel_ir(levels, 0, False))
    assert not any(name in static for name in names)
    hits = body(_kernel_ir(levels, 2, False))
    assert all(name in hits for name in names[:3]) and ((names[3] in hits) == (levels > 0))
    counting = body(_kernel_ir(levels, 0, True))
    assert "%hit_total_ptr" in counting and "%hit_distance_ptr" not in counting
