"""``python -m jaxrt.bench.gpu``: the GPU traversal kernel against the portable path and NVIDIA Warp, on one GPU.

For each procedural scene (the noisy closed sphere and the random soup of :mod:`jaxrt.bench.scenes`) it
measures the LBVH build (jitted, on the device) and its SAH cost, then traces three ray sets of
:mod:`jaxrt.bench.rays`: primary (camera, scanline order) and diffuse (cosine-weighted from surface points)
rays for the nearest hit, and shadow rays to a point light for any hit. It times

- ``kernel``: the Triton kernel alone on arrays packed beforehand (what a peer's query call does);
- ``trace``: the kernel with the packing of nodes, triangles and rays (``traversal.gpu.trace``);
- ``intersect``: ``Intersector.intersect`` with the result fields (what users call);
- ``portable``: ``Intersector(backend="portable")`` on the same device;

and counts the rays where the kernel and the portable path disagree (hit or miss, or the primitive). Times are
medians of warm repeats, each call followed by ``block_until_ready`` (one call per sync); ``kernel``
and Warp are also timed as ``pipelined``: several calls, then one sync, divided by the count. ``--peers`` adds
Warp's ``wp.Mesh`` (SAH and LBVH builders) with ``mesh_query_ray`` / ``mesh_query_ray_anyhit`` on the same
rays, and prints jaxrt's speed-up over each.

The SAH cost is ``(sum of internal node areas + sum of leaf areas * primitives per leaf) / root area``
(traversal and intersection cost 1 each), over the real primitives only.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import sys
import time
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

import jaxrt as rt
from jaxrt._src.intersector import _enabled, _resolve_backend
from jaxrt._src.traversal import gpu, packed
from jaxrt.bench.rays import RayBatch, diffuse_rays, primary_rays, shadow_rays
from jaxrt.bench.scenes import noisy_sphere, random_soup

__all__ = ["main", "sah_cost"]

SCENES = {"sphere": noisy_sphere, "soup": random_soup}
#: (ray set, any hit) pairs traced per scene.
QUERIES = (("primary", False), ("diffuse", False), ("shadow", True))
#: Kernel variants compared with ``--variants`` (the default options first).
VARIANTS = {
    "default": gpu.DEFAULT_OPTIONS,
    "scalar-loads": dataclasses.replace(gpu.DEFAULT_OPTIONS, vector_loads=not gpu.DEFAULT_OPTIONS.vector_loads),
    "leaf-branch": dataclasses.replace(gpu.DEFAULT_OPTIONS, leaf_branch=not gpu.DEFAULT_OPTIONS.leaf_branch),
    "fp-fusion": dataclasses.replace(gpu.DEFAULT_OPTIONS, fp_fusion=not gpu.DEFAULT_OPTIONS.fp_fusion),
    "64-rays": dataclasses.replace(gpu.DEFAULT_OPTIONS, rays_per_program=64),
}


def _log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def _median_s(fn: Callable[[], Any], repeats: int, warmup: int = 2) -> float:
    """Median seconds of ``fn()`` followed by ``block_until_ready``, after ``warmup`` calls."""
    for _ in range(warmup):
        jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def _pipelined_s(fn: Callable[[], Any], calls: int, sync: Callable[[Any], Any] = jax.block_until_ready) -> float:
    """Seconds per call of ``calls`` back-to-back calls with one sync at the end (median of 3 such runs)."""
    runs = []
    for _ in range(3):
        start = time.perf_counter()
        out = [fn() for _ in range(calls)]
        sync(out)
        runs.append((time.perf_counter() - start) / calls)
    return statistics.median(runs)


def sah_cost(structure: rt.PrimitiveAccelerationStructure) -> float:
    """SAH cost of a structure (see the module docstring), computed on the host in float64."""
    lower = np.asarray(structure.node_lower, np.float64)
    upper = np.asarray(structure.node_upper, np.float64)
    children = np.asarray(structure.node_children)

    def area(lo, hi):
        extent = np.where(lo <= hi, hi - lo, 0.0)
        return 2.0 * (
            extent[..., 0] * extent[..., 1] + extent[..., 1] * extent[..., 2] + extent[..., 2] * extent[..., 0]
        )

    child_area = area(lower, upper)  # (C-1, 2)
    root = area(lower[0].min(axis=0), upper[0].max(axis=0))
    # Every internal node but the root is the child of one node; leaves are children too.
    internal = child_area[children >= 0].sum() + root
    leaves = child_area[children < 0].sum()
    return float((internal + leaves) / root)


def _rays(name: str, scene, n: int) -> RayBatch:
    if name == "primary":
        return primary_rays(scene.vertices, n)
    if name == "diffuse":
        return diffuse_rays(scene.vertices, scene.indices, n)
    return shadow_rays(scene.vertices, scene.indices, n)


def _device_rays(batch: RayBatch) -> dict[str, jax.Array]:
    ray = batch.to_jaxrt()
    enabled = _enabled(ray)
    return dict(
        origin=ray.origin,
        direction=ray.direction,
        t_min=ray.min_distance,
        t_max=ray.max_distance,
        enabled=enabled,
    )


def _agreement(a: np.ndarray, b: np.ndarray) -> dict[str, int]:
    """Rays where two tracers disagree on hit or miss, and on the primitive where both hit (ids, -1 on a miss)."""
    return {
        "hit_miss": int(((a >= 0) != (b >= 0)).sum()),
        "primitive": int(((a >= 0) & (b >= 0) & (a != b)).sum()),
    }


def _bench_kernel(structure, rays: dict[str, jax.Array], any_hit: bool, options: gpu.KernelOptions, repeats: int):
    """Kernel-only timing on pre-packed arrays; returns (seconds, pipelined seconds, leaf array)."""
    n = rays["origin"].shape[0]
    size = -(-n // options.rays_per_program) * options.rays_per_program
    nodes = packed.pack_nodes(structure.node_lower, structure.node_upper, structure.node_children)
    triangles = packed.pack_triangles(structure.leaf_triangle)
    block = packed.pack_rays(rays["origin"], rays["direction"], rays["t_min"], rays["t_max"], rays["enabled"], size)
    launch = jax.jit(
        lambda nd, tr, rb: gpu._launch(nd, tr, rb, any_hit=any_hit, cull=0, stack=structure.max_depth, options=options)
    )
    out = jax.block_until_ready(launch(nodes, triangles, block))
    seconds = _median_s(lambda: launch(nodes, triangles, block), repeats)
    pipelined = _pipelined_s(lambda: launch(nodes, triangles, block), 20)
    return seconds, pipelined, np.asarray(out[1])[:n], np.asarray(out[2])[:n]


def _warp_tracer(scene, constructor: str):
    """A Warp mesh and its query functions, or ``None`` with a reason when Warp is missing."""
    import warp as wp

    wp.config.quiet = True
    wp.init()

    @wp.kernel
    def closest(mesh: wp.uint64, o: wp.array(dtype=wp.vec3), d: wp.array(dtype=wp.vec3), far: wp.array(dtype=float), face: wp.array(dtype=int), t: wp.array(dtype=float)):  # fmt: skip
        i = wp.tid()
        q = wp.mesh_query_ray(mesh, o[i], d[i], far[i])
        if q.result:
            face[i] = q.face
            t[i] = q.t
        else:
            face[i] = -1
            t[i] = wp.inf

    @wp.kernel
    def anyhit(mesh: wp.uint64, o: wp.array(dtype=wp.vec3), d: wp.array(dtype=wp.vec3), far: wp.array(dtype=float), hit: wp.array(dtype=int)):  # fmt: skip
        i = wp.tid()
        hit[i] = wp.where(wp.mesh_query_ray_anyhit(mesh, o[i], d[i], far[i]), 1, 0)

    points = wp.array(scene.vertices, dtype=wp.vec3)
    indices = wp.array(scene.indices.reshape(-1), dtype=wp.int32)

    def build():
        mesh = wp.Mesh(points, indices, bvh_constructor=constructor)
        wp.synchronize()
        return mesh

    return wp, build, closest, anyhit


def _warp_query(wp, kernels, mesh, batch: RayBatch, any_hit: bool, repeats: int) -> dict[str, Any]:
    """Time one Warp query over ``batch``; the result holds the faces (nearest) or hit flags (any hit)."""
    closest, anyhit = kernels
    n = len(batch)
    o = wp.array(batch.origin, dtype=wp.vec3)
    d = wp.array(batch.direction, dtype=wp.vec3)
    far = wp.array(np.where(np.isinf(batch.max_distance), np.float32(1e30), batch.max_distance), dtype=float)
    if any_hit:
        hit = wp.zeros(n, dtype=int)

        def run():
            wp.launch(anyhit, n, inputs=[mesh.id, o, d, far, hit])

    else:
        face, t = wp.zeros(n, dtype=int), wp.zeros(n, dtype=float)

        def run():
            wp.launch(closest, n, inputs=[mesh.id, o, d, far, face, t])

    def call():
        run()
        wp.synchronize()

    call()
    seconds = _median_s(call, repeats, warmup=1)
    pipelined = _pipelined_s(run, 20, sync=lambda _: wp.synchronize())
    result = (hit.numpy() > 0) if any_hit else face.numpy()
    return {"mrays_s": n / seconds / 1e6, "pipelined_mrays_s": n / pipelined / 1e6, "result": result}


def _bench_warp(scene, batches: dict[str, RayBatch], repeats: int) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for constructor in ("sah", "lbvh"):
        wp, build, closest, anyhit = _warp_tracer(scene, constructor)
        mesh = build()
        build_s = _median_s(build, max(3, repeats // 3), warmup=1)
        entry: dict[str, Any] = {"build_ms": build_s * 1e3, "build_mprims_s": scene.triangle_count / build_s / 1e6}
        for name, any_hit in QUERIES:
            entry[name] = _warp_query(wp, (closest, anyhit), mesh, batches[name], any_hit, repeats)
        out[constructor] = entry
    return out


def _bench_query(structure, batch: RayBatch, any_hit: bool, portable_rays: int, repeats: int, variants: bool):
    """The jaxrt measurements of one ray set: portable path, kernel (variants), trace and intersect."""
    n_rays = len(batch)
    q: dict[str, Any] = {"rays": n_rays, "any_hit": any_hit}
    portable = rt.Intersector(backend="portable", accept_any_intersection=any_hit)
    subset = batch.take(np.arange(min(portable_rays, n_rays))).to_jaxrt()
    portable_fn = jax.jit(portable.intersect)
    reference = jax.block_until_ready(portable_fn(subset, structure))
    seconds = _median_s(lambda: portable_fn(subset, structure), max(3, repeats // 3))
    q["portable"] = {"rays": int(subset.min_distance.shape[0]), "mrays_s": subset.min_distance.shape[0] / seconds / 1e6}
    if gpu.unavailable_reason(rt.Intersector()) is not None:
        return q
    reference_primitive = np.asarray(reference.primitive_id)
    rays = _device_rays(batch)
    for label, options in VARIANTS.items() if variants else [("default", gpu.DEFAULT_OPTIONS)]:
        s, p, leaf, visited = _bench_kernel(structure, rays, any_hit, options, repeats)
        q[f"kernel/{label}"] = {
            "mrays_s": n_rays / s / 1e6,
            "pipelined_mrays_s": n_rays / p / 1e6,
            "mismatch_vs_portable": _agreement(
                _primitive_of_leaf(structure, leaf[: len(reference_primitive)]), reference_primitive
            ),
            "visited_mean": float(visited.mean()),
            "visited_max": int(visited.max()),
        }
        if label == "default":
            q["leaf"] = leaf
    trace = jax.jit(lambda r, s: gpu.trace(s, **r, any_hit=any_hit, cull=0))
    jax.block_until_ready(trace(rays, structure))
    q["trace"] = {
        "mrays_s": n_rays / _median_s(lambda: trace(rays, structure), repeats) / 1e6,
        "pipelined_mrays_s": n_rays / _pipelined_s(lambda: trace(rays, structure), 20) / 1e6,
    }
    fast = jax.jit(rt.Intersector(backend="gpu", accept_any_intersection=any_hit).intersect)
    full = batch.to_jaxrt()
    jax.block_until_ready(fast(full, structure))
    q["intersect"] = {
        "mrays_s": n_rays / _median_s(lambda: fast(full, structure), repeats) / 1e6,
        "pipelined_mrays_s": n_rays / _pipelined_s(lambda: fast(full, structure), 20) / 1e6,
    }
    return q


def bench_scene(
    name: str, n_triangles: int, n_rays: int, portable_rays: int, repeats: int, variants: bool, peers: bool
):
    """All measurements of one scene (a JSON-ready dict; ``result`` arrays are dropped by the caller)."""
    scene = SCENES[name](n_triangles, 0)
    _log(f"{name}: {scene.description}")
    vertices, indices = jnp.asarray(scene.vertices), jnp.asarray(scene.indices)
    build = jax.jit(lambda v, i: rt.build_primitive_structure(rt.TriangleGeometry(v, i)))
    structure = jax.block_until_ready(build(vertices, indices))
    build_s = _median_s(lambda: build(vertices, indices), repeats)
    entry: dict[str, Any] = {
        "triangles": scene.triangle_count,
        "build_ms": build_s * 1e3,
        "build_mprims_s": scene.triangle_count / build_s / 1e6,
        "sah_cost": sah_cost(structure),
        "max_depth_bound": structure.max_depth,
        "queries": {},
    }
    _log(f"  build {build_s * 1e3:.2f} ms, SAH cost {entry['sah_cost']:.1f}")
    batches = {q: _rays(q, scene, n_rays) for q, _ in QUERIES}
    for query, any_hit in QUERIES:
        q = _bench_query(structure, batches[query], any_hit, portable_rays, repeats, variants)
        entry["queries"][query] = q
        rates = ", ".join(f"{k} {v['mrays_s']:.1f}" for k, v in q.items() if isinstance(v, dict) and "mrays_s" in v)
        _log(f"  {query}: {rates}")
    if peers:
        warp = _bench_warp(scene, batches, repeats)
        for w in warp.values():
            for query, any_hit in QUERIES:
                result = w[query].pop("result")
                leaf = entry["queries"][query].get("leaf")
                if leaf is not None:
                    mine = _primitive_of_leaf(structure, leaf)
                    if any_hit:
                        w[query]["mismatch_vs_kernel"] = {"hit_miss": int(((mine >= 0) != result).sum())}
                    else:
                        w[query]["mismatch_vs_kernel"] = _agreement(mine, result)
        entry["warp"] = warp
        _log("  warp: " + json.dumps({c: {k: v for k, v in w.items()} for c, w in warp.items()}, default=float))
    for q in entry["queries"].values():
        q.pop("leaf", None)
    return entry


def _primitive_of_leaf(structure, leaf: np.ndarray) -> np.ndarray:
    return np.where(leaf >= 0, np.asarray(structure.leaf_primitive)[np.maximum(leaf, 0)], -1)


def build_only(name: str, n_triangles: int, repeats: int) -> dict[str, Any]:
    """Build time and SAH cost of a (large) scene."""
    scene = SCENES[name](n_triangles, 0)
    vertices, indices = jnp.asarray(scene.vertices), jnp.asarray(scene.indices)
    build = jax.jit(lambda v, i: rt.build_primitive_structure(rt.TriangleGeometry(v, i)))
    structure = jax.block_until_ready(build(vertices, indices))
    seconds = _median_s(lambda: build(vertices, indices), repeats)
    return {
        "triangles": scene.triangle_count,
        "build_ms": seconds * 1e3,
        "build_mprims_s": scene.triangle_count / seconds / 1e6,
        "sah_cost": sah_cost(structure),
    }


def format_table(results: dict[str, Any]) -> str:
    """The summary table (Mrays/s; ratios are jaxrt's kernel over the peer)."""
    lines = [f"backend picked by Intersector(): {results['auto_backend']}", ""]
    head = "| scene | query | kernel | kernel pipelined | trace pipelined | intersect | intersect pipelined | portable | mismatches (hit/miss, prim) |"
    warp_cols = ""
    if any("warp" in s for s in results["scenes"].values()):
        warp_cols = " Warp SAH | Warp LBVH | x SAH | x LBVH |"
    lines.append(head + warp_cols)
    lines.append("|" + "---|" * (head.count("|") - 1 + warp_cols.count("|")))
    for name, s in results["scenes"].items():
        for query, q in s["queries"].items():
            k = q.get("kernel/default", {})
            mm = k.get("mismatch_vs_portable", {})
            row = (
                f"| {name} | {query}{' (any)' if q['any_hit'] else ''} | {k.get('mrays_s', float('nan')):.0f} | "
                f"{k.get('pipelined_mrays_s', float('nan')):.0f} | {q.get('trace', {}).get('pipelined_mrays_s', float('nan')):.0f} | "
                f"{q.get('intersect', {}).get('mrays_s', float('nan')):.0f} | "
                f"{q.get('intersect', {}).get('pipelined_mrays_s', float('nan')):.0f} | {q['portable']['mrays_s']:.1f} | "
                f"{mm.get('hit_miss', '-')}, {mm.get('primitive', '-')} |"
            )
            if "warp" in s:
                ws, wl = s["warp"]["sah"][query], s["warp"]["lbvh"][query]
                kp = k.get("pipelined_mrays_s", float("nan"))
                row += f" {ws['pipelined_mrays_s']:.0f} | {wl['pipelined_mrays_s']:.0f} | {kp / ws['pipelined_mrays_s']:.2f} | {kp / wl['pipelined_mrays_s']:.2f} |"
            lines.append(row)
    lines += [
        "",
        "| scene | triangles | LBVH build ms | Mprims/s | SAH cost | Warp SAH build ms | Warp LBVH build ms |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, s in {**results["scenes"], **results.get("builds", {})}.items():
        warp = s.get("warp", {})
        lines.append(
            f"| {name} | {s['triangles']:,} | {s['build_ms']:.2f} | {s['build_mprims_s']:.0f} | {s['sah_cost']:.1f} | "
            f"{warp.get('sah', {}).get('build_ms', float('nan')):.1f} | {warp.get('lbvh', {}).get('build_ms', float('nan')):.2f} |"
        )
    variant_rows = []
    for name, s in results["scenes"].items():
        for query, q in s["queries"].items():
            cells = [
                f"{q[k]['pipelined_mrays_s']:.0f} ({q[k]['mismatch_vs_portable']['hit_miss']}/{q[k]['mismatch_vs_portable']['primitive']})"
                for k in q
                if k.startswith("kernel/")
            ]
            if len(cells) > 1:
                variant_rows.append(f"| {name} | {query} | " + " | ".join(cells) + " |")
    if variant_rows:
        labels = [k for k in next(iter(results["scenes"].values()))["queries"]["primary"] if k.startswith("kernel/")]
        lines += [
            "",
            "kernel variants, pipelined Mrays/s (mismatches hit-miss/primitive vs portable):",
            "| scene | query | " + " | ".join(labels) + " |",
            "|---|---|" + "---|" * len(labels),
        ]
        lines += variant_rows
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Run the GPU bench; prints the table last and returns the results."""
    parser = argparse.ArgumentParser(prog="python -m jaxrt.bench.gpu", description=__doc__.split("\n\n")[0])
    parser.add_argument("--peers", action="store_true", help="also run NVIDIA Warp (SAH and LBVH) on the same rays")
    parser.add_argument("--json", metavar="FILE", help="write all numbers to FILE")
    parser.add_argument("--triangles", type=int, default=1 << 20, help="triangles per scene (default 2**20)")
    parser.add_argument("--rays", type=int, default=1 << 20, help="rays per ray set (default 2**20)")
    parser.add_argument("--portable-rays", type=int, default=1 << 20, help="rays traced by the portable path")
    parser.add_argument("--repeats", type=int, default=10, help="timed repeats (median)")
    parser.add_argument("--scenes", default="sphere,soup", help="comma-separated scene names")
    parser.add_argument("--variants", action="store_true", help="also time kernel code-generation variants")
    parser.add_argument("--build-sizes", default="", help="extra build-only sizes, e.g. 10000000 (comma-separated)")
    args = parser.parse_args(argv)
    results: dict[str, Any] = {
        "device": str(jax.devices()[0]),
        "jax": jax.__version__,
        "auto_backend": _resolve_backend(rt.Intersector()),
        "kernel_unavailable_reason": gpu.unavailable_reason(rt.Intersector()),
        "default_options": dataclasses.asdict(gpu.DEFAULT_OPTIONS),
        "scenes": {},
        "builds": {},
    }
    if results["kernel_unavailable_reason"]:
        _log(f"GPU kernel not run: {results['kernel_unavailable_reason']}")

    def save():
        if args.json:
            with open(args.json, "w") as f:
                json.dump(results, f, indent=1, default=float)

    for name in args.scenes.split(","):
        results["scenes"][name] = bench_scene(
            name, args.triangles, args.rays, args.portable_rays, args.repeats, args.variants, args.peers
        )
        save()
    for size in filter(None, args.build_sizes.split(",")):
        for name in args.scenes.split(","):
            results["builds"][f"{name}-{int(size) / 1e6:g}M"] = build_only(name, int(size), args.repeats)
            save()
    print(format_table(results))
    return results


if __name__ == "__main__":
    main()
