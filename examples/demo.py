"""Render a procedural scene with sun light, soft shadows and sky light, and print a speed/accuracy summary.

Each pixel averages several jittered camera rays (antialiasing). Curved objects are shaded with smooth
normals interpolated from per-vertex normals (``rt.shading.vertex_normals``, ``interpolate_normals``), lit by
a sun whose shadow rays find what stands between, and by the sky through ambient occlusion (cosine-weighted
rays from the surface, which darken contacts and creases). Shadow and occlusion rays go through one any-hit
trace. The occlusion is then smoothed by an edge-avoiding a-trous filter guided by the hit normals and
surface planes (Dammertz, Sewtz, Hanika, Lensch, "Edge-Avoiding A-Trous Wavelet Transform for fast Global
Illumination Filtering", HPG 2010). A sample of the camera rays is checked against a float64 brute force.

Run: ``python examples/demo.py [--width 320] [--height 240] [--spp 4] [--ao-samples 8] [--out out/demo.png]
[--quiet]``
"""

from __future__ import annotations

import argparse
import functools
import time
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from _progress import progress

import jaxrt as rt


def icosphere(center, radius, subdivisions=3):
    """A closed, nearly uniform sphere mesh: a subdivided icosahedron projected onto the sphere."""
    t = (1.0 + 5**0.5) / 2.0
    v = [
        (-1, t, 0),
        (1, t, 0),
        (-1, -t, 0),
        (1, -t, 0),
        (0, -1, t),
        (0, 1, t),
        (0, -1, -t),
        (0, 1, -t),
        (t, 0, -1),
        (t, 0, 1),
        (-t, 0, -1),
        (-t, 0, 1),
    ]
    f = [
        (0, 11, 5),
        (0, 5, 1),
        (0, 1, 7),
        (0, 7, 10),
        (0, 10, 11),
        (1, 5, 9),
        (5, 11, 4),
        (11, 10, 2),
        (10, 7, 6),
        (7, 1, 8),
        (3, 9, 4),
        (3, 4, 2),
        (3, 2, 6),
        (3, 6, 8),
        (3, 8, 9),
        (4, 9, 5),
        (2, 4, 11),
        (6, 2, 10),
        (8, 6, 7),
        (9, 8, 1),
    ]
    vertices = [np.array(p, float) / np.linalg.norm(p) for p in v]
    faces = f
    for _ in range(subdivisions):
        cache, new_faces = {}, []

        def midpoint(a, b, cache=cache):
            key = (min(a, b), max(a, b))
            if key not in cache:
                m = vertices[a] + vertices[b]
                vertices.append(m / np.linalg.norm(m))
                cache[key] = len(vertices) - 1
            return cache[key]

        for a, b, c in faces:
            ab, bc, ca = midpoint(a, b), midpoint(b, c), midpoint(c, a)
            new_faces += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = new_faces
    return np.asarray(vertices) * radius + np.asarray(center), np.asarray(faces)


def torus(center, major, minor, nu=96, nv=48):
    """A closed torus around the y axis."""
    u, v = np.meshgrid(
        np.linspace(0, 2 * np.pi, nu, endpoint=False), np.linspace(0, 2 * np.pi, nv, endpoint=False), indexing="ij"
    )
    x = (major + minor * np.cos(v)) * np.cos(u)
    z = (major + minor * np.cos(v)) * np.sin(u)
    y = minor * np.sin(v)
    vertices = np.stack([x, y, z], -1).reshape(-1, 3) + np.asarray(center)
    i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    a, b = i * nv + j, ((i + 1) % nu) * nv + j
    c, d = i * nv + (j + 1) % nv, ((i + 1) % nu) * nv + (j + 1) % nv
    faces = np.concatenate([np.stack([a, c, b], -1), np.stack([b, c, d], -1)]).reshape(-1, 3)
    return vertices, faces


