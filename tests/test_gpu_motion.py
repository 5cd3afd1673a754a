"""The GPU kernel on scenes with keyframe motion, against the portable traversal.

As in ``test_gpu_instanced.py``: the kernel runs in Triton's interpreter on the CPU (in a fresh process) or on
a CUDA GPU, launched through the same :class:`gpu.KernelCall`. The reference is the portable traversal of the
same scene view with the portable leaf tests of the intersector (``MotionLeaves``: triangles blended at each
ray's time, moving leaves vanishing on a "vanish" border; node boxes blended by ``step._node_boxes_at``;
moving instances by ``instances.instance_motion_at``). Both make the same decisions step for step, so the
leaf, the instance chain and the traversal counters are equal; distances agree to rounding (rtol 1e-6, as in
``test_gpu_instanced.py``: XLA may contract the blends' and the watertight test's multiply-adds into fused
ones, the kernel never does). Times cover before the range, every keyframe, between keyframes and after it,
with both border modes at each end.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_gpu_instanced import (
    LAUNCHES,
    ON_GPU,
    _transforms,
    assert_same_fields,
    kernel_launches_here,
    kernel_test,
    run_kernel_tests_in_interpreter,
)

import jaxrt as rt
from jaxrt._src import leaves as leaf_tests
from jaxrt._src import pipeline
from jaxrt._src.motion import at_time, keyframe_times
from jaxrt._src.scene_view import scene_view
from jaxrt._src.traversal import drivers, gpu

START, END = 0.5, 2.5
#: Every border mode at each end.
SPECS = (
    rt.MotionSpec(START, END, start_border="vanish", end_border="clamp"),
    rt.MotionSpec(START, END, start_border="clamp", end_border="vanish"),
)
TAGS = (rt.tags.primitive_motion, rt.tags.instance_motion, rt.tags.instancing, rt.tags.max_levels(2))
ALL_RAYS = np.uint32(0xFFFFFFFF)


def _times(keyframes: int) -> list[float]:
    """Before the range, every keyframe, between keyframes (off centre), after the range."""
    keys = keyframe_times(SPECS[0], keyframes)
    between = [0.5 * (a + b) + 0.1 * (b - a) for a, b in zip(keys[:-1], keys[1:], strict=True)]
    return [START - 0.75, *keys, *between, END + 0.75]


def _triangle_keys(rng, keyframes: int, count: int) -> np.ndarray:
    """``(K, 3 count, 3)`` triangles that move and turn between keyframes."""
    base = rng.uniform(-1.0, 1.0, size=(count, 1, 3)) + rng.uniform(-0.6, 0.6, size=(count, 3, 3))
    keys = []
    for k in range(keyframes):
        angle = 0.4 * k
        rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
        keys.append((base @ rotation.T + np.array([0.3 * k, -0.2 * k, 0.25 * k])).reshape(-1, 3))
    return np.asarray(keys, np.float32)


def moving_mesh(rng, keyframes: int, spec: rt.MotionSpec, count: int = 16) -> rt.PrimitiveAccelerationStructure:
    """Moving triangles and a static geometry (which never vanishes) in one motion structure."""
    still = rng.uniform(-1.2, 1.2, size=(4, 1, 3)) + rng.uniform(-0.5, 0.5, size=(4, 3, 3))
    geometries = [
        rt.MotionTriangleGeometry(_triangle_keys(rng, keyframes, count)),
        rt.TriangleGeometry(still.reshape(-1, 3).astype(np.float32)),
    ]
    return rt.build_primitive_structure(geometries, motion=spec)


def static_mesh(rng, count: int = 8) -> rt.PrimitiveAccelerationStructure:
    tri = rng.uniform(-0.4, 0.4, (count, 1, 3)) + 0.6 * rng.standard_normal((count, 3, 3))
    return rt.build_primitive_structure(rt.TriangleGeometry(tri.reshape(-1, 3).astype(np.float32)))


def moving_instances(rng, index, keyframes: int, spread: float, *, still: int = 1) -> rt.Instances:
    """``(N, K, 3, 4)`` transforms that turn and slide between keyframes; the first ``still`` repeat theirs."""
    n = len(index)
    base = _transforms(rng, n, spread, mirrored=1)
    keys = []
    for k in range(keyframes):
        angle = 0.3 * k
        turn = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
        step = base.copy()
        step[:, :, :3] = turn @ base[:, :, :3]
        step[:, :, 3] += np.array([0.4 * k, 0.2 * k, -0.3 * k])
        keys.append(step)
    keys = np.stack(keys, axis=1).astype(np.float32)
    keys[:still] = keys[:still, :1]
    return rt.Instances(np.asarray(index, np.int32), keys)


def rays(n: int, times: list[float], seed: int = 1, spread: float = 1.5):
    """Rays from a shell around the scene aimed at random points inside it, ``n`` per time."""
    rng = np.random.default_rng(seed)
    count = n * len(times)
    target = rng.uniform(-spread, spread, (count, 3))
    origin = target + rng.normal(size=(count, 3)) * 2.0 * spread
    direction = ((target - origin) * rng.uniform(0.3, 1.0, (count, 1))).astype(np.float32)
    t_min = np.where(rng.random(count) < 0.15, rng.uniform(0.0, 0.3, count), 0.0).astype(np.float32)
    t_max = np.full(count, np.inf, np.float32)
    enabled = np.ones(count, bool)
    enabled[-2:] = False
    mask = np.full(count, ALL_RAYS)
    time = np.repeat(np.asarray(times, np.float32), n)
    arrays = (origin.astype(np.float32), direction, t_min, t_max, enabled, mask, time)
    return tuple(jnp.asarray(a) for a in arrays)


def check(structure, ray_args, intersector: rt.Intersector, *, any_hit: bool = False):
    """The kernel against the portable traversal of the same view: equal leaves, chains and counters."""
    view = scene_view(structure)
    assert view.layout.motion
    scene, layout = view.traversal, view.layout
    *geometry, mask, time = ray_args
    cull = intersector.cull
    got = gpu.trace_scene(
        scene, layout, *geometry, mask, any_hit=any_hit, cull=cull, time=time, leaf_motion=gpu.leaf_motion(view)
    )
    tester = leaf_tests.leaf_tester(intersector, view)
    fn = functools.partial(drivers.traverse, scene, layout, tester, any_hit=any_hit)
    want = jax.jit(jax.vmap(fn))(*ray_args)
    for name in ("leaf", "instances", "nodes_visited", "primitives_tested"):
        np.testing.assert_array_equal(np.asarray(getattr(got, name)), np.asarray(getattr(want, name)), err_msg=name)
    np.testing.assert_allclose(np.asarray(got.distance), np.asarray(want.distance), rtol=1e-6, atol=1e-7)
    assert not np.asarray(got.stack_overflow).any()
    return got


def aimed_rays(structure, spec: rt.MotionSpec, n: int, times: list[float], seed: int):
    """Rays from above at random points of random triangles of ``structure`` as they are at each ray's time
    (clamped to the range), ``n`` per time."""
    rng = np.random.default_rng(seed)
    keys = np.asarray(structure.motion_triangle)
    real = np.flatnonzero(np.asarray(structure.leaf_geometry) >= 0)
    target = []
    for t in times:
        at = np.asarray(at_time(keys, spec, t))[rng.choice(real, n)]
        w = rng.dirichlet(np.ones(3), n)
        target.append(np.einsum("nv,nvc->nc", w, at))
    target = np.concatenate(target)
    count = target.shape[0]
    origin = target + np.concatenate([0.5 * rng.normal(size=(count, 2)), np.full((count, 1), 4.0)], axis=1)
    direction = ((target - origin) * rng.uniform(0.3, 1.0, (count, 1))).astype(np.float32)
    t_min = np.zeros(count, np.float32)
    t_max = np.full(count, np.inf, np.float32)
    enabled = np.ones(count, bool)
    enabled[-2:] = False
    time = np.repeat(np.asarray(times, np.float32), n)
    arrays = (origin.astype(np.float32), direction, t_min, t_max, enabled, np.full(count, ALL_RAYS), time)
    return tuple(jnp.asarray(a) for a in arrays)


def _hits_per_time(got, times: list[float], n: int) -> np.ndarray:
    return (np.asarray(got.leaf) >= 0).reshape(len(times), n).sum(axis=1)


# --- running the kernel in Triton's interpreter -----------------------------------------------------------------


kernel_here = pytest.fixture(kernel_launches_here, name="kernel_here")


def test_kernel_in_interpreter():
    """Runs this module's kernel tests in Triton's interpreter, in a fresh process."""
    run_kernel_tests_in_interpreter(__file__)


# --- the kernel's tests -------------------------------------------------------------------------------------------


@kernel_test
@pytest.mark.parametrize("keyframes, spec", [(2, SPECS[0]), (3, SPECS[1])])
def test_moving_triangles(keyframes, spec, kernel_here):
    """A primitive structure: node boxes and triangles blended at each ray's time; before the range
    ("vanish": only the static geometry is hit) and after it ("clamp", or "vanish")."""
    rng = np.random.default_rng(keyframes)
    structure = moving_mesh(rng, keyframes, spec)
    times = _times(keyframes)
    n = 12
    got = check(structure, aimed_rays(structure, spec, n, times, keyframes), rt.Intersector(*TAGS[:1]))
    hits = _hits_per_time(got, times, n)
    assert hits[1:-1].min() >= n - 3
    view = scene_view(structure)
    primitive = np.asarray(view.leaves.geometry)[np.maximum(np.asarray(got.leaf), 0)].reshape(len(times), n)
    moving_hit = ((np.asarray(got.leaf) >= 0).reshape(len(times), n) & (primitive == 0)).sum(axis=1)
    inside = moving_hit[1:-1].sum()
    assert inside > 10
    vanishing_end = 0 if spec.start_border == "vanish" else -1
    assert moving_hit[vanishing_end] == 0  # the moving geometry is gone on the "vanish" side
    assert moving_hit[-1 - vanishing_end] > 0  # and held on the "clamp" side


@kernel_test
@pytest.mark.parametrize("cull_mode, any_hit", [("back", False), ("front", True)])
def test_moving_triangles_culling_and_any_hit(cull_mode, any_hit, kernel_here):
    rng = np.random.default_rng(5)
    structure = moving_mesh(rng, 4, SPECS[0])
    times = _times(4)
    intersector = rt.Intersector(rt.tags.primitive_motion, triangle_cull_mode=cull_mode)
    got = check(structure, aimed_rays(structure, SPECS[0], 8, times, 6), intersector, any_hit=any_hit)
    assert (np.asarray(got.leaf) >= 0).sum() > 15


@kernel_test
def test_moving_instances_one_level(kernel_here):
    """A moving instance table (one instance keeps still) over a moving mesh and a static one: the ray is
    moved by the inverse of the blended transform; instances vanish after the range."""
    rng = np.random.default_rng(11)
    spec = SPECS[1]
    children = [moving_mesh(rng, 3, spec, count=6), static_mesh(rng)]
    structure = rt.build_instance_structure(children, moving_instances(rng, [0, 1, 0, 1], 3, 1.0), motion=spec)
    times = _times(3)
    n = 9  # 63 rays: two programs of 32 lanes
    got = check(structure, rays(n, times, seed=12, spread=2.0), rt.Intersector(*TAGS))
    hits = _hits_per_time(got, times, n)
    assert hits[1:-1].sum() > 10 and hits[-1] == 0  # every instance moves: none left after the range


@kernel_test
@pytest.mark.parametrize("moving_level", [1, 2])
def test_moving_and_static_instances_two_levels(moving_level, kernel_here):
    """Two levels, one of them a moving table (the other static), a moving mesh below: the chains, the
    per-level rays and the vanish border of the moving table."""
    rng = np.random.default_rng(20 + moving_level)
    spec = SPECS[0]
    mesh, other = moving_mesh(rng, 2, spec, count=6), static_mesh(rng)
    inner_index = [0, 1, 0]
    if moving_level == 1:
        inner = rt.build_instance_structure([mesh, other], moving_instances(rng, inner_index, 4, 0.8), motion=spec)
        outer_instances = rt.Instances(np.array([0, 1, 0], np.int32), _transforms(rng, 3, 1.6, mirrored=1))
        structure = rt.build_instance_structure([inner, other], outer_instances)
    else:
        inner_instances = rt.Instances(np.asarray(inner_index, np.int32), _transforms(rng, 3, 0.8, mirrored=1))
        inner = rt.build_instance_structure([mesh, other], inner_instances)
        structure = rt.build_instance_structure(
            [inner, mesh], moving_instances(rng, [0, 1, 0], 2, 1.6, still=0), motion=spec
        )
    times = _times(3)
    n = 9
    got = check(structure, rays(n, times, seed=30 + moving_level, spread=2.0), rt.Intersector(*TAGS))
    chains = np.asarray(got.instances)
    hit = np.asarray(got.leaf) >= 0
    assert hit.sum() > 6 and ((chains[hit] >= 0).sum(axis=1) == 2).any()


@kernel_test
def test_vmap_over_moving_scenes_is_one_launch(kernel_here):
    """``jax.vmap`` over (rays, scene) pairs of moving scenes: the keyframe rows are concatenated with the
    scenes (one launch), and each scene's answer is its own portable traversal's."""
    spec = SPECS[1]
    structures = [moving_mesh(np.random.default_rng(60 + s), 2, spec, count=6) for s in range(2)]
    views = [scene_view(s) for s in structures]
    layout = views[0].layout
    assert views[1].layout == layout
    times = _times(2)
    per_scene = [aimed_rays(s, spec, 6, times, 70 + i) for i, s in enumerate(structures)]
    stack = lambda *xs: jax.tree.map(lambda *a: jnp.stack(a), *xs)  # noqa: E731
    scenes = stack(*[v.traversal for v in views])
    keys = jnp.stack([gpu.leaf_motion(v).triangle for v in views])
    moving = jnp.stack([gpu.leaf_motion(v).moving for v in views])

    def trace(scene, triangle, flags, *ray_args):
        *geometry, mask, time = ray_args
        motion = gpu.LeafMotion(spec, triangle, flags)
        return gpu.trace_scene(scene, layout, *geometry, mask, any_hit=False, cull=0, time=time, leaf_motion=motion)

    got = jax.jit(jax.vmap(trace))(scenes, keys, moving, *stack(*per_scene))
    if not ON_GPU:
        assert [n for _, n in LAUNCHES] == [64], LAUNCHES  # 2 x 24 rays in one launch (padded to 2 x 32)
    intersector = rt.Intersector(rt.tags.primitive_motion)
    for i, view in enumerate(views):
        one = jax.tree.map(lambda a, i=i: a[i], got)
        tester = leaf_tests.leaf_tester(intersector, view)
        fn = functools.partial(drivers.traverse, view.traversal, layout, tester, any_hit=False)
        want = jax.jit(jax.vmap(fn))(*per_scene[i])
        for name in ("leaf", "nodes_visited", "primitives_tested"):
            np.testing.assert_array_equal(np.asarray(getattr(one, name)), np.asarray(getattr(want, name)), name)
        np.testing.assert_allclose(np.asarray(one.distance), np.asarray(want.distance), rtol=1e-6, atol=1e-7)
        assert (np.asarray(one.leaf) >= 0).sum() > 12


@kernel_test
def test_intersector_takes_the_kernel_for_motion(kernel_here, monkeypatch):
    """``Intersector(backend="gpu")`` on a scene with both kinds of motion: the kernel runs (a launch with
    the motion constants) and every field, ``time`` included, equals the portable path's."""
    if not ON_GPU:
        monkeypatch.setattr(gpu, "unavailable_reason", lambda intersector: None)
    rng = np.random.default_rng(40)
    spec = SPECS[1]
    children = [moving_mesh(rng, 2, spec, count=6), static_mesh(rng)]
    structure = rt.build_instance_structure(children, moving_instances(rng, [0, 1, 0], 2, 1.0), motion=spec)
    times = _times(2)
    origin, direction, t_min, t_max, _, _, time = rays(8, times, seed=41, spread=2.0)
    ray = rt.Ray(origin, direction, t_min, t_max, time=time)
    tags = (*TAGS, rt.tags.triangle_data, rt.tags.world_space_data, rt.tags.stats)
    calls = []
    kernel_call = gpu.kernel_call
    monkeypatch.setattr(gpu, "kernel_call", lambda *a, **k: calls.append(a[4]) or kernel_call(*a, **k))
    got = rt.Intersector(*tags, backend="gpu").intersect(ray, structure)
    assert calls and calls[0].leaf_keys == 2 and calls[0].instance_keys == 2, calls
    if not ON_GPU:
        assert LAUNCHES, "the kernel did not run"
    want = rt.Intersector(*tags, backend="portable").intersect(ray, structure)
    assert (np.asarray(want.type) != 0).sum() > 5
    assert_same_fields(got, want, rtol=1e-5)


