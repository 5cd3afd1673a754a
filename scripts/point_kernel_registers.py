"""Registers and spills of every point-kernel variant (:data:`jaxrt._src.traversal.triton_points.VARIANTS`),
compiled for sm_90a (H100 / H200) without a GPU: Triton's compiler to PTX, then the ``ptxas`` shipped with Triton
(``ptxas-blackwell`` where the other is older than the PTX) with ``-v``.

Usage: ``python scripts/point_kernel_registers.py [STACK]`` (``STACK``: the stack entries compiled in; 52 is the
bound for 1M leaves). One line per variant and kernel: registers per thread, spill stores and loads (bytes).
One-warp programs keep 32 warps resident per multiprocessor up to 64 registers per thread (2048 threads, 64K
registers), 28 at 72, 25 at 80.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tempfile

import triton
from triton.backends.compiler import GPUTarget
from triton.compiler import ASTSource

from jaxrt._src.traversal import triton_points as tp

_INT_POINTERS = {"flag_ptr", "geometry_ptr", "stack_ptr", "parent_ptr"}
_SCALARS = {"n_points", "n_programs", "per_program"}


def _ptxas() -> str:
    folder = os.path.join(os.path.dirname(triton.__file__), "backends", "nvidia", "bin")
    for name in ("ptxas-blackwell", "ptxas"):
        path = os.path.join(folder, name)
        if os.path.exists(path):
            return path
    raise FileNotFoundError(f"no ptxas in {folder}")


def kernels(v: tp.Variant, stack: int) -> list[tuple[str, dict, bool]]:
    """``(kernel name, compile-time constants, whether it writes floats)`` of variant ``v``."""
    base = dict(LANES=v.lanes, BOXES=False)
    flags = dict(VECTOR=v.vector_loads, BATCH=v.leaf_batch)
    if v.walk == "stack":
        return [("nearest_kernel", dict(base, STACK=stack), False), ("winding_kernel", dict(base, STACK=stack), True)]
    if v.walk in ("near", "refill"):
        nearest = dict(base, STACK=stack, SKIP=v.skip, **flags)
        winding = dict(base, STACK=stack, **flags)
        return [(f"nearest_{v.walk}_kernel", nearest, False), (f"winding_{v.walk}_kernel", winding, True)]
    return [("nearest_stackless_kernel", dict(base, **flags), False), ("winding_stackless_kernel", dict(base, **flags), True)]  # fmt: skip


def resources(kernel: str, constants: dict, floats: bool) -> tuple[int, int, int]:
    """``(registers, spill store bytes, spill load bytes)`` of ``kernel`` compiled with ``constants``."""
    fn = getattr(tp, kernel)
    signature = {}
    for name in fn.arg_names:
        if name in constants:
            signature[name] = "constexpr"
        elif name in _SCALARS:
            signature[name] = "i32"
        elif name == "out_ptr":
            signature[name] = "*fp32" if floats else "*i32"
        else:
            signature[name] = "*i32" if name in _INT_POINTERS else "*fp32"
    options = dict(num_warps=1, num_stages=1, enable_fp_fusion=False)
    compiled = triton.compile(ASTSource(fn, signature, constants), target=GPUTarget("cuda", 90, 32), options=options)
    with tempfile.TemporaryDirectory() as folder:
        ptx = os.path.join(folder, "kernel.ptx")
        with open(ptx, "w") as f:
            f.write(compiled.asm["ptx"])
        done = subprocess.run(
            [_ptxas(), "-v", "--gpu-name", "sm_90a", ptx, "-o", os.devnull], capture_output=True, text=True
        )
    log = done.stderr
    if done.returncode != 0:
        raise RuntimeError(log)
    spills = re.search(r"(\d+) bytes spill stores, (\d+) bytes spill loads", log)
    return int(re.search(r"Used (\d+) registers", log).group(1)), int(spills.group(1)), int(spills.group(2))


def main(argv: list[str]) -> None:
    stack = int(argv[0]) if argv else 52
    for name, v in tp.VARIANTS.items():
        for kernel, constants, floats in kernels(v, stack):
            registers, stores, loads = resources(kernel, constants, floats)
            print(f"{name:18} {kernel:26} {registers:4d} registers, spills {stores} B stored, {loads} B loaded")


if __name__ == "__main__":
    main(sys.argv[1:])