def box(center, size, angle=0.0):
    """A closed box rotated by ``angle`` about the y axis."""
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float) * np.asarray(size) / 2
    c, s = np.cos(angle), np.sin(angle)
    corners = corners @ np.array([[c, 0, -s], [0, 1, 0], [s, 0, c]]).T + np.asarray(center)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces = [(a, b, c) for a, b, c, _ in quads] + [(a, c, d) for a, _, c, d in quads]
    return corners, np.asarray(faces)


def ground(size, cells=32):
    """A square grid in the plane y = 0, facing up."""
    g = np.linspace(-size, size, cells + 1)
    x, z = np.meshgrid(g, g, indexing="ij")
    vertices = np.stack([x, np.zeros_like(x), z], -1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(cells), np.arange(cells), indexing="ij")
    a, b, c, d = i * (cells + 1) + j, (i + 1) * (cells + 1) + j, i * (cells + 1) + j + 1, (i + 1) * (cells + 1) + j + 1
    faces = np.concatenate([np.stack([a, c, b], -1), np.stack([b, c, d], -1)]).reshape(-1, 3)
    return vertices, faces


class Material(NamedTuple):
    """Linear RGB albedo, Blinn-Phong specular weight and exponent, and whether normals are interpolated."""

    albedo: tuple[float, float, float]
    specular: float = 0.0
    shininess: float = 32.0
    smooth: bool = False


#: The ground's material (its albedo is replaced by a checkerboard of the two below).
GROUND = Material((0.6, 0.56, 0.5))
CHECKER = ((0.5, 0.46, 0.4), (0.3, 0.28, 0.25))


def scene():
    """The demo scene: spheres, a torus and boxes on a ground plane; returns ((vertices, faces), material) per
    object."""
    objects = [
        (ground(8.0), GROUND),
        (icosphere((-1.6, 1.0, 0.0), 1.0, 5), Material((0.72, 0.16, 0.12), 0.45, 60.0, True)),
        (torus((1.4, 0.45, 0.6), 0.9, 0.45), Material((0.85, 0.58, 0.16), 0.6, 40.0, True)),
        (box((0.6, 0.6, -2.0), (1.2, 1.2, 1.2), 0.5), Material((0.16, 0.34, 0.7), 0.1)),
        (icosphere((2.6, 0.5, -1.2), 0.5, 4), Material((0.18, 0.55, 0.3), 0.5, 60.0, True)),
    ]
    for k in range(6):
        step = box((-3.2 + 1.0 * k, 0.15 + 0.15 * k, -3.6), (0.8, 0.3 + 0.3 * k, 0.8), 0.2 * k)
        objects.append((step, Material((0.2 + 0.1 * k, 0.45 - 0.02 * k, 0.6 - 0.07 * k), 0.05)))
    return objects


def brute_force_float64(origins, directions, triangles):
    """Nearest hit (distance, triangle) of each ray over all triangles, in float64 (Möller-Trumbore)."""
    o, d, tri = origins.astype(np.float64), directions.astype(np.float64), triangles.astype(np.float64)
    v0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    best_t, best_i = np.full(len(o), np.inf), np.full(len(o), -1)
    for start in range(0, len(o), 16):  # 16 rays at a time: the (rays, triangles) temporaries stay small
        oo, dd = o[start : start + 16, None], d[start : start + 16, None]
        p = np.cross(dd, e2)
        det = np.einsum("tk,rtk->rt", e1, p)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = oo - v0
            u = np.einsum("rtk,rtk->rt", s, p) / det
            q = np.cross(s, e1)
            v = np.einsum("rtk,rtk->rt", dd, q) / det
            t = np.einsum("tk,rtk->rt", e2, q) / det
        ok = (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0) & (det != 0)
        t = np.where(ok, t, np.inf)
        best_t[start : start + 16], best_i[start : start + 16] = (
            t.min(1),
            np.where(np.isfinite(t.min(1)), t.argmin(1), -1),
        )
    return best_t, best_i


