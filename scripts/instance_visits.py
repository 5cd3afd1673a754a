"""Mean nodes visited per ray on the island of ``jaxrt.bench.instancing`` for each instance tree quality.

    python scripts/instance_visits.py high,fast 65536                  # the bench's island, instanced only
    python scripts/instance_visits.py high,fast 65536 --flat --small   # a smaller island, with the flattened tree

Traces with ``rt.tags.stats`` through ``Intersector.intersect`` (the CPU traversal on a CPU), camera rays of
the bench. ``--small``: 256 x 256 terrain, 512 leaves per tree, 32 groves of 32 trees (2M flattened triangles).
"""

from __future__ import annotations

import sys
import time

import jax
import numpy as np

import jaxrt as rt
from jaxrt.bench import instancing


def main(argv: list[str]) -> None:
    qualities = argv[0].split(",")
    n_rays = int(argv[1]) if len(argv) > 1 else 65536
    sizes = dict(instancing._DEFAULTS)
    if "--small" in argv:
        sizes.update(terrain=256, leaves=512, grove_trees=32, groves=32)
    scene = instancing.island(sizes)
    meshes = [instancing._mesh(scene[k]) for k in ("terrain", "trunk", "leaf")]
    rays = instancing.camera_rays(n_rays)
    builds = {}
    if "--flat" in argv:
        builds["flattened"] = (lambda: instancing._mesh(instancing._flat_triangles(scene)), 0)
    for q in qualities:
        builds[f"2 levels, {q}"] = (lambda q=q: instancing._build_two_levels(scene, meshes, q), 2)
        builds[f"3 levels, {q}"] = (lambda q=q: instancing._build_three_levels(scene, meshes, q), 3)
    for name, (build, levels) in builds.items():
        jax.block_until_ready(build())
        start = time.perf_counter()
        structure = jax.block_until_ready(build())
        seconds = time.perf_counter() - start
        tags = (rt.tags.stats,) + ((rt.tags.instancing, rt.tags.max_levels(levels)) if levels else ())
        hit = rt.Intersector(*tags).intersect(rays, structure)
        visits = np.asarray(hit.nodes_visited)
        print(f"{name}: visits/ray {visits.mean():.1f} (max {visits.max()}), warm build {seconds:.2f} s", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
