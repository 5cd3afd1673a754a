"""Portable traversal speed of a moving sphere against the same sphere standing still, and the growth of its
node boxes: the SAH cost of the union boxes (over all keyframes) and of each keyframe's boxes (what the
traversal blends at a ray's time), over that of a static build.

The sphere moves by 10% of its diameter over the time range, through K evenly spaced keyframes on a
line (so the union of the keyframe boxes is the same for every K; what changes with K is the keyframe data
the leaf tests read). Primary rays from a pinhole camera, one random time per ray.

Usage::

    python -m jaxrt.bench.motion [--segments 224] [--rays 65536] [--rounds 5]
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxrt as rt


def uv_sphere(segments: int) -> tuple[np.ndarray, np.ndarray]:
    """A unit UV sphere with about ``2 segments**2`` triangles: ``(vertices, indices)``."""
    theta = np.linspace(0.0, np.pi, segments)
    phi = np.linspace(0.0, 2.0 * np.pi, segments + 1)[:-1]
    t, p = np.meshgrid(theta, phi, indexing="ij")
    vertices = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(segments - 1), np.arange(segments), indexing="ij")
    a = i * segments + j
    b = i * segments + (j + 1) % segments
    c, d = a + segments, b + segments
    indices = np.concatenate([np.stack([a, b, d], -1), np.stack([a, d, c], -1)]).reshape(-1, 3)
    return vertices.astype(np.float32), indices.astype(np.int32)


def camera_rays(n: int, seed: int = 0) -> rt.Ray:
    side = int(np.sqrt(n))
    y, x = np.meshgrid(np.linspace(1.3, -1.3, side), np.linspace(-1.3, 1.3, side), indexing="ij")
    direction = np.stack([x, y, np.full_like(x, -3.0)], -1).reshape(-1, 3).astype(np.float32) / 3.0
    origin = np.broadcast_to(np.array([0.1, 0.0, 3.0], np.float32), direction.shape)
    times = np.random.default_rng(seed).uniform(0.0, 1.0, direction.shape[0]).astype(np.float32)
    return rt.Ray(origin, direction, time=times)


def keyframe_tree(structure: rt.PrimitiveAccelerationStructure, k: int) -> rt.PrimitiveAccelerationStructure:
    """The structure with keyframe ``k``'s node boxes in place of the union boxes."""
    return dataclasses.replace(
        structure, node_lower=structure.motion_node_lower[k], node_upper=structure.motion_node_upper[k]
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--segments", type=int, default=224)
    parser.add_argument("--rays", type=int, default=65536)
    parser.add_argument("--rounds", type=int, default=5, help="timed rounds (each times every structure once)")
    args = parser.parse_args()
    vertices, indices = uv_sphere(args.segments)
    rays = camera_rays(args.rays)
    print(f"{indices.shape[0]} triangles, {rays.shape[0]} rays, backend {jax.default_backend()}")
    spec = rt.MotionSpec(0.0, 1.0)
    plain = rt.Intersector(backend="portable")
    moving = rt.Intersector(rt.tags.primitive_motion, backend="portable")
    static = rt.build_primitive_structure(rt.TriangleGeometry(vertices, indices))
    runs = {"static": (lambda: plain.intersect(rays, static).distance, rt.sah_cost(static), None)}
    for keyframes in (2, 4, 8):
        shift = np.linspace(0.0, 0.2, keyframes)  # 10% of the diameter (2) over the range
        keys = jnp.asarray(vertices[None] + shift[:, None, None] * np.array([1.0, 0.0, 0.0], np.float32))
        s = rt.build_primitive_structure(rt.MotionTriangleGeometry(keys, indices), motion=spec)
        # The boxes a ray at a keyframe's time meets: that keyframe's node boxes (the traversal blends them).
        keyed = float(np.mean([rt.sah_cost(keyframe_tree(s, k)) for k in range(keyframes)]))
        runs[f"{keyframes} keyframes"] = (lambda s=s: moving.intersect(rays, s).distance, rt.sah_cost(s), keyed)
        if keyframes == 2:  # the same structure traced with its union boxes only (no blended node boxes)
            union = dataclasses.replace(s, motion_node_lower=None, motion_node_upper=None)
            runs["2, union"] = (lambda u=union: moving.intersect(rays, u).distance, rt.sah_cost(s), rt.sah_cost(s))
    for fn, _, _ in runs.values():
        jax.block_until_ready(fn())  # compile
    best = dict.fromkeys(runs, np.inf)
    for _ in range(args.rounds):  # interleaved, so that a busy machine slows every run alike
        for name, (fn, _, _) in runs.items():
            start = time.perf_counter()
            jax.block_until_ready(fn())
            best[name] = min(best[name], time.perf_counter() - start)
    base, base_sah = best["static"], runs["static"][1]
    for name, (_, sah, keyed) in runs.items():
        line = f"{name:11s} {rays.shape[0] / best[name] / 1e6:6.3f} Mrays/s  SAH {sah:7.2f}"
        if keyed is not None:
            line += (
                f" union, {keyed:6.2f} per keyframe (speed {base / best[name]:.2f}x static; SAH "
                f"{sah / base_sah:.2f}x union, {keyed / base_sah:.2f}x per keyframe)"
            )
        print(line)


if __name__ == "__main__":
    main()
