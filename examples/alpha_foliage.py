"""Alpha-tested foliage: leaf quads cut out by a texture, traced with a filter and with an intersection query.

Each leaf is a quad of two non-opaque triangles (``opaque=False``) whose per-triangle UVs live in
``primitive_data``. The filter interpolates the UVs at the candidate's barycentrics and looks up a procedural
leaf-shaped alpha mask (veins cut out); rejected candidates let the ray go on to the leaves, trunk and ground
behind. Shadow rays toward the sun use the same filter with ``accept_any_intersection``. The same image is
then traced with ``rt.intersection_query`` and the alpha test in the user's own loop (the loop of Metal's
WWDC21 alpha-testing example), and the two images are compared pixel by pixel.

Run: ``python examples/alpha_foliage.py [--width 160] [--height 120] [--leaves 400] [--out out/alpha_foliage.png]``
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

import jaxrt as rt

SUN = np.array([0.5, 0.8, 0.3]) / np.linalg.norm([0.5, 0.8, 0.3])
CORNERS = jnp.array([[0, 1, 2]])  # rt.shading.interpolate over one triangle's three corner values


def leaf_mask(size=64):
    """``(size, size)`` alpha: a pointed leaf (u across, v along the leaf) with its midrib and side veins cut out."""
    v, u = np.meshgrid((np.arange(size) + 0.5) / size, (np.arange(size) + 0.5) / size - 0.5, indexing="ij")
    half_width = 0.46 * np.sin(np.pi * v) ** 0.8 * (1.0 - 0.35 * v)
    blade = np.abs(u) < half_width
    midrib = (np.abs(u) < 0.025) & (v > 0.08) & (v < 0.9)
    side = np.abs(((v - 1.4 * np.abs(u)) * 7.0) % 1.0 - 0.5) < 0.07  # chevrons along the midrib
    veins = midrib | (side & (np.abs(u) < 0.8 * half_width) & (v > 0.15))
    return (blade & ~veins).astype(np.float32)


def alpha_test(texture, uv_corners, barycentric):
    """Whether the texture is opaque at the hit: UVs interpolated from the triangle's corners, bilinear lookup."""
    uv = rt.shading.interpolate(uv_corners, CORNERS, jnp.int32(0), barycentric)
    return rt.shading.texture_lookup(texture, uv) >= 0.5


def scene(leaves, seed=0):
    """Ground, trunk (opaque) and leaf quads (non-opaque), all with one primitive-data layout."""
    rng = np.random.default_rng(seed)

    def geometry(triangles, albedo, uv=None, opaque=True):
        t = np.asarray(triangles, np.float32).reshape(-1, 3, 3)
        normal = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        data = {
            "uv": np.zeros((len(t), 3, 2), np.float32) if uv is None else uv.astype(np.float32),
            "normal": (normal / np.linalg.norm(normal, axis=1, keepdims=True)).astype(np.float32),
            "albedo": np.broadcast_to(np.asarray(albedo, np.float32), (len(t), 3)).copy(),
        }
        return rt.TriangleGeometry(t.reshape(-1, 3), primitive_data=data, opaque=opaque)

    g = 8.0
    ground = [[-g, 0, -g], [g, 0, g], [g, 0, -g], [-g, 0, -g], [-g, 0, g], [g, 0, g]]
    angle = np.linspace(0, 2 * np.pi, 9)
    ring = lambda r, y: np.stack([r * np.cos(angle), np.full(9, y), r * np.sin(angle)], 1)  # noqa: E731
    bottom, top = ring(0.22, 0.0), ring(0.12, 2.6)
    trunk = [[bottom[i], top[i], bottom[i + 1]] for i in range(8)] + [
        [bottom[i + 1], top[i], top[i + 1]] for i in range(8)
    ]
    # Leaves: quads around a crown, each with a random orientation; corners (0,0) (1,0) (1,1) (0,1) in UV space.
    center = np.array([0.0, 2.7, 0.0]) + rng.normal(size=(leaves, 3)) * [0.9, 0.55, 0.9]
    axes = np.linalg.qr(rng.normal(size=(leaves, 3, 3)))[0] * 0.22
    quad = np.array([[-0.5, 0], [0.5, 0], [0.5, 1.6], [-0.5, 1.6]])
    corners = center[:, None] + quad[None, :, :1] * axes[:, None, 0] + quad[None, :, 1:] * axes[:, None, 1]
    uv = np.array([[0.0, 0], [1, 0], [1, 1], [0, 1]])
    triangles = np.stack([corners[:, [0, 1, 2]], corners[:, [0, 2, 3]]], 1).reshape(-1, 3, 3)
    leaf_uv = np.tile(np.stack([uv[[0, 1, 2]], uv[[0, 2, 3]]]), (leaves, 1, 1))
    green = np.repeat([0.18, 0.45, 0.12] * rng.uniform(0.7, 1.2, (leaves, 1)), 2, axis=0)
    return [
        geometry(ground, [0.55, 0.5, 0.4]),
        geometry(trunk, [0.35, 0.22, 0.12]),
        geometry(triangles, green, leaf_uv, opaque=False),
    ]


