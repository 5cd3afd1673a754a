"""Where the time of ``Intersector.intersect`` goes on the GPU, beside the Triton kernel alone.

Each stage is jitted and timed alone on 2**20 rays (pipelined: 20 calls, one sync, median of 3 runs, as
``python -m jaxrt.bench.gpu`` times):

- ``kernel``: the kernel on a scene and a ray block packed beforehand;
- ``kernel+rays``: the kernel with the ray block packed in the call (sanitised rays to the packed block);
- ``trace``: ``pipeline.gpu_trace`` (the scene's packing, where the structure holds no packed layout, the
  rays' packing and the kernel);
- ``scene pack`` / ``ray pack``: the packing passes alone;
- ``fields``: the result fields from a found leaf (sanitising included), without the traversal;
- ``intersect``: ``jax.jit(Intersector(backend="gpu").intersect)``, what users call;
- ``intersect, eager``: ``Intersector.intersect`` called without an enclosing ``jit``;
- ``kernel+SoA rays`` / ``SoA ray pack``: as ``kernel+rays`` / ``ray pack`` with the variant
  :func:`pack_rays_soa` (origin and direction transposed first, then the block row by row; checked bit-equal);
- ``intersect, no layout``: the jitted intersect on the structure without its packed kernel layout, where the
  tree has one.

Usage: ``python scripts/intersect_profile.py [--scenes bunny,sphere,soup] [--bunny FILE.npz] [--label NAME]``.
The bunny is read from an ``.npz`` (``vertices``, ``indices``) or through ``jaxrt.bench.gpu.load_mesh_scene``.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import statistics
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

import jaxrt as rt
from jaxrt._src import fields as result_fields
from jaxrt._src.numerics import safe_reciprocal
from jaxrt._src.pipeline import gpu_trace, sanitized_rays
from jaxrt._src.scene_view import scene_view, traversal_scene
from jaxrt._src.traversal import gpu, packed
from jaxrt.bench.rays import diffuse_rays, primary_rays, shadow_rays
from jaxrt.bench.scenes import Scene, noisy_sphere, random_soup

QUERIES = (("primary", False), ("diffuse", False), ("shadow", True))


def _sheared_rows(dx, dy, dz):
    """``triangle.shear_ray`` on direction components ``(N,)`` (the same operations, so the same bits)."""
    ax, ay, az = jnp.abs(dx), jnp.abs(dy), jnp.abs(dz)
    kz = jnp.where(ax >= ay, jnp.where(ax >= az, 0, 2), jnp.where(ay >= az, 1, 2)).astype(jnp.int32)
    kx = (kz + 1) % 3
    ky = (kx + 1) % 3

    def component(k):
        return jnp.where(k == 0, dx, jnp.where(k == 1, dy, dz))

    d_z = component(kz)
    kx, ky = jnp.where(d_z < 0, ky, kx), jnp.where(d_z < 0, kx, ky)
    safe = jnp.where(d_z == 0, 1.0, d_z)
    return kx, ky, kz, component(kx) / safe, component(ky) / safe, 1.0 / safe


def pack_rays_soa(origin, direction, t_min, t_max, enabled, size):
    """A variant of ``packed.pack_rays`` (the same bits): origin and direction transposed to ``(3, N)`` in a
    pass of their own (an optimization barrier keeps XLA from fusing it into strided reads), then every row
    of the block computed elementwise."""
    n = origin.shape[0]
    o, d = lax.optimization_barrier((origin.T, direction.T))
    kx, ky, kz, sx, sy, sz = _sheared_rows(d[0], d[1], d[2])
    rows = [o[0], o[1], o[2], *(safe_reciprocal(d[i]) for i in range(3)), sx, sy, sz]
    rows += [t_min, jnp.where(enabled, t_max, -jnp.inf), kx, ky, kz, enabled]
    rows = [r.astype(jnp.float32) for r in rows] + [jnp.zeros((n,), jnp.float32)]
    return jnp.pad(jnp.stack(rows), ((0, 0), (0, size - n)))


def _pipelined_s(fn, calls: int = 20) -> float:
    runs = []
    for _ in range(3):
        start = time.perf_counter()
        out = [fn() for _ in range(calls)]
        jax.block_until_ready(out)
        runs.append((time.perf_counter() - start) / calls)
    return statistics.median(runs)


def _timed(fn) -> float:
    for _ in range(3):
        jax.block_until_ready(fn())
    return _pipelined_s(fn)


def _scene(name: str, bunny: str | None) -> Scene:
    if name == "sphere":
        return noisy_sphere(1 << 20, 0)
    if name == "soup":
        return random_soup(1 << 20, 0)
    if bunny:
        data = np.load(bunny)
        return Scene("bunny", data["vertices"], data["indices"], "Stanford bunny")
    from jaxrt.bench.gpu import load_mesh_scene

    return load_mesh_scene("bunny")


def _rays(query: str, scene: Scene, n: int):
    if query == "primary":
        return primary_rays(scene.vertices, n, eye=scene.eye, target=scene.target)
    if query == "diffuse":
        return diffuse_rays(scene.vertices, scene.indices, n)
    return shadow_rays(scene.vertices, scene.indices, n)


def _without_layout(structure):
    names = {f.name for f in dataclasses.fields(structure)}
    if "kernel_layout" not in names or structure.kernel_layout is None:
        return None
    return dataclasses.replace(structure, kernel_layout=None)


def profile(structure, ray: rt.Ray, any_hit: bool) -> dict[str, float]:
    """Seconds per call of each stage (pipelined)."""
    options = gpu.DEFAULT_OPTIONS
    n = ray.origin.shape[0]
    size = -(-n // options.rays_per_program) * options.rays_per_program
    scene, layout = traversal_scene(structure)
    config = gpu._Config(
        any_hit=any_hit, cull=0, stack=layout.stack_size, levels=0, primitive_leaves=layout.primitive_leaves,
        options=options, roots=False,
    )  # fmt: skip

    def pack_scene(s):
        sc, _ = traversal_scene(s)
        nodes = gpu.pack_nodes(options, sc.node_lower, sc.node_upper, sc.node_children, sc.node_range)
        triangles = packed.pack_triangles(sc.leaf_triangle)
        instances = packed.pack_instances(
            sc.instance_world_to_object, sc.instance_child_root, sc.instance_facing, sc.instance_mask
        )
        return nodes, triangles, instances

    def pack_ray(r):
        s = sanitized_rays(r)
        return packed.pack_rays(s.origin, s.direction, s.t_min, s.t_max, s.enabled, size)

    scene_fn = jax.jit(pack_scene)
    ray_fn = jax.jit(pack_ray)
    nodes, triangles, instances = jax.block_until_ready(scene_fn(structure))
    block = jax.block_until_ready(ray_fn(ray))
    launch = jax.jit(lambda nd, tr, ins, rb: gpu._launch(gpu.kernel_call(nd, tr, ins, rb, config))[:2])
    launch_rays = jax.jit(lambda nd, tr, ins, r: gpu._launch(gpu.kernel_call(nd, tr, ins, pack_ray(r), config))[:2])

    def trace(s, r):
        z = sanitized_rays(r)
        found = gpu_trace(s, z.origin, z.direction, z.t_min, z.t_max, z.enabled, any_hit=any_hit, cull=0)
        return found.distance, found.leaf

    trace_fn = jax.jit(trace)
    distance, leaf = jax.block_until_ready(trace_fn(structure, ray))
    intersector = rt.Intersector(backend="gpu", accept_any_intersection=any_hit)

    def fields(s, r, leaf, distance):
        z = sanitized_rays(r)
        view = scene_view(s)
        chain = jnp.zeros((leaf.shape[0], 0), jnp.int32)
        return result_fields.hit_fields(
            intersector, view, z.origin, z.direction, z.t_min, z.t_max, leaf, distance, chain
        )

    fields_fn = jax.jit(fields)
    intersect_fn = jax.jit(intersector.intersect)
    out = {
        "kernel": _timed(lambda: launch(nodes, triangles, instances, block)),
        "kernel+rays": _timed(lambda: launch_rays(nodes, triangles, instances, ray)),
        "trace": _timed(lambda: trace_fn(structure, ray)),
        "scene pack": _timed(lambda: scene_fn(structure)),
        "ray pack": _timed(lambda: ray_fn(ray)),
        "fields": _timed(lambda: fields_fn(structure, ray, leaf, distance)),
        "intersect": _timed(lambda: intersect_fn(ray, structure)),
    }
    out["intersect, eager"] = _timed(lambda: intersector.intersect(ray, structure))

    def pack_soa(r):
        s = sanitized_rays(r)
        return pack_rays_soa(s.origin, s.direction, s.t_min, s.t_max, s.enabled, size)

    launch_soa = jax.jit(lambda nd, tr, ins, r: gpu._launch(gpu.kernel_call(nd, tr, ins, pack_soa(r), config))[:2])
    soa_fn = jax.jit(pack_soa)
    out["_soa_block_equal"] = bool(
        np.array_equal(np.asarray(soa_fn(ray)).view(np.uint32), np.asarray(block).view(np.uint32))
    )
    out["kernel+SoA rays"] = _timed(lambda: launch_soa(nodes, triangles, instances, ray))
    out["SoA ray pack"] = _timed(lambda: soa_fn(ray))
    bare = _without_layout(structure)
    if bare is not None:
        out["intersect, no layout"] = _timed(lambda: intersect_fn(ray, bare))
    result = intersect_fn(ray, structure)
    digest = hashlib.sha256()
    for name in sorted(result):
        digest.update(np.asarray(result[name]).tobytes())
    out["_digest"] = digest.hexdigest()[:16]  # equal digests: bit-identical fields (compare two trees)
    if bare is not None:
        other = intersect_fn(ray, bare)
        out["_same_without_layout"] = all(
            np.array_equal(np.asarray(result[k]).view(np.uint8), np.asarray(other[k]).view(np.uint8)) for k in result
        )
    out["_check_leaf_primitive"] = bool(
        np.array_equal(
            np.asarray(result.primitive_id),
            np.where(np.asarray(leaf) >= 0, np.asarray(structure.leaf_primitive)[np.maximum(np.asarray(leaf), 0)], -1),
        )
    )
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", default="bunny,sphere,soup")
    parser.add_argument("--bunny", default=None, help="an .npz with vertices and indices")
    parser.add_argument("--rays", type=int, default=1 << 20)
    parser.add_argument("--label", default="")
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    print(f"device {jax.devices()[0]}, jax {jax.__version__}", file=sys.stderr, flush=True)
    results = {}
    for name in args.scenes.split(","):
        scene = _scene(name, args.bunny)
        structure = jax.block_until_ready(
            rt.build_primitive_structure(rt.TriangleGeometry(jnp.asarray(scene.vertices), jnp.asarray(scene.indices)))
        )
        for query, any_hit in QUERIES:
            ray = jax.block_until_ready(_rays(query, scene, args.rays).to_jaxrt())
            results[f"{name}/{query}"] = profile(structure, ray, any_hit)
            print(f"{args.label} {name}/{query}: {results[f'{name}/{query}']}", file=sys.stderr, flush=True)
    stages = [k for k in next(iter(results.values())) if not k.startswith("_")]
    print(f"\n{args.label}: microseconds per call of {args.rays} rays (pipelined), Mrays/s of kernel and intersect")
    print(
        "| scene/query | "
        + " | ".join(stages)
        + " | kernel Mrays/s | intersect Mrays/s | leaf ok, digest, same without layout |"
    )
    print("|---|" + "---|" * (len(stages) + 3))
    for key, r in results.items():
        cells = " | ".join(f"{r[s] * 1e6:.0f}" if s in r else "-" for s in stages)
        rates = f"{args.rays / r['kernel'] / 1e6:.0f} | {args.rays / r['intersect'] / 1e6:.0f}"
        check = (
            f"{r['_check_leaf_primitive']} {r['_digest']} {r.get('_same_without_layout', '-')} {r['_soa_block_equal']}"
        )
        print(f"| {key} | {cells} | {rates} | {check} |")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)


if __name__ == "__main__":
    main()