def timed(fn, *args, repeats=3):
    """(result, compile+first-run seconds, best warm seconds)."""
    start = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    first = time.perf_counter() - start
    best = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - start)
    return out, first, best


#: The B3-spline kernel of the a-trous transform, per axis.
_KERNEL = np.array([1 / 16, 1 / 4, 3 / 8, 1 / 4, 1 / 16], np.float32)
#: The 25 taps of the 5 x 5 kernel: row offset, column offset (in steps) and weight.
_TAPS = np.array([(i - 2, j - 2, _KERNEL[i] * _KERNEL[j]) for i in range(5) for j in range(5)], np.float32)


def _shift(image, dy, dx):
    """``image[y + dy, x + dx]`` with edge pixels repeated past the border (``dy``, ``dx`` may be traced)."""
    h, w = image.shape[:2]
    rows = jnp.clip(jnp.arange(h) + dy, 0, h - 1)
    cols = jnp.clip(jnp.arange(w) + dx, 0, w - 1)
    return image[rows][:, cols]


@jax.jit
def denoise(value, normal, point, depth, valid, pixel_angle):
    """Edge-avoiding a-trous filtering of a noisy per-pixel ``value`` ``(H, W)``.

    Four passes of the 5 x 5 B3-spline kernel with holes (steps 1, 2, 4, 8), each neighbour weighted by
    how well its normal agrees, how close it lies to the pixel's tangent plane (relative to the pixel's
    footprint at its depth), and how close its value is; pixels without a hit take no part.
    """
    taps = jnp.asarray(_TAPS)

    def level(k, result):
        step = 2**k
        footprint = jnp.maximum(depth * pixel_angle * step, 1e-6)
        value_sigma = 0.3 / step

        def tap(t, sums):
            total, weights = sums
            dy, dx = (taps[t, 0] * step).astype(jnp.int32), (taps[t, 1] * step).astype(jnp.int32)
            q_value, q_normal = _shift(result, dy, dx), _shift(normal, dy, dx)
            q_point, q_valid = _shift(point, dy, dx), _shift(valid, dy, dx)
            w_normal = jnp.maximum(jnp.sum(normal * q_normal, -1), 0.0) ** 32
            plane = jnp.sum(normal * (q_point - point), -1) / footprint
            w = taps[t, 2] * w_normal * jnp.exp(-plane * plane) * jnp.exp(-(((q_value - result) / value_sigma) ** 2))
            w = jnp.where(q_valid & valid, w, 0.0)
            return total + w * q_value, weights + w

        zero = jnp.zeros_like(value)
        total, weights = jax.lax.fori_loop(0, len(_TAPS), tap, (zero, zero))
        return jnp.where(valid, total / jnp.maximum(weights, 1e-12), value)

    return jax.lax.fori_loop(0, 4, level, value)


#: Direction towards the sun, its colour, and the sky's colours (linear RGB).
SUN = np.array([-0.75, 0.55, 0.3]) / np.linalg.norm([-0.75, 0.55, 0.3])
SUN_COLOR = np.array([1.0, 0.92, 0.8]) * 1.7
SKY_ZENITH = np.array([0.22, 0.38, 0.75])
SKY_HORIZON = np.array([0.7, 0.78, 0.9])
_ALL = 0xFFFFFFFF


def sky(direction):
    """The sky's colour seen along unit ``direction`` (a gradient from the horizon to the zenith)."""
    t = jnp.clip(direction[..., 1:2] * 2.5, 0.0, 1.0)
    return (1 - t) * SKY_HORIZON + t * SKY_ZENITH


