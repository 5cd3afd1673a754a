"""Compiling the GPU kernel without a GPU: Triton's compiler (and its bundled ``ptxas``) for a CUDA target,
for tests that check the generated code or that every specialisation builds."""

from __future__ import annotations

from typing import Any

import jax.numpy as jnp

from jaxrt._src.traversal import gpu

#: The CUDA target the kernel is compiled for in these tests (Hopper; warp size 32).
TARGET = ("cuda", 90, 32)
STAGES = ("ttir", "ttgir", "llir", "ptx", "cubin")


def compile_trace_kernel(config: Any, params: dict | None = None, stage: str = "cubin") -> Any:
    """``trace_kernel`` for ``config`` (a ``gpu._Config``; ``params`` overrides compile-time constants) up to
    ``stage``: Triton IR text (``"ttir"``), ..., PTX text (``"ptx"``) or the binary (``"cubin"``)."""
    from triton._C.libtriton import ir
    from triton.backends.compiler import GPUTarget
    from triton.compiler.compiler import ASTSource, make_backend

    from jaxrt._src.traversal import triton_kernel

    fn = triton_kernel.trace_kernel
    target = GPUTarget(*TARGET)
    backend = make_backend(target)
    options = backend.parse_options(dict(num_warps=1, num_stages=1, enable_fp_fusion=False))
    call = gpu.kernel_call(jnp.zeros((1, 16)), jnp.zeros((1, 12)), jnp.zeros((1, 16)), jnp.zeros((20, 64)), config)
    constants = {**call.params, **(params or {})}
    arrays = [a for a in call.args if not isinstance(a, int)] + list(call.out_shape)
    kinds = iter({jnp.float32: "*fp32", jnp.bool_: "*i1"}.get(a.dtype.type, "*i32") for a in arrays)
    signature = {}
    for name in fn.arg_names:
        if name in constants:
            signature[name] = "constexpr"
        elif name in ("n_rays", "n_programs", "n_primitives", "n_real"):
            signature[name] = "i32"
        else:
            signature[name] = next(kinds)
    source = ASTSource(fn, signature, {k: v for k, v in constants.items() if k in fn.arg_names})
    context = ir.context()
    ir.load_dialects(context)
    backend.load_dialects(context)
    out = source.make_ir(target, options, backend.get_codegen_implementation(options), {}, context)
    stages: dict = {}
    backend.add_stages(stages, options, source.language)
    metadata: dict = {}
    for name in STAGES[: STAGES.index(stage) + 1]:
        out = stages[name](out, metadata)
    return str(out) if stage == "ttir" else out
