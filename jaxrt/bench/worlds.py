"""``python -m jaxrt.bench.worlds``: many worlds per step, each rebuilt (or refit) and rendered by its camera.

Every world holds a ground quad and five deforming, moving low-poly spheres (502 triangles, structure capacity
512), placed at random per world. One step of the simulation loop, jitted as one program, takes a time per
world and, for the worlds a mask selects (:func:`jaxrt.update_worlds`): moves and deforms the meshes, rebuilds
the world's structure (``rebuild``) or refits last step's (``refit``), and traces one ``side x side`` camera
giving a depth image (hit distance, ``inf`` on a miss) and a segmentation image (the object hit: 0 ground,
1-5 the spheres, -1 a miss). Worlds outside the mask keep their structures and images.

Reported per image side, world count and mode: the full step (every world) in ms and in frames per second
(one frame = one world's depth and segmentation images), the step with 10% of the worlds selected (the bucket
rounded up to a power of two) and its cost against the full step, the structures alone (every world rebuilt or
refit, no camera: ``struct ms``, on one device), and the memory per world (the arrays the
state keeps: structure and images; on a GPU also the device's peak over the run divided by the worlds). With
``--devices 1,4`` each configuration runs with the worlds split over the first 1 and the first 4 devices
(``update_worlds(..., mesh=...)``) and the speed-up is printed.

Flags: ``--worlds 256,1024,4096``, ``--sides 64,128``, ``--modes rebuild,refit``, ``--devices 1``,
``--fraction 0.1``, ``--repeats 5``, ``--json PATH``, ``--quick`` (CPU smoke sizes: 16 and 64 worlds, 16x16
and 32x32 images, one repeat).
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
import time
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

import jaxrt as rt
from jaxrt.bench.gradients import noisy_sphere
from jaxrt.bench.instancing import nbytes
from jaxrt.bench.report import machine_info
from jaxrt.bench.timing import timed

__all__ = ["initial_state", "main", "make_step", "world_params", "world_update"]

OBJECTS = 5
SPHERE_RINGS = 5  # 4 * 5**2 = 100 triangles per sphere: with the ground 502, capacity 512
GROUND = 10.0  # half-width of the ground quad, metres


def world_params(worlds: int, seed: int = 0) -> dict[str, jax.Array]:
    """Random placements for ``worlds`` worlds: ``centre (W, 5, 3)``, ``scale (W, 5)``, ``phase (W, 5)``,
    ``camera_angle (W,)``, ``camera_height (W,)``."""
    rng = np.random.default_rng(seed)
    centre = np.concatenate(
        [rng.uniform(-4, 4, (worlds, OBJECTS, 1)), rng.uniform(0.8, 1.5, (worlds, OBJECTS, 1)),
         rng.uniform(-4, 4, (worlds, OBJECTS, 1))], -1
    )  # fmt: skip
    return {
        "centre": jnp.asarray(centre, jnp.float32),
        "scale": jnp.asarray(rng.uniform(0.5, 1.2, (worlds, OBJECTS)), jnp.float32),
        "phase": jnp.asarray(rng.uniform(0, 2 * np.pi, (worlds, OBJECTS)), jnp.float32),
        "camera_angle": jnp.asarray(rng.uniform(0, 2 * np.pi, worlds), jnp.float32),
        "camera_height": jnp.asarray(rng.uniform(2.5, 5, worlds), jnp.float32),
    }


_SPHERE_VERTICES, _SPHERE_INDICES = noisy_sphere(4 * SPHERE_RINGS**2)
_GROUND = np.array([[-1, 0, -1], [-1, 0, 1], [1, 0, -1], [1, 0, 1]], np.float32) * GROUND
_GROUND_INDICES = np.array([[0, 1, 2], [2, 1, 3]], np.int32)


def world_geometries(params: dict[str, jax.Array], t: jax.Array) -> list[rt.TriangleGeometry]:
    """One world's meshes at time ``t`` (seconds): the ground, then five spheres that orbit, bounce and
    breathe (radius waves along their height)."""
    sphere = jnp.asarray(_SPHERE_VERTICES)
    geometries = [rt.TriangleGeometry(jnp.asarray(_GROUND), _GROUND_INDICES)]
    for k in range(OBJECTS):
        phase = params["phase"][k]
        orbit = 1.5 * jnp.stack([jnp.cos(t + phase), jnp.abs(jnp.sin(2 * t + phase)) / 3, jnp.sin(t + phase)])
        wave = 1 + 0.15 * jnp.sin(3 * sphere[:, 1:2] + 2 * t + phase)
        vertices = params["centre"][k] + orbit + params["scale"][k] * sphere * wave
        geometries.append(rt.TriangleGeometry(vertices, _SPHERE_INDICES))
    return geometries


def world_camera(params: dict[str, jax.Array], t: jax.Array, side: int) -> rt.Ray:
    """A ``side x side`` pinhole camera orbiting the world's centre."""
    angle = params["camera_angle"] + 0.1 * t
    eye = jnp.stack([7 * jnp.cos(angle), params["camera_height"], 7 * jnp.sin(angle)])
    return rt.shading.pinhole_rays(side, side, eye=eye, target=jnp.array([0.0, 0.5, 0.0]), fov_degrees=60.0)


