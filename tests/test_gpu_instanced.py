"""The GPU kernel on instanced scenes and on batches of scenes, against the portable traversal.

The kernel runs in Triton's interpreter on the CPU (in a fresh process: Triton decides when it is imported
whether its own library functions are interpreted), launched through the same :class:`gpu.KernelCall` as on
a GPU; tests marked ``gpu`` run it on a CUDA GPU. The reference is the portable stack traversal on the same
:class:`~jaxrt._src.traversal.scene.TraversalScene`: both make the same decisions step for step, so the leaf,
the instance chain and the traversal counters are equal, and distances agree to rounding (XLA on the CPU may
contract multiply-adds, the kernel does not). Scenes are tiny: the interpreter runs a few thousand steps a
second.
"""

from __future__ import annotations

import functools
import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrt as rt
from jaxrt._src.primitives import triangle
from jaxrt._src.scene_view import traversal_scene
from jaxrt._src.traversal import gpu

INTERPRETED = os.environ.get("TRITON_INTERPRET") == "1"
ON_GPU = jax.default_backend() == "gpu" and gpu._import_error() is None
Options = rt.InstanceOptions
ALL_RAYS = np.uint32(0xFFFFFFFF)


# --- scenes -----------------------------------------------------------------------------------------------------


def _mesh(rng, triangles: int = 8):
    """A small blob of random triangles around the origin."""
    centre = rng.uniform(-0.4, 0.4, (triangles, 1, 3))
    tri = centre + 0.6 * rng.standard_normal((triangles, 3, 3))
    return rt.build_primitive_structure(rt.TriangleGeometry(tri.reshape(-1, 3).astype(np.float32)))


def _transforms(rng, count: int, spread: float, mirrored: int = 0) -> np.ndarray:
    """Rotations with non-uniform scale and translation; the first ``mirrored`` have a negative determinant."""
    out = []
    for i in range(count):
        q, r = np.linalg.qr(rng.normal(size=(3, 3)))
        q = q * np.sign(np.diag(r))
        if np.linalg.det(q) < 0:
            q[:, 0] *= -1
        linear = q * rng.uniform(0.6, 1.4, 3)
        if i < mirrored:
            linear[:, 1] *= -1
        out.append(np.concatenate([linear, rng.uniform(-spread, spread, (3, 1))], axis=1))
    return np.asarray(out, np.float32)


def _instances(rng, index, spread, *, masks=False, options=False, mirrored=1):
    n = len(index)
    fields = {}
    if masks:
        fields["mask"] = rng.choice(np.array([0x1, 0x2, 0x3, 0xFF], np.uint32), n)
    if options:
        choices = [
            Options.NONE,
            Options.DISABLE_TRIANGLE_CULLING,
            Options.TRIANGLE_FRONT_FACING_WINDING_COUNTERCLOCKWISE,
        ]
        fields["options"] = np.array([int(choices[i % 3]) for i in range(n)], np.uint32)
    return rt.Instances(np.asarray(index, np.int32), _transforms(rng, n, spread, mirrored), **fields)


def scene_of_levels(levels: int, seed: int = 0, *, masks: bool = True, options: bool = True, count=None):
    """An instance structure ``levels`` deep; every level also instances a mesh directly (shorter chains)."""
    rng = np.random.default_rng(seed)
    a, b = _mesh(rng), _mesh(rng)
    structure = rt.build_instance_structure([a, b], _instances(rng, [0, 1, 0, 1, 0], 1.0, masks=masks, options=options))
    for level in range(2, levels + 1):
        children = [structure, a] if level % 2 == 0 else [structure, b]
        index = [0, 0, 1, 0]
        last = level == levels
        structure = rt.build_instance_structure(
            children,
            _instances(rng, index, 0.8 * level, masks=masks, options=options, mirrored=2),
            count=count if last else None,
        )
    return structure


def rays(n: int, seed: int = 1, *, spread: float = 1.5, masks: bool = True):
    """Rays from a shell around the scene aimed at random points inside it; a few disabled ones."""
    rng = np.random.default_rng(seed)
    target = rng.uniform(-spread, spread, (n, 3))
    origin = target + rng.normal(size=(n, 3)) * 2.0 * spread
    direction = ((target - origin) * rng.uniform(0.3, 1.0, (n, 1))).astype(np.float32)
    t_min = np.where(rng.random(n) < 0.2, rng.uniform(0.0, 0.5, n), 0.0).astype(np.float32)
    t_max = np.where(rng.random(n) < 0.2, rng.uniform(0.5, 1.5, n), np.inf).astype(np.float32)
    enabled = np.ones(n, bool)
    enabled[-3:] = False
    mask = rng.choice(np.array([0x1, 0x2, 0xFFFFFFFF], np.uint32), n) if masks else np.full(n, ALL_RAYS)
    return tuple(jnp.asarray(a) for a in (origin.astype(np.float32), direction, t_min, t_max, enabled, mask))


