"""Motion blur: a spinning, sliding cube (instance motion) and a rolling ball (primitive motion) over a
static floor, each pixel averaging rays at stratified random times in the shutter interval.

The cube's instance has five keyframed transforms (a quarter turn and a slide), blended at each ray's time;
the ball is a ``MotionBoundingBoxGeometry`` whose intersection function (a sphere inscribed in the box) sees
the box blended at the ray's time. Everything else is ordinary tracing: one ``Intersector`` with the
``instance_motion`` and ``primitive_motion`` tags.

Run: ``python examples/motion_blur.py [--width 160] [--height 120] [--samples 16] [--out out/motion_blur.png]``
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxrt as rt
from jaxrt import intersection_functions as F

SUN = np.array([0.45, 0.8, 0.4]) / np.linalg.norm([0.45, 0.8, 0.4])
SPEC = rt.MotionSpec(0.0, 1.0)  # the shutter interval
KEYS = 5


def _rotation_y(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def cube() -> tuple[np.ndarray, np.ndarray]:
    """A unit cube around the origin: ``(triangle vertices (12, 3, 3), face normals (12, 3))``."""
    faces = []
    normals = []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            n = np.zeros(3)
            n[axis] = sign
            u, v = np.eye(3)[(axis + 1) % 3], np.eye(3)[(axis + 2) % 3]
            corners = [0.5 * n + 0.5 * (a * u + b * v) for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
            faces += [[corners[0], corners[1], corners[2]], [corners[0], corners[2], corners[3]]]
            normals += [n, n]
    return np.asarray(faces, np.float32), np.asarray(normals, np.float32)


def scene():
    """The instance structure, the cube's face normals and the ball's keyframed centres and radius."""
    triangles, face_normals = cube()
    floor = np.array([[-6.0, 0, -6], [6, 0, 6], [6, 0, -6], [-6, 0, -6], [-6, 0, 6], [6, 0, 6]], np.float32)
    radius = 0.45
    centres = np.stack([np.linspace(-2.0, -1.3, KEYS), np.full(KEYS, radius), np.full(KEYS, 1.0)], -1)
    ball = rt.MotionBoundingBoxGeometry(centres[:, None] - radius, centres[:, None] + radius)
    structures = [
        rt.build_primitive_structure(rt.TriangleGeometry(floor)),
        rt.build_primitive_structure(rt.TriangleGeometry(triangles.reshape(-1, 3))),
        rt.build_primitive_structure(ball, motion=SPEC),
    ]
    identity = np.eye(3, 4)
    spin = []
    for k in range(KEYS):  # a quarter turn and a slide to the right over the shutter
        m = np.eye(3, 4)
        m[:, :3] = _rotation_y(0.5 * np.pi * k / (KEYS - 1)) * 1.2
        m[:, 3] = [0.8 + 0.6 * k / (KEYS - 1), 0.6, -0.5]
        spin.append(m)
    transforms = np.stack([[identity] * KEYS, spin, [identity] * KEYS]).astype(np.float32)  # (3, K, 3, 4)
    instances = rt.Instances([0, 1, 2], transforms)
    return rt.build_instance_structure(structures, instances, motion=SPEC), face_normals, centres, radius


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--height", type=int, default=120)
    parser.add_argument("--samples", type=int, default=16, help="rays (random times) per pixel")
    parser.add_argument("--out", default="out/motion_blur.png")
    args = parser.parse_args(argv)

    structure, face_normals, centres, _ = scene()
    intersector = rt.Intersector(
        rt.tags.instancing,
        rt.tags.instance_motion,
        rt.tags.primitive_motion,
        rt.tags.world_space_data,
        intersection_functions={0: F.sphere},
    )
    sun = jnp.asarray(SUN, jnp.float32)

    @jax.jit
    def render(key):
        time_key, pixel_key = jax.random.split(key)
        keys = jax.random.split(pixel_key, args.samples)
        camera = jax.vmap(
            lambda k: rt.shading.pinhole_rays(
                args.width, args.height, eye=(0.0, 2.2, 5.5), target=(0.0, 0.4, 0.0), fov_degrees=40, key=k
            )
        )(keys)
        # Stratified shutter times: sample s of every pixel falls in the s-th of `samples` equal intervals.
        strata = jnp.arange(args.samples, dtype=jnp.float32).reshape(-1, 1, 1)
        times = (strata + jax.random.uniform(time_key, camera.shape)) / args.samples
        rays = rt.Ray(camera.origin, camera.direction, time=times).reshape(-1)
        hit = intersector.intersect(rays, structure)
        point = rt.shading.hit_points(rays, hit)
        instance = hit.instance_id[:, 0]
        # Normals: the floor's +y; the cube's face normal turned by the instance's transform at the ray's
        # time; the ball's from its centre blended at the ray's time.
        rotation = hit.object_to_world_transform[:, :, :3]
        cube_normal = jnp.einsum("nij,nj->ni", rotation, jnp.asarray(face_normals)[jnp.maximum(hit.primitive_id, 0)])
        centre = jax.vmap(lambda t: SPEC.interpolate(centres.astype(np.float32), t))(rays.time)
        normal = jnp.where((instance == 1)[:, None], cube_normal, jnp.array([0.0, 1.0, 0.0]))
        normal = jnp.where((instance == 2)[:, None], point - centre, normal)
        normal = normal / jnp.maximum(jnp.linalg.norm(normal, axis=-1, keepdims=True), 1e-12)
        checker = (jnp.floor(point[:, 0]) + jnp.floor(point[:, 2])) % 2
        albedo = jnp.stack(
            [
                jnp.stack([0.55 + 0.2 * checker] * 3, -1),
                jnp.broadcast_to(jnp.array([0.85, 0.35, 0.15]), point.shape),
                jnp.broadcast_to(jnp.array([0.2, 0.45, 0.9]), point.shape),
            ]
        )[jnp.clip(instance, 0, 2), jnp.arange(point.shape[0])]
        light = 0.25 + 0.8 * rt.shading.lambert(normal, sun)
        sky = jnp.array([0.65, 0.78, 0.95]) + 0.2 * rays.direction[:, 1:2]
        colour = jnp.where((hit.type != 0)[:, None], albedo * light[:, None], sky)
        return jnp.mean(colour.reshape(args.samples, args.height, args.width, 3), axis=0)

    start = time.perf_counter()
    image = jax.block_until_ready(render(jax.random.key(0)))
    first = time.perf_counter() - start
    start = time.perf_counter()
    image = jax.block_until_ready(render(jax.random.key(1)))
    again = time.perf_counter() - start
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    from PIL import Image

    pixels = (np.clip(np.asarray(image), 0, 1) ** (1 / 2.2) * 255).astype(np.uint8)
    Image.fromarray(pixels, "RGB").save(out)
    rays = args.width * args.height * args.samples
    print(f"{rays} rays: {first:.2f} s with compilation, {again:.2f} s after ({rays / again / 1e6:.2f} Mrays/s)")
    print(f"wrote {out}")
    return {"image": np.asarray(image), "seconds": again}


if __name__ == "__main__":
    main()
