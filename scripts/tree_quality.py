"""Build time, SAH cost and mean nodes visited per ray of each build quality, on the default backend.

    JAXRT_DATA_DIR=../shared/data python scripts/tree_quality.py bunny,dragon,sponza fast,high,sah 65536
    python scripts/tree_quality.py sphere fast,sah 16384          # the 1M-triangle noisy sphere

Arguments: scenes of ``jaxrt.bench.gpu`` (comma-separated), qualities, rays per set (primary and diffuse rays
of ``jaxrt.bench.rays``). Build: ``jax.jit(build_primitive_structure)``, median of 3 warm calls (and the first
call, with its compile). Nodes visited: ``rt.tags.stats`` through ``Intersector.intersect``.
"""

from __future__ import annotations

import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxrt as rt
from jaxrt.bench.gpu import _load_scene, _rays, sah_cost


def main(argv: list[str]) -> None:
    names, qualities = argv[0].split(","), argv[1].split(",")
    n_rays = int(argv[2]) if len(argv) > 2 else 65536
    for name in names:
        scene = _load_scene(name, 1 << 20, None)
        vertices, indices = jnp.asarray(scene.vertices), jnp.asarray(scene.indices)
        batches = {k: _rays(k, scene, n_rays).to_jaxrt() for k in ("primary", "diffuse")}
        for quality in qualities:
            build = jax.jit(lambda v, i, q=quality: rt.build_primitive_structure(rt.TriangleGeometry(v, i), quality=q))
            start = time.perf_counter()
            structure = jax.block_until_ready(build(vertices, indices))
            first = time.perf_counter() - start
            times = []
            for _ in range(3):
                start = time.perf_counter()
                jax.block_until_ready(build(vertices, indices))
                times.append(time.perf_counter() - start)
            row = (
                f"{name} {scene.triangle_count} {quality}: build {np.median(times) * 1e3:.0f} ms (first {first:.1f} s) "
                f"SAH {sah_cost(structure):.1f}"
            )
            for kind, rays in batches.items():
                hit = rt.Intersector(rt.tags.stats).intersect(rays, structure)
                row += f" {kind} visits {float(np.mean(np.asarray(hit.nodes_visited))):.1f}"
            print(row, flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