# --- the portable reference -------------------------------------------------------------------------------------


class _Triangles:
    """Watertight triangle tests with a per-level facing (the portable leaf tester of instanced scenes)."""

    def __init__(self, leaf_triangle, cull: int):
        self.leaf_triangle, self.cull = leaf_triangle, cull

    def prepare(self, origin, direction, facing=None):
        return triangle.shear_ray(origin, direction), (1 if facing is None else facing) * self.cull

    def __call__(self, context, leaves, t_min, t_max):
        sheared, sense = context
        hit = triangle.watertight(sheared, t_min, t_max, self.leaf_triangle[jnp.maximum(leaves, 0)], 0)
        accept = hit.hit & (leaves >= 0)
        if self.cull != 0:
            accept &= ~((sense > 0) & hit.clockwise) & ~((sense < 0) & ~hit.clockwise)
        return accept, hit.distance


def portable(scene, layout, origin, direction, t_min, t_max, enabled, mask, *, any_hit: bool, cull: int) -> dict:
    """The portable traversal of the same scene view (``drivers.traverse``, one ray per ``vmap`` lane)."""
    from jaxrt._src.traversal import drivers

    fn = functools.partial(drivers.traverse, scene, layout, _Triangles(scene.leaf_triangle, cull), any_hit=any_hit)
    out = jax.jit(jax.vmap(fn))(origin, direction, t_min, t_max, enabled, mask)
    names = ("distance", "leaf", "instances", "nodes_visited", "primitives_tested")
    return {name: getattr(out, name) for name in names}


def assert_same(got, want: dict, *, rtol: float = 1e-6) -> None:
    """Equal leaves, chains and counters; distances to rounding; no overflow."""
    for name in ("leaf", "instances", "nodes_visited", "primitives_tested"):
        np.testing.assert_array_equal(np.asarray(getattr(got, name)), np.asarray(want[name]), err_msg=name)
    np.testing.assert_allclose(np.asarray(got.distance), np.asarray(want["distance"]), rtol=rtol, atol=1e-7)
    assert not np.asarray(got.stack_overflow).any()


def assert_same_fields(got, want, rtol: float = 1e-6) -> None:
    """Every result field of the kernel path equals the portable path's: ids exactly, floats to ``rtol``
    (``atol`` 1e-6)."""
    assert set(got) == set(want)
    for name in want:
        pairs = zip(jax.tree.leaves(got[name]), jax.tree.leaves(want[name]), strict=True)
        for a, b in ((np.asarray(a), np.asarray(b)) for a, b in pairs):
            if a.dtype.kind == "f":
                np.testing.assert_allclose(a, b, rtol=rtol, atol=1e-6, err_msg=name)
            else:
                np.testing.assert_array_equal(a, b, err_msg=name)


def check(structure, ray_args, *, any_hit=False, cull=0, rtol=1e-6):
    scene, layout = traversal_scene(structure)
    got = gpu.trace_scene(scene, layout, *ray_args, any_hit=any_hit, cull=cull)
    want = portable(scene, layout, *ray_args, any_hit=any_hit, cull=cull)
    assert_same(got, want, rtol=rtol)
    return got, want


# --- running the kernel in Triton's interpreter -----------------------------------------------------------------


class _HostArray:
    """A NumPy array that Triton's interpreter accepts as a tensor (it expects torch-like methods)."""

    def __init__(self, array: np.ndarray):
        self.array = np.ascontiguousarray(array)
        self.dtype = self.array.dtype

    def data_ptr(self) -> int:
        return self.array.ctypes.data

    def untyped_storage(self):
        return self

    def cpu(self):
        return self

    def new_empty(self, *args, **kwargs):
        return self

    def set_(self, *args):
        return self

    def storage_offset(self) -> int:
        return 0

    def size(self):
        return self.array.shape

    def stride(self):
        return self.array.strides

    def copy_(self, other):
        return self


#: Launches run by :func:`interpreted_launch` (kernel name, padded rays), for tests that count launches.
LAUNCHES: list[tuple[str, int]] = []


