"""``python -m jaxrt.bench.custom`` (also ``python -m jaxrt.bench --custom``): custom geometry, speed against
error.

Two tables:

1. *Spheres.* The same random spheres as bounding boxes with the built-in analytic intersection function
   (``rt.intersection_functions.sphere``, which the GPU kernel traces itself), as boxes with a user function
   calling it (on the GPU: the kernel lists candidate boxes, JAX calls the function), and tessellated to icospheres of 80, 320 and 1280
   triangles. Mrays/s of camera rays, and the distance error of each against the float64 analytic nearest
   hit (median and max relative error over rays where both hit, and rays whose hit/miss differs from the
   reference).
2. *Filters.* One triangle mesh traced opaque without a filter, opaque with a filter (which opaque geometry
   never uses), non-opaque with a filter that accepts everything, non-opaque with an alpha filter that
   rejects about half the triangles by their primitive data (decided once per primitive on the GPU), and one
   that reads the hit's barycentrics (called per candidate, in candidate waves on the GPU); also the 4
   nearest hits (``max_hits=4``), ``count_intersections``, and the alpha filter as the loop of an
   intersection query (``rt.intersection_query``: on the GPU the kernel lists its candidates).
   Each row of both tables names the traversal that ran (``path``: the GPU kernel, the CPU traversal or the
   portable one).

Flags: ``--quick`` (tiny sizes, one repeat), ``--spheres``, ``--triangles``, ``--rays``, ``--repeats``,
``--json PATH``; ``--waves K,LATER ...`` adds a third table (``--waves-only``: only it): the alpha filter and
the user sphere function with ``K`` candidates per ray in the first wave and ``LATER`` in the others, each
with the rays still active before each wave (``jaxrt._src.traversal.waves``), and the opaque mesh as
reference. Only jax and numpy are needed.
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

import jaxrt as rt
from jaxrt._src import pipeline
from jaxrt._src.intersector import _CountingIntersector
from jaxrt.bench.gradients import camera_rays, noisy_sphere
from jaxrt.bench.report import machine_info
from jaxrt.bench.timing import timed

__all__ = ["main", "icosphere", "sphere_reference"]

_DEFAULTS = dict(spheres=2_000, triangles=100_000, rays=1 << 16, repeats=3)
_QUICK = dict(spheres=50, triangles=2_000, rays=1 << 10, repeats=1)


def icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """A unit icosphere: ``(vertices, faces)`` with ``20 * 4**subdivisions`` faces, vertices on the sphere."""
    t = (1 + 5**0.5) / 2
    v = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t), (0, -1, -t), (0, 1, -t)]
    v += [(t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]
    f = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2)]
    f += [(10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5), (2, 4, 11)]
    f += [(6, 2, 10), (8, 6, 7), (9, 8, 1)]
    vertices = [np.array(p, float) / np.linalg.norm(p) for p in v]
    faces = f
    for _ in range(subdivisions):
        cache: dict[tuple[int, int], int] = {}

        def middle(a: int, b: int, cache: dict = cache) -> int:
            key = (min(a, b), max(a, b))
            if key not in cache:
                m = vertices[a] + vertices[b]
                vertices.append(m / np.linalg.norm(m))
                cache[key] = len(vertices) - 1
            return cache[key]

        faces = [
            face
            for a, b, c in faces
            for face in ((a, middle(a, b), middle(c, a)), (b, middle(b, c), middle(a, b)),
                         (c, middle(c, a), middle(b, c)), (middle(a, b), middle(b, c), middle(c, a)))
        ]  # fmt: skip
    return np.array(vertices), np.array(faces, np.int32)


def random_spheres(count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``count`` spheres in the cube [-1, 1]^3, a sparse particle cloud: a ray through the cube's full depth
    crosses about 0.67 spheres (half such rays miss every sphere), the mean radius is 0.066 (100k spheres) of
    the mean spacing ``(8 / count)^(1/3)`` and the spheres fill about 0.1% of the cube."""
    rng = np.random.default_rng(seed)
    center = rng.uniform(-1, 1, (count, 3))
    radius = rng.uniform(0.5, 1.0, count) * 1.2 / np.sqrt(count)
    return center, radius


