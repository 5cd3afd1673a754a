"""``python -m jaxrt.bench.spheres``: built-in spheres (``rt.SphereGeometry``) against the same spheres as
bounding boxes with the built-in analytic sphere function, in one run, speed against error.

Random spheres in a cube seen by a pinhole camera (nearest hit); each row gives the traversal that ran, the
build and trace times (Mrays/s, median of the repeats after a compiling call), the BVH nodes visited per ray
(``rt.tags.stats``, from one more call), the bytes of the structure per primitive (all arrays, and the leaf
arrays alone), and the error of the hit distances against the float64 nearest hit over every sphere on
``--check`` of the rays (median and max relative error where both hit, and rays whose hit or miss differs).

Flags: ``--spheres`` (default 100,000 on a CPU, 1,000,000 on a GPU), ``--rays`` (default 2^16 on a CPU, 2^20 on
a GPU), ``--check`` (rays compared with float64, default 1024), ``--repeats``, ``--backend`` (an intersector
backend for every row, default ``auto``), ``--triangles`` (a third row: one triangle per sphere, inscribed in
its great circle facing the camera, for the traversal's cost on as many primitives of the same extent; its
errors are against the spheres, so not shown), ``--quality`` (tree qualities, comma-separated: ``fast``, ``high``, ``sah``; default ``fast``), ``--quick`` (tiny sizes), ``--json PATH``. Only jax and numpy
are needed.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from typing import Any

import jax
import numpy as np

import jaxrt as rt
from jaxrt.bench.custom import _errors, random_spheres, sphere_reference, traversal_path
from jaxrt.bench.report import machine_info
from jaxrt.bench.timing import timed

__all__ = ["bench", "main"]


def _bytes(structure: Any, count: int) -> dict[str, float]:
    sizes = rt.structure_sizes(structure).arrays
    leaf = sum(v for k, v in sizes.items() if k.startswith(".leaf_"))
    return {"bytes_per_primitive": sum(sizes.values()) / count, "leaf_bytes_per_primitive": leaf / count}


EYE = (0.0, 0.5, 4.0)


def facing_triangles(center: np.ndarray, radius: np.ndarray, eye: tuple = EYE) -> np.ndarray:
    """``(N, 3, 3)`` float32: per sphere, the equilateral triangle inscribed in its great circle that faces
    ``eye`` (as many primitives as spheres, of the same extent)."""
    w = np.asarray(eye, np.float64) - center
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    u = np.cross(w, [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(w, u)
    angles = (0.0, 2 * np.pi / 3, 4 * np.pi / 3)
    corners = [center + radius[:, None] * (np.cos(a) * u + np.sin(a) * v) for a in angles]
    return np.stack(corners, 1).astype(np.float32)


def bench(
    count: int,
    n_rays: int,
    check: int,
    repeats: int,
    backend: str = "auto",
    seed: int = 0,
    triangles: bool = False,
    qualities: Sequence[str] = ("fast",),
) -> list[dict]:
    """The two rows (built-in spheres, boxes with the analytic sphere function) on the same spheres and rays,
    and with ``triangles`` a third: one triangle per sphere (:func:`facing_triangles`); each for every tree
    quality of ``qualities`` (``rt.build_primitive_structure``'s ``quality``)."""
    center, radius = random_spheres(count, seed)
    side = max(1, int(round(n_rays**0.5)))
    camera = rt.shading.pinhole_rays(side, side, eye=EYE, target=(0.0, 0.0, 0.0), fov_degrees=40.0)
    origin = np.asarray(camera.origin).reshape(-1, 3)
    direction = np.asarray(camera.direction).reshape(-1, 3)
    rays = rt.Ray(origin, direction)
    checked = np.random.default_rng(seed).choice(origin.shape[0], min(check, origin.shape[0]), replace=False)
    c32, r32 = center.astype(np.float32), radius.astype(np.float32)
    reference = sphere_reference(c32.astype(np.float64), r32.astype(np.float64), origin[checked], direction[checked])
    lower, upper = rt.intersection_functions.sphere_bounds(c32, r32)
    boxes = rt.BoundingBoxGeometry(lower, upper, primitive_data={"center": c32, "radius": r32})
    functions = {0: rt.intersection_functions.sphere}
    cases = [
        ("built-in spheres (rt.SphereGeometry)", rt.SphereGeometry(c32, r32), None),
        ("boxes + analytic sphere function", boxes, functions),
    ]
    if triangles:
        cases.append(
            ("one triangle per sphere", rt.TriangleGeometry(facing_triangles(center, radius).reshape(-1, 3)), None)
        )
    rows = []
    for (name, geometry, fns), quality in ((case, q) for q in qualities for case in cases):
        intersector = rt.Intersector(backend=backend, intersection_functions=fns)
        counted = rt.Intersector(rt.tags.stats, backend=backend, intersection_functions=fns)
        build, structure = timed(lambda g=geometry, q=quality: rt.build_primitive_structure(g, quality=q), repeats)
        fn = jax.jit(lambda r, s, i=intersector: i.intersect(r, s).distance)
        trace, distance = timed(lambda fn=fn, s=structure: fn(rays, s), repeats)
        distance = np.asarray(distance)[checked]
        visited = float(np.mean(np.asarray(counted.intersect(rays, structure).nodes_visited)))
        sphere = not name.startswith("one triangle")
        rows.append(
            {
                "geometry": name,
                "quality": quality,
                "primitives": count,
                "rays": int(origin.shape[0]),
                "path": traversal_path(intersector, structure),
                "build": build.as_dict(count, "mprims_s"),
                "trace": trace.as_dict(int(origin.shape[0])),
                "nodes_visited_per_ray": visited,
                **_bytes(structure, count),
                "checked_rays": int(checked.shape[0]),
                **(_errors(distance, reference) if sphere else {}),
            }
        )
    return rows


def _print(rows: list[dict]) -> None:
    print(f"{'geometry':<40} {'tree':<5} {'path':<14} {'Mrays/s':>9} {'first s':>8} {'nodes/ray':>9} {'B/prim':>7} {'leaf B':>7} "
          f"{'med err':>9} {'max err':>9} {'mismatch':>8}")  # fmt: skip
    for r in rows:
        t = r["trace"]
        errors = (f"{r['median_rel_error']:>9.2e} {r['max_rel_error']:>9.2e} {r['hit_mismatches']:>8d}"
                  if "hit_mismatches" in r else f"{'-':>9} {'-':>9} {'-':>8}")  # fmt: skip
        print(f"{r['geometry']:<40} {r['quality']:<5} {r['path']:<14} {t['mrays_s']:>9.2f} {t['first_s']:>8.2f} "
              f"{r['nodes_visited_per_ray']:>9.1f} {r['bytes_per_primitive']:>7.1f} {r['leaf_bytes_per_primitive']:>7.1f} "
              f"{errors}")  # fmt: skip
    for quality in dict.fromkeys(r["quality"] for r in rows):
        pair = [r for r in rows if r["quality"] == quality][:2]
        if len(pair) == 2 and pair[1]["trace"]["mrays_s"] > 0:
            print(f"built-in / boxes ({quality}): {pair[0]['trace']['mrays_s'] / pair[1]['trace']['mrays_s']:.2f}x")


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m jaxrt.bench.spheres", description=__doc__.split("\n\n")[0])
    gpu = jax.default_backend() == "gpu"
    parser.add_argument("--spheres", type=int, default=1_000_000 if gpu else 100_000)
    parser.add_argument("--rays", type=int, default=(1 << 20) if gpu else (1 << 16))
    parser.add_argument("--check", type=int, default=1024)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--backend", default="auto")
    parser.add_argument("--triangles", action="store_true")
    parser.add_argument("--quality", default="fast", help="tree qualities, comma-separated (fast, high, sah)")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    if args.quick:
        args.spheres, args.rays, args.check, args.repeats = 200, 1 << 10, 64, 1
    qualities = tuple(q for q in args.quality.split(",") if q)
    rows = bench(
        args.spheres, args.rays, args.check, args.repeats, args.backend, triangles=args.triangles, qualities=qualities
    )
    info = machine_info()
    print(f"# spheres={args.spheres} rays={args.rays} checked={args.check} repeats={args.repeats} {info}")
    _print(rows)
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"machine": info, "rows": rows}, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
