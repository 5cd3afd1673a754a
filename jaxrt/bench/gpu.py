"""``python -m jaxrt.bench.gpu``: the GPU traversal kernel against the portable path, NVIDIA Warp and Embree.

For each scene (the noisy closed sphere and the random soup of :mod:`jaxrt.bench.scenes`, and the real meshes:
the Stanford bunny and dragon, also subdivided to about 1M triangles, and the Sponza and Sibenik interiors) it
builds one tree per build quality (``--quality fast,high``: the LBVH and the clustering build) on the device,
reports each build's time and SAH cost, then traces three ray sets of :mod:`jaxrt.bench.rays`: primary
(camera, scanline order) and diffuse (cosine-weighted from surface points) rays for the nearest hit, and
shadow rays to a point light for any hit. It times

- ``kernel``: the Triton kernel alone on the structure's rows packed beforehand and on the ray arrays as given
  (``KernelOptions.fused_rays``; what a peer's query call does), per tree; ``--variants ray-block`` adds the
  kernel on a ray block packed beforehand, and ``intersect`` with the block packed in the call;
- ``trace``: the kernel with the packing of nodes, triangles and rays (``pipeline.gpu_trace``);
- ``intersect``: ``Intersector.intersect`` with the result fields (what users call);
- ``portable``: ``Intersector(backend="portable")`` on the same device (``--portable-rays 0`` skips it);

and counts the rays where the kernel and the portable path disagree (hit or miss, or the primitive). Times are
medians of warm repeats, each call followed by ``block_until_ready`` (one call per sync); ``kernel``
and Warp are also timed as ``pipelined``: several calls, then one sync, divided by the count. ``--peers`` adds
Warp's ``wp.Mesh`` (SAH and LBVH builders) with ``mesh_query_ray`` / ``mesh_query_ray_anyhit`` on the same
rays, and Embree (through embreex, one host thread) where embreex is installed, and prints jaxrt's speed-up
over each.

The SAH cost is ``(sum of internal node areas + sum of leaf areas * primitives per leaf) / root area``
(traversal and intersection cost 1 each), over the real primitives only.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

import jaxrt as rt
from jaxrt._src import pipeline
from jaxrt._src.pipeline import enabled_rays as _enabled
from jaxrt._src.pipeline import resolve_backend as _resolve_backend
from jaxrt._src.traversal import gpu, packed
from jaxrt.bench.peers import Embree, embree_unavailable_reason
from jaxrt.bench.rays import RayBatch, diffuse_rays, primary_rays, shadow_rays
from jaxrt.bench.scenes import Scene, default_data_dir, noisy_sphere, random_soup

__all__ = ["main", "sah_cost", "subdivide", "load_mesh_scene"]

SCENES = {"sphere": noisy_sphere, "soup": random_soup}
#: Real meshes: ``(file, folder under the shared data folder, description, eye, target)``. The file is looked
#: up in ``--meshes`` first (a flat folder), then in the shared data folder. ``NAME-1M`` is ``NAME`` with every
#: triangle split into 16 (two midpoint subdivisions).
MESHES = {
    "bunny": ("bun_zipper.binary.ply", "stanford-bunny", "Stanford bunny", None, None),
    "dragon": ("dragon_vrip_res3.obj.gz", "stanford-dragon-decimated", "Stanford dragon (vrip res3)", None, None),
    # Interiors: the camera stands inside and looks along the nave (z is up).
    "sponza": ("sponza.derived.ply", "sponza-dabrovic-3ds", "Dabrovic Sponza", (-14.0, 0.0, 3.0), (14.0, 0.0, 5.0)),
    "sibenik": ("sibenik.derived.ply", "sibenik-3ds", "Sibenik cathedral", (-250.0, 0.0, 150.0), (900.0, 0.0, 250.0)),
}
#: Build qualities of ``rt.build_primitive_structure``.
QUALITIES = ("fast", "high")
#: (ray set, any hit) pairs traced per scene.
QUERIES = (("primary", False), ("diffuse", False), ("shadow", True))
#: Kernel variants compared with ``--variants`` (the default options first).
VARIANTS = {
    label: options
    for label, options in {
        "default": gpu.DEFAULT_OPTIONS,
        "scalar-loads": dataclasses.replace(gpu.DEFAULT_OPTIONS, vector_loads=not gpu.DEFAULT_OPTIONS.vector_loads),
        "64-rays": dataclasses.replace(gpu.DEFAULT_OPTIONS, rays_per_program=64),
        "ray-block": dataclasses.replace(gpu.DEFAULT_OPTIONS, fused_rays=not gpu.DEFAULT_OPTIONS.fused_rays),
        "binary": dataclasses.replace(gpu.DEFAULT_OPTIONS, node_width=2),
        "wide-leaf-4": dataclasses.replace(gpu.DEFAULT_OPTIONS, node_width=4, leaf_size=4),
        "wide-leaf-2": dataclasses.replace(gpu.DEFAULT_OPTIONS, node_width=4, leaf_size=2),
        "wide-leaf-1": dataclasses.replace(gpu.DEFAULT_OPTIONS, node_width=4, leaf_size=1),
    }.items()
    if label == "default" or options != gpu.DEFAULT_OPTIONS
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


def subdivide(vertices: np.ndarray, indices: np.ndarray, levels: int) -> tuple[np.ndarray, np.ndarray]:
    """Split every triangle into four at its edge midpoints, ``levels`` times (a soup: no shared vertices).

    A midpoint is ``(a + b) / 2`` in float32, the same for both triangles of a shared edge, so a closed mesh
    stays closed.
    """
    tri = vertices[indices]
    for _ in range(levels):
        a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
        ab, bc, ca = (a + b) / np.float32(2), (b + c) / np.float32(2), (c + a) / np.float32(2)
        tri = np.concatenate([np.stack(t, 1) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    return tri.reshape(-1, 3).astype(np.float32), np.arange(3 * len(tri), dtype=np.int32).reshape(-1, 3)


def load_mesh_scene(name: str, mesh_dir: str | None = None) -> Scene:
    """A real mesh of :data:`MESHES` (``NAME-1M``: subdivided twice), read with ``jaxrt.io.load_mesh``."""
    from jaxrt.io import load_mesh

    base, _, suffix = name.partition("-")
    file, folder, description, eye, target = MESHES[base]
    candidates = [Path(mesh_dir) / file] if mesh_dir else []
    data = default_data_dir()
    if data is not None:
        candidates.append(data / folder / file)
    path = next((c for c in candidates if c.is_file()), None)
    if path is None:
        raise FileNotFoundError(f"bench.gpu: mesh {file!r} not found in {[str(c) for c in candidates]}")
    vertices, indices = load_mesh(path)
    if suffix:
        vertices, indices = subdivide(vertices, indices, 2)
        description += ", subdivided twice"
    return Scene(name, vertices, indices, f"{description}, {len(indices):,} triangles", eye, target)


def _load_scene(name: str, n_triangles: int, mesh_dir: str | None) -> Scene:
    if name in SCENES:
        return SCENES[name](n_triangles, 0)
    return load_mesh_scene(name, mesh_dir)


def _rays(name: str, scene: Scene, n: int) -> RayBatch:
    if name == "primary":
        return primary_rays(scene.vertices, n, eye=scene.eye, target=scene.target)
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


def kernel_launch(
    structure, rays: dict[str, jax.Array], any_hit: bool, options: gpu.KernelOptions
) -> Callable[[], tuple]:
    """The kernel alone on the structure's pre-packed scene arrays: a function of no arguments that launches it
    (jitted) and returns its outputs. With ``options.fused_rays`` (binary nodes) the kernel reads the ray arrays
    as given, as a Warp query does; else it reads a ray block packed beforehand."""
    from jaxrt._src.scene_view import traversal_scene

    n = rays["origin"].shape[0]
    size = -(-n // options.rays_per_program) * options.rays_per_program
    scene, layout = traversal_scene(structure)
    nodes = gpu.pack_nodes(options, scene.node_lower, scene.node_upper, scene.node_children, scene.node_range)
    triangles = packed.pack_triangles(scene.leaf_triangle)
    instances = packed.pack_instances(
        scene.instance_world_to_object, scene.instance_child_root, scene.instance_facing, scene.instance_mask
    )
    config = gpu._Config(
        any_hit=any_hit, cull=0, stack=layout.stack_size, levels=0, primitive_leaves=layout.primitive_leaves,
        options=options, roots=False,
    )  # fmt: skip
    arrays = tuple(rays[k] for k in ("origin", "direction", "t_min", "t_max", "enabled"))
    if options.fused_rays and options.node_width == 2:
        block = arrays
        ray_input = lambda rb: gpu.FusedRays(*rb, size)  # noqa: E731
    else:
        block = packed.pack_rays(*arrays, size)
        ray_input = lambda rb: rb  # noqa: E731
    launch = jax.jit(lambda nd, tr, ins, rb: gpu._launch(gpu.kernel_call(nd, tr, ins, ray_input(rb), config)))
    return lambda: launch(nodes, triangles, instances, block)


def _bench_kernel(structure, rays: dict[str, jax.Array], any_hit: bool, options: gpu.KernelOptions, repeats: int):
    """Kernel-only timing (:func:`kernel_launch`); returns (seconds, pipelined seconds, leaf array, nodes
    visited)."""
    n = rays["origin"].shape[0]
    launch = kernel_launch(structure, rays, any_hit, options)
    out = jax.block_until_ready(launch())
    seconds = _median_s(launch, repeats)
    pipelined = _pipelined_s(launch, 20)
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


def _bench_query(
    structures: dict, batch: RayBatch, any_hit: bool, portable_rays: int, repeats: int, variants: str | None
):
    """The jaxrt measurements of one ray set: portable path, kernel on every tree (variants on the first),
    trace and intersect on the first tree."""
    n_rays = len(batch)
    first = next(iter(structures))
    structure = structures[first]
    q: dict[str, Any] = {"rays": n_rays, "any_hit": any_hit, "kernel": {}, "leaf": {}}
    reference_primitive = None
    if portable_rays:
        portable = rt.Intersector(backend="portable", accept_any_intersection=any_hit)
        subset = batch.take(np.arange(min(portable_rays, n_rays))).to_jaxrt()
        portable_fn = jax.jit(portable.intersect)
        reference = jax.block_until_ready(portable_fn(subset, structure))
        seconds = _median_s(lambda: portable_fn(subset, structure), max(3, repeats // 3))
        count = subset.min_distance.shape[0]
        q["portable"] = {"rays": int(count), "tree": first, "mrays_s": count / seconds / 1e6}
        reference_primitive = np.asarray(reference.primitive_id)
    if gpu.unavailable_reason(rt.Intersector()) is not None:
        return q
    rays = _device_rays(batch)
    for quality, tree in structures.items():
        runs = [("default", gpu.DEFAULT_OPTIONS)]
        if variants and quality == first:
            runs = [
                (k, v) for k, v in VARIANTS.items() if k == "default" or variants == "all" or k in variants.split(",")
            ]
        q["kernel"][quality] = {}
        for label, options in runs:
            s, p, leaf, visited = _bench_kernel(tree, rays, any_hit, options, repeats)
            k = {
                "mrays_s": n_rays / s / 1e6,
                "pipelined_mrays_s": n_rays / p / 1e6,
                "visited_mean": float(visited.mean()),
                "visited_max": int(visited.max()),
            }
            if reference_primitive is not None:
                mine = _primitive_of_leaf(tree, leaf[: len(reference_primitive)])
                k["mismatch_vs_portable"] = _agreement(mine, reference_primitive)
            q["kernel"][quality][label] = k
            if label == "default":
                q["leaf"][quality] = leaf
    trace = jax.jit(lambda r, s: pipeline.gpu_trace(s, **r, any_hit=any_hit, cull=0))
    jax.block_until_ready(trace(rays, structure))
    q["trace"] = {
        "tree": first,
        "mrays_s": n_rays / _median_s(lambda: trace(rays, structure), repeats) / 1e6,
        "pipelined_mrays_s": n_rays / _pipelined_s(lambda: trace(rays, structure), 20) / 1e6,
    }
    fast = jax.jit(rt.Intersector(backend="gpu", accept_any_intersection=any_hit).intersect)
    full = batch.to_jaxrt()
    jax.block_until_ready(fast(full, structure))
    q["intersect"] = {
        "tree": first,
        "mrays_s": n_rays / _median_s(lambda: fast(full, structure), repeats) / 1e6,
        "pipelined_mrays_s": n_rays / _pipelined_s(lambda: fast(full, structure), 20) / 1e6,
    }
    if variants:  # intersect with the other ray input (a packed ray block, or the fused rays)
        other = VARIANTS["ray-block"]
        with _default_kernel_options(other):
            slow = jax.jit(rt.Intersector(backend="gpu", accept_any_intersection=any_hit).intersect)
            same = jax.block_until_ready(slow(full, structure))
            q["intersect_ray_block" if not other.fused_rays else "intersect_fused_rays"] = {
                "tree": first,
                "pipelined_mrays_s": n_rays / _pipelined_s(lambda: slow(full, structure), 20) / 1e6,
                "bitwise_equal": all(
                    np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True)
                    for a, b in zip(jax.tree.leaves(same), jax.tree.leaves(fast(full, structure)), strict=True)
                ),
            }
    return q


@contextlib.contextmanager
def _default_kernel_options(options: gpu.KernelOptions):
    """Trace ``Intersector.intersect`` with other default kernel options (their traces dropped before and after)."""
    saved = gpu.DEFAULT_OPTIONS

    def drop():
        gpu._traversal.cache_clear()
        pipeline._intersect_jit.clear_cache()
        pipeline._intersect_chunks.clear_cache()

    gpu.DEFAULT_OPTIONS = options
    drop()
    try:
        yield
    finally:
        gpu.DEFAULT_OPTIONS = saved
        drop()


def _build_fn(quality: str):
    return jax.jit(lambda v, i: rt.build_primitive_structure(rt.TriangleGeometry(v, i), quality=quality))


def _bench_builds(scene: Scene, qualities: tuple[str, ...], repeats: int) -> tuple[dict, dict]:
    """One structure per build quality, with build time and SAH cost."""
    vertices, indices = jnp.asarray(scene.vertices), jnp.asarray(scene.indices)
    structures, builds = {}, {}
    for quality in qualities:
        build = _build_fn(quality)
        structures[quality] = jax.block_until_ready(build(vertices, indices))
        seconds = _median_s(lambda build=build: build(vertices, indices), repeats)
        builds[quality] = {
            "build_ms": seconds * 1e3,
            "build_mprims_s": scene.triangle_count / seconds / 1e6,
            "sah_cost": sah_cost(structures[quality]),
        }
        _log(f"  {quality} build {seconds * 1e3:.2f} ms, SAH cost {builds[quality]['sah_cost']:.1f}")
    return structures, builds


def _bench_embree(scene: Scene, batches: dict[str, RayBatch], leaves: dict, structure) -> dict[str, Any]:
    """Embree on the same rays (one host thread), with its disagreements with the kernel."""
    tracer = Embree(scene.vertices, scene.indices)
    start = time.perf_counter()
    tracer.build()
    out: dict[str, Any] = {"build_ms": (time.perf_counter() - start) * 1e3, "version": Embree.version()}
    for query, any_hit in QUERIES:
        batch = batches[query]
        start = time.perf_counter()
        result = tracer.any_hit(batch) if any_hit else tracer.closest(batch).primitive
        entry: dict[str, Any] = {"mrays_s": len(batch) / (time.perf_counter() - start) / 1e6}
        leaf = leaves.get(query)
        if leaf is not None:
            mine = _primitive_of_leaf(structure, leaf)
            entry["mismatch_vs_kernel"] = (
                {"hit_miss": int(((mine >= 0) != result).sum())} if any_hit else _agreement(mine, result)
            )
        out[query] = entry
    return out


def bench_scene(
    name: str,
    n_triangles: int,
    n_rays: int,
    portable_rays: int,
    repeats: int,
    variants: str | None,
    peers: bool,
    qualities: tuple[str, ...] = QUALITIES,
    mesh_dir: str | None = None,
):
    """All measurements of one scene (a JSON-ready dict; ``leaf`` arrays are dropped before it returns)."""
    scene = _load_scene(name, n_triangles, mesh_dir)
    _log(f"{name}: {scene.description}")
    structures, builds = _bench_builds(scene, qualities, repeats)
    first = qualities[0]
    entry: dict[str, Any] = {
        "triangles": scene.triangle_count,
        "builds": builds,
        "max_depth_bound": structures[first].max_depth,
        "queries": {},
    }
    batches = {q: _rays(q, scene, n_rays) for q, _ in QUERIES}
    for query, any_hit in QUERIES:
        q = _bench_query(structures, batches[query], any_hit, portable_rays, repeats, variants)
        entry["queries"][query] = q
        rates = (
            ", ".join(f"kernel[{t}] {k['default']['pipelined_mrays_s']:.0f}" for t, k in q["kernel"].items())
            or f"portable {q.get('portable', {}).get('mrays_s', float('nan')):.1f}"
        )
        _log(f"  {query}: {rates}")
    leaves = {query: q["leaf"].get(first) for query, q in entry["queries"].items()}
    if peers:
        try:
            import warp  # noqa: F401
        except ImportError as error:
            _log(f"  Warp not run: {error}")
        else:
            warp_results = _bench_warp(scene, batches, repeats)
            for w in warp_results.values():
                for query, any_hit in QUERIES:
                    result = w[query].pop("result")
                    if leaves[query] is not None:
                        mine = _primitive_of_leaf(structures[first], leaves[query])
                        w[query]["mismatch_vs_kernel"] = (
                            {"hit_miss": int(((mine >= 0) != result).sum())} if any_hit else _agreement(mine, result)
                        )
            entry["warp"] = warp_results
            _log("  warp: " + json.dumps(warp_results, default=float))
        reason = embree_unavailable_reason()
        if reason is None:
            entry["embree"] = _bench_embree(scene, batches, leaves, structures[first])
            _log("  embree: " + json.dumps(entry["embree"], default=float))
        else:
            _log(
                f"  Embree not run here ({reason}); its numbers come from the CPU bench, python -m jaxrt.bench --peers"
            )
    for q in entry["queries"].values():
        q.pop("leaf", None)
    return entry


def _primitive_of_leaf(structure, leaf: np.ndarray) -> np.ndarray:
    return np.where(leaf >= 0, np.asarray(structure.leaf_primitive)[np.maximum(leaf, 0)], -1)


def build_only(name: str, n_triangles: int, repeats: int, qualities: tuple[str, ...] = QUALITIES) -> dict[str, Any]:
    """Build times and SAH costs of a (large) scene."""
    scene = SCENES[name](n_triangles, 0)
    _, builds = _bench_builds(scene, qualities, repeats)
    return {"triangles": scene.triangle_count, "builds": builds}


def huge_batch(n_rays: int, n_triangles: int = 1 << 20) -> dict[str, Any]:
    """Trace ``n_rays`` primary rays (2**20 camera rays tiled) on the noisy sphere in one ``intersect`` call.

    Checks that every tile's result equals that of the 2**20 rays traced alone, and reports the time of the
    second call and the device's peak memory (where the backend reports it), to set the documented cap.
    """
    scene = noisy_sphere(n_triangles, 0)
    structure = rt.build_primitive_structure(rt.TriangleGeometry(scene.vertices, scene.indices))
    base = primary_rays(scene.vertices, 1 << 20)
    intersector = rt.Intersector()
    alone = np.asarray(intersector.intersect(base.to_jaxrt(), structure).primitive_id)
    tiles = -(-n_rays // len(base))
    origin = jnp.tile(jnp.asarray(base.origin), (tiles, 1))[:n_rays]
    direction = jnp.tile(jnp.asarray(base.direction), (tiles, 1))[:n_rays]
    rays = jax.block_until_ready(rt.Ray(origin, direction))
    del origin, direction
    jax.block_until_ready(intersector.intersect(rays, structure).primitive_id)
    start = time.perf_counter()
    primitive = jax.block_until_ready(intersector.intersect(rays, structure).primitive_id)
    seconds = time.perf_counter() - start
    full = (n_rays // len(base)) * len(base)
    tiled = np.asarray(primitive[:full]).reshape(-1, len(base))
    stats = jax.devices()[0].memory_stats() or {}
    out = {
        "rays": n_rays,
        "seconds": seconds,
        "mrays_s": n_rays / seconds / 1e6,
        "tiles_equal_to_one_call": bool((tiled == alone).all()),
        "rest_equal": bool((np.asarray(primitive[full:]) == alone[: n_rays - full]).all()),
        "peak_bytes": stats.get("peak_bytes_in_use"),
        "bytes_limit": stats.get("bytes_limit"),
    }
    _log("huge batch: " + json.dumps(out))
    return out


def _nan(x: Any) -> float:
    return float("nan") if x is None else float(x)


def format_table(results: dict[str, Any]) -> str:
    """The summary tables (Mrays/s; ratios are jaxrt's pipelined kernel on each tree over Warp's SAH query)."""
    qualities = results.get("qualities", list(QUALITIES))
    lines = [f"backend picked by Intersector(): {results['auto_backend']}", ""]
    tree_cols = "".join(f" kernel {t} |" for t in qualities)
    ratio_cols = "".join(f" {t} / Warp SAH |" for t in qualities)
    head = (
        f"| scene | query |{tree_cols} intersect | portable | mismatches vs portable | Warp SAH | Warp LBVH |"
        f"{ratio_cols} {qualities[0]} / Warp LBVH | Embree (1 thread) |"
    )
    lines += [head, "|" + "---|" * (head.count("|") - 1)]
    for name, s in results["scenes"].items():
        for query, q in s["queries"].items():
            kernels = q.get("kernel", {})
            rate = {t: _nan(kernels.get(t, {}).get("default", {}).get("pipelined_mrays_s")) for t in qualities}
            mm = ", ".join(
                f"{t} {k['default']['mismatch_vs_portable']['hit_miss']}/{k['default']['mismatch_vs_portable']['primitive']}"
                for t, k in kernels.items()
                if "mismatch_vs_portable" in k.get("default", {})
            )
            warp = s.get("warp", {})
            ws = _nan(warp.get("sah", {}).get(query, {}).get("pipelined_mrays_s"))
            wl = _nan(warp.get("lbvh", {}).get(query, {}).get("pipelined_mrays_s"))
            embree = _nan(s.get("embree", {}).get(query, {}).get("mrays_s"))
            row = f"| {name} | {query}{' (any)' if q['any_hit'] else ''} |"
            row += "".join(f" {rate[t]:.0f} |" for t in qualities)
            row += f" {_nan(q.get('intersect', {}).get('pipelined_mrays_s')):.0f} |"
            row += f" {_nan(q.get('portable', {}).get('mrays_s')):.1f} | {mm or '-'} | {ws:.0f} | {wl:.0f} |"
            row += "".join(f" {rate[t] / ws:.2f} |" for t in qualities)
            row += f" {rate[qualities[0]] / wl:.2f} | {embree:.1f} |"
            lines.append(row)
    build_cols = "".join(f" {t} ms | {t} Mprims/s | {t} SAH |" for t in qualities)
    head = f"| scene | triangles |{build_cols} Warp SAH ms | Warp LBVH ms | Embree ms |"
    lines += ["", head, "|" + "---|" * (head.count("|") - 1)]
    for name, s in {**results["scenes"], **results.get("builds", {})}.items():
        row = f"| {name} | {s['triangles']:,} |"
        for t in qualities:
            b = s["builds"].get(t, {})
            row += f" {_nan(b.get('build_ms')):.2f} | {_nan(b.get('build_mprims_s')):.0f} | {_nan(b.get('sah_cost')):.1f} |"
        warp = s.get("warp", {})
        row += f" {_nan(warp.get('sah', {}).get('build_ms')):.1f} | {_nan(warp.get('lbvh', {}).get('build_ms')):.2f} |"
        row += f" {_nan(s.get('embree', {}).get('build_ms')):.1f} |"
        lines.append(row)
    variant_rows, labels = [], []
    for name, s in results["scenes"].items():
        for query, q in s["queries"].items():
            runs = dict(q.get("kernel", {}).get(qualities[0], {}))
            for key in ("intersect", "intersect_ray_block", "intersect_fused_rays"):
                if len(runs) > 1 and key in q:
                    runs[key.replace("_", " ")] = q[key]
            if len(runs) > 1:
                labels = list(runs)
                cells = [
                    f"{r['pipelined_mrays_s']:.0f}"
                    + (
                        f" ({r['mismatch_vs_portable']['hit_miss']}/{r['mismatch_vs_portable']['primitive']})"
                        if "mismatch_vs_portable" in r
                        else ""
                    )
                    + (
                        {True: " (fields bit-equal)", False: " (fields differ)"}[r["bitwise_equal"]]
                        if "bitwise_equal" in r
                        else ""
                    )
                    for r in runs.values()
                ]
                variant_rows.append(f"| {name} | {query} | " + " | ".join(cells) + " |")
    if variant_rows:
        lines += [
            "",
            f"kernel variants on the {qualities[0]} tree, pipelined Mrays/s (mismatches hit-miss/primitive vs portable):",
            "| scene | query | " + " | ".join(labels) + " |",
            "|---|---|" + "---|" * len(labels),
        ]
        lines += variant_rows
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Run the GPU bench; prints the table last and returns the results."""
    parser = argparse.ArgumentParser(prog="python -m jaxrt.bench.gpu", description=__doc__.split("\n\n")[0])
    parser.add_argument("--peers", action="store_true", help="also run NVIDIA Warp (SAH and LBVH) and Embree")
    parser.add_argument("--json", metavar="FILE", help="write all numbers to FILE")
    parser.add_argument("--triangles", type=int, default=1 << 20, help="triangles per procedural scene (2**20)")
    parser.add_argument("--rays", type=int, default=1 << 20, help="rays per ray set (default 2**20)")
    parser.add_argument("--portable-rays", type=int, default=1 << 20, help="rays traced by the portable path (0: none)")
    parser.add_argument("--repeats", type=int, default=10, help="timed repeats (median)")
    parser.add_argument(
        "--scenes",
        default="sphere,soup",
        help=f"comma-separated scenes: {', '.join(SCENES)}, {', '.join(MESHES)} and NAME-1M for a subdivided mesh",
    )
    parser.add_argument("--meshes", metavar="DIR", help="folder holding the mesh files (else the shared data folder)")
    parser.add_argument(
        "--quality", default=",".join(QUALITIES), help="build qualities to trace, first is the reference"
    )
    parser.add_argument(
        "--variants",
        nargs="?",
        const="all",
        help=f"also time kernel code-generation variants: all, or some of {', '.join(VARIANTS)} (comma-separated)",
    )
    parser.add_argument("--build-sizes", default="", help="extra build-only sizes, e.g. 10000000 (comma-separated)")
    parser.add_argument("--build-scenes", default="sphere,soup", help="procedural scenes of --build-sizes")
    parser.add_argument("--huge-rays", type=int, default=0, help="also trace this many rays in one intersect call")
    args = parser.parse_args(argv)
    qualities = tuple(args.quality.split(","))
    results: dict[str, Any] = {
        "device": str(jax.devices()[0]),
        "jax": jax.__version__,
        "auto_backend": _resolve_backend(rt.Intersector()),
        "kernel_unavailable_reason": gpu.unavailable_reason(rt.Intersector()),
        "default_options": dataclasses.asdict(gpu.DEFAULT_OPTIONS),
        "qualities": list(qualities),
        "scenes": {},
        "builds": {},
    }
    if results["kernel_unavailable_reason"]:
        _log(f"GPU kernel not run: {results['kernel_unavailable_reason']}")

    def save():
        if args.json:
            with open(args.json, "w") as f:
                json.dump(results, f, indent=1, default=float)

    for name in filter(None, args.scenes.split(",")):
        results["scenes"][name] = bench_scene(
            name,
            args.triangles,
            args.rays,
            args.portable_rays,
            args.repeats,
            args.variants,
            args.peers,
            qualities,
            args.meshes,
        )
        save()
    for size in filter(None, args.build_sizes.split(",")):
        for name in filter(None, args.build_scenes.split(",")):
            results["builds"][f"{name}-{int(size) / 1e6:g}M"] = build_only(name, int(size), args.repeats, qualities)
            save()
    if args.huge_rays:
        results["huge_batch"] = huge_batch(args.huge_rays, args.triangles)
        save()
    print(format_table(results))
    return results


if __name__ == "__main__":
    main()
