"""Trace speed of a moving sphere against the same sphere standing still, and the growth of its node boxes.

The sphere moves by 10% of its diameter over the time range, through K evenly spaced keyframes on a
line (so the union of the keyframe boxes is the same for every K; what changes with K is the keyframe data
the leaf tests read). Primary rays from a pinhole camera, one random time per ray.

Where the GPU kernel can run (a CUDA GPU with Triton), :func:`gpu_main` traces a sphere of about a million
triangles with 2, 4 and 8 keyframes and reports, per K: the Mrays/s of the motion kernel against the static
kernel on the same rays (the kernel alone, ``traversal.gpu.trace_scene``, and the whole
``Intersector.intersect``), and the box growth: the summed surface area of the node boxes of each keyframe,
of the boxes blended at the middle of each keyframe segment, and of the union boxes, over that of the static
build. The portable traversal's speed on a slice of the rays is given for reference. Elsewhere the portable
traversal is timed as before (:func:`portable_main`): speed and the SAH cost of the union boxes and of each
keyframe's boxes over that of a static build; with ``--cpu`` the same rows for the compiled CPU traversal
(``backend="cpu"``, static and moving).

Usage::

    python -m jaxrt.bench.motion [--segments N] [--rays N] [--rounds 5] [--json PATH] [--portable | --cpu]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import time
from typing import Any

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


def moving_sphere(
    vertices: np.ndarray, indices: np.ndarray, keyframes: int, spec: rt.MotionSpec
) -> rt.PrimitiveAccelerationStructure:
    """The sphere sliding along +x by 10% of its diameter over the range, through ``keyframes`` keyframes."""
    shift = np.linspace(0.0, 0.2, keyframes)
    keys = jnp.asarray(vertices[None] + shift[:, None, None] * np.array([1.0, 0.0, 0.0], np.float32))
    return rt.build_primitive_structure(rt.MotionTriangleGeometry(keys, indices), motion=spec)


def node_area(lower: Any, upper: Any) -> float:
    """Summed surface area of the child boxes ``(..., 2, 3)`` of every node (empty children count 0)."""
    lower, upper = np.asarray(lower, np.float64), np.asarray(upper, np.float64)
    extent = upper - lower
    valid = np.all(np.isfinite(extent) & (extent >= 0), axis=-1)
    x, y, z = (np.where(valid, extent[..., i], 0.0) for i in range(3))
    return float(np.sum(2.0 * (x * y + y * z + z * x)))


def box_growth(structure: rt.PrimitiveAccelerationStructure, static_area: float) -> dict[str, float]:
    """Node surface area of a motion structure over ``static_area`` (the static build's): each keyframe's
    boxes (mean), the boxes blended at the middle of each keyframe segment (mean: what a ray at that time
    meets), and the union boxes."""
    lower, upper = np.asarray(structure.motion_node_lower), np.asarray(structure.motion_node_upper)
    keyed = np.mean([node_area(lower[k], upper[k]) for k in range(lower.shape[0])])
    middle = np.mean(
        [
            node_area(0.5 * lower[k] + 0.5 * lower[k + 1], 0.5 * upper[k] + 0.5 * upper[k + 1])
            for k in range(lower.shape[0] - 1)
        ]
    )
    union = node_area(structure.node_lower, structure.node_upper)
    return {
        "area_keyframes_vs_static": keyed / static_area,
        "area_segment_middle_vs_static": middle / static_area,
        "area_union_vs_static": union / static_area,
    }


def kernel_trace(moving: bool):
    """A jitted ``trace(structure, rays)`` through the GPU kernel alone (``traversal.gpu.trace_scene``: leaf
    and distance, no result fields); ``moving`` passes the rays' times and the triangle keyframes."""
    from jaxrt._src.pipeline import enabled_rays
    from jaxrt._src.scene_view import scene_view
    from jaxrt._src.traversal import gpu

    @jax.jit
    def trace(structure, rays: rt.Ray):
        view = scene_view(structure)
        motion = dict(time=rays.time, leaf_motion=gpu.leaf_motion(view)) if moving else {}
        n = rays.origin.shape[0]
        found = gpu.trace_scene(
            view.traversal,
            view.layout,
            rays.origin,
            rays.direction,
            jnp.broadcast_to(rays.min_distance, (n,)),
            jnp.broadcast_to(rays.max_distance, (n,)),
            enabled_rays(rays),
            jnp.broadcast_to(rays.mask, (n,)).astype(jnp.uint32),
            any_hit=False,
            cull=0,
            **motion,
        )
        return found.distance, found.leaf

    return trace


def _best(fn, rounds: int) -> float:
    """Seconds of the fastest of ``rounds`` warm calls (after one compiling call)."""
    jax.block_until_ready(fn())
    best = np.inf
    for _ in range(rounds):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - start)
    return best