def world_update(side: int, rebuild: bool, intersector: rt.Intersector | None = None) -> Any:
    """The update of one world: ``fn(params, t, structure) -> (structure, depth, segmentation)``.

    Moves the meshes to time ``t``, rebuilds the structure (``rebuild``) or refits ``structure`` (the last
    step's), and traces the camera: depth ``(side, side)`` float32 (``inf`` on a miss) and segmentation
    ``(side, side)`` int32 (the geometry hit: 0 ground, 1.. the objects; -1 a miss).
    """
    intersector = rt.Intersector() if intersector is None else intersector

    def update(params, t, structure):
        geometries = world_geometries(params, t)
        if rebuild:
            structure = rt.build_primitive_structure(geometries)
        else:
            structure = rt.refit(structure, geometries)
        hit = intersector.intersect(world_camera(params, t, side), structure)
        found = hit.type != rt.IntersectionType.NONE
        return structure, jnp.where(found, hit.distance, jnp.inf), jnp.where(found, hit.geometry_id, -1)

    return update


@jax.jit
@jax.vmap
def _build_at_start(params: dict[str, jax.Array]) -> rt.PrimitiveAccelerationStructure:
    return rt.build_primitive_structure(world_geometries(params, jnp.float32(0)))


@jax.jit
@jax.vmap
def _rebuild_all(params: dict[str, jax.Array], t: jax.Array) -> rt.PrimitiveAccelerationStructure:
    return rt.build_primitive_structure(world_geometries(params, t))


@jax.jit
@jax.vmap
def _refit_all(params: dict[str, jax.Array], t: jax.Array, structure: Any) -> rt.PrimitiveAccelerationStructure:
    return rt.refit(structure, world_geometries(params, t))


def initial_state(params: dict[str, jax.Array], side: int) -> tuple:
    """Every world built at ``t = 0``, its images empty: ``(structures, depth, segmentation)``."""
    worlds = params["scale"].shape[0]
    depth = jnp.full((worlds, side, side), jnp.inf, jnp.float32)
    return _build_at_start(params), depth, jnp.full((worlds, side, side), -1, jnp.int32)


@functools.lru_cache(maxsize=32)
def make_step(side: int, rebuild: bool, mesh: Any = None) -> Any:
    """The jitted step ``step(state, params, t, mask, capacity) -> state`` (``capacity`` static): every
    world the mask selects is moved to its time ``t`` (an array, one per world), rebuilt or refit and
    rendered; the others keep their state. ``state`` is donated (updated in place where the backend can)."""
    update = world_update(side, rebuild)

    def step(state, params, t, mask, capacity):
        return rt.update_worlds(update, mask, state, params, t, state[0], capacity=capacity, mesh=mesh)

    return jax.jit(step, static_argnames="capacity", donate_argnums=0)


def _peak_bytes() -> int | None:
    stats = jax.devices()[0].memory_stats() if jax.default_backend() != "cpu" else None
    return None if not stats else int(stats.get("peak_bytes_in_use", 0)) or None


