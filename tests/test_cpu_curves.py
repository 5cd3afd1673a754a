"""Round and flat curve segments on the compiled CPU traversal, against the portable traversal and the float64
reference (scenes and checks of ``test_gpu_curves.py``).

The CPU traversal tests curve leaves with the shared curve formula (:mod:`jaxrt._src.formulas.curve`) compiled
by Numba, which evaluates ``curve.intersect``'s operations in its order without contraction, while XLA
contracts some multiply-adds: leaves (hit or miss, and which segment) and the traversal counters are compared
exactly, distances within the float32 distance tolerance of ``tests/reference.py`` (8 eps relative), and the
nearest hits against the float64 reference of ``jaxrt.bench.curves``.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from reference import TOLERANCE
from test_curves_primitive import aimed_rays
from test_curves_structure import hair
from test_gpu_curves import COMBOS, FLAT_COMBOS, _aim_at_free_ends, _flat_kinked, _kinked, _rays, check_reference
from test_gpu_instanced import assert_same_fields

import jaxrt as rt
from jaxrt._src import leaves as leaf_tests
from jaxrt._src import pipeline
from jaxrt._src.scene_view import scene_view
from jaxrt._src.traversal import cpu, drivers, gpu

pytestmark = pytest.mark.skipif(cpu.unavailable_reason() is not None, reason=str(cpu.unavailable_reason()))

ALL_RAYS = np.uint32(0xFFFFFFFF)
RTOL = TOLERANCE[np.dtype(np.float32)].distance
CURVE = int(rt.IntersectionType.CURVE)


def _curves(intersector, view):
    leaves = gpu.curve_leaves(view, leaf_tests.curve_configuration(intersector, view))
    return cpu.CurveLeaves(view.leaves.curve, view.leaves.curve_flags, leaves.options)


def check(structure, ray_args, intersector: rt.Intersector | None = None, *, any_hit: bool = False, **query):
    """The CPU traversal against the portable traversal of the same view: equal leaves and counters, distances
    within the float32 distance tolerance (``query``: ``max_hits`` or ``count_all``: the hit lists too)."""
    intersector = intersector or rt.Intersector()
    view = scene_view(structure)
    assert pipeline.kernel_declines(intersector, view.geometry_info, "cpu") is None
    origin, direction, t_min, t_max, enabled = (jnp.asarray(a) for a in ray_args)
    mask = jnp.full(origin.shape[:1], ALL_RAYS, jnp.uint32)
    geometry = (origin, direction, t_min, t_max, enabled, mask)
    curves = _curves(intersector, view)
    got = cpu.trace_scene(view.traversal, view.layout, *geometry, any_hit=any_hit, cull=0, curves=curves, **query)
    tester = leaf_tests.leaf_tester(intersector, view)
    fn = functools.partial(drivers.traverse, view.traversal, view.layout, tester, any_hit=any_hit)
    if query:
        fn = functools.partial(fn, max_hits=query.get("max_hits") or 0, count_all=query.get("count_all", False))
    want = jax.jit(jax.vmap(fn))(*geometry)
    if query:
        np.testing.assert_array_equal(np.asarray(got.hits.total), np.asarray(want.hits.total))
        if query.get("count_all"):
            return np.asarray(got.hits.total)
        np.testing.assert_array_equal(np.asarray(got.hits.leaf), np.asarray(want.hits.leaf))
        np.testing.assert_allclose(np.asarray(got.hits.distance), np.asarray(want.hits.distance), rtol=RTOL, atol=0)
        return np.asarray(got.hits.total)
    for name in ("leaf", "nodes_visited", "primitives_tested"):
        np.testing.assert_array_equal(np.asarray(getattr(got, name)), np.asarray(getattr(want, name)), err_msg=name)
    np.testing.assert_allclose(np.asarray(got.distance), np.asarray(want.distance), rtol=RTOL, atol=0)
    assert not np.asarray(got.stack_overflow).any()
    return np.asarray(got.leaf), np.asarray(got.distance)


def test_registry_covers_curves_in_primitive_structures():
    """Round and flat curves of a static primitive structure are the CPU traversal's; below instances or with
    keyframe motion they are declined, each with its reason."""
    round_ = rt.build_primitive_structure(hair(seed=1, strands=2))
    flat = rt.build_primitive_structure(hair(seed=1, strands=2, curve_type="flat"))
    plain = rt.Intersector()
    for structure in (round_, flat):
        infos = tuple(structure.geometry_info)
        assert pipeline.kernel_declines(plain, infos, "cpu") is None
        assert "curves below instances" in pipeline.kernel_declines(plain, infos, "cpu", levels=1)
        assert "keyframe motion" in pipeline.kernel_declines(plain, infos, "cpu", motion=True)


@pytest.mark.parametrize(("basis", "count", "caps"), COMBOS)
def test_every_basis_and_cap(basis, count, caps):
    """Every basis and control point count, each end cap kind, with interval limits and disabled rays."""
    geometry = hair(seed=len(basis) + count, strands=3, basis=basis, count=count, end_caps=caps)
    rng = np.random.default_rng(count)
    n = 32
    t_min = np.where(rng.random(n) < 0.2, rng.uniform(4.0, 12.0, n), 0.0)
    t_max = np.where(rng.random(n) < 0.2, rng.uniform(4.0, 12.0, n), np.inf)
    ray_args = _rays(geometry, n, seed=count + 7, t_min=t_min, t_max=np.maximum(t_max, t_min), disabled=2)
    leaf, distance = check(rt.build_primitive_structure(geometry), ray_args)
    assert (leaf[-2:] == -1).all()
    check_reference(geometry, ray_args, leaf, distance)


@pytest.mark.parametrize(("basis", "count", "caps"), FLAT_COMBOS)
def test_flat_every_basis_and_cap(basis, count, caps):
    """Flat (ray-facing ribbon) segments of every basis and cap kind, rays aimed at the free ends too."""
    geometry = hair(seed=len(basis) + count + 1, strands=3, basis=basis, count=count, end_caps=caps, curve_type="flat")
    rng = np.random.default_rng(count + 20)
    n = 32
    t_min = np.where(rng.random(n) < 0.2, rng.uniform(4.0, 12.0, n), 0.0)
    t_max = np.where(rng.random(n) < 0.2, rng.uniform(4.0, 12.0, n), np.inf)
    ray_args = _rays(geometry, n, seed=count + 27, t_min=t_min, t_max=np.maximum(t_max, t_min), disabled=2)
    structure = rt.build_primitive_structure(geometry)
    _aim_at_free_ends(structure, ray_args, 12, seed=count)
    leaf, distance = check(structure, ray_args)
    assert (leaf[-2:] == -1).all()
    check_reference(geometry, ray_args, leaf, distance)


def _joint_rays(n: int, seed: int, joints: np.ndarray):
    rng = np.random.default_rng(seed)
    target = joints[rng.integers(0, len(joints), n)] + rng.normal(scale=0.1, size=(n, 3))
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    origin = (target - 8.0 * direction).astype(np.float32)
    t_max = np.where(rng.random(n) < 0.25, rng.uniform(6.0, 9.0, n), np.inf).astype(np.float32)
    return origin, direction.astype(np.float32), np.zeros(n, np.float32), t_max, np.ones(n, bool)


def test_joints_mixed_with_triangles_any_hit_hit_lists_and_options():
    """Kinked joints (round and flat), mixed with triangles in one structure, nearest and any hit, the K
    nearest hits and counting, round and flat segments in one structure, and static options."""
    rng = np.random.default_rng(5)
    triangles = rt.TriangleGeometry(rng.uniform(-1, 2.5, (12, 3)).astype(np.float32))
    ray_args = _joint_rays(64, 6, np.array([[1, 0, 1], [1, 0, 0], [1.1, 1, 0]], np.float64))
    round_linear, round_bezier = _kinked("sphere")
    flat_linear, flat_bezier = _flat_kinked("disk")
    structure = rt.build_primitive_structure([triangles, round_bezier, flat_linear])
    leaf, _ = check(structure, ray_args)
    flags = np.asarray(scene_view(structure).leaves.curve_flags)[np.maximum(leaf, 0)]
    assert ((flags != 0) & (leaf >= 0)).sum() > 10 and ((flags == 0) & (leaf >= 0)).sum() > 5
    assert ((flags & 16 != 0) & (leaf >= 0)).sum() > 2 and ((flags & 16 == 0) & (flags != 0) & (leaf >= 0)).sum() > 2
    check(structure, ray_args, any_hit=True)
    assert (check(structure, ray_args, max_hits=3) > 1).sum() > 3
    assert (check(structure, ray_args, count_all=True) > 1).sum() > 3
    check(structure, ray_args, rt.Intersector(curve_type="flat"))
    linear = rt.build_primitive_structure(round_linear)
    check(linear, ray_args)
    geometry = hair(seed=8, strands=3, end_caps="disk")
    ray_args = _rays(geometry, 32, seed=9)
    for options in (rt.CurveOptions(pieces=5, iterations=2, approach_iterations=1), rt.CurveOptions(iterations=0)):
        check(rt.build_primitive_structure(geometry), ray_args, rt.Intersector(curve_options=options))


@pytest.mark.parametrize(("curve_type", "end_caps", "seed"), [("round", "sphere", 12), ("flat", "disk", 22)])
def test_intersector_fields_and_gradients(curve_type, end_caps, seed):
    """``Intersector(backend="cpu")`` on tubes or ribbons with triangles: the traversal picks the leaf and
    reports the hit's curve parameter and part; the result fields and gradients equal the portable path's."""
    geometry = hair(seed=seed, strands=3, end_caps=end_caps, curve_type=curve_type)
    rng = np.random.default_rng(seed + 1)
    triangles = rt.TriangleGeometry(rng.uniform(-2, 2, (12, 3)).astype(np.float32))
    origin, direction = aimed_rays(rng, geometry, 32)
    mask = np.full(32, ALL_RAYS)
    mask[:3] = 0
    tags = (rt.tags.curve_data, rt.tags.triangle_data)

    def run(backend, points, ray_origin):
        g = rt.CurveGeometry(points, geometry.radii, geometry.indices, basis="catmull_rom", control_point_count=4,
                             end_caps=end_caps, curve_type=curve_type)  # fmt: skip
        structure = rt.build_primitive_structure([triangles, g])
        ray = rt.Ray(ray_origin, jnp.asarray(direction), mask=jnp.asarray(mask))
        return rt.Intersector(*tags, backend=backend).intersect(ray, structure)

    args = (geometry.control_points, jnp.asarray(origin))
    got, want = run("cpu", *args), run("portable", *args)
    types = np.asarray(want.type)
    assert (types == CURVE).sum() > 10 and (types[:3] == 0).all()
    assert_same_fields(got, want, rtol=1e-5)

    def loss(backend):
        def f(points, ray_origin):
            result = run(backend, points, ray_origin)
            hit = result.type == CURVE
            return jnp.sum(jnp.where(hit, result.distance + result.curve_parameter, 0.0))

        return jax.grad(f, argnums=(0, 1))(*args)

    # The hit's curve parameter, where the differentiable re-intersection starts polishing, is the Numba
    # formula's (a few ulps from XLA's, up to 1e-5 where the entry is ill conditioned in u): where the polish
    # stops short of the root, the point the gradient is taken at differs by about that (measured: 1.8e-4
    # relative on one component).
    for a, b in zip(loss("cpu"), loss("portable"), strict=True):
        assert np.isfinite(np.asarray(a)).all() and np.abs(np.asarray(b)).max() > 0
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-3, atol=1e-5)


def test_float64_and_vmap():
    """Float64 segments and rays (the scene's dtype end to end), and ``vmap`` over rays."""
    geometry32 = hair(seed=40, strands=3, end_caps="sphere")
    origin, direction = aimed_rays(np.random.default_rng(41), geometry32, 64)
    compiled = rt.Intersector(rt.tags.curve_data, backend="cpu")
    portable = rt.Intersector(rt.tags.curve_data, backend="portable")
    with jax.enable_x64(True):
        g = geometry32
        geometry = rt.CurveGeometry(np.asarray(g.control_points, np.float64), np.asarray(g.radii, np.float64),
                                    g.indices, basis=g.basis.value, control_point_count=4, end_caps="sphere")  # fmt: skip
        structure = rt.build_primitive_structure(geometry)
        assert structure.node_lower.dtype == np.float64
        ray = rt.Ray(jnp.asarray(origin, jnp.float64), jnp.asarray(direction, jnp.float64))
        got, want = compiled.intersect(ray, structure), portable.intersect(ray, structure)
        assert got.distance.dtype == np.float64 and (np.asarray(got.type) == CURVE).sum() > 20
        assert_same_fields(got, want, rtol=1e-9)
    structure32 = rt.build_primitive_structure(geometry32)
    ray = rt.Ray(jnp.asarray(origin), jnp.asarray(direction))
    flat = compiled.intersect(ray, structure32)
    folded = jax.tree_util.tree_map(lambda a: a.reshape(2, 32, *a.shape[1:]), ray)
    batched = jax.vmap(lambda r: compiled.intersect(r, structure32).distance)(folded)
    np.testing.assert_array_equal(np.asarray(batched).reshape(-1), np.asarray(flat.distance))