@kernel_test
def test_gradients_through_the_kernel_path(kernel_here, monkeypatch):
    """The kernel only picks the leaf: gradients with respect to the keyframe vertices and the ray times come
    from the differentiable re-intersection, as on the portable path."""
    if not ON_GPU:
        monkeypatch.setattr(gpu, "unavailable_reason", lambda intersector: None)
    spec = SPECS[1]
    keys = jnp.asarray(_triangle_keys(np.random.default_rng(3), 2, 8))
    times = _times(2)
    probe = rt.build_primitive_structure(rt.MotionTriangleGeometry(keys), motion=spec)
    origin, direction, t_min, t_max, _, _, time = aimed_rays(probe, spec, 8, times, 4)

    def loss(keys, time, backend):
        structure = rt.build_primitive_structure(rt.MotionTriangleGeometry(keys), motion=spec)
        ray = rt.Ray(origin, direction, t_min, t_max, time=time)
        hit = rt.Intersector(rt.tags.primitive_motion, backend=backend).intersect(ray, structure)
        return jnp.sum(jnp.where(hit.type != 0, hit.distance, 0.0))

    got = jax.grad(loss, argnums=(0, 1))(keys, time, "gpu")
    if not ON_GPU:
        assert LAUNCHES, "the kernel did not run"
    want = jax.grad(loss, argnums=(0, 1))(keys, time, "portable")
    assert float(jnp.abs(want[0]).sum()) > 1.0 and float(jnp.abs(want[1]).sum()) > 0.1
    for a, b in zip(got, want, strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-5)


