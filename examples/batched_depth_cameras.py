"""1024 small random scenes, one depth camera each, built and traced as one batched program (``jax.vmap``).

Each scene (a simulated environment, say) has its own ground and its own box-shaped crown mesh, placed 31
times by its own instance transforms. ``jax.vmap`` runs the primitive builds, the instance build and
``intersect`` over the scene axis, so every environment is traced against its own structure in one compiled
program. A few scenes are checked against tracing them one at a time.

Run: ``python examples/batched_depth_cameras.py [--scenes 1024] [--side 32] [--out out/batched_depth.png]``
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxrt as rt
from jaxrt.bench.instancing import batched_forests, depth_camera_rays


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=int, default=1024)
    parser.add_argument("--side", type=int, default=32, help="depth image side, pixels")
    parser.add_argument("--out", default="out/batched_depth.png")
    args = parser.parse_args(argv)

    ground, crown, instances = batched_forests(args.scenes, trees=31)
    cameras = depth_camera_rays(args.scenes, args.side)
    intersector = rt.Intersector(rt.tags.instancing)

    @jax.jit
    def build(ground, crown, instances):
        grounds = jax.vmap(rt.build_primitive_structure)(ground)
        crowns = jax.vmap(rt.build_primitive_structure)(crown)
        return jax.vmap(lambda g, c, i: rt.build_instance_structure([g, c], i))(grounds, crowns, instances)

    @jax.jit
    def depth(cameras, scenes):
        hit = jax.vmap(intersector.intersect)(cameras, scenes)
        return jnp.where(hit.type != 0, hit.distance, jnp.inf)

    timings = {}
    jax.block_until_ready(build(ground, crown, instances))  # compiles
    start = time.perf_counter()
    scenes = jax.block_until_ready(build(ground, crown, instances))
    timings["build"] = time.perf_counter() - start
    jax.block_until_ready(depth(cameras, scenes))  # compiles
    start = time.perf_counter()
    images = jax.block_until_ready(depth(cameras, scenes))
    timings["trace"] = time.perf_counter() - start
    rays = args.scenes * args.side * args.side

    # Scenes traced alone give the same depths.
    for s in (0, args.scenes // 2, args.scenes - 1):
        alone = intersector.intersect(
            rt.Ray(cameras.origin[s], cameras.direction[s]), jax.tree.map(lambda a, s=s: a[s], scenes)
        )
        single = np.where(np.asarray(alone.type) != 0, np.asarray(alone.distance), np.inf)
        np.testing.assert_allclose(np.asarray(images[s]), single, rtol=1e-5)

    out = {
        "scenes": args.scenes,
        "rays_per_scene": args.side * args.side,
        "build_s": timings["build"],
        "trace_s": timings["trace"],
        "scene_rays_per_s": rays / timings["trace"],
        "hit_fraction": float(jnp.mean(jnp.isfinite(images))),
    }
    print(
        f"{args.scenes} scenes x {args.side}x{args.side} depth rays on {jax.default_backend()}: batched build "
        f"{timings['build'] * 1e3:.1f} ms, trace {timings['trace'] * 1e3:.1f} ms = "
        f"{out['scene_rays_per_s'] / 1e6:.3f} M scene-rays/s; {out['hit_fraction']:.0%} of rays hit; "
        "3 scenes match tracing them alone"
    )
    try:
        from PIL import Image
    except ImportError:
        print("pillow is not installed: no image written")
        return out
    tiles = min(64, args.scenes)
    columns = 8
    grid = np.asarray(images[:tiles]).reshape(tiles, args.side, args.side)
    finite = np.isfinite(grid)
    near, far = np.percentile(grid[finite], [1, 99]) if finite.any() else (0.0, 1.0)
    shade = np.where(finite, 1.0 - np.clip((grid - near) / max(far - near, 1e-6), 0, 1), 0.0)
    rows = -(-tiles // columns)
    mosaic = np.zeros((rows * args.side, columns * args.side))
    for k in range(tiles):
        r, c = divmod(k, columns)
        mosaic[r * args.side : (r + 1) * args.side, c * args.side : (c + 1) * args.side] = shade[k]
    path = Path(args.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray((mosaic * 255).astype(np.uint8), "L").save(path)
    print(f"wrote {path} (the first {tiles} depth images)")
    return out


if __name__ == "__main__":
    main()