def query_trace(structure, texture, any_hit):
    """Trace rays with ``rt.intersection_query``: the alpha test runs in the user's loop, as in Metal::

    intersection_query<triangle_data> i(r, accel);
    while (i.next()) {
        if (i.get_candidate_intersection_type() == intersection_type::triangle) {
            if (alphaTest(i.get_candidate_primitive_id(), i.get_candidate_triangle_barycentric_coord()))
                i.commit_triangle_intersection();
        }
    }
    ... i.get_committed_intersection_type(), i.get_committed_distance() ...
    """

    def one(ray):
        q = rt.intersection_query(ray, structure, rt.Intersector(accept_any_intersection=any_hit))

        def body(q):
            is_triangle = q.candidate_type == rt.IntersectionType.TRIANGLE
            accept = alpha_test(texture, q.candidate_primitive_data["uv"], q.candidate_triangle_barycentric_coord)
            return q.commit_triangle_intersection(is_triangle & accept).next()

        q = lax.while_loop(lambda q: q.has_candidate, body, q.next())  # while (i.next()) { body }
        return {
            "type": q.committed_type,
            "distance": q.committed_distance,
            "primitive_data": q.committed_primitive_data,
        }

    # A vmapped loop runs until its slowest ray ends: small batches of rays, one after another, waste less.
    return jax.jit(lambda rays: lax.map(one, rays, batch_size=64))


def filter_trace(structure, texture, any_hit):
    """Trace rays with the intersector: the same alpha test as its filter."""
    keep = lambda c: alpha_test(texture, c.primitive_data["uv"], c.barycentric_coord)  # noqa: E731
    intersector = rt.Intersector(rt.tags.primitive_data, filter=keep, accept_any_intersection=any_hit)

    def trace(rays):
        hit = intersector.intersect(rays, structure)
        return {k: hit[k] for k in ("type", "distance", "primitive_data")}  # the fields the query loop returns

    return jax.jit(trace)


@jax.jit
def shadow_rays(rays, hit):
    """Rays from the lit side of each hit toward the sun (disabled for misses and surfaces facing away)."""
    found = hit["type"] != 0
    point = rays.origin + jnp.where(found, hit["distance"], 0.0)[:, None] * rays.direction
    normal = rt.shading.face_forward(hit["primitive_data"]["normal"], rays.direction)
    lit = found & (jnp.sum(normal * SUN, -1) > 0)
    origin = rt.offset_ray_origin(point, normal)
    return rt.Ray(origin, jnp.broadcast_to(SUN, origin.shape), 0.0, jnp.where(lit, 100.0, -1.0))


@jax.jit
def shade(rays, hit, blocked):
    """Lambert under the sun, shadowed where ``blocked``, over a sky gradient: ``(N, 3)`` in [0, 1]."""
    normal = rt.shading.face_forward(hit["primitive_data"]["normal"], rays.direction)
    sun = rt.shading.lambert(normal, jnp.asarray(SUN, jnp.float32)) * ~blocked
    color = hit["primitive_data"]["albedo"] * (0.25 + 0.9 * sun)[:, None]
    sky = jnp.array([0.55, 0.7, 0.95]) + 0.3 * rays.direction[:, 1:2]
    return jnp.clip(jnp.where((hit["type"] != 0)[:, None], color, sky), 0, 1)


def render(primary, shadow, rays):
    """Primary hits, shadow rays, shading: only the two traces differ between the filter and the query."""
    hit = primary(rays)
    return shade(rays, hit, shadow(shadow_rays(rays, hit))["type"] != 0)


def timed(fn, *args):
    """(result, first call seconds, warm call seconds)."""
    start = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    first = time.perf_counter() - start
    start = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return out, first, time.perf_counter() - start


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--height", type=int, default=120)
    parser.add_argument("--leaves", type=int, default=400)
    parser.add_argument("--out", default="out/alpha_foliage.png")
    args = parser.parse_args(argv)

    texture = jnp.asarray(leaf_mask())
    structure, build_first, build = timed(rt.build_primitive_structure, scene(args.leaves))
    camera = rt.shading.pinhole_rays(args.width, args.height, eye=(4.0, 2.2, 5.0), target=(0, 1.9, 0), fov_degrees=50)
    rays = camera.reshape(-1)
    print(
        f"alpha foliage on {jax.default_backend()}: {args.leaves} leaves ({2 * args.leaves} non-opaque triangles), "
        f"{args.width}x{args.height} pixels, build {build * 1e3:.1f} ms; primary + shadow rays:"
    )
    images, report = {}, {}
    for name, make in (("filter", filter_trace), ("query", query_trace)):
        primary, shadow = make(structure, texture, False), make(structure, texture, True)
        images[name], first, warm = timed(render, primary, shadow, rays)
        report[name] = dict(first_s=first, warm_s=warm)
        print(f"  {name:6s} first call (compiles) {first:6.2f} s, warm {warm * 1e3:7.1f} ms")
    differing = int(np.sum(np.any(np.asarray(images["filter"]) != np.asarray(images["query"]), axis=-1)))
    print(f"  filter and query images differ in {differing} of {args.width * args.height} pixels")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    from PIL import Image

    image = np.asarray(images["filter"]).reshape(args.height, args.width, 3)
    Image.fromarray((image ** (1 / 2.2) * 255).astype(np.uint8), "RGB").save(out)
    print(f"wrote {out}")
    assert differing == 0, f"the filter and the query loop disagree on {differing} pixels"
    return {"differing_pixels": differing, "build_s": build, **report}


if __name__ == "__main__":
    main()