@jax.jit
def shading_normals(hits, rays, vertex_normals, indices, smooth):
    """Unit normals facing the ray: ``(geometric, shading)``; the shading normal is interpolated from the
    per-vertex normals on smooth geometries and the geometric one elsewhere."""
    geometric = rt.shading.face_forward(hits.normal, rays.direction)
    interpolated = rt.shading.interpolate_normals(
        vertex_normals, indices, hits.primitive_id, hits.triangle_barycentric_coord, hits.geometry_id
    )
    interpolated = jnp.where(jnp.sum(interpolated * geometric, -1, keepdims=True) < 0, -interpolated, interpolated)
    use = smooth[jnp.maximum(hits.geometry_id, 0)][..., None] & (jnp.sum(interpolated**2, -1, keepdims=True) > 0)
    return geometric, jnp.where(use, interpolated, geometric)


@functools.partial(jax.jit, static_argnames=("samples",))
def occlusion_rays(key, points, normals, valid, *, samples, radius):
    """``samples`` cosine-weighted sky rays within ``radius`` (rows ``0 .. K-1``) and a sun ray (row ``K``)
    per point."""
    keys = jax.random.split(key, samples)
    sky_dirs = jax.vmap(lambda k: rt.shading.cosine_hemisphere(k, normals))(keys)
    sun = jnp.broadcast_to(jnp.asarray(SUN, jnp.float32), normals.shape)[None]
    directions = jnp.concatenate([sky_dirs, sun])
    origin = jnp.broadcast_to(rt.offset_ray_origin(points, normals), directions.shape)
    facing_sun = jnp.sum(normals * sun[0], -1) > 0
    enabled = jnp.concatenate([jnp.broadcast_to(valid, sky_dirs.shape[:-1]), (valid & facing_sun)[None]])
    far = jnp.concatenate([jnp.full(sky_dirs.shape[:-1], radius), jnp.full((1, *valid.shape), jnp.inf)])
    mask = jnp.where(enabled, jnp.uint32(_ALL), jnp.uint32(0))
    return rt.Ray(origin, directions, 0.0, far.astype(jnp.float32), mask)


