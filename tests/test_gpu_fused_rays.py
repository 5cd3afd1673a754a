"""The GPU kernel reading the caller's ray arrays (``KernelOptions.fused_rays``) against the packed ray block.

With fused rays the kernel computes each ray's reciprocal direction and watertight shear itself (dividing as
XLA divides on the GPU), so every result field must be bit for bit the one traced from the block that
``packed.pack_rays`` builds, on rays whose constants are the hard ones: axis-parallel directions (clamped
reciprocals), signed zeros, components below the clamp and above its inverse, negative dominant axes (swapped
shear axes), disabled rays, and a ray count that is not a multiple of the rays per program. As in
``test_gpu_instanced.py``, the kernel runs in Triton's interpreter on the CPU (in a fresh process) or on a GPU.
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest
from test_gpu import _scene
from test_gpu_instanced import ON_GPU, kernel_launches_here, kernel_test, run_kernel_tests_in_interpreter

import jaxrt as rt
from jaxrt._src import pipeline
from jaxrt._src.traversal import gpu

kernel_here = pytest.fixture(kernel_launches_here, name="kernel_here")


def test_kernel_in_interpreter():
    """Runs this module's kernel tests in Triton's interpreter, in a fresh process."""
    run_kernel_tests_in_interpreter(__file__, "not interpreter and not xla_divides")  # that one needs a GPU


def hard_rays(n: int = 77, seed: int = 3) -> rt.Ray:
    """Rays towards the scene of ``test_gpu._scene`` whose per-ray constants are the hard cases."""
    rng = np.random.default_rng(seed)
    origin = rng.uniform(-2.5, 2.5, (n, 3)).astype(np.float32)
    direction = (rng.uniform(-0.8, 0.8, (n, 3)) - origin).astype(np.float32)
    axis = rng.integers(0, 3, 12)
    direction[:12] = 0.0  # axis-parallel, either sign, some with a signed zero beside it
    direction[np.arange(12), axis] = np.where(np.arange(12) % 2 == 0, -1.0, 1.0)
    direction[1:12:3, (axis[1:12:3] + 1) % 3] = -0.0
    direction[12:18, 0] = rng.choice([1e-30, -1e-30, 3e-20, -3e-20], 6)  # below the reciprocal clamp
    direction[18:22] *= np.float32(1e30)  # above the clamp's inverse after scaling
    direction[22:26] = -np.abs(direction[22:26])  # negative dominant axis: the shear's axes swap
    t_min = np.where(rng.random(n) < 0.2, rng.uniform(0.0, 2.0, n), 0.0).astype(np.float32)
    t_max = np.where(rng.random(n) < 0.2, rng.uniform(0.5, 3.0, n), np.inf).astype(np.float32)
    direction[26:28] = 0.0  # zero direction: disabled
    t_max[28:30] = -1.0  # empty interval: disabled
    origin[30, 1] = np.nan  # not finite: disabled
    return rt.Ray(origin, direction, t_min, t_max)


@kernel_test
@pytest.mark.parametrize(
    "options", [dict(), dict(accept_any_intersection=True, triangle_cull_mode="back"), dict(max_hits=3)]
)
def test_fused_rays_equal_the_packed_block(kernel_here, monkeypatch, options):
    structure, _ = _scene()
    rays = hard_rays()
    fused_flags = []
    kernel_call = gpu.kernel_call

    def recorded(*args, **kwargs):
        call = kernel_call(*args, **kwargs)
        fused_flags.append(call.params["FUSED_RAYS"])
        return call

    monkeypatch.setattr(gpu, "kernel_call", recorded)
    if not ON_GPU:  # the interpreter stands in for the GPU
        monkeypatch.setattr(gpu, "unavailable_reason", lambda intersector: None)
    tags = (rt.tags.triangle_data, rt.tags.stats)
    results = {}
    for fused in (True, False):
        monkeypatch.setattr(gpu, "DEFAULT_OPTIONS", dataclasses.replace(gpu.DEFAULT_OPTIONS, fused_rays=fused))
        gpu._traversal.cache_clear()
        pipeline._intersect_jit.clear_cache()  # the options are read when the call is traced
        results[fused] = rt.Intersector(*tags, backend="gpu", **options).intersect(rays, structure)
    assert fused_flags == [True, False]
    want = results[False]
    for name in want:
        for a, b in zip(jax.tree.leaves(results[True][name]), jax.tree.leaves(want[name]), strict=True):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=name)
    hit = np.asarray(want["type"]).reshape(77, -1)[:, 0] != 0  # the nearest hit (the first of a hit list)
    assert 10 < hit.sum() < 67  # the rays hit and miss
    portable = rt.Intersector(*tags, backend="portable", **options).intersect(rays, structure)
    np.testing.assert_array_equal(np.asarray(want["type"]), np.asarray(portable["type"]))
    np.testing.assert_array_equal(np.asarray(want["primitive_id"]), np.asarray(portable["primitive_id"]))


@pytest.mark.skipif(not ON_GPU, reason="needs a CUDA GPU with Triton and jax-triton")
def test_xla_divides_as_the_kernel_divides():
    """The kernel computes a ray's reciprocal and shear with Triton's ``/`` because XLA's GPU backend divides
    with the same (approximate) instruction: every quotient and reciprocal equal bit for bit, over a wide range
    of magnitudes with zeros, signed zeros, infinities and NaN. Should XLA change its division, this fails
    and the kernel's ``_safe_reciprocal`` and ``_shear`` must follow."""
    import jax.numpy as jnp
    import jax_triton as jt
    import triton
    import triton.language as tl

    @triton.jit
    def divide(a_ptr, b_ptr, quotient_ptr, reciprocal_ptr, BLOCK: tl.constexpr):
        i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
        a = tl.load(a_ptr + i)
        b = tl.load(b_ptr + i)
        tl.store(quotient_ptr + i, a / b)
        tl.store(reciprocal_ptr + i, 1.0 / b)

    rng = np.random.default_rng(0)
    n = 1 << 20
    scale = lambda: np.float32(10.0) ** rng.integers(-30, 31, n).astype(np.float32)  # noqa: E731
    a = (rng.standard_normal(n).astype(np.float32) * scale()).astype(np.float32)
    b = (rng.standard_normal(n).astype(np.float32) * scale()).astype(np.float32)
    b[:256], b[256:512], b[512:768], a[768:1024] = 0.0, -0.0, np.inf, np.nan
    shape = jax.ShapeDtypeStruct((n,), jnp.float32)
    quotient, reciprocal = jt.triton_call(
        jnp.asarray(a), jnp.asarray(b), kernel=divide, out_shape=[shape, shape], grid=(n // 256,), BLOCK=256,
        enable_fp_fusion=False,
    )  # fmt: skip
    for got, want in ((quotient, jax.jit(lambda x, y: x / y)(a, b)), (reciprocal, jax.jit(lambda y: 1.0 / y)(b))):
        got, want = np.asarray(got), np.asarray(want)
        np.testing.assert_array_equal(got, want)  # NaN where the other is NaN (payloads may differ)
        number = ~np.isnan(want)
        np.testing.assert_array_equal(np.signbit(got[number]), np.signbit(want[number]))  # signed zeros too