def sphere_reference(center: np.ndarray, radius: np.ndarray, origin: np.ndarray, direction: np.ndarray):
    """Float64 nearest analytic hit distance of each ray over all spheres (``inf``: miss)."""
    best = np.full(origin.shape[0], np.inf)
    o, d = origin.astype(np.float64), direction.astype(np.float64)
    a = np.sum(d * d, axis=1)
    for start in range(0, center.shape[0], 256):
        c, r = center[start : start + 256], radius[start : start + 256]
        f = o[:, None, :] - c[None]
        b = np.sum(f * d[:, None, :], axis=2)
        # Closest-approach form of the discriminant (Haines et al., Ray Tracing Gems ch. 7).
        g = f - (b / a[:, None])[..., None] * d[:, None, :]
        disc = r[None] ** 2 - np.sum(g * g, axis=2)
        ok = disc >= 0
        q = -b - np.sign(b + (b == 0)) * np.sqrt(np.where(ok, disc, 0) * a[:, None])
        t0 = np.where(q != 0, q / a[:, None], 0.0)
        t1 = np.where(q != 0, (np.sum(f * f, axis=2) - r[None] ** 2) / np.where(q != 0, q, 1), 0.0)
        near, far = np.minimum(t0, t1), np.maximum(t0, t1)
        t = np.where(near >= 0, near, far)
        best = np.minimum(best, np.where(ok & (t >= 0), t, np.inf).min(axis=1))
    return best


def _errors(distance: np.ndarray, reference: np.ndarray) -> dict[str, float]:
    hit, ref_hit = np.isfinite(distance), np.isfinite(reference)
    both = hit & ref_hit
    relative = np.abs(distance[both] - reference[both]) / reference[both]
    return {
        "hits": int(hit.sum()),
        "hit_mismatches": int((hit != ref_hit).sum()),
        "median_rel_error": float(np.median(relative)) if relative.size else 0.0,
        "max_rel_error": float(relative.max()) if relative.size else 0.0,
    }


def _trace(intersector: rt.Intersector, structure: Any, rays: rt.Ray, repeats: int) -> tuple[dict, Any]:
    fn = jax.jit(lambda r, s: intersector.intersect(r, s).distance)
    timing, distance = timed(lambda: fn(rays, structure), repeats)
    return timing.as_dict(int(rays.origin.shape[0])), np.asarray(distance)


def bench_spheres(count: int, n_rays: int, repeats: int, seed: int = 0) -> list[dict[str, Any]]:
    """Spheres as boxes with the analytic function against tessellated spheres (see the module docstring)."""
    center, radius = random_spheres(count, seed)
    rays = rt.shading.pinhole_rays(
        *(2 * [max(1, int(round(n_rays**0.5)))]), eye=(0.0, 0.5, 4.0), target=(0.0, 0.0, 0.0), fov_degrees=40.0
    )
    origin = np.asarray(rays.origin).reshape(-1, 3)
    direction = np.asarray(rays.direction).reshape(-1, 3)
    rays = rt.Ray(origin, direction)
    reference = sphere_reference(center, radius, origin, direction)
    rows = []
    lower, upper = rt.intersection_functions.sphere_bounds(center.astype(np.float32), radius.astype(np.float32))
    data = {"center": center.astype(np.float32), "radius": radius.astype(np.float32)}
    boxes = rt.BoundingBoxGeometry(lower, upper, primitive_data=data)
    build, structure = timed(lambda: rt.build_primitive_structure(boxes), repeats)

    def user_sphere(ray, candidate):
        return rt.intersection_functions.sphere(ray, candidate)

    functions = (("boxes + analytic sphere", rt.intersection_functions.sphere),
                 ("boxes + user sphere function", user_sphere))  # fmt: skip
    for name, fn in functions:
        intersector = rt.Intersector(intersection_functions={0: fn})
        trace, distance = _trace(intersector, structure, rays, repeats)
        rows.append({"geometry": name, "primitives": count, "build": build.as_dict(count, "mprims_s"), "trace": trace,
                     **_errors(distance, reference), "path": traversal_path(intersector, structure)})  # fmt: skip
    for level in (1, 2, 3):
        unit, faces = icosphere(level)
        vertices = (center[:, None, :] + radius[:, None, None] * unit[None]).reshape(-1, 3).astype(np.float32)
        indices = (faces[None] + (np.arange(count) * unit.shape[0])[:, None, None]).reshape(-1, 3)
        mesh = rt.TriangleGeometry(vertices, indices)
        build, structure = timed(lambda mesh=mesh: rt.build_primitive_structure(mesh), repeats)
        trace, distance = _trace(rt.Intersector(), structure, rays, repeats)
        rows.append({"geometry": f"icospheres, {faces.shape[0]} triangles each", "primitives": int(indices.shape[0]),
                     "build": build.as_dict(int(indices.shape[0]), "mprims_s"), "trace": trace,
                     **_errors(distance, reference), "path": traversal_path(rt.Intersector(), structure)})  # fmt: skip
    return rows