def interpreted_launch(call: gpu.KernelCall) -> tuple[jax.Array, ...]:
    """Run a :class:`gpu.KernelCall` in Triton's interpreter (inside ``jit`` through ``pure_callback``).

    Outputs start poisoned, so a result the kernel does not write shows up.
    """
    from jaxrt._src.traversal import triton_kernel

    kernel = getattr(triton_kernel, call.kernel)
    results = gpu.returned(call)
    lanes = call.args[4] if call.kernel == "trace_kernel" else call.args[3]  # rays traced, padding included

    def host(*arrays):
        LAUNCHES.append((call.kernel, int(lanes)))
        inputs = iter(arrays)
        args = [a if isinstance(a, int) else _HostArray(np.asarray(next(inputs))) for a in call.args]
        outs = [_HostArray(np.full(s.shape, -7 if s.dtype == jnp.int32 else np.nan, s.dtype)) for s in call.out_shape]
        for index in call.zeroed:
            outs[index].array[...] = 0
        kernel[(call.programs,)](*args, *outs, **call.params)
        return tuple(o.array for o in outs[:results])

    arrays = [a for a in call.args if not isinstance(a, int)]
    return jax.pure_callback(host, tuple(call.out_shape[:results]), *arrays)


def kernel_launches_here(monkeypatch):
    """The kernel launch on this machine: the GPU, or the interpreter (a few programs: the strided loop runs);
    fresh kernel caches and launch record. Modules register it as their ``kernel_here`` fixture."""
    if not ON_GPU:
        monkeypatch.setattr(gpu, "_launch", interpreted_launch)
        monkeypatch.setattr(gpu, "MAX_PROGRAMS", 2)
    gpu._traversal.cache_clear()
    LAUNCHES.clear()
    yield
    gpu._traversal.cache_clear()


kernel_here = pytest.fixture(kernel_launches_here, name="kernel_here")