def gpu_main(args: argparse.Namespace) -> dict[str, Any]:
    """The GPU kernel on a moving sphere of about ``2 segments**2`` triangles (see the module docstring)."""
    from jaxrt.bench.instancing import compiled_path

    segments = args.segments or 708
    n_rays = args.rays or 1 << 22
    vertices, indices = uv_sphere(segments)
    rays = camera_rays(n_rays)
    n = rays.shape[0]
    portable_rays = jax.tree_util.tree_map(lambda a: a[: args.portable_rays], rays)
    device = jax.devices()[0].device_kind
    print(f"{indices.shape[0]} triangles, {n} rays, {device}", flush=True)
    spec = rt.MotionSpec(0.0, 1.0)
    static = rt.build_primitive_structure(rt.TriangleGeometry(vertices, indices))
    static_area = node_area(static.node_lower, static.node_upper)
    kernel_static, kernel_moving = kernel_trace(False), kernel_trace(True)
    plain, moving = rt.Intersector(), rt.Intersector(rt.tags.primitive_motion)
    out: dict[str, Any] = {
        "device": device,
        "platform": platform.platform(),
        "triangles": int(indices.shape[0]),
        "rays": n,
        "rounds": args.rounds,
        "motion": "a translation by 10% of the sphere's diameter over [0, 1]; random ray times",
    }

    def speeds(structure, kernel, intersector, portable_intersector) -> dict[str, Any]:
        row = {
            "path": compiled_path(lambda r: intersector.intersect(r, structure).distance, rays),
            "kernel_mrays_s": n / _best(lambda: kernel(structure, rays), args.rounds) / 1e6,
            "intersect_mrays_s": n / _best(lambda: intersector.intersect(rays, structure).distance, args.rounds) / 1e6,
        }
        if portable_intersector is not None:
            seconds = _best(lambda: portable_intersector.intersect(portable_rays, structure).distance, 2)
            row["portable_mrays_s"] = portable_rays.shape[0] / seconds / 1e6
            row["portable_rays"] = portable_rays.shape[0]
        return row

    reference = args.portable_rays > 0
    base = speeds(static, kernel_static, plain, rt.Intersector(backend="portable") if reference else None)
    out["static"] = base
    print(f"static       kernel {base['kernel_mrays_s']:8.1f} Mrays/s  intersect {base['intersect_mrays_s']:8.1f}", flush=True)  # fmt: skip
    out["keyframes"] = {}
    for keyframes in (2, 4, 8):
        s = moving_sphere(vertices, indices, keyframes, spec)
        portable = (
            rt.Intersector(rt.tags.primitive_motion, backend="portable") if reference and keyframes == 2 else None
        )
        row = speeds(s, kernel_moving, moving, portable)
        row["kernel_vs_static"] = row["kernel_mrays_s"] / base["kernel_mrays_s"]
        row["intersect_vs_static"] = row["intersect_mrays_s"] / base["intersect_mrays_s"]
        row.update(box_growth(s, static_area))
        out["keyframes"][str(keyframes)] = row
        print(
            f"{keyframes} keyframes  kernel {row['kernel_mrays_s']:8.1f} Mrays/s ({row['kernel_vs_static']:.2f}x static)"
            f"  intersect {row['intersect_mrays_s']:8.1f} ({row['intersect_vs_static']:.2f}x)  node area: keyframes "
            f"{row['area_keyframes_vs_static']:.2f}x, segment middle {row['area_segment_middle_vs_static']:.2f}x, "
            f"union {row['area_union_vs_static']:.2f}x static  [{row['path']}]",
            flush=True,
        )
        del s
    if reference:
        print(
            f"portable ({args.portable_rays} rays): static {base['portable_mrays_s']:.2f} Mrays/s, 2 keyframes "
            f"{out['keyframes']['2']['portable_mrays_s']:.2f} Mrays/s"
        )
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--segments", type=int, default=None, help="UV sphere segments (224 portable, 708 GPU)")
    parser.add_argument("--rays", type=int, default=None, help="primary rays (65536 portable, 2**22 GPU)")
    parser.add_argument("--rounds", type=int, default=5, help="timed rounds (each times every structure once)")
    parser.add_argument("--portable-rays", type=int, default=1 << 16, help="GPU: rays of the portable reference (0: none)")  # fmt: skip
    parser.add_argument("--portable", action="store_true", help="time the portable traversal even on a GPU")
    parser.add_argument("--cpu", action="store_true", help="time the compiled CPU traversal (on the CPU backend)")
    parser.add_argument("--json", metavar="PATH", help="also write the numbers to PATH")
    args = parser.parse_args()
    from jaxrt._src.traversal import gpu

    if args.cpu:
        out = portable_main(args, "cpu")
    elif not args.portable and gpu.unavailable_reason(rt.Intersector(rt.tags.primitive_motion)) is None:
        out = gpu_main(args)
    else:
        out = portable_main(args)
    if args.json:
        with open(args.json, "w") as handle:
            json.dump(out, handle, indent=2, default=float)


