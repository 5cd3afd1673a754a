"""How the GPU kernel spreads rays over its programs and what its warp-uniform slab test assumes.

- Work stealing (``KernelOptions.work_stealing``): a launch of at most ``gpu.STEALING_PROGRAMS`` programs, each
  taking the next untraced block of rays from a counter that is zeroed before the launch; hit lists and the
  4-wide layout keep the fixed stride.
- The plain slab test: a warp none of whose live rays has a zero direction component skips the parallel-ray
  case of the slab test. Warps that mix such rays with others must take the full test.

The launch shapes are checked here; the traced results against the portable traversal run on a GPU, or in
Triton's interpreter in a fresh process (where ``gpu.MAX_PROGRAMS`` is 2, so that every program takes several
blocks).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_gpu_instanced import ON_GPU, kernel_launches_here, kernel_test, run_kernel_tests_in_interpreter

import jaxrt as rt
from jaxrt._src.traversal import gpu

kernel_here = pytest.fixture(kernel_launches_here, name="kernel_here")

BLOCKS = 2**20 // 32


def _call(n: int, options: gpu.KernelOptions = gpu.DEFAULT_OPTIONS, **config) -> gpu.KernelCall:
    """The launch for ``n`` float32 rays (fused: the caller's arrays) of a primitive structure."""
    settings = dict(any_hit=False, cull=0, stack=24, levels=0, primitive_leaves=8, options=options, roots=False)
    settings.update(config)
    zeros = jnp.zeros((n, 3), jnp.float32)
    one = jnp.zeros((n,), jnp.float32)
    rays = gpu.FusedRays(zeros, zeros, one, one, jnp.ones((n,), bool), n)
    return gpu.kernel_call(jnp.zeros((1, 16)), jnp.zeros((1, 12)), jnp.zeros((1, 16)), rays, gpu._Config(**settings))


def test_work_stealing_launches_fewer_programs_with_a_zeroed_counter():
    call = _call(2**20)
    assert call.params["STEAL"] and call.programs == gpu.STEALING_PROGRAMS < BLOCKS
    (counter,) = call.zeroed
    assert counter == len(call.out_shape) - 1
    assert call.out_shape[counter].shape == (1,) and call.out_shape[counter].dtype == jnp.int32
    # Fewer blocks than programs: one program per block.
    assert _call(64).programs == 2 and _call(64).params["STEAL"]


def test_without_work_stealing_programs_stride():
    call = _call(2**20, dataclasses.replace(gpu.DEFAULT_OPTIONS, work_stealing=False))
    assert not call.params["STEAL"] and call.zeroed == ()
    assert call.programs == min(BLOCKS, gpu.MAX_PROGRAMS)


@pytest.mark.parametrize("config", [dict(max_hits=2), dict(count=True)])
def test_hit_lists_keep_the_stride(config):
    """Hit lists (and counts) keep the fixed stride."""
    call = _call(2**20, **config)
    assert not call.params["STEAL"] and call.zeroed == () and call.programs == min(BLOCKS, gpu.MAX_PROGRAMS)


def test_wide_layout_keeps_the_stride():
    rays = jnp.zeros((16, 2**20), jnp.float32)
    options = dataclasses.replace(gpu.DEFAULT_OPTIONS, node_width=4)
    config = gpu._Config(False, 0, 24, 0, 8, options, False)
    call = gpu.kernel_call(jnp.zeros((1, 32)), jnp.zeros((1, 12)), jnp.zeros((1, 16)), rays, config)
    assert call.kernel == "trace_wide_kernel" and call.zeroed == () and call.programs == min(BLOCKS, gpu.MAX_PROGRAMS)


def test_kernel_in_interpreter():
    """Runs this module's kernel tests in Triton's interpreter, in a fresh process."""
    run_kernel_tests_in_interpreter(__file__, "kernel_mixed")


def _scene_and_rays(seed: int = 5):
    """A closed sphere of triangles with a soup inside, and 12 warps of rays from around it. Warps 0, 3, 6 and 9
    each hold one ray (at a random lane) with zero direction components: along an axis, or in a coordinate
    plane; warp 1 has only such rays; the rest none. Some rays end inside the sphere."""
    rng = np.random.default_rng(seed)
    u, v = np.meshgrid(np.linspace(0, np.pi, 13), np.linspace(0, 2 * np.pi, 25), indexing="ij")
    grid = np.stack([np.sin(u) * np.cos(v), np.sin(u) * np.sin(v), np.cos(u)], -1).astype(np.float32)
    a, b, c, d = grid[:-1, :-1], grid[1:, :-1], grid[1:, 1:], grid[:-1, 1:]
    sphere = np.concatenate([np.stack([a, b, c], 2), np.stack([a, c, d], 2)]).reshape(-1, 3, 3)
    soup = rng.uniform(-0.6, 0.6, (40, 1, 3)) + 0.2 * rng.standard_normal((40, 3, 3))
    triangles = np.concatenate([sphere, soup.astype(np.float32)]).reshape(-1, 3)
    structure = rt.build_primitive_structure(rt.TriangleGeometry(triangles))
    n = 12 * 32
    origin = rng.uniform(-2.0, 2.0, (n, 3)).astype(np.float32)
    direction = (rng.uniform(-0.5, 0.5, (n, 3)) - origin).astype(np.float32)
    special = [w * 32 + rng.integers(32) for w in (0, 3, 6, 9)] + list(range(32, 64))
    for k, ray in enumerate(special):
        zeros = rng.choice(3, size=1 + k % 2, replace=False)  # one or two zero components
        direction[ray, zeros] = 0.0
        if not direction[ray].any():
            direction[ray, (zeros[0] + 1) % 3] = 1.0
    t_max = np.where(rng.random(n) < 0.25, rng.uniform(0.5, 2.5, n), np.inf).astype(np.float32)
    return structure, rt.Ray(origin, direction, np.zeros(n, np.float32), t_max)


@kernel_test
@pytest.mark.parametrize("any_hit", [False, True])
def test_kernel_mixed_warps_and_work_stealing_equal_the_portable_path(any_hit, kernel_here, monkeypatch):
    """Every field equals the portable path's, with work stealing on and off (bit for bit between the two).

    (With the clamped reciprocal the plain slab test differs from the full one only for boxes some 1e27 from
    the ray: this checks the kernel's answers on mixed warps, not which test a warp took.)"""
    if not ON_GPU:  # the interpreter stands in for the GPU
        monkeypatch.setattr(gpu, "unavailable_reason", lambda intersector: None)
    structure, rays = _scene_and_rays()
    tags = (rt.tags.triangle_data, rt.tags.stats)
    want = rt.Intersector(*tags, backend="portable", accept_any_intersection=any_hit).intersect(rays, structure)
    assert (np.asarray(want.type) != 0).sum() > 100  # the rays do hit
    results = {}
    for steal in (True, False):
        monkeypatch.setattr(gpu, "DEFAULT_OPTIONS", dataclasses.replace(gpu.DEFAULT_OPTIONS, work_stealing=steal))
        gpu._traversal.cache_clear()
        got = rt.Intersector(*tags, backend="gpu", accept_any_intersection=any_hit).intersect(rays, structure)
        results[steal] = got
        for name in want:
            if name == "distance" or name == "triangle_barycentric_coord":  # XLA may contract multiply-adds
                np.testing.assert_allclose(got[name], want[name], rtol=1e-6, atol=1e-7, err_msg=name)
            else:
                np.testing.assert_array_equal(got[name], want[name], err_msg=name)
    for a, b in zip(jax.tree.leaves(results[True]), jax.tree.leaves(results[False]), strict=True):
        np.testing.assert_array_equal(a, b)
