"""``python -m jaxrt.bench.instancing``: multi-level instancing against the flattened scene, and many scenes at once.

A procedural island in the spirit of Disney's Moana scene: a terrain mesh; a tree made of a trunk mesh and
many instances of a leaf mesh; a few grove variants, each an instance structure of trees; and the island,
instancing the terrain and many groves. The same trees are traced three ways:

==============  =================================================================================
scene           structure
==============  =================================================================================
``flattened``   every triangle baked into one primitive structure (no instancing)
``2 levels``    forest -> tree -> {trunk, leaf}: every tree placed by its world transform
``3 levels``    island -> grove -> tree -> {trunk, leaf}: groves reused across the island
==============  =================================================================================

Reported: stored bytes of each structure (the arrays of its pytree), build time (all builds of a structure,
warm median), trace speed (Mrays/s, closest hit, pinhole camera over the island) and how many rays agree
with the flattened trace. Each structure is traced by ``Intersector.intersect`` (the ``path`` column says
whether its compiled program launches the GPU kernel or runs the portable traversal) and, where the kernel
can run, by the kernel alone (``traversal.gpu.trace_scene`` on the structure's scene view: the leaf, its
distance and the instance chain, no result fields), with the mean nodes visited per ray and the kernel's
scratch memory (stack and per-level rays). Batched scenes: ``jax.vmap`` of the builds, of ``intersect`` and of
the kernel over many small random forests, each traced by its own depth camera (scenes x rays per second).

Flags: ``--quick`` (small sizes, one repeat), ``--json PATH``, ``--repeats``, ``--rays``, ``--trees``,
``--leaves``, ``--terrain``, ``--scenes`` (batched scenes), ``--max-flat`` (skip the flattened build above this
many triangles), ``--instance-quality high,fast`` (also build the instance levels with the LBVH over instances). Only jax and numpy are needed.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

import jaxrt as rt
from jaxrt.bench.timing import timed

__all__ = ["main", "island", "tree_meshes", "batched_forests", "kernel_tracer", "compiled_path"]

_DEFAULTS = dict(
    terrain=512, trunk=16, leaves=512, grove_trees=64, groves=256, variants=4, rays=1 << 20, scenes=1024,
    scene_rays=64, repeats=3, max_flat=40_000_000,
)  # fmt: skip
_QUICK = dict(
    terrain=48, trunk=6, leaves=24, grove_trees=12, groves=16, variants=2, rays=1 << 14, scenes=64, scene_rays=16,
    repeats=1, max_flat=40_000_000,
)  # fmt: skip
ISLAND = 100.0  # half-width of the terrain, metres


# --- procedural meshes -------------------------------------------------------------------------------------------


def terrain(n: int, seed: int = 0) -> np.ndarray:
    """``(2 n^2, 3, 3)`` triangles of an ``n x n`` heightfield over ``[-ISLAND, ISLAND]^2`` (y up)."""
    x = np.linspace(-ISLAND, ISLAND, n + 1)
    gx, gz = np.meshgrid(x, x, indexing="ij")
    y = _height(gx, gz, seed)
    p = np.stack([gx, y, gz], -1)
    a, b, c, d = p[:-1, :-1], p[1:, :-1], p[:-1, 1:], p[1:, 1:]
    tri = np.concatenate([np.stack([a, c, b], -2), np.stack([b, c, d], -2)]).reshape(-1, 3, 3)
    return tri.astype(np.float32)


def _height(x, z, seed: int = 0):
    rng = np.random.default_rng(seed)
    phase = rng.uniform(0, 2 * np.pi, 4)
    return (
        4.0 * np.sin(x / 23.0 + phase[0]) * np.cos(z / 31.0 + phase[1])
        + 1.5 * np.sin(x / 7.0 + phase[2]) * np.sin(z / 9.0 + phase[3])
        - 0.0008 * (x**2 + z**2)
    )


def tree_meshes(segments: int) -> tuple[np.ndarray, np.ndarray]:
    """A trunk (a tapered cylinder, ``2 * segments * segments // 2`` triangles) and a leaf (4 triangles)."""
    rings = max(2, segments // 2)
    angle = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    height = np.linspace(0, 2.5, rings + 1)
    radius = 0.18 * (1 - 0.5 * height / height[-1])
    ring = np.stack(
        [
            radius[:, None] * np.cos(angle),
            np.broadcast_to(height[:, None], (rings + 1, segments)),
            radius[:, None] * np.sin(angle),
        ],
        -1,
    )
    a, b = ring[:-1], np.roll(ring[:-1], -1, axis=1)
    c, d = ring[1:], np.roll(ring[1:], -1, axis=1)
    trunk = np.concatenate([np.stack([a, c, b], -2), np.stack([b, c, d], -2)]).reshape(-1, 3, 3)
    leaf = np.array(
        [
            [[0, 0, 0], [0.12, 0.02, 0.15], [0, 0.04, 0.35]],
            [[0, 0, 0], [0, 0.04, 0.35], [-0.12, 0.02, 0.15]],
            [[0, 0.04, 0.35], [0.1, 0.03, 0.5], [0, 0.02, 0.6]],
            [[0, 0.04, 0.35], [0, 0.02, 0.6], [-0.1, 0.03, 0.5]],
        ]
    )
    return trunk.astype(np.float32), leaf.astype(np.float32)


def _rotation_y(angle):
    c, s = np.cos(angle), np.sin(angle)
    zero, one = np.zeros_like(angle), np.ones_like(angle)
    return np.stack([np.stack([c, zero, s], -1), np.stack([zero, one, zero], -1), np.stack([-s, zero, c], -1)], -2)


def _random_rotations(rng, n):
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def _affine(linear, translation) -> np.ndarray:
    return np.concatenate([linear, translation[..., None]], axis=-1)


def _leaf_transforms(rng, leaves: int) -> np.ndarray:
    """Leaves in a crown: random directions and scales around a point above the trunk."""
    direction = rng.normal(size=(leaves, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    position = np.array([0.0, 2.6, 0.0]) + direction * rng.uniform(0.3, 1.1, (leaves, 1)) * [1.0, 0.8, 1.0]
    linear = _random_rotations(rng, leaves) * rng.uniform(0.7, 1.3, (leaves, 1, 1))
    return _affine(linear, position).astype(np.float32)


def _compose(outer: np.ndarray, inner: np.ndarray) -> np.ndarray:
    """``outer o inner`` for 3x4 affine transforms (float64)."""
    linear = outer[..., :3] @ inner[..., :3]
    translation = np.einsum("...ij,...j->...i", outer[..., :3], inner[..., 3]) + outer[..., 3]
    return _affine(linear, translation)


def island(sizes: dict[str, int], seed: int = 0) -> dict[str, Any]:
    """The procedural island (see the module docstring) as numpy arrays: meshes and the three transform sets.

    Returns:
      ``terrain``, ``trunk``, ``leaf`` ``(T, 3, 3)``; ``leaf_transforms`` ``(L, 3, 4)``; ``grove_trees``
      ``(variants, K, 3, 4)`` tree transforms within each grove variant; ``grove_index`` ``(G,)`` and
      ``grove_transforms`` ``(G, 3, 4)``; ``tree_world`` ``(G * K, 3, 4)``: every tree's world transform.
    """
    rng = np.random.default_rng(seed)
    ground = terrain(sizes["terrain"], seed)
    trunk, leaf = tree_meshes(sizes["trunk"])
    leaves = _leaf_transforms(rng, sizes["leaves"])
    k, v, g = sizes["grove_trees"], sizes["variants"], sizes["groves"]
    radius = 6.0
    local = rng.uniform(-radius, radius, (v, k, 2))
    tree_linear = _rotation_y(rng.uniform(0, 2 * np.pi, (v, k))) * rng.uniform(0.7, 1.4, (v, k, 1, 1))
    grove_trees = _affine(tree_linear, np.stack([local[..., 0], np.zeros((v, k)), local[..., 1]], -1))
    centre = rng.uniform(-0.85 * ISLAND, 0.85 * ISLAND, (g, 2))
    grove_index = rng.integers(0, v, g).astype(np.int32)
    grove_linear = _rotation_y(rng.uniform(0, 2 * np.pi, g))
    grove_transforms = _affine(
        grove_linear, np.stack([centre[:, 0], _height(centre[:, 0], centre[:, 1], seed), centre[:, 1]], -1)
    )
    tree_world = _compose(grove_transforms[:, None], grove_trees[grove_index]).reshape(-1, 3, 4)
    return dict(
        terrain=ground,
        trunk=trunk,
        leaf=leaf,
        leaf_transforms=leaves,
        grove_trees=grove_trees.astype(np.float32),
        grove_index=grove_index,
        grove_transforms=grove_transforms.astype(np.float32),
        tree_world=tree_world.astype(np.float32),
    )


def _flat_triangles(scene: dict[str, Any]) -> np.ndarray:
    """Every triangle of the island in world space (float32): terrain, then each tree's trunk and leaves."""
    leaves = _apply(scene["leaf_transforms"][:, None], scene["leaf"][None])  # (L, 4, 3, 3) tree space
    tree = np.concatenate([scene["trunk"], leaves.reshape(-1, 3, 3)])
    world = _apply(scene["tree_world"][:, None], tree[None])
    return np.concatenate([scene["terrain"], world.reshape(-1, 3, 3).astype(np.float32)])


def _apply(transform, triangles):
    return np.einsum("...ij,...kj->...ki", transform[..., :3], triangles) + transform[..., None, :, 3]


# --- structures -----------------------------------------------------------------------------------------------


def _mesh(triangles: np.ndarray):
    return rt.build_primitive_structure(rt.TriangleGeometry(triangles.reshape(-1, 3)))


def _instances(index, transforms):
    return rt.Instances(np.asarray(index, np.int32), np.asarray(transforms, np.float32))


def _build_two_levels(scene, meshes, quality: str = "high"):
    ground, trunk, leaf = meshes
    eye = np.eye(3, 4, dtype=np.float32)[None]
    tree = rt.build_instance_structure(
        [trunk, leaf],
        _instances([0] + [1] * len(scene["leaf_transforms"]), np.concatenate([eye, scene["leaf_transforms"]])),
        quality=quality,
    )
    trees = scene["tree_world"]
    return rt.build_instance_structure(
        [ground, tree], _instances([0] + [1] * len(trees), np.concatenate([eye, trees])), quality=quality
    )


def _build_three_levels(scene, meshes, quality: str = "high"):
    ground, trunk, leaf = meshes
    eye = np.eye(3, 4, dtype=np.float32)[None]
    tree = rt.build_instance_structure(
        [trunk, leaf],
        _instances([0] + [1] * len(scene["leaf_transforms"]), np.concatenate([eye, scene["leaf_transforms"]])),
        quality=quality,
    )
    groves = [
        rt.build_instance_structure([tree], _instances(np.zeros(len(v), np.int32), v), quality=quality)
        for v in scene["grove_trees"]
    ]
    index = np.concatenate([[0], 1 + scene["grove_index"]])
    return rt.build_instance_structure(
        [ground, *groves], _instances(index, np.concatenate([eye, scene["grove_transforms"]])), quality=quality
    )


def nbytes(tree: Any) -> int:
    """Bytes of every array in a pytree (each shared array once)."""
    seen, total = set(), 0
    for leaf in jax.tree_util.tree_leaves(tree):
        if id(leaf) not in seen and hasattr(leaf, "nbytes"):
            seen.add(id(leaf))
            total += int(leaf.nbytes)
    return total


def camera_rays(count: int) -> rt.Ray:
    """A pinhole camera above the island's edge looking across it (``count`` rays, a square image)."""
    side = max(1, int(round(count**0.5)))
    u, v = np.meshgrid(np.linspace(-1, 1, side), np.linspace(-0.6, 0.6, side), indexing="xy")
    eye = np.array([0.0, 40.0, -1.3 * ISLAND])
    forward = np.array([0.0, -0.35, 1.0])
    forward /= np.linalg.norm(forward)
    right = np.cross([0.0, 1.0, 0.0], forward)
    right /= np.linalg.norm(right)
    up = np.cross(forward, right)
    direction = (forward + 0.7 * (u[..., None] * right + v[..., None] * up)).reshape(-1, 3)
    return rt.Ray(np.broadcast_to(eye, direction.shape).astype(np.float32), direction.astype(np.float32))


# --- batched scenes ---------------------------------------------------------------------------------------------


def batched_forests(scenes: int, trees: int, seed: int = 1) -> tuple[Any, Any, Any]:
    """``scenes`` small random forests of equal shapes: per-scene ground, tree meshes and tree placements.

    Returns:
      ``(ground, crown, instances)``: stacked :class:`~jaxrt.TriangleGeometry` pytrees (a ground quad pair and
      a box-shaped crown of 12 triangles per scene) and stacked :class:`~jaxrt.Instances` (``trees`` crowns
      and the ground, per scene), ready for ``jax.vmap`` of the builds.
    """
    rng = np.random.default_rng(seed)
    ground = np.array(
        [[[-10, 0, -10], [-10, 0, 10], [10, 0, -10]], [[10, 0, -10], [-10, 0, 10], [10, 0, 10]]], np.float32
    )
    grounds = np.broadcast_to(ground, (scenes, 2, 3, 3)) + rng.normal(0, 0.2, (scenes, 2, 3, 3)).astype(np.float32) * [
        0,
        1,
        0,
    ]
    corner = np.array([[x, y, z] for x in (-1, 1) for y in (0, 2) for z in (-1, 1)], np.float32) * 0.5
    faces = np.array(
        [
            [0, 1, 3],
            [0, 3, 2],
            [4, 6, 7],
            [4, 7, 5],
            [0, 4, 5],
            [0, 5, 1],
            [2, 3, 7],
            [2, 7, 6],
            [0, 2, 6],
            [0, 6, 4],
            [1, 5, 7],
            [1, 7, 3],
        ]
    )
    crowns = corner[faces][None] * rng.uniform(0.6, 1.6, (scenes, 1, 1, 3)).astype(np.float32)
    linear = _rotation_y(rng.uniform(0, 2 * np.pi, (scenes, trees))) * rng.uniform(0.5, 1.5, (scenes, trees, 1, 1))
    position = np.concatenate(
        [rng.uniform(-8, 8, (scenes, trees, 1)), np.zeros((scenes, trees, 1)), rng.uniform(-8, 8, (scenes, trees, 1))],
        -1,
    )
    transform = np.concatenate([np.tile(np.eye(3, 4), (scenes, 1, 1, 1)), _affine(linear, position)], axis=1).astype(
        np.float32
    )
    index = np.concatenate([np.zeros((scenes, 1)), np.ones((scenes, trees))], axis=1).astype(np.int32)
    stack = lambda *xs: jnp.stack(xs)  # noqa: E731
    ground_geometry = jax.tree.map(stack, *[rt.TriangleGeometry(g.reshape(-1, 3)) for g in grounds])
    crown_geometry = jax.tree.map(stack, *[rt.TriangleGeometry(c.reshape(-1, 3)) for c in crowns])
    instances = jax.tree.map(stack, *[rt.Instances(index[s], transform[s]) for s in range(scenes)])
    return ground_geometry, crown_geometry, instances


def depth_camera_rays(scenes: int, side: int, seed: int = 2) -> rt.Ray:
    """One ``side x side`` depth camera per scene, each at its own random pose above the ground."""
    rng = np.random.default_rng(seed)
    u, v = np.meshgrid(np.linspace(-0.5, 0.5, side), np.linspace(-0.5, 0.5, side), indexing="xy")
    angle = rng.uniform(0, 2 * np.pi, scenes)
    eye = np.stack([12 * np.cos(angle), rng.uniform(3, 8, scenes), 12 * np.sin(angle)], -1)
    forward = -eye / np.linalg.norm(eye, axis=1, keepdims=True)
    right = np.cross(np.array([0.0, 1.0, 0.0]), forward)
    right /= np.linalg.norm(right, axis=1, keepdims=True)
    up = np.cross(forward, right)
    direction = (
        forward[:, None, None] + u[None, ..., None] * right[:, None, None] + v[None, ..., None] * up[:, None, None]
    )
    origin = np.broadcast_to(eye[:, None, None], direction.shape)
    return rt.Ray(origin.reshape(scenes, -1, 3).astype(np.float32), direction.reshape(scenes, -1, 3).astype(np.float32))


# --- the GPU kernel ---------------------------------------------------------------------------------------------


def compiled_path(fn: Any, *args: Any) -> str:
    """``"kernel"`` when the program of ``fn(*args)`` launches the GPU kernel, else ``"portable"``."""
    return "kernel" if "triton_kernel_call" in str(jax.make_jaxpr(fn)(*args)) else "portable"


def kernel_tracer(any_hit: bool = False) -> Any:
    """``trace(structure, rays)`` through ``traversal.gpu.trace_scene`` (rays of any batch shape, flattened), or
    ``None`` where the kernel cannot run (no GPU, or no Triton)."""
    from jaxrt._src.scene_view import traversal_scene
    from jaxrt._src.traversal import gpu

    if gpu.unavailable_reason(rt.Intersector(rt.tags.instancing)) is not None:
        return None

    def trace(structure, rays: rt.Ray):
        scene, layout = traversal_scene(structure)
        flat = lambda a: a.reshape(-1, *a.shape[rays.min_distance.ndim :])  # noqa: E731
        origin, direction = flat(rays.origin), flat(rays.direction)
        t_min, t_max = flat(jnp.broadcast_to(rays.min_distance, rays.shape)), flat(rays.max_distance)
        mask = flat(jnp.broadcast_to(rays.mask, rays.shape)).astype(jnp.uint32)
        enabled = jnp.any(direction != 0, axis=-1) & (t_min <= t_max) & (mask != 0)
        return gpu.trace_scene(scene, layout, origin, direction, t_min, t_max, enabled, mask, any_hit=any_hit, cull=0)

    return trace


def kernel_scratch_bytes(structure: Any, rays: int) -> int:
    """Bytes of the kernel's scratch buffers for ``rays`` rays (stack, per-level rays and instance chains)."""
    from jaxrt._src.scene_view import traversal_scene
    from jaxrt._src.traversal import gpu

    _, layout = traversal_scene(structure)
    lanes = gpu.DEFAULT_OPTIONS.rays_per_program
    programs = max(1, min(-(-rays // lanes), gpu.MAX_PROGRAMS))
    per_lane = layout.stack_size + (8 * (layout.levels + 1) if layout.levels else 0)
    return 4 * (programs * lanes * per_lane + layout.levels * rays)


def _launches(fn: Any, *args: Any) -> int:
    """Kernel launches in the compiled program of ``fn(*args)`` (custom calls in its HLO)."""
    flat, tree = jax.tree_util.tree_flatten(args)
    lowered = jax.jit(lambda *leaves: fn(*jax.tree_util.tree_unflatten(tree, leaves))).lower(*flat)
    return lowered.as_text().count("custom_call @triton_kernel_call")


def program_sweep(kernel: Any, structures: dict[str, Any], rays: rt.Ray, batched: tuple, counts, repeats: int):
    """Kernel speed and scratch memory for several caps on the programs per launch (``gpu.MAX_PROGRAMS``)."""
    from jaxrt._src.traversal import gpu

    n_rays = int(np.prod(rays.shape))
    default, out = gpu.MAX_PROGRAMS, {}
    try:
        for count in counts:
            gpu.MAX_PROGRAMS = count
            gpu._traversal.cache_clear()
            jax.clear_caches()  # compiled traces captured the previous cap
            row = {}
            for name, structure in structures.items():
                timing, _ = timed(lambda s=structure: jax.jit(kernel)(s, rays), repeats)
                row[name] = {
                    "mrays_s": n_rays / timing.median_s / 1e6,
                    "scratch_bytes": kernel_scratch_bytes(structure, n_rays),
                }
            batch_fn = jax.jit(jax.vmap(kernel))
            timing, _ = timed(lambda f=batch_fn: f(*batched), repeats)
            scene_rays = int(np.prod(batched[1].shape))
            row["batched_scene_rays_per_s"] = scene_rays / timing.median_s
            out[count] = row
    finally:
        gpu.MAX_PROGRAMS = default
        gpu._traversal.cache_clear()
    return out


def _agreement(hit: Any, distance: Any, reference: Any) -> float:
    """Fraction of rays whose hit or miss, and distance where both hit, match the reference ``intersect``."""
    want = reference.type != 0
    same = hit == want
    close = jnp.abs(distance - reference.distance) <= 1e-3 * jnp.maximum(1.0, reference.distance)
    return float(jnp.mean(same & (close | ~(hit & want))))


# --- the run ----------------------------------------------------------------------------------------------------


def _machine() -> dict[str, Any]:
    device = jax.devices()[0]
    return {
        "backend": jax.default_backend(),
        "device_kind": device.device_kind,
        "device_count": jax.device_count(),
        "jax_version": jax.__version__,
        "python": platform.python_version(),
        "cpu_count": os.cpu_count(),
        "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
    }


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m jaxrt.bench.instancing",
        description="Multi-level instancing against the flattened scene, and many scenes at once (jax.vmap).",
    )
    parser.add_argument("--quick", action="store_true", help="small sizes and one repeat: a smoke test")
    parser.add_argument("--json", metavar="PATH", help="also write every number and the machine info to PATH")
    parser.add_argument("--repeats", type=int, help=f"warm calls per measurement (default {_DEFAULTS['repeats']})")
    parser.add_argument("--rays", type=int, help=f"camera rays over the island (default {_DEFAULTS['rays']:,})")
    parser.add_argument("--terrain", type=int, help=f"terrain grid side (default {_DEFAULTS['terrain']})")
    parser.add_argument("--leaves", type=int, help=f"leaf instances per tree (default {_DEFAULTS['leaves']})")
    parser.add_argument("--groves", type=int, help=f"grove instances on the island (default {_DEFAULTS['groves']})")
    parser.add_argument("--grove-trees", type=int, help=f"trees per grove (default {_DEFAULTS['grove_trees']})")
    parser.add_argument("--scenes", type=int, help=f"batched scenes (default {_DEFAULTS['scenes']})")
    parser.add_argument("--max-flat", type=int, help="skip the flattened structure above this many triangles")
    parser.add_argument(
        "--instance-quality",
        default="high",
        help="instance tree qualities to build, comma-separated (high: SAH, fast: LBVH); the first is unsuffixed",
    )
    parser.add_argument(
        "--programs", help="also time the kernel with these caps on programs per launch (e.g. 4096,8192)"
    )
    return parser


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run the benchmark, print its tables and return every number.

    Args:
      argv: command-line arguments (``sys.argv[1:]`` when ``None``); see ``--help``.

    Returns:
      ``{"machine", "config", "scene", "results", "batched"}``: triangle counts, and per structure its bytes,
      build timing, trace timing with ``mrays_s``, and agreement with the flattened trace; ``batched`` holds
      the vmapped build and trace timings and ``scene_rays_per_s``.

    Examples:
      >>> from jaxrt.bench import instancing
      >>> out = instancing.main(["--quick"])  # doctest: +SKIP
    """
    args = _parser().parse_args(argv)
    sizes = dict(_QUICK if args.quick else _DEFAULTS)
    for name in sizes:
        value = getattr(args, name, None)
        if value is not None:
            sizes[name] = value
    repeats = sizes["repeats"]
    machine = _machine()
    start = time.perf_counter()

    scene = island(sizes)
    tree_triangles = scene["trunk"].shape[0] + scene["leaf"].shape[0] * sizes["leaves"]
    trees = sizes["groves"] * sizes["grove_trees"]
    virtual = scene["terrain"].shape[0] + trees * tree_triangles
    stored = scene["terrain"].shape[0] + scene["trunk"].shape[0] + scene["leaf"].shape[0]
    info = {
        "virtual_triangles": int(virtual),
        "stored_triangles": int(stored),
        "trees": int(trees),
        "tree_triangles": int(tree_triangles),
        "terrain_triangles": int(scene["terrain"].shape[0]),
    }
    rays = camera_rays(sizes["rays"])
    n_rays = int(np.prod(rays.shape))
    results: dict[str, dict[str, Any]] = {}

    def build_meshes():
        return tuple(_mesh(scene[k]) for k in ("terrain", "trunk", "leaf"))

    qualities = args.instance_quality.split(",")
    builders = {}
    for quality in qualities:
        suffix = "" if quality == qualities[0] else f" ({quality} instance trees)"
        builders[f"2 levels{suffix}"] = (lambda q=quality: _build_two_levels(scene, build_meshes(), q), 2)
        builders[f"3 levels{suffix}"] = (lambda q=quality: _build_three_levels(scene, build_meshes(), q), 3)
    flat = reference = None
    kernel = kernel_tracer()
    kernel_fn = None if kernel is None else jax.jit(kernel)

    def kernel_entry(structure, base: dict[str, Any]) -> dict[str, Any]:
        timing, found = timed(lambda: kernel_fn(structure, rays), repeats)
        entry = dict(
            base, trace=timing.as_dict(n_rays), path="kernel", scratch_bytes=kernel_scratch_bytes(structure, n_rays)
        )
        hit = found.leaf >= 0
        entry["hit_fraction"] = float(jnp.mean(hit))
        entry["nodes_visited_mean"] = float(jnp.mean(found.nodes_visited))
        if reference is not None:
            entry["agree_with_flattened"] = _agreement(hit, found.distance.reshape(reference.distance.shape), reference)
        return entry

    if virtual <= sizes["max_flat"]:
        triangles = _flat_triangles(scene)
        geometry = rt.TriangleGeometry(jnp.asarray(triangles.reshape(-1, 3)))
        build_timing, flat = timed(lambda: rt.build_primitive_structure(geometry), repeats)
        backends = ["auto"] if machine["backend"] == "cpu" else ["auto", "portable"]
        for backend in backends:
            intersector = rt.Intersector(backend=backend)
            trace_timing, hit = timed(lambda it=intersector: it.intersect(rays, flat), repeats)
            name = "flattened" if backend == "auto" else "flattened (portable)"
            results[name] = {
                "bytes": nbytes(flat),
                "build": build_timing.as_dict(),
                "trace": trace_timing.as_dict(n_rays),
                "hit_fraction": float(jnp.mean(hit.type != 0)),
                "path": compiled_path(intersector.intersect, rays, flat),
            }
            if backend == "auto":
                reference = hit
        if kernel_fn is not None:
            results["flattened (kernel)"] = kernel_entry(flat, {"bytes": nbytes(flat), "build": build_timing.as_dict()})
    built = {}
    for name, (build, levels) in builders.items():
        build_timing, structure = timed(build, repeats)
        built[name] = structure
        intersector = rt.Intersector(rt.tags.instancing, rt.tags.max_levels(levels))
        trace_timing, hit = timed(lambda it=intersector, s=structure: it.intersect(rays, s), repeats)
        entry = {
            "bytes": nbytes(structure),
            "build": build_timing.as_dict(),
            "trace": trace_timing.as_dict(n_rays),
            "hit_fraction": float(jnp.mean(hit.type != 0)),
            "path": compiled_path(intersector.intersect, rays, structure),
        }
        if reference is not None:
            entry["agree_with_flattened"] = _agreement(hit.type != 0, hit.distance, reference)
        results[name] = entry
        if kernel_fn is not None:
            results[f"{name} (kernel)"] = kernel_entry(structure, {"bytes": entry["bytes"], "build": entry["build"]})

    # Many scenes at once: vmapped builds and a vmapped intersect over (rays, structure) pairs.
    scenes, side = sizes["scenes"], sizes["scene_rays"]
    ground, crown, instances = batched_forests(scenes, trees=31)
    camera = depth_camera_rays(scenes, side)

    @jax.jit
    def build_batch(ground, crown, instances):
        grounds = jax.vmap(rt.build_primitive_structure)(ground)
        crowns = jax.vmap(rt.build_primitive_structure)(crown)
        return jax.vmap(lambda g, c, i: rt.build_instance_structure([g, c], i))(grounds, crowns, instances)

    depth = rt.Intersector(rt.tags.instancing)
    batch_build, batch = timed(lambda: build_batch(ground, crown, instances), repeats)
    batch_intersect = jax.jit(jax.vmap(depth.intersect))
    batch_trace, batch_hit = timed(lambda: batch_intersect(camera, batch), repeats)
    scene_rays = scenes * side * side
    batched = {
        "scenes": scenes,
        "rays_per_scene": side * side,
        "triangles_per_scene": 2 + 31 * 12,
        "build": batch_build.as_dict(scenes, unit="mscenes_s"),
        "trace": batch_trace.as_dict(scene_rays),
        "scene_rays_per_s": scene_rays / batch_trace.median_s,
        "hit_fraction": float(jnp.mean(batch_hit.type != 0)),
        "path": compiled_path(jax.vmap(depth.intersect), camera, batch),
    }
    if kernel is not None:
        batch_kernel = jax.jit(jax.vmap(kernel))
        kernel_timing, found = timed(lambda: batch_kernel(batch, camera), repeats)
        hit = found.leaf >= 0
        same = (hit == (batch_hit.type != 0)) & (~hit | (jnp.abs(found.distance - batch_hit.distance) <= 1e-4))
        batched["kernel"] = {
            "trace": kernel_timing.as_dict(scene_rays),
            "scene_rays_per_s": scene_rays / kernel_timing.median_s,
            "hit_fraction": float(jnp.mean(hit)),
            "agree_with_intersect": float(jnp.mean(same)),
            "launches": _launches(jax.vmap(kernel), batch, camera),
        }
        if args.programs:
            counts = [int(p) for p in args.programs.split(",")]
            batched["kernel"]["program_sweep"] = program_sweep(kernel, built, rays, (batch, camera), counts, repeats)

    config = dict(sizes, rays=n_rays, quick=bool(args.quick), instance_quality=qualities)
    out = {"machine": machine, "config": config, "scene": info, "results": results, "batched": batched}
    out["wall_s"] = time.perf_counter() - start
    _print(out)
    if args.json:
        with open(args.json, "w") as handle:
            json.dump(out, handle, indent=2, default=float)
    return out


def _print(out: dict[str, Any]) -> None:
    machine, info, results, batched = out["machine"], out["scene"], out["results"], out["batched"]
    load = machine["load_average"]
    print(
        f"jaxrt instancing bench on {machine['backend']} ({machine['device_kind']}), jax {machine['jax_version']}, "
        f"{machine['cpu_count']} CPUs" + (f", 1-min load {load[0]:.1f}" if load else "")
    )
    print(
        f"island: {info['virtual_triangles']:,} virtual triangles ({info['trees']:,} trees of {info['tree_triangles']:,}, "
        f"terrain {info['terrain_triangles']:,}), {info['stored_triangles']:,} stored; {out['config']['rays']:,} camera rays"
    )
    print(
        f"  {'structure':22s} {'path':>8s} {'MB':>9s} {'build ms':>9s} {'trace ms':>9s} {'Mrays/s':>8s} {'hit':>6s} "
        f"{'agree':>6s} {'visited':>7s} {'scratch MB':>10s} {'compile s':>9s}"
    )
    for name, entry in results.items():
        agree = entry.get("agree_with_flattened")
        visited = entry.get("nodes_visited_mean")
        scratch = entry.get("scratch_bytes")
        print(
            f"  {name:22s} {entry.get('path', '-'):>8s} {entry['bytes'] / 1e6:9.2f} {entry['build']['median_s'] * 1e3:9.1f} "
            f"{entry['trace']['median_s'] * 1e3:9.1f} {entry['trace']['mrays_s']:8.3f} {entry['hit_fraction']:6.3f} "
            f"{'-' if agree is None else f'{agree:.4f}':>6s} {'-' if visited is None else f'{visited:.1f}':>7s} "
            f"{'-' if scratch is None else f'{scratch / 1e6:.1f}':>10s} {entry['trace']['compile_s']:9.1f}"
        )
    print(
        f"batched: {batched['scenes']:,} scenes x {batched['rays_per_scene']:,} rays ({batched['triangles_per_scene']} "
        f"triangles each, 2 levels): build {batched['build']['median_s'] * 1e3:.1f} ms, intersect ({batched['path']}) "
        f"{batched['trace']['median_s'] * 1e3:.1f} ms = {batched['scene_rays_per_s'] / 1e6:.3f} M scene-rays/s"
    )
    kernel = batched.get("kernel")
    if kernel:
        print(
            f"batched kernel ({kernel['launches']} launch): {kernel['trace']['median_s'] * 1e3:.2f} ms = "
            f"{kernel['scene_rays_per_s'] / 1e6:.1f} M scene-rays/s, hit {kernel['hit_fraction']:.3f}, "
            f"agrees with intersect on {kernel['agree_with_intersect']:.4f}"
        )
        for count, row in kernel.get("program_sweep", {}).items():
            levels = ", ".join(
                f"{name} {entry['mrays_s']:.1f} Mrays/s ({entry['scratch_bytes'] / 1e6:.0f} MB scratch)"
                for name, entry in row.items()
                if isinstance(entry, dict)
            )
            print(
                f"  at most {count} programs: {levels}; batched {row['batched_scene_rays_per_s'] / 1e6:.0f} M scene-rays/s"
            )


if __name__ == "__main__":
    main(sys.argv[1:])
