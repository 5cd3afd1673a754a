"""Render Sintel's bust with her hair: triangles and round Catmull-Rom curves in one structure.

Hair is shaded with the Kajiya-Kay model (the curve tangent at the hit, from ``curve_parameter``), the bust
with Lambert; both get a shadow ray towards the light. Prints the scene size, build and trace times.

Run: ``python examples/hair.py [--width 320] [--height 320] [--data DIR] [--out out/hair.png]``
(``DIR`` holds ``tressfx-hair-sintel/``; default ``$JAXRT_DATA_DIR`` or ``../shared/data``). Without the
data, a procedural hair ball is rendered instead.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxrt as rt

LIGHT = np.array([0.5, 0.9, 0.6]) / np.linalg.norm([0.5, 0.9, 0.6])


def data_folder(arg: str | None) -> Path | None:
    for candidate in (arg, os.environ.get("JAXRT_DATA_DIR"), Path(__file__).resolve().parents[2] / "shared" / "data"):
        if candidate and Path(candidate).is_dir():
            return Path(candidate)
    return None


def catmull_rom_tangent(points: np.ndarray, first: np.ndarray, u: jax.Array) -> jax.Array:
    """Unit tangent of uniform Catmull-Rom segments (first control point ``first``) at parameter ``u``."""
    p = jnp.asarray(points)[jnp.asarray(first)[..., None] + jnp.arange(4)]  # (..., 4, 3)
    u = u[..., None]
    d = 0.5 * (
        (-p[..., 0, :] + p[..., 2, :])
        + 2 * u * (2 * p[..., 0, :] - 5 * p[..., 1, :] + 4 * p[..., 2, :] - p[..., 3, :])
        + 3 * u**2 * (-p[..., 0, :] + 3 * p[..., 1, :] - 3 * p[..., 2, :] + p[..., 3, :])
    )
    return d / jnp.maximum(jnp.linalg.norm(d, axis=-1, keepdims=True), 1e-12)


def kajiya_kay(tangent, direction, light, shininess=40.0):
    """Diffuse and specular terms of the Kajiya-Kay hair model."""
    tl = jnp.sum(tangent * light, -1)
    tv = jnp.sum(tangent * -direction, -1)
    sin_tl = jnp.sqrt(jnp.clip(1 - tl**2, 0, 1))
    sin_tv = jnp.sqrt(jnp.clip(1 - tv**2, 0, 1))
    specular = jnp.clip(tl * tv + sin_tl * sin_tv, 0, 1) ** shininess
    return sin_tl, specular


def scene(data: Path | None):
    """``(geometries, curves, name, eye, target)``; curves is the hair's :class:`HairCurves`."""
    sintel = data / "tressfx-hair-sintel" if data else None
    if sintel and (sintel / "sintel_hair.tfx").is_file():
        curves = rt.io.load_hair(sintel / "sintel_hair.tfx", basis="catmull_rom", width=0.12)
        vertices, faces = rt.io.load_mesh(sintel / "sintel_bust.obj")
        bust = rt.TriangleGeometry(vertices, faces)
        hair = curves.geometry(end_caps="sphere")
        return [bust, hair], curves, "Sintel", (0.0, 36.0, 48.0), (0.0, 33.0, 0.0)
    from jaxrt.bench.curves import hair_ball

    curves = hair_ball(3000)
    ball = rt.TriangleGeometry(*unit_sphere())
    return [ball, curves.geometry(end_caps="sphere")], curves, "hair ball", (0.0, 0.6, 3.6), (0.0, 0.0, 0.0)