def traversal_path(intersector: rt.Intersector, structure: Any) -> str:
    """Which traversal ``intersector`` runs on ``structure`` on this machine: ``"gpu kernel"``,
    ``"cpu traversal"`` or ``"portable"`` (the choice :func:`jaxrt._src.pipeline.trace` makes)."""
    backend = pipeline.resolve_backend(intersector)
    if backend == "portable" or pipeline.kernel_declines(intersector, structure.geometry_info, backend):
        return "portable"
    return "gpu kernel" if backend == "gpu" else "cpu traversal"


def alpha_at_hit(candidate: rt.TriangleCandidate) -> jax.Array:
    """An alpha test that reads the hit (as a texture lookup does): the primitive's alpha shifted by the
    barycentrics, so that about half the candidates are rejected and the filter runs per candidate."""
    u, v = candidate.barycentric_coord[0], candidate.barycentric_coord[1]
    return candidate.primitive_data["alpha"] + 0.25 * (u - v) >= 0.5


def bench_filters(triangles: int, n_rays: int, repeats: int, seed: int = 0) -> list[dict[str, Any]]:
    """The cost of filters on opaque and non-opaque geometry, of multi-hit and of counting."""
    vertices, indices = noisy_sphere(triangles, seed)
    alpha = np.random.default_rng(seed).uniform(0, 1, indices.shape[0]).astype(np.float32)
    rays = camera_rays(n_rays).reshape(-1)
    n = int(rays.origin.shape[0])

    def structure(opaque: bool):
        geometry = rt.TriangleGeometry(vertices, indices, opaque=opaque, primitive_data={"alpha": alpha})
        return rt.build_primitive_structure(geometry)

    opaque, clear = structure(True), structure(False)
    everything = lambda c: jnp.asarray(True)  # noqa: E731
    half = lambda c: c.primitive_data["alpha"] >= 0.5  # noqa: E731
    cases = [
        ("opaque, no filter", rt.Intersector(), opaque),
        ("opaque, filter (never called)", rt.Intersector(filter=half), opaque),
        ("non-opaque, filter accepting all", rt.Intersector(filter=everything), clear),
        ("non-opaque, alpha filter (~50% rejected)", rt.Intersector(filter=half), clear),
        ("non-opaque, alpha at the hit (~50% rejected)", rt.Intersector(filter=alpha_at_hit), clear),
        ("opaque, max_hits=4", rt.Intersector(max_hits=4), opaque),
    ]
    rows = []
    for name, intersector, s in cases:
        trace, distance = _trace(intersector, s, rays, repeats)
        hits = np.isfinite(distance if distance.ndim == 1 else distance[:, 0])
        rows.append({"case": name, "trace": trace, "hits": int(hits.sum()), "path": traversal_path(intersector, s)})
    count = jax.jit(rt.count_intersections)
    timing, counts = timed(lambda: count(rays, opaque), repeats)
    rows.append({"case": "opaque, count_intersections", "trace": timing.as_dict(n), "hits": int(np.sum(counts > 0)),
                 "path": traversal_path(_CountingIntersector(), opaque)})  # fmt: skip
    timing, distance = timed(lambda: _alpha_query(rays, clear), repeats)
    rows.append({"case": "non-opaque, alpha test in an intersection query's loop (~50% rejected)",
                 "trace": timing.as_dict(n), "hits": int(np.sum(np.isfinite(np.asarray(distance)))),
                 "path": query_path(rt.Intersector(), clear)})  # fmt: skip
    return rows


