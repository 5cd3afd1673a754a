"""Many worlds per step: deforming meshes rebuilt and rendered (depth and segmentation) in the worlds a mask picks.

A simulation loop keeps ``--worlds`` worlds (a ground and five moving, breathing spheres each). Every step one
jitted program takes the mask of worlds to update (here a quarter of them in turn, as an environment loop that
renders only the agents that act this step), moves their meshes, rebuilds their structures (or refits them
with ``--refit``) and traces their cameras, through ``rt.update_worlds``: the selected worlds are gathered into
a bucket of ``rt.worlds_capacity(mask)`` slots, so the work follows the mask, not the world count. The other
worlds keep their structures and images exactly, which the script checks. With several devices the worlds
are split over them (``--devices``).

Run: ``python examples/worlds.py [--worlds 64] [--side 64] [--steps 8] [--refit] [--devices 1]
[--out out/worlds.png]``
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxrt as rt
from jaxrt.bench.worlds import initial_state, make_step, world_params


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worlds", type=int, default=64)
    parser.add_argument("--side", type=int, default=64, help="image side, pixels")
    parser.add_argument("--steps", type=int, default=8)
    parser.add_argument("--refit", action="store_true", help="refit the structures instead of rebuilding them")
    parser.add_argument("--devices", type=int, default=1, help="split the worlds over this many devices")
    parser.add_argument("--out", default="out/worlds.png")
    args = parser.parse_args(argv)

    mesh = None if args.devices == 1 else rt.device_mesh(args.devices, "worlds")
    params = world_params(args.worlds)
    state = initial_state(params, args.side)
    if mesh is not None and args.worlds % mesh.size == 0:  # the worlds live on their devices from the start
        spread = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("worlds"))
        params, state = jax.device_put((params, state), spread)
    step = make_step(args.side, not args.refit, mesh)
    index = np.arange(args.worlds)
    schedule = [index % 4 == k for k in range(4)]  # a quarter of the worlds, in turn
    capacity = max(rt.worlds_capacity(chosen, mesh) for chosen in schedule)  # one bucket size: one compilation
    updated, seconds = 0, []
    for k in range(args.steps):
        chosen = schedule[k % 4]
        t = jnp.full(args.worlds, 0.05 * (k + 1), jnp.float32)
        before = jax.tree_util.tree_map(np.asarray, state[1:])  # the images, to check the untouched worlds
        start = time.perf_counter()
        state = jax.block_until_ready(step(state, params, t, jnp.asarray(chosen), capacity))
        seconds.append(time.perf_counter() - start)
        updated += int(chosen.sum())
        for new, old in zip(state[1:], before, strict=True):
            assert np.array_equal(np.asarray(new)[~chosen], old[~chosen]), "an untouched world changed"
    # The first step compiles; so may the second, where the state came back from the first laid out otherwise.
    warm = seconds[2:] or seconds[-1:]
    depth, segmentation = (np.asarray(a) for a in state[1:])
    out = {
        "worlds": args.worlds,
        "side": args.side,
        "mode": "refit" if args.refit else "rebuild",
        "step_ms": 1e3 * float(np.median(warm)),
        "frames_per_s": updated / args.steps / float(np.median(warm)),
        "hit_fraction": float((segmentation >= 0).mean()),
    }
    print(
        f"{args.worlds} worlds, {args.side}x{args.side} depth + segmentation, {out['mode']} every step, a quarter of "
        f"the worlds per step, on {jax.default_backend()} x{1 if mesh is None else mesh.size}: "
        f"{out['step_ms']:.1f} ms per step = {out['frames_per_s']:,.0f} frames/s; {out['hit_fraction']:.0%} of "
        f"pixels hit; {updated} world updates, the others unchanged"
    )
    try:
        from PIL import Image
    except ImportError:
        print("pillow is not installed: no image written")
        return out
    tiles = min(8, args.worlds)
    finite = np.isfinite(depth[:tiles])
    near, far = np.percentile(depth[:tiles][finite], [1, 99]) if finite.any() else (0.0, 1.0)
    shade = np.where(finite, 1.0 - np.clip((depth[:tiles] - near) / max(far - near, 1e-6), 0, 1), 0.0)
    palette = np.array([[90, 90, 90], [230, 80, 60], [60, 160, 230], [250, 200, 60], [120, 200, 90], [190, 110, 220]])
    colour = np.where(segmentation[:tiles, ..., None] >= 0, palette[np.maximum(segmentation[:tiles], 0) % 6], 0)
    top = np.concatenate(list(np.repeat((shade * 255)[..., None], 3, -1)), axis=1)
    bottom = np.concatenate(list(colour), axis=1)
    path = Path(args.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.concatenate([top, bottom]).astype(np.uint8), "RGB").save(path)
    print(f"wrote {path} (depth above, segmentation below, the first {tiles} worlds)")
    return out


if __name__ == "__main__":
    main()