def measure(worlds: int, side: int, rebuild: bool, devices: int, fraction: float, repeats: int) -> dict[str, Any]:
    """Times one configuration: the full step and the step on a random ``fraction`` of the worlds."""
    mesh = None if devices == 1 else rt.device_mesh(devices, "worlds")
    params = world_params(worlds)
    state = initial_state(params, side)
    if mesh is not None:  # the worlds live on their devices from the start
        spread = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("worlds"))
        params, state = jax.device_put((params, state), spread)
    step = make_step(side, rebuild, mesh)
    clock = [0.0]
    holder = [state]

    def run(mask, capacity):
        clock[0] += 1.0 / 60
        t = jnp.full(worlds, clock[0], jnp.float32)
        holder[0] = step(holder[0], params, t, mask, capacity)
        return holder[0]

    full_mask = jnp.ones(worlds, bool)
    start = time.perf_counter()
    jax.block_until_ready(run(full_mask, worlds))  # compiles
    first_s = time.perf_counter() - start
    # timed's own first call is the second step: a step whose state came back laid out otherwise may compile again.
    full, _ = timed(lambda: run(full_mask, worlds), repeats)
    rng = np.random.default_rng(1)
    chosen = np.zeros(worlds, bool)
    chosen[rng.choice(worlds, max(1, int(round(fraction * worlds))), replace=False)] = True
    capacity = rt.worlds_capacity(chosen, mesh)
    partial_mask = jnp.asarray(chosen)
    partial, out = timed(lambda: run(partial_mask, capacity), repeats)
    structures, depth, segmentation = out
    state_bytes = nbytes(out)
    structure_s = None
    if mesh is None:  # the structures alone (no camera), every world: the build's share of the full step
        t = jnp.full(worlds, 0.5, jnp.float32)
        alone = (lambda: _rebuild_all(params, t)) if rebuild else (lambda: _refit_all(params, t, structures))
        structure_s = timed(alone, repeats)[0].median_s
    return {
        "worlds": worlds,
        "side": side,
        "mode": "rebuild" if rebuild else "refit",
        "devices": devices,
        "full": full.as_dict(worlds, unit="mframes_s"),
        "first_step_s": first_s,
        "frames_s": worlds / full.median_s,
        "partial": dict(partial.as_dict(int(chosen.sum()), unit="mframes_s"), worlds=int(chosen.sum())),
        "partial_capacity": capacity,
        "partial_cost": partial.median_s / full.median_s,
        "structures_alone_s": structure_s,
        "bytes_per_world": state_bytes / worlds,
        "structure_bytes_per_world": nbytes(structures) / worlds,
        "hit_fraction": float(jnp.mean(segmentation >= 0)),
    }


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run, print one line per configuration, and write the JSON file if asked; returns the results."""
    parser = argparse.ArgumentParser(prog="python -m jaxrt.bench.worlds", description=__doc__.splitlines()[0])
    parser.add_argument("--worlds", default="256,1024,4096", help="world counts, comma-separated")
    parser.add_argument("--sides", default="64,128", help="image sides, comma-separated")
    parser.add_argument("--modes", default="rebuild,refit", help="rebuild and/or refit")
    parser.add_argument("--devices", default="1", help="device counts to split the worlds over, comma-separated")
    parser.add_argument("--fraction", type=float, default=0.1, help="worlds selected in the partial step")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--quick", action="store_true", help="16 and 64 worlds, 16x16 and 32x32, one repeat")
    parser.add_argument("--json", metavar="PATH")
    args = parser.parse_args(argv)
    if args.quick:
        args.worlds, args.sides, args.repeats = "16,64", "16,32", 1
    worlds = [int(x) for x in args.worlds.split(",")]
    sides = [int(x) for x in args.sides.split(",")]
    modes = [m.strip() for m in args.modes.split(",")]
    devices = [int(x) for x in args.devices.split(",")]
    for m in modes:
        if m not in ("rebuild", "refit"):
            raise ValueError(f"--modes: expected rebuild and/or refit, got {m!r}")
    if not 0 < args.fraction <= 1:
        raise ValueError(f"--fraction must be in (0, 1], got {args.fraction}")
    machine = machine_info()
    print(
        f"jaxrt worlds bench on {machine['backend']} ({machine['device_kind']}) x{machine['device_count']}, "
        f"jax {machine['jax_version']}; {OBJECTS} deforming spheres + ground per world "
        f"({4 * SPHERE_RINGS**2 * OBJECTS + 2} triangles), one depth+segmentation camera"
    )
    print(
        f"{'side':>5s} {'worlds':>6s} {'mode':>8s} {'dev':>3s} {'full ms':>9s} {'frames/s':>11s} "
        f"{'part ms':>8s} {'part/full':>9s} {'bucket':>6s} {'struct ms':>9s} {'KB/world':>8s} {'hit':>5s} "
        f"{'compile s':>9s}"
    )
    rows = []
    start = time.perf_counter()
    for side in sides:
        for n in worlds:
            for mode in modes:
                for d in devices:
                    row = measure(n, side, mode == "rebuild", d, args.fraction, args.repeats)
                    rows.append(row)
                    alone = row["structures_alone_s"]
                    struct = "-" if alone is None else f"{alone * 1e3:.2f}"
                    print(
                        f"{side:5d} {n:6d} {mode:>8s} {d:3d} {row['full']['median_s'] * 1e3:9.2f} "
                        f"{row['frames_s']:11,.0f} {row['partial']['median_s'] * 1e3:8.2f} {row['partial_cost']:9.1%} "
                        f"{row['partial_capacity'] * d:6d} {struct:>9s} {row['bytes_per_world'] / 1e3:8.1f} "
                        f"{row['hit_fraction']:5.2f} "
                        f"{row['first_step_s'] - row['full']['median_s']:9.1f}",
                        flush=True,
                    )
    peak = _peak_bytes()
    if len(devices) > 1:
        base = {(r["side"], r["worlds"], r["mode"]): r for r in rows if r["devices"] == devices[0]}
        for r in rows:
            if r["devices"] != devices[0]:
                b = base[(r["side"], r["worlds"], r["mode"])]
                r["speedup"] = b["full"]["median_s"] / r["full"]["median_s"]
                print(
                    f"speed-up {r['devices']} vs {devices[0]} device(s), {r['side']}x{r['side']}, {r['worlds']} "
                    f"worlds, {r['mode']}: {r['speedup']:.2f}x"
                )
    if peak is not None:
        print(f"device 0 peak memory over the run: {peak / 1e9:.2f} GB ({peak / max(worlds) / 1e3:.0f} KB per world)")
    results = {"machine": machine, "rows": rows, "peak_bytes": peak, "wall_s": time.perf_counter() - start}
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1, default=float)
    return results


if __name__ == "__main__":
    main(sys.argv[1:])
    sys.exit(0)