@jax.jit
def _alpha_query(rays: rt.Ray, structure: Any) -> jax.Array:
    """The alpha filter as Metal's intersection-query loop: each candidate committed where its alpha passes."""

    def one(ray):
        def body(q):
            return q.commit_triangle_intersection(q.candidate_primitive_data["alpha"] >= 0.5).next()

        q = rt.intersection_query(ray, structure, rt.Intersector())
        return lax.while_loop(lambda q: q.has_candidate, body, q.next()).committed_distance

    return jax.vmap(one)(rays)


def query_path(intersector: rt.Intersector, structure: Any) -> str:
    """How ``rt.intersection_query`` finds candidates on this machine: ``"gpu kernel (listing)"`` or
    ``"portable"`` (its traversal, stepped per candidate)."""
    from jaxrt._src import query

    return "gpu kernel (listing)" if query.lists_with_the_kernel(intersector, structure) else "portable"


@functools.partial(jax.jit, static_argnums=(0, 4))
def _wave(intersector: rt.Intersector, structure: Any, rays: rt.Ray, state: Any, k: int) -> Any:
    """One candidate wave of ``k`` per ray (the first when ``state`` is ``None``)."""
    from jaxrt._src.leaves import leaf_tester
    from jaxrt._src.scene_view import scene_view
    from jaxrt._src.traversal import waves

    view = scene_view(structure)
    sanitized = pipeline.sanitized_rays(rays)
    lister = pipeline.wave_lister(intersector, view, sanitized)
    loop = waves.WaveLoop(intersector, leaf_tester(intersector, view), sanitized, lister)
    return loop.wave(loop.initial() if state is None else state, k)


def wave_counts(intersector: rt.Intersector, structure: Any, rays: rt.Ray, first: int, later: int) -> list[int]:
    """The rays still active before each candidate wave (:mod:`jaxrt._src.traversal.waves`), wave by wave."""
    counts = [int(jnp.sum(pipeline.sanitized_rays(rays).enabled))]
    state = _wave(intersector, structure, rays, None, first)
    while int(jnp.sum(state.active)) and len(counts) < 64:
        counts.append(int(jnp.sum(state.active)))
        state = _wave(intersector, structure, rays, state, later)
    return counts


def bench_waves(triangles: int, spheres: int, n_rays: int, repeats: int, settings: Sequence[tuple[int, int]],
                seed: int = 0) -> list[dict[str, Any]]:  # fmt: skip
    """The alpha filter and the user sphere function with ``(K, LATER)`` candidates per wave: speed, and the
    active rays before each wave."""
    from jaxrt._src.traversal import waves

    vertices, indices = noisy_sphere(triangles, seed)
    alpha = np.random.default_rng(seed).uniform(0, 1, indices.shape[0]).astype(np.float32)
    mesh = rt.TriangleGeometry(vertices, indices, opaque=False, primitive_data={"alpha": alpha})
    center, radius = random_spheres(spheres, seed)
    lower, upper = rt.intersection_functions.sphere_bounds(center.astype(np.float32), radius.astype(np.float32))
    data = {"center": center.astype(np.float32), "radius": radius.astype(np.float32)}
    boxes = rt.BoundingBoxGeometry(lower, upper, primitive_data=data)

    def user_sphere(ray, candidate):
        return rt.intersection_functions.sphere(ray, candidate)

    camera = rt.shading.pinhole_rays(
        *(2 * [max(1, int(round(n_rays**0.5)))]), eye=(0.0, 0.5, 4.0), target=(0.0, 0.0, 0.0), fov_degrees=40.0
    ).reshape(-1)
    cases = [
        ("alpha at the hit (~50% rejected)", rt.Intersector(filter=alpha_at_hit),
         rt.build_primitive_structure(mesh), camera_rays(n_rays).reshape(-1)),
        ("user sphere function", rt.Intersector(intersection_functions={0: user_sphere}),
         rt.build_primitive_structure(boxes), camera),
        ("opaque reference (no waves)", rt.Intersector(), rt.build_primitive_structure(
            rt.TriangleGeometry(vertices, indices)), camera_rays(n_rays).reshape(-1)),
    ]  # fmt: skip
    rows = []
    saved = waves.CANDIDATES, waves.LATER_CANDIDATES
    try:
        for first, later in settings:
            waves.CANDIDATES, waves.LATER_CANDIDATES = first, later
            jax.clear_caches()
            for name, intersector, structure, rays in cases:
                trace, _ = _trace(intersector, structure, rays, repeats)
                path = traversal_path(intersector, structure)
                uses_waves = "waves" not in name and path == "gpu kernel"  # elsewhere: the portable traversal
                counts = wave_counts(intersector, structure, rays, first, later) if uses_waves else []
                rows.append({"case": name, "candidates": [first, later], "trace": trace, "active_per_wave": counts,
                             "path": path})  # fmt: skip
    finally:
        waves.CANDIDATES, waves.LATER_CANDIDATES = saved
    return rows


