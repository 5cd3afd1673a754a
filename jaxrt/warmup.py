"""Compile the common traversal specialisations ahead of time: ``python -m jaxrt.warmup``.

Each specialisation (triangles, any hit, ``max_hits``, instances, keyframe motion, round and flat curves, boxes
with a built-in intersection function) is traced once on a small scene with ``backend="auto"``. On a GPU this
fills the kernel cache (:mod:`jaxrt._src.traversal.kernel_cache`: ``$JAXRT_KERNEL_CACHE``, else
``~/.cache/jaxrt/kernels``), so that a later process's first call skips Triton's compiler; on the CPU it fills
Numba's cache beside the package. Set ``JAX_COMPILATION_CACHE_DIR`` as well to keep XLA's programs around the
kernels (JAX's persistent compilation cache).

    python -m jaxrt.warmup                 # every specialisation; prints each one's first-call time
    python -m jaxrt.warmup --only curves   # names from --list
    python -m jaxrt.warmup --clear         # empty the kernel cache first
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

import jaxrt as rt

#: Rays per warm-up call: one power-of-two bucket, small enough for the CPU.
RAYS = 1024


def _rays(count: int = RAYS, seed: int = 0) -> rt.Ray:
    rng = np.random.default_rng(seed)
    origin = rng.uniform(-3.0, 3.0, (count, 3)).astype(np.float32)
    target = rng.uniform(-0.5, 0.5, (count, 3)).astype(np.float32)
    return rt.Ray(jnp.asarray(origin), jnp.asarray(target - origin), time=jnp.asarray(rng.random(count), jnp.float32))


def _triangles(seed: int = 0, count: int = 64) -> rt.TriangleGeometry:
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-1.0, 1.0, (count, 1, 3))
    return rt.TriangleGeometry((centres + 0.2 * rng.normal(size=(count, 3, 3))).reshape(-1, 3).astype(np.float32))


def _curves(curve_type: str) -> rt.CurveGeometry:
    rng = np.random.default_rng(1)
    strands, points = 16, 8
    roots = rng.uniform(-1.0, 1.0, (strands, 1, 3))
    steps = np.cumsum(0.15 * rng.normal(size=(strands, points, 3)), axis=1)
    control = (roots + steps).reshape(-1, 3).astype(np.float32)
    first = (np.arange(strands)[:, None] * points + np.arange(points - 3)[None, :]).reshape(-1).astype(np.int32)
    radii = np.full(len(control), 0.02, np.float32)
    return rt.CurveGeometry(
        control, radii, first, basis="catmull_rom", control_point_count=4, curve_type=curve_type
    )


def _triangle_scene() -> rt.PrimitiveAccelerationStructure:
    return rt.build_primitive_structure(_triangles())


def _instanced_scene() -> rt.InstanceAccelerationStructure:
    leaf = _triangle_scene()
    transform = np.tile(np.eye(3, 4, dtype=np.float32), (4, 1, 1))
    transform[:, :, 3] = np.array([[0, 0, 0], [1.5, 0, 0], [0, 1.5, 0], [0, 0, 1.5]], np.float32)
    return rt.build_instance_structure([leaf], rt.Instances(np.zeros(4, np.int32), transform))


def _motion_scene() -> rt.PrimitiveAccelerationStructure:
    start = np.asarray(_triangles().vertices)
    keys = np.stack([start, start + np.float32(0.3)])
    return rt.build_primitive_structure(rt.MotionTriangleGeometry(keys), motion=rt.MotionSpec(0.0, 1.0))


def _sphere_boxes() -> rt.PrimitiveAccelerationStructure:
    rng = np.random.default_rng(2)
    centres = rng.uniform(-1.0, 1.0, (64, 3)).astype(np.float32)
    radius = np.float32(0.1)
    return rt.build_primitive_structure(rt.BoundingBoxGeometry(centres - radius, centres + radius))


def specialisations() -> dict[str, Callable[[], object]]:
    """Name -> a function that compiles and runs one specialisation once (returns the result)."""
    rays = _rays()
    F = rt.intersection_functions

    def trace(intersector: rt.Intersector, build: Callable[[], object]) -> Callable[[], object]:
        return lambda: jax.block_until_ready(intersector.intersect(rays, build()))

    return {
        "triangles": trace(rt.Intersector(rt.tags.triangle_data), _triangle_scene),
        "any_hit": trace(rt.Intersector(accept_any_intersection=True), _triangle_scene),
        "max_hits": trace(rt.Intersector(max_hits=4), _triangle_scene),
        "instances": trace(rt.Intersector(rt.tags.instancing), _instanced_scene),
        "motion": trace(rt.Intersector(rt.tags.primitive_motion), _motion_scene),
        "curves": trace(rt.Intersector(rt.tags.curve_data), lambda: rt.build_primitive_structure(_curves("round"))),
        "flat_curves": trace(rt.Intersector(rt.tags.curve_data), lambda: rt.build_primitive_structure(_curves("flat"))),
        "sphere_boxes": trace(rt.Intersector(intersection_functions={0: F.sphere}), _sphere_boxes),
    }


def main(argv: list[str] | None = None) -> dict[str, float]:
    """Run the warm-up; returns each specialisation's first-call time in seconds."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", nargs="*", help="specialisations to compile (default: all)")
    parser.add_argument("--list", action="store_true", help="print the specialisations' names and exit")
    parser.add_argument("--clear", action="store_true", help="empty the kernel cache first")
    parser.add_argument("--json", help="write {name: seconds} to this file")
    args = parser.parse_args(argv)
    from jaxrt._src.traversal import kernel_cache

    table = specialisations()
    if args.list:
        print("\n".join(table))
        return {}
    if args.clear:
        print(f"kernel cache: removed {kernel_cache.clear()} entries")
    unknown = sorted(set(args.only or ()) - set(table))
    if unknown:
        parser.error(f"unknown specialisations {unknown}; known: {sorted(table)}")
    start = time.perf_counter()
    jax.block_until_ready(jnp.zeros(8) + 1)  # the backend's start, so that it is not charged to the first row
    print(f"{'backend start':14s}            {time.perf_counter() - start:7.2f} s", flush=True)
    seconds = {}
    for name in args.only or table:
        start = time.perf_counter()
        table[name]()
        seconds[name] = time.perf_counter() - start
        print(f"{name:14s} first call {seconds[name]:7.2f} s", flush=True)
    where = kernel_cache.cache_dir()
    print(f"backend {jax.default_backend()}; kernel cache {where or 'off'} ({len(kernel_cache.entries())} entries)")
    if args.json:
        with open(args.json, "w") as handle:
            json.dump(seconds, handle)
    return seconds


if __name__ == "__main__":
    main()
