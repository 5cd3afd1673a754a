"""Time the first `Intersector.intersect` call of a fresh process (Numba's compile or cache load and XLA's
compile included) on the Stanford bunny from the shared data folder, 65,536 primary or diffuse rays.

    NUMBA_CACHE_DIR=$(mktemp -d) python scripts/first_call.py diffuse   # a cold Numba cache
    python scripts/first_call.py primary                                # the package's cache, once warm
"""

from __future__ import annotations

import sys
import time

start = time.perf_counter()

import jax  # noqa: E402

import jaxrt as rt  # noqa: E402
from jaxrt.bench.rays import diffuse_rays, primary_rays  # noqa: E402
from jaxrt.bench.scenes import shared_mesh  # noqa: E402


def main(kind: str) -> None:
    scene = shared_mesh("bunny")
    rays = (
        diffuse_rays(scene.vertices, scene.indices, 65536) if kind == "diffuse" else primary_rays(scene.vertices, 65536)
    )
    structure = rt.build_primitive_structure(rt.TriangleGeometry(scene.vertices, scene.indices))
    jax.block_until_ready(structure.node_lower)
    rays = rays.to_jaxrt()
    timings = []
    for _ in range(2):
        t = time.perf_counter()
        jax.block_until_ready(rt.Intersector().intersect(rays, structure))
        timings.append(time.perf_counter() - t)
    print(
        f"{kind}: first call {timings[0]:.2f} s, second {timings[1]:.3f} s, "
        f"process {time.perf_counter() - start:.1f} s (backend {jax.default_backend()})"
    )


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "primary")