def unit_sphere(n: int = 48):
    theta, phi = np.meshgrid(np.linspace(0, np.pi, n), np.linspace(0, 2 * np.pi, 2 * n))
    v = np.stack([np.sin(theta) * np.cos(phi), np.cos(theta), np.sin(theta) * np.sin(phi)], -1).reshape(-1, 3)
    i = np.arange(2 * n * n).reshape(2 * n, n)
    a, b, c, d = i[:-1, :-1], i[1:, :-1], i[1:, 1:], i[:-1, 1:]
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return (0.98 * v).astype(np.float32), faces.astype(np.int32)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=320)
    parser.add_argument("--data", help="shared data folder")
    parser.add_argument("--out", default="out/hair.png")
    args = parser.parse_args(argv)

    geometries, curves, name, eye, target = scene(data_folder(args.data))
    start = time.perf_counter()
    structure = jax.block_until_ready(rt.build_primitive_structure(geometries))
    build_s = time.perf_counter() - start
    rays = rt.shading.pinhole_rays(args.width, args.height, eye=eye, target=target, fov_degrees=35)
    intersector = rt.Intersector(rt.tags.curve_data)
    start = time.perf_counter()
    hits = jax.block_until_ready(intersector.intersect(rays, structure))
    trace_s = time.perf_counter() - start
    start = time.perf_counter()  # again: the compiled program alone
    jax.block_until_ready(intersector.intersect(rays, structure))
    again_s = time.perf_counter() - start

    is_curve = hits.type == rt.IntersectionType.CURVE
    is_mesh = hits.type == rt.IntersectionType.TRIANGLE
    points = rt.shading.hit_points(rays, hits, miss_value=0.0)
    light = jnp.asarray(LIGHT, jnp.float32)
    # Shadows: one ray per hit towards the light, started a little off the surface.
    shadow = rt.Ray(points + 1e-3 * light, jnp.broadcast_to(light, points.shape), max_distance=1e3)
    lit = rt.Intersector(accept_any_intersection=True).intersect(shadow, structure).type == 0
    # Hair: Kajiya-Kay with the tangent of the hit segment.
    first = jnp.asarray(curves.indices)[jnp.maximum(hits.primitive_id, 0)]
    tangent = catmull_rom_tangent(curves.control_points, first, hits.curve_parameter)
    diffuse, specular = kajiya_kay(tangent, rays.direction, light)
    hair = jnp.asarray([0.35, 0.2, 0.1]) * (0.25 + 0.75 * lit[..., None] * diffuse[..., None])
    hair = hair + 0.35 * (lit * specular)[..., None]
    # Bust: Lambert with the triangle normal.
    mesh = geometries[0]
    normals = rt.shading.triangle_normals(mesh.vertices, mesh.indices, jnp.where(is_mesh, hits.primitive_id, -1))
    normals = jnp.where(jnp.sum(normals * rays.direction, -1, keepdims=True) > 0, -normals, normals)
    skin = jnp.asarray([0.85, 0.7, 0.6]) * (0.3 + 0.7 * lit[..., None] * rt.shading.lambert(normals, light)[..., None])
    background = jnp.asarray([0.15, 0.17, 0.2])
    image = jnp.where(is_curve[..., None], hair, jnp.where(is_mesh[..., None], skin, background))
    image = np.asarray(jnp.clip(image, 0, 1) ** (1 / 2.2) * 255).astype(np.uint8)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    from PIL import Image

    Image.fromarray(image, "RGB").save(out)
    stats = dict(
        scene=name,
        triangles=geometries[0].primitive_count,
        curve_segments=geometries[1].primitive_count,
        rays=args.width * args.height,
        build_s=build_s,
        trace_s=trace_s,
        again_s=again_s,
        curve_pixels=int(is_curve.sum()),
        mesh_pixels=int(is_mesh.sum()),
    )
    print(
        f"{name}: {stats['triangles']} triangles + {stats['curve_segments']} curve segments; build {build_s:.2f} s, "
        f"trace {stats['rays']} rays {trace_s:.2f} s (first call, compile included), {again_s * 1e3:.0f} ms again; "
        f"{stats['curve_pixels']} hair pixels, {stats['mesh_pixels']} mesh pixels -> {out}"
    )
    return stats


if __name__ == "__main__":
    main()