def format_tables(results: dict[str, Any]) -> str:
    """Both tables as Markdown."""
    lines = ["| spheres as | primitives | build Mprims/s | Mrays/s | hits | hit/miss vs ref | median rel err | max rel err | traversal |",
             "|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for r in results["spheres"]:
        lines.append(
            f"| {r['geometry']} | {r['primitives']:,} | {r['build']['mprims_s']:.2f} | {r['trace']['mrays_s']:.3f} "
            f"| {r['hits']:,} | {r['hit_mismatches']} | {r['median_rel_error']:.1e} | {r['max_rel_error']:.1e} "
            f"| {r.get('path', '')} |"
        )
    lines += ["", "| filter case | Mrays/s | hits | traversal |", "|---|---|---|---|"]
    for r in results["filters"]:
        lines.append(f"| {r['case']} | {r['trace']['mrays_s']:.3f} | {r['hits']:,} | {r.get('path', '')} |")
    if results.get("waves"):
        lines += [
            "",
            "| case | K, later | Mrays/s | active rays before each wave | traversal |",
            "|---|---|---|---|---|",
        ]
        for r in results["waves"]:
            k, later = r["candidates"]
            counts = ", ".join(f"{c:,}" for c in r["active_per_wave"]) or "-"
            lines.append(f"| {r['case']} | {k}, {later} | {r['trace']['mrays_s']:.3f} | {counts} | {r['path']} |")
    return "\n".join(lines)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m jaxrt.bench.custom", description=__doc__.splitlines()[0])
    parser.add_argument("--spheres", type=int, help=f"spheres (default {_DEFAULTS['spheres']:,})")
    parser.add_argument("--triangles", type=int, help=f"mesh triangles (default {_DEFAULTS['triangles']:,})")
    parser.add_argument("--rays", type=int, help=f"camera rays (default {_DEFAULTS['rays']:,})")
    parser.add_argument("--repeats", type=int, help="warm runs per measurement (default 3)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true", help="tiny sizes and one repeat: a smoke test")
    parser.add_argument("--json", metavar="PATH", help="also write every number and the machine info to PATH")
    parser.add_argument("--waves", nargs="+", metavar="K,LATER",
                        help="also a table of candidate waves with these candidates per ray (first wave, later ones)")  # fmt: skip
    parser.add_argument("--waves-only", action="store_true", help="only the table of candidate waves")
    return parser


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run both tables, print them, and write the JSON file if asked; returns the results."""
    args = _parser().parse_args(argv)
    sizes = {**(_QUICK if args.quick else _DEFAULTS), **{k: v for k, v in vars(args).items() if v is not None}}
    results = {
        "machine": machine_info(),
        "config": {k: sizes[k] for k in ("spheres", "triangles", "rays", "repeats", "seed")},
        "spheres": []
        if args.waves_only
        else bench_spheres(sizes["spheres"], sizes["rays"], sizes["repeats"], args.seed),
        "filters": []
        if args.waves_only
        else bench_filters(sizes["triangles"], sizes["rays"], sizes["repeats"], args.seed),
    }
    if args.waves or args.waves_only:
        settings = [tuple(int(x) for x in setting.split(",")) for setting in (args.waves or ["4,16"])]
        settings = [(s[0], s[-1]) for s in settings]
        results["waves"] = bench_waves(
            sizes["triangles"], sizes["spheres"], sizes["rays"], sizes["repeats"], settings, args.seed
        )
    print(format_tables(results))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)
        print(f"wrote {args.json}")
    return results


if __name__ == "__main__":
    main(sys.argv[1:])
    sys.exit(0)