# --- coverage (no kernel run) -------------------------------------------------------------------------------------


def test_motion_in_instance_structures_is_declined_only_by_the_cpu_traversal():
    """The kernel covers keyframe motion everywhere; the CPU traversal covers moving triangles in primitive
    structures (tests/test_cpu_backend.py) and declines keyframe motion below instances."""
    rng = np.random.default_rng(50)
    structure = moving_mesh(rng, 2, SPECS[0], count=2)
    infos = structure.geometry_info
    intersector = rt.Intersector(rt.tags.primitive_motion)
    assert pipeline.kernel_declines(intersector, infos) is None
    assert pipeline.kernel_declines(intersector, infos, "gpu", True) is None
    assert pipeline.kernel_declines(intersector, infos, "gpu", True, levels=1) is None
    assert pipeline.kernel_declines(intersector, infos, "cpu") is None
    assert pipeline.kernel_declines(rt.Intersector(max_hits=2), infos, "cpu") is None
    reason = "keyframe motion in instance structures is not covered by the CPU traversal"
    assert pipeline.kernel_declines(intersector, infos, "cpu", levels=1) == reason
    assert pipeline.kernel_declines(rt.Intersector(), static_mesh(rng).geometry_info, "cpu", True, levels=1) == reason
    assert {"primitive_motion", "instance_motion"} <= gpu.COVERED_TAGS


