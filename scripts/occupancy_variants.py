"""Launch-shape and register variants of the GPU kernel, timed alone on one GPU (docs/performance.md,
"Where the kernel's time goes").

Usage: ``python scripts/occupancy_variants.py SCENES [VARIANTS] [JSON]`` with comma-separated scenes of
``jaxrt.bench.gpu`` (meshes read from ``.meshes/``) and variants of :data:`VARIANTS` (default: all). For each
scene and ray set (2^20 rays) it prints the kernel's pipelined Mrays/s per variant (best of two runs, the spread
in brackets, ``d``: rays whose leaf differs from the first variant's), and ``intersect``'s for the first and
last variant.

Variants: *default*: one program per block of 32 rays (at most ``gpu.MAX_PROGRAMS``), no work stealing;
*maxnreg64*: the same with at most 64 registers per thread (``.maxnreg``, set through Triton's compile
options); *static4096*: 4,096 programs striding over the blocks; *stealN*: at most N programs taking blocks
from a counter (``KernelOptions.work_stealing``); ``+64``: with the register cap.
"""

from __future__ import annotations

import dataclasses
import json
import sys

import jax
from triton.backends.nvidia import compiler as cuda_compiler

import jaxrt as rt
from jaxrt._src.traversal import gpu
from jaxrt.bench import gpu as bench

#: name: (register cap or None, programs at most, work stealing)
VARIANTS = {
    "default": (None, 1 << 15, False),
    "maxnreg64": (64, 1 << 15, False),
    "static4096": (None, 4096, False),
    "steal4096": (None, 4096, True),
    "steal8192": (None, 8192, True),
    "steal4096+64": (64, 4096, True),
    "steal8192+64": (64, 8192, True),
}

_register_cap: list[int | None] = [None]
_parse_options = cuda_compiler.CUDABackend.parse_options


def _capped_options(self, options):
    if _register_cap[0]:
        options = dict(options, maxnreg=_register_cap[0])
    return _parse_options(self, options)


def _use(variant: str) -> None:
    """Make ``variant`` the kernel's default launch (jax-triton's compiled kernels and traces dropped)."""
    import jax_triton.triton_lib as triton_lib

    cap, programs, steal = VARIANTS[variant]
    _register_cap[0] = cap
    gpu.MAX_PROGRAMS = programs if not steal else 1 << 15
    gpu.STEALING_PROGRAMS = programs
    gpu.DEFAULT_OPTIONS = dataclasses.replace(gpu.DEFAULT_OPTIONS, work_stealing=steal)
    triton_lib._COMPILED_KERNEL_CACHE.clear()
    gpu._traversal.cache_clear()


def main(argv: list[str]) -> None:
    cuda_compiler.CUDABackend.parse_options = _capped_options
    scenes = argv[0].split(",")
    variants = argv[1].split(",") if len(argv) > 1 else list(VARIANTS)
    out = {}
    for name in scenes:
        scene = bench._load_scene(name, 1 << 20, ".meshes")
        build = jax.jit(lambda v, i: rt.build_primitive_structure(rt.TriangleGeometry(v, i)))
        structure = build(scene.vertices, scene.indices)
        for query, any_hit in bench.QUERIES:
            batch = bench._rays(query, scene, 1 << 20)
            rays = bench._device_rays(batch)
            row, first = {}, None
            for variant in variants:
                _use(variant)
                rates, leaf = [], None
                for _ in range(2):
                    _, pipelined, leaf, _ = bench._bench_kernel(structure, rays, any_hit, gpu.DEFAULT_OPTIONS, 5)
                    rates.append(len(batch) / pipelined / 1e6)
                first = leaf if first is None else first
                hit_only = (leaf >= 0) != (first >= 0)
                row[variant] = {
                    "kernel": max(rates),
                    "spread": abs(rates[0] - rates[1]),
                    "leaf_differs": int(hit_only.sum() if any_hit else (leaf != first).sum()),
                }
            for variant in dict.fromkeys((variants[0], variants[-1])):
                _use(variant)
                with bench._default_kernel_options(gpu.DEFAULT_OPTIONS):
                    intersect = jax.jit(rt.Intersector(backend="gpu", accept_any_intersection=any_hit).intersect)
                    full = batch.to_jaxrt()
                    jax.block_until_ready(intersect(full, structure))
                    seconds = bench._pipelined_s(lambda: intersect(full, structure), 20)  # noqa: B023
                    row[variant]["intersect"] = len(batch) / seconds / 1e6
            out[f"{name}/{query}"] = row
            cells = []
            for variant, r in row.items():
                cell = f"{variant}={r['kernel']:.0f}(±{r['spread']:.0f},d{r['leaf_differs']})"
                cells.append(cell + (f"/intersect {r['intersect']:.0f}" if "intersect" in r else ""))
            print(name, query, " ".join(cells), flush=True)
    if len(argv) > 2:
        with open(argv[2], "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main(sys.argv[1:])