@jax.jit
def compose(rays, hits, points, geometric, normal, sunlit, sky_visibility, albedo, specular, shininess):
    """Linear RGB per sample: albedo times (sun + sky light), plus the sun's highlight; the sky for misses."""
    valid = (hits.type != 0)[..., None]
    g = jnp.maximum(hits.geometry_id, 0)
    base = jnp.asarray(albedo)[g]
    cell = (jnp.floor(points[..., 0]) + jnp.floor(points[..., 2])) % 2 == 0
    checker = jnp.where(cell[..., None], jnp.asarray(CHECKER[0]), jnp.asarray(CHECKER[1]))
    base = jnp.where((hits.geometry_id == 0)[..., None], checker, base)
    sun = jnp.asarray(SUN, jnp.float32)
    view = -rays.direction
    lit = rt.shading.blinn_phong(
        normal, sun, view, albedo=1.0, specular=jnp.asarray(specular)[g], shininess=jnp.asarray(shininess)[g]
    )
    diffuse = jnp.maximum(jnp.sum(normal * sun, -1), 0.0)
    highlight = jnp.maximum(lit - diffuse, 0.0)
    direct = sunlit[..., None] * (diffuse[..., None] * base + highlight[..., None]) * SUN_COLOR
    # sky light from above, a little ground bounce from below, both scaled by the occlusion
    up = 0.5 + 0.5 * normal[..., 1:2]
    ambient = (up * SKY_ZENITH * 0.75 + (1 - up) * np.array([0.25, 0.22, 0.18])) * sky_visibility[..., None]
    color = direct + ambient * base
    return jnp.where(valid, color, sky(rays.direction))


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--spp", type=int, default=4, help="jittered camera rays per pixel")
    parser.add_argument("--ao-samples", type=int, default=8, help="sky (occlusion) rays per camera ray")
    parser.add_argument("--no-denoise", action="store_true", help="keep the raw Monte Carlo sky occlusion")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument("--check-rays", type=int, default=1024, help="rays checked against float64 brute force")
    parser.add_argument("--out", default="out/demo.png")
    args = parser.parse_args(argv)

    objects = scene()
    materials = [m for _, m in objects]
    meshes = [(v.astype(np.float32), f.astype(np.int32)) for (v, f), _ in objects]
    geometries = [rt.TriangleGeometry(v, f) for v, f in meshes]
    n_tris = sum(g.primitive_count for g in geometries)
    structure, build_first, build = timed(rt.build_primitive_structure, geometries)

    steps = ["camera rays", "shadow and sky rays", "shading"]
    bar = progress(steps, quiet=args.quiet, desc="demo", unit="step")
    stages = iter(bar)
    next(stages)
    keys = jax.random.split(jax.random.key(0), args.spp + 1)
    camera = dict(eye=(0.5, 3.0, 7.5), target=(0.0, 0.7, -0.8), fov_degrees=45)
    rays = jax.vmap(lambda k: rt.shading.pinhole_rays(args.width, args.height, key=k, **camera))(keys[1:])
    intersector = rt.Intersector(rt.tags.triangle_data, rt.tags.normal)
    hits, trace_first, trace = timed(intersector.intersect, rays, structure, repeats=1)
    valid = hits.type != 0
    points = rt.shading.hit_points(rays, hits, miss_value=0.0)
    vertex_normals = [rt.shading.vertex_normals(v, f) for v, f in meshes]
    smooth = jnp.asarray([m.smooth for m in materials])
    geometric, normal = shading_normals(hits, rays, vertex_normals, [f for _, f in meshes], smooth)

    # One any-hit trace for the sky (ambient occlusion) rays and the sun's shadow ray of every camera ray.
    next(stages)
    occluders = occlusion_rays(keys[0], points, geometric, valid, samples=args.ao_samples, radius=1.5)
    shadow_tracer = rt.Intersector(accept_any_intersection=True)
    blocked, occlusion_first, occlusion = timed(
        lambda r, s: shadow_tracer.intersect(r, s).type != 0, occluders, structure, repeats=1
    )
    sunlit = ~blocked[-1] & (occluders.mask[-1] != 0)
    sky_visibility = 1.0 - jnp.mean(blocked[:-1].astype(jnp.float32), axis=0)

    # Sky occlusion per pixel (over its camera rays that hit), smoothed by the edge-avoiding filter guided by
    # the first camera ray of each pixel; then every sample is shaded and the samples are averaged.
    next(stages)
    hit_count = jnp.sum(valid, axis=0)
    pixel_visibility = jnp.sum(jnp.where(valid, sky_visibility, 0.0), axis=0) / jnp.maximum(hit_count, 1)
    if not args.no_denoise:
        pixel_angle = 2.0 * np.tan(np.deg2rad(45) / 2) / args.height
        guide = (geometric[0], points[0], hits.distance[0], valid[0])
        pixel_visibility = denoise(pixel_visibility, guide[0], guide[1], guide[2], guide[3], pixel_angle)
    sky_light = jnp.broadcast_to(pixel_visibility, valid.shape)
    albedo = np.array([m.albedo for m in materials], np.float32)
    specular = np.array([m.specular for m in materials], np.float32)
    shininess = np.array([m.shininess for m in materials], np.float32)
    color = compose(rays, hits, points, geometric, normal, sunlit, sky_light, albedo, specular, shininess)
    color = jnp.mean(color, axis=0)
    color = color / (1.0 + 0.15 * color)  # a gentle shoulder for the brightest highlights
    image = np.asarray(jnp.clip(color, 0, 1) ** (1 / 2.2) * 255 + 0.5).astype(np.uint8)
    for _ in stages:
        pass
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        from PIL import Image

        Image.fromarray(image, "RGB").save(out)
    except ImportError:  # PNG writer not installed: keep a portable colour image instead
        out = out.with_suffix(".ppm")
        out.write_bytes(b"P6 %d %d 255\n" % (args.width, args.height) + image.tobytes())

    # Accuracy: a random subset of the camera rays against float64 brute force over all triangles.
    offsets = np.cumsum([0] + [g.primitive_count for g in geometries])
    vertices = np.concatenate([v for v, _ in meshes])
    vertex_offsets = np.cumsum([0] + [len(v) for v, _ in meshes])
    faces = np.concatenate([f + vertex_offsets[i] for i, (_, f) in enumerate(meshes)])
    global_id = jnp.where(valid, jnp.asarray(offsets)[jnp.maximum(hits.geometry_id, 0)] + hits.primitive_id, -1)
    total_rays = int(np.prod(valid.shape))
    rng = np.random.default_rng(0)
    pick = rng.choice(total_rays, size=min(args.check_rays, total_rays), replace=False)
    o = np.asarray(rays.origin).reshape(-1, 3)[pick]
    d = np.asarray(rays.direction).reshape(-1, 3)[pick]
    ref_t, ref_i = brute_force_float64(o, d, vertices[faces])
    got_t = np.asarray(hits.distance).reshape(-1)[pick]
    got_i = np.asarray(global_id).reshape(-1)[pick]
    ref_hit, got_hit = np.isfinite(ref_t), np.isfinite(got_t)
    both = ref_hit & got_hit
    rel = np.abs(got_t[both] - ref_t[both]) / np.maximum(ref_t[both], 1e-30)
    # A different triangle at the same float64 distance (a shared edge or vertex) is a tie, not an error.
    mismatch = np.flatnonzero(both & (got_i != ref_i))
    ties = np.array(
        [brute_force_float64(o[k : k + 1], d[k : k + 1], vertices[faces][got_i[k]][None])[0][0] for k in mismatch]
    )
    ties = np.isclose(ties, ref_t[mismatch], rtol=1e-6, atol=0)
    occlusion_rays_traced = int(np.sum(np.asarray(occluders.mask) != 0))
    summary = {
        "backend": jax.default_backend(),
        "triangles": n_tris,
        "build_ms": build * 1e3,
        "build_mprims_per_s": n_tris / build / 1e6,
        "primary_rays": total_rays,
        "primary_mrays_per_s": total_rays / trace / 1e6,
        "occlusion_rays": occlusion_rays_traced,
        "occlusion_mrays_per_s": occlusion_rays_traced / occlusion / 1e6,
        "compile_s": build_first - build + trace_first - trace + occlusion_first - occlusion,
        "denoised": not args.no_denoise,
        "checked_rays": len(pick),
        "hit_miss_mismatches": int((ref_hit != got_hit).sum()),
        "primitive_mismatches": int((~ties).sum()),
        "max_rel_distance_error": float(rel.max()) if rel.size else 0.0,
        "image": str(out),
    }
    print(
        f"jaxrt demo on {summary['backend']}: {n_tris} triangles, {args.width}x{args.height} pixels, "
        f"{args.spp} camera rays/pixel, {args.ao_samples} sky rays and 1 sun ray each"
        f"{'' if args.no_denoise else ', denoised'} -> {out}"
    )
    print(f"  build             {summary['build_ms']:8.1f} ms   {summary['build_mprims_per_s']:7.2f} Mprims/s")
    print(f"  camera rays       {summary['primary_mrays_per_s']:8.3f} Mrays/s (closest hit, triangle_data, normal)")
    print(
        f"  shadow + sky rays {summary['occlusion_mrays_per_s']:8.3f} Mrays/s (any hit, {occlusion_rays_traced:,} rays)"
    )
    print(f"  compile           {summary['compile_s']:8.1f} s (first calls)")
    print(
        f"  accuracy vs float64 brute force on {len(pick)} rays: {summary['hit_miss_mismatches']} hit/miss and "
        f"{summary['primitive_mismatches']} primitive mismatches, max relative distance error "
        f"{summary['max_rel_distance_error']:.2e}"
    )
    return summary


if __name__ == "__main__":
    main()