def run_kernel_tests_in_interpreter(test_file: str, select: str = "not interpreter") -> None:
    """Runs the tests of ``test_file`` that ``-k select`` picks in Triton's interpreter, in a fresh process
    (Triton decides when it is imported whether it interprets); skipped where they run directly."""
    pytest.importorskip("triton")
    if INTERPRETED or ON_GPU:
        pytest.skip("the kernel tests run directly here")
    command = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-x", test_file, "-k", select]
    env = dict(os.environ, TRITON_INTERPRET="1", JAX_PLATFORMS="cpu")
    done = subprocess.run(command, env=env, cwd=Path(__file__).parents[1], capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stdout[-4000:] + done.stderr[-2000:]
    assert " passed" in done.stdout and " skipped" not in done.stdout.splitlines()[-1], done.stdout[-2000:]


def test_kernel_in_interpreter():
    """Runs this module's kernel tests in Triton's interpreter, in a fresh process."""
    run_kernel_tests_in_interpreter(__file__)


kernel_test = pytest.mark.skipif(not (INTERPRETED or ON_GPU), reason="runs in the interpreter process or on a GPU")


# --- the kernel's tests -------------------------------------------------------------------------------------------


@kernel_test
@pytest.mark.parametrize("levels", [1, 2, 3])
def test_levels_masks_mirrors_and_options(levels, kernel_here):
    """Chains of every length up to ``levels`` (a mesh is also instanced at each level), ray and instance
    masks, mirrored transforms and per-instance culling options, with culling off."""
    got, want = check(scene_of_levels(levels, seed=levels), rays(64, seed=levels))
    chains = np.asarray(got.instances)
    hit = np.asarray(got.leaf) >= 0
    assert hit.sum() > 10 and (chains[hit] >= 0).sum(axis=1).max() == levels
    if levels > 1:
        assert ((chains[hit] >= 0).sum(axis=1) < levels).any()  # shorter chains (a mesh instanced directly)


@kernel_test
@pytest.mark.parametrize("cull, any_hit", [(1, False), (-1, True)])
def test_culling_below_mirrors_and_instance_options(cull, any_hit, kernel_here):
    """Cull sense per level: the chain's mirror flips, the counterclockwise option, the no-culling option."""
    got, _ = check(scene_of_levels(2, seed=7, masks=False), rays(64, seed=8, masks=False), cull=cull, any_hit=any_hit)
    assert (np.asarray(got.leaf) >= 0).sum() > 5


@kernel_test
def test_indirect_count_changes_without_recompiling(kernel_here, monkeypatch):
    """Instances past the count do not exist; the count is an array, so a new count reuses the compiled trace."""
    traces = []
    kernel = gpu._kernel
    monkeypatch.setattr(gpu, "_kernel", lambda *a, **k: traces.append(1) or kernel(*a, **k))
    ray_args = rays(48, seed=3, masks=False)

    @jax.jit
    def trace(structure, *ray_args):
        scene, layout = traversal_scene(structure)
        return gpu.trace_scene(scene, layout, *ray_args, any_hit=False, cull=0)

    hits = []
    for count in (4, 2, 0):
        structure = scene_of_levels(2, seed=5, masks=False, options=False, count=jnp.int32(count))
        got = trace(structure, *ray_args)
        scene, layout = traversal_scene(structure)
        assert_same(got, portable(scene, layout, *ray_args, any_hit=False, cull=0))
        hits.append(int((np.asarray(got.leaf) >= 0).sum()))
    assert len(traces) == 1, "a new instance count recompiled the trace"
    assert hits[0] > hits[1] > hits[2] == 0


def _stack(trees):
    return jax.tree.map(lambda *xs: jnp.stack(xs), *trees)


@kernel_test
@pytest.mark.parametrize("levels", [0, 2])
def test_vmap_over_scenes_is_one_launch(levels, kernel_here):
    """``jax.vmap`` over (rays, scene) pairs: one launch over all rays; each scene's ids in its own numbering."""
    count = 3
    if levels:
        structures = [scene_of_levels(levels, seed=20 + s) for s in range(count)]
    else:
        rng = np.random.default_rng(4)
        structures = [_mesh(rng, 12) for _ in range(count)]
    views = [traversal_scene(s) for s in structures]
    layout = views[0][1]
    assert all(v[1] == layout for v in views)
    per_scene = [rays(40, seed=30 + s, spread=1.0 if levels == 0 else 3.0) for s in range(count)]
    batch = _stack([v[0] for v in views])
    ray_batch = _stack(per_scene)
    fn = lambda scene, *r: gpu.trace_scene(scene, layout, *r, any_hit=False, cull=0)  # noqa: E731
    got = jax.jit(jax.vmap(fn))(batch, *ray_batch)
    if not ON_GPU:
        assert [n for _, n in LAUNCHES] == [128], LAUNCHES  # 3 x 40 rays in one launch (padded to 4 x 32)
    for s, (scene, _) in enumerate(views):
        one = jax.tree.map(lambda a, s=s: a[s], got)
        assert_same(one, portable(scene, layout, *per_scene[s], any_hit=False, cull=0))
        assert (np.asarray(one.leaf) >= 0).sum() > 3


@kernel_test
def test_vmap_over_ray_batches_folds_into_one_launch(kernel_here):
    structure = scene_of_levels(1, seed=11)
    scene, layout = traversal_scene(structure)
    ray_args = rays(64, seed=12)
    folded = [a.reshape(2, 32, *a.shape[1:]) for a in ray_args]
    got = jax.vmap(lambda *r: gpu.trace_scene(scene, layout, *r, any_hit=False, cull=0))(*folded)
    if not ON_GPU:
        assert [n for _, n in LAUNCHES] == [64], LAUNCHES
    flat = jax.tree.map(lambda a: a.reshape(64, *a.shape[2:]), got)
    assert_same(flat, portable(scene, layout, *ray_args, any_hit=False, cull=0))


@kernel_test
def test_primitive_structure_through_trace_scene(kernel_here):
    """Zero levels: the flat kernel, an empty chain, ray masks ignored (only enabled matters)."""
    rng = np.random.default_rng(2)
    structure = _mesh(rng, 16)
    got, _ = check(structure, rays(64, seed=2, spread=1.0), cull=1)
    assert got.instances.shape == (64, 0)


@kernel_test
def test_intersector_reaches_the_kernel_for_instances(kernel_here, monkeypatch):
    """``Intersector(backend="gpu")`` on an instance structure: the kernel runs and every field equals the
    portable path's."""
    if not ON_GPU:
        monkeypatch.setattr(gpu, "unavailable_reason", lambda intersector: None)
    structure = scene_of_levels(2, seed=9)
    origin, direction, t_min, t_max, _, mask = rays(64, seed=10)
    ray = rt.Ray(origin, direction, t_min, t_max, mask=mask)
    tags = (rt.tags.instancing, rt.tags.max_levels(2), rt.tags.triangle_data, rt.tags.world_space_data)
    tags += (rt.tags.user_instance_id, rt.tags.stats)
    got = rt.Intersector(*tags, backend="gpu").intersect(ray, structure)
    if not ON_GPU:
        assert LAUNCHES, "the kernel did not run"
    want = rt.Intersector(*tags, backend="portable").intersect(ray, structure)
    assert (np.asarray(want.type) != 0).sum() > 10
    assert_same_fields(got, want, rtol=1e-5)
