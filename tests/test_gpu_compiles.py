"""Every specialisation of the GPU kernel that the pipeline can ask for compiles to a CUDA binary for sm_90:
Triton's compiler and its bundled ``ptxas`` only, no GPU (skipped where Triton is not installed). The kernel
tests run these variants in Triton's interpreter, which accepts code that the compiler may reject."""

from __future__ import annotations

import dataclasses

import pytest

pytest.importorskip("triton")

from kernel_binaries import compile_trace_kernel  # noqa: E402

from jaxrt._src.traversal import gpu  # noqa: E402

BASE = gpu._Config(False, 0, 24, 0, 8, gpu.DEFAULT_OPTIONS, False)

#: ``_Config`` changes: instance levels, queries, culling, hit lists, keyframe motion, analytic and curve leaves.
VARIANTS = {
    "static": {},
    "any hit, culling": dict(any_hit=True, cull=1),
    "1 level": dict(levels=1, roots=True),
    "2 levels, any hit": dict(levels=2, roots=True, any_hit=True, cull=-1),
    "max_hits 4": dict(max_hits=4),
    "max_hits 4, 2 levels": dict(max_hits=4, levels=2, roots=True),
    "counting, 1 level": dict(count=True, levels=1, roots=True),
    "motion, flat": dict(node_keys=2, leaf_keys=2),
    "motion, instances": dict(levels=1, roots=True, instance_keys=3),
    "analytic spheres": dict(analytic=1),
    "analytic shapes and triangles, 1 level, any hit": dict(analytic=15, levels=1, roots=True, any_hit=True),
    "analytic disks, max_hits 4": dict(analytic=2, max_hits=4),
    "round curves, sphere caps": dict(curves=(8, 3, 2, 1e-3, False, True, 0)),
    "round curves, disk caps, any hit": dict(curves=(4, 2, 1, 1e-3, True, False, 0), any_hit=True),
    "round curves, linear, max_hits 4": dict(curves=(1, 0, 0, 1e-3, False, False, 0), max_hits=4),
    "flat curves, disk and sphere caps, counting": dict(curves=(8, 3, 3, 1e-3, True, True, 1), count=True),
    "round and flat curves, no Newton steps, any hit": dict(curves=(5, 0, 0, 1e-3, True, False, 2), any_hit=True),
    "round curves tested on sight (curve_batch 0)": dict(
        curves=(8, 3, 2, 1e-3, False, True, 0), options=dataclasses.replace(gpu.DEFAULT_OPTIONS, curve_batch=0)
    ),
    "round and flat curves, batches of 32, max_hits 4": dict(
        curves=(8, 3, 3, 1e-3, True, True, 2),
        max_hits=4,
        options=dataclasses.replace(gpu.DEFAULT_OPTIONS, curve_batch=32),
    ),
}


@pytest.mark.parametrize("name", list(VARIANTS))
def test_kernel_compiles_to_a_cuda_binary(name):
    config = dataclasses.replace(BASE, **VARIANTS[name])
    binary = compile_trace_kernel(config, stage="cubin")
    assert isinstance(binary, bytes) and binary[:4] == b"\x7fELF"


@pytest.mark.parametrize("name", ["static", "any hit, culling", "max_hits 4", "counting"])
def test_kernel_with_fused_rays_compiles_to_a_cuda_binary(name):
    """The kernel that reads the caller's ray arrays (``KernelOptions.fused_rays``: primitive structures whose
    rays need only the basic block)."""
    config = dataclasses.replace(BASE, **VARIANTS.get(name, dict(count=True)))
    binary = compile_trace_kernel(config, params=dict(FUSED_RAYS=True), stage="cubin")
    assert isinstance(binary, bytes) and binary[:4] == b"\x7fELF"