def portable_main(args: argparse.Namespace, backend: str = "portable") -> dict[str, Any]:
    """The portable traversal (or ``backend``: ``"cpu"``) on a moving sphere of about ``2 segments**2``
    triangles."""
    args.segments = args.segments or 224
    args.rays = args.rays or 65536
    vertices, indices = uv_sphere(args.segments)
    rays = camera_rays(args.rays)
    print(f"{indices.shape[0]} triangles, {rays.shape[0]} rays, backend {jax.default_backend()}, {backend} traversal")
    spec = rt.MotionSpec(0.0, 1.0)
    plain = rt.Intersector(backend=backend)
    moving = rt.Intersector(rt.tags.primitive_motion, backend=backend)
    static = rt.build_primitive_structure(rt.TriangleGeometry(vertices, indices))
    runs = {"static": (lambda: plain.intersect(rays, static).distance, rt.sah_cost(static), None)}
    for keyframes in (2, 4, 8):
        s = moving_sphere(vertices, indices, keyframes, spec)
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
    out: dict[str, Any] = {"backend": jax.default_backend(), "triangles": int(indices.shape[0]), "rays": rays.shape[0]}
    out["traversal"] = backend
    for name, (_, sah, keyed) in runs.items():
        out[name] = {f"{backend}_mrays_s": rays.shape[0] / best[name] / 1e6, "sah": float(sah), "sah_keyframes": keyed}
        line = f"{name:11s} {rays.shape[0] / best[name] / 1e6:6.3f} Mrays/s  SAH {sah:7.2f}"
        if keyed is not None:
            line += (
                f" union, {keyed:6.2f} per keyframe (speed {base / best[name]:.2f}x static; SAH "
                f"{sah / base_sah:.2f}x union, {keyed / base_sah:.2f}x per keyframe)"
            )
        print(line)
    return out


if __name__ == "__main__":
    main()
