"""Render a multi-level instanced forest (island -> grove -> tree -> trunk and leaves) with sun shadows.

The procedural island of ``python -m jaxrt.bench.instancing``: one terrain mesh, one trunk mesh and one leaf
mesh are stored; trees instance the leaf hundreds of times, groves instance the tree, and the island
instances the groves. Primary rays find the nearest hit (with ``world_space_data`` to turn object-space
normals into world space), shadow rays toward the sun use ``accept_any_intersection``.

Run: ``python examples/forest.py [--width 320] [--height 200] [--out out/forest.png] [--large]``
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxrt as rt
from jaxrt.bench.instancing import island, nbytes

SUN = np.array([0.45, 0.8, -0.35]) / np.linalg.norm([0.45, 0.8, -0.35])


def build(scene: dict) -> rt.InstanceAccelerationStructure:
    """island -> groves -> tree -> {trunk, leaf}, with the terrain instanced beside the groves."""
    mesh = lambda t: rt.build_primitive_structure(rt.TriangleGeometry(t.reshape(-1, 3)))  # noqa: E731
    terrain, trunk, leaf = mesh(scene["terrain"]), mesh(scene["trunk"]), mesh(scene["leaf"])
    eye = np.eye(3, 4, dtype=np.float32)[None]
    leaves = scene["leaf_transforms"]
    tree = rt.build_instance_structure(
        [trunk, leaf], rt.Instances([0] + [1] * len(leaves), np.concatenate([eye, leaves]))
    )
    groves = [rt.build_instance_structure([tree], rt.Instances(np.zeros(len(t), int), t)) for t in scene["grove_trees"]]
    index = np.concatenate([[0], 1 + scene["grove_index"]])
    return rt.build_instance_structure(
        [terrain, *groves], rt.Instances(index, np.concatenate([eye, scene["grove_transforms"]]))
    )


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=200)
    parser.add_argument("--out", default="out/forest.png")
    parser.add_argument("--large", action="store_true", help="a bigger island (for a GPU)")
    args = parser.parse_args(argv)

    sizes = dict(terrain=128, trunk=8, leaves=160, grove_trees=24, groves=48, variants=3)
    if args.large:
        sizes.update(terrain=512, trunk=16, leaves=512, grove_trees=64, groves=256, variants=4)
    scene = island(sizes)
    start = time.perf_counter()
    structure = jax.block_until_ready(build(scene))
    build_s = time.perf_counter() - start
    tree_triangles = len(scene["trunk"]) + len(scene["leaf"]) * sizes["leaves"]
    virtual = len(scene["terrain"]) + sizes["groves"] * sizes["grove_trees"] * tree_triangles
    stored = len(scene["terrain"]) + len(scene["trunk"]) + len(scene["leaf"])

    rays = rt.shading.pinhole_rays(
        args.width, args.height, eye=(0.0, 45.0, -135.0), target=(0.0, 0.0, 10.0), fov_degrees=40.0
    )
    primary = rt.Intersector(rt.tags.instancing, rt.tags.max_levels(3), rt.tags.world_space_data)
    shadow = rt.Intersector(rt.tags.instancing, rt.tags.max_levels(3), accept_any_intersection=True)
    meshes = [jnp.asarray(scene[k]) for k in ("terrain", "trunk", "leaf")]

    @jax.jit
    def render(rays, structure):
        hit = primary.intersect(rays, structure)
        found = hit.type != 0
        # Which mesh: a hit one level down is the terrain; three levels down, the trunk is the tree's instance 0.
        chain = hit.instance_id
        kind = jnp.where(hit.instance_count == 1, 0, jnp.where(chain[..., 2] == 0, 1, 2))
        primitive = jnp.maximum(hit.primitive_id, 0)
        which = kind[..., None, None]
        vertices = jnp.select(
            [which == 0, which == 1],
            [meshes[0][primitive % len(meshes[0])], meshes[1][primitive % len(meshes[1])]],
            meshes[2][primitive % len(meshes[2])],
        )
        normal = jnp.cross(vertices[..., 1, :] - vertices[..., 0, :], vertices[..., 2, :] - vertices[..., 0, :])
        # Normals transform by the transpose of the world-to-object matrix.
        normal = jnp.einsum("...ji,...j->...i", hit.world_to_object_transform[..., :3], normal)
        normal = normal / jnp.maximum(jnp.linalg.norm(normal, axis=-1, keepdims=True), 1e-20)
        normal = jnp.where(jnp.sum(normal * rays.direction, -1, keepdims=True) > 0, -normal, normal)
        point = rays.origin + hit.distance[..., None] * rays.direction
        sun = jnp.asarray(SUN, jnp.float32)
        lit = shadow.intersect(
            rt.Ray(
                rt.offset_ray_origin(point, normal),
                jnp.broadcast_to(sun, point.shape),
                max_distance=jnp.where(found, jnp.inf, -1.0),
            ),
            structure,
        )
        light = jnp.where(lit.type != 0, 0.0, jnp.maximum(jnp.sum(normal * sun, -1), 0.0))
        albedo = jnp.asarray([[0.55, 0.5, 0.35], [0.35, 0.22, 0.12], [0.2, 0.5, 0.15]], jnp.float32)[kind]
        colour = albedo * (0.25 + 0.75 * light[..., None])
        sky = jnp.asarray([0.6, 0.75, 0.95], jnp.float32) * (0.8 + 0.2 * rays.direction[..., 1:2])
        return jnp.where(found[..., None], colour, sky), found

    image, found = jax.block_until_ready(render(rays, structure))  # compiles
    start = time.perf_counter()
    image, found = jax.block_until_ready(render(rays, structure))
    render_s = time.perf_counter() - start
    n = args.width * args.height
    out = {
        "virtual_triangles": int(virtual),
        "stored_triangles": int(stored),
        "structure_mb": nbytes(structure) / 1e6,
        "flattened_mb_estimate": virtual * nbytes(structure.primitive_structures[0]) / len(scene["terrain"]) / 1e6,
        "build_s": build_s,
        "render_s": render_s,
        "mrays_s": 2 * n / render_s / 1e6,
        "hit_fraction": float(jnp.mean(found)),
    }
    print(
        f"forest: {virtual:,} virtual triangles from {stored:,} stored ({out['structure_mb']:.1f} MB; flattened about "
        f"{out['flattened_mb_estimate']:.0f} MB), 3 levels; built in {build_s:.2f} s (compiles included)"
    )
    print(
        f"{args.width}x{args.height}: primary + shadow rays in {render_s * 1e3:.0f} ms = {out['mrays_s']:.3f} Mrays/s "
        f"on {jax.default_backend()}; {out['hit_fraction']:.0%} of pixels hit"
    )
    try:
        from PIL import Image
    except ImportError:
        print("pillow is not installed: no image written")
        return out
    path = Path(args.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    pixels = (np.clip(np.asarray(image), 0, 1) ** (1 / 2.2) * 255).astype(np.uint8)
    Image.fromarray(pixels, "RGB").save(path)
    print(f"wrote {path}")
    return out


if __name__ == "__main__":
    main()
