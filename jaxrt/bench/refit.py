"""``python -m jaxrt.bench.refit``: refit against rebuild on a deforming mesh, frame by frame.

The mesh (the Stanford bunny from the shared data folder, or with ``--scene sphere`` or when the data is
absent, the procedural noisy sphere) is twisted about its vertical axis, a little more each frame: each vertex
turns by ``angle * h`` where ``h`` in ``[-1/2, 1/2]`` is its relative height. Each frame the structure built
at frame 0 is refit (:func:`jaxrt.refit`: same topology, new boxes) and a new one is built, and the bench
reports for both the build time, the SAH cost (:func:`jaxrt.sah_cost`), the nodes visited per primary ray
(``rt.tags.stats``) and the trace time, and checks that both give the same hits.

The refit keeps the Morton order of frame 0, so as primitives move relative to each other its boxes grow and
overlap: the SAH drift ``sah(refit) / sah(rebuild)`` tracks the extra traversal work. The rule this bench
supports (docs/lifecycle.md): refit while ``sah_cost(refit) <= 1.2 * sah_cost`` of the structure at its last
build, and rebuild past it (the ratio needs no rebuild to compute; ``sah_cost`` is a host pass over the nodes,
so check it every few frames).
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import jax
import numpy as np

import jaxrt as rt
from jaxrt.bench.rays import primary_rays
from jaxrt.bench.scenes import Scene, noisy_sphere, shared_mesh
from jaxrt.bench.timing import timed

__all__ = ["main", "twist", "run"]


def twist(vertices: np.ndarray, angle: float) -> np.ndarray:
    """Turn each vertex about the vertical (y) axis through the box centre by ``angle * h`` radians, ``h`` its
    height relative to the box, in ``[-1/2, 1/2]``."""
    lower, upper = vertices.min(axis=0), vertices.max(axis=0)
    centre = (lower + upper) / 2.0
    h = (vertices[:, 1] - centre[1]) / max(float(upper[1] - lower[1]), 1e-30)
    theta = angle * h
    c, s = np.cos(theta), np.sin(theta)
    x, z = vertices[:, 0] - centre[0], vertices[:, 2] - centre[2]
    out = np.stack([c * x + s * z + centre[0], vertices[:, 1], -s * x + c * z + centre[2]], axis=1)
    return out.astype(np.float32)


def _scene(name: str, triangles: int) -> tuple[Scene, str | None]:
    if name == "sphere":
        return noisy_sphere(triangles), None
    try:
        return shared_mesh(name), None
    except (FileNotFoundError, KeyError) as error:
        return noisy_sphere(triangles), f"{name} unavailable ({error}); using the procedural sphere"


def run(scene: Scene, *, frames: int, max_angle: float, rays: int, repeats: int) -> list[dict]:
    """One row per frame: ``angle``, and for ``refit`` and ``rebuild`` the build ms, SAH cost, mean nodes
    visited, trace ms and Mrays/s; ``mismatches``: rays whose hit (primitive or distance) differs."""
    indices = np.asarray(scene.indices)
    base = np.asarray(scene.vertices, np.float32)
    batch = primary_rays(base, rays)
    ray = rt.Ray(batch.origin, batch.direction)
    intersector = rt.Intersector(rt.tags.stats)
    structure = rt.build_primitive_structure(rt.TriangleGeometry(base, indices))
    trace = jax.jit(lambda s: intersector.intersect(ray, s))
    rows = []
    for frame in range(frames + 1):
        angle = max_angle * frame / max(frames, 1)
        geometry = rt.TriangleGeometry(twist(base, angle), indices)
        refit_time, refitted = timed(lambda g=geometry: rt.refit(structure, g), repeats)
        build_time, rebuilt = timed(lambda g=geometry: rt.build_primitive_structure(g), repeats)
        row = {"frame": frame, "angle": angle}
        results = {}
        for name, s, t in (("refit", refitted, refit_time), ("rebuild", rebuilt, build_time)):
            trace_time, result = timed(lambda s=s: trace(s), repeats)
            results[name] = result
            row[name] = {
                "build_ms": t.median_s * 1e3,
                "sah": rt.sah_cost(s),
                "nodes_per_ray": float(np.mean(np.asarray(result.nodes_visited))),
                "trace_ms": trace_time.median_s * 1e3,
                "mrays_s": rays / trace_time.median_s / 1e6,
            }
        a, b = results["refit"], results["rebuild"]
        row["mismatches"] = int(
            np.sum(
                (np.asarray(a.primitive_id) != np.asarray(b.primitive_id))
                | (np.asarray(a.distance) != np.asarray(b.distance))
            )
        )
        row["drift"] = row["refit"]["sah"] / row["rebuild"]["sah"]
        rows.append(row)
    return rows


def table(rows: list[dict]) -> str:
    """A markdown table of :func:`run`'s rows."""
    lines = [
        "| frame | twist (rad) | refit ms | rebuild ms | SAH refit | SAH rebuild | drift | nodes/ray refit | "
        "nodes/ray rebuild | Mrays/s refit | Mrays/s rebuild | mismatches |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        a, b = r["refit"], r["rebuild"]
        lines.append(
            f"| {r['frame']} | {r['angle']:.2f} | {a['build_ms']:.1f} | {b['build_ms']:.1f} | {a['sah']:.1f} | "
            f"{b['sah']:.1f} | {r['drift']:.2f} | {a['nodes_per_ray']:.1f} | {b['nodes_per_ray']:.1f} | "
            f"{a['mrays_s']:.2f} | {b['mrays_s']:.2f} | {r['mismatches']} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point (see the module docstring)."""
    parser = argparse.ArgumentParser(prog="python -m jaxrt.bench.refit", description=__doc__.split("\n")[0])
    parser.add_argument("--scene", default="bunny", help="bunny (shared data), another shared mesh, or sphere")
    parser.add_argument("--triangles", type=int, default=100_000, help="triangles of the procedural sphere")
    parser.add_argument("--frames", type=int, default=6, help="frames after the first")
    parser.add_argument("--max-angle", type=float, default=3.0, help="twist at the last frame, radians")
    parser.add_argument("--rays", type=int, default=128 * 128)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--json", help="write the rows to this file")
    args = parser.parse_args(argv)
    scene, note = _scene(args.scene, args.triangles)
    if note:
        print(f"note: {note}", file=sys.stderr)
    print(f"{scene.description}; {args.rays} primary rays; jax {jax.__version__} on {jax.default_backend()}")
    start = time.perf_counter()
    rows = run(scene, frames=args.frames, max_angle=args.max_angle, rays=args.rays, repeats=args.repeats)
    print(table(rows))
    print(f"({time.perf_counter() - start:.0f} s)")
    if args.json:
        with open(args.json, "w") as file:
            json.dump({"scene": scene.description, "rows": rows}, file, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