def test_static_scenes_compile_no_motion_code():
    """The motion constants are 0 for a static scene (its kernel is the one without motion code), and a
    motion scene's ray block carries the keyframe rows."""
    rng = np.random.default_rng(51)
    structure = static_mesh(rng)
    view = scene_view(structure)
    config = gpu._Config(False, 0, 8, 0, int(view.layout.primitive_leaves), gpu.DEFAULT_OPTIONS, False)
    _, config = gpu._motion_arguments(view.traversal, view.layout, None, config)
    assert not config.motion
    call = gpu.kernel_call(jnp.zeros((1, 16)), jnp.zeros((1, 12)), jnp.zeros((1, 16)), jnp.zeros((16, 32)), config)
    assert (call.params["NODE_KEYS"], call.params["LEAF_KEYS"], call.params["IWIDTH"]) == (0, 0, 0)
    moving = scene_view(moving_mesh(rng, 3, SPECS[0], count=2))
    _, config = gpu._motion_arguments(moving.traversal, moving.layout, gpu.leaf_motion(moving), config)
    assert (config.node_keys, config.leaf_keys, config.instance_keys) == (3, 3, 0)
    flags = np.asarray(gpu.leaf_motion(moving).moving)
    geometry = np.asarray(moving.leaves.geometry)
    np.testing.assert_array_equal(flags, geometry == 0)  # the moving geometry's leaves (not the static one's)
