"""``python -m jaxrt.bench.gradients``: the cost of gradients through intersections.

Forward against forward + backward throughput (Mrays/s) on a procedural mesh (a noisy UV sphere) seen by a
pinhole camera, for the differentiable hit quantities (the distance and ``triangle_barycentric_coord``):

============================  ==============================================================================
measurement                   what one call does
============================  ==============================================================================
``trace``                     intersect (closest hit, ``triangle_data``) with a prebuilt structure
``trace+grad(rays)``          the same and the gradient of a weighted sum of distances and barycentrics
                              with respect to every ray origin and direction
``build+trace``               build the structure from the vertices, then intersect
``build+trace+grad(vertices)`` the same and the gradient with respect to every vertex position
``build+trace+grad(all)``     the same and the gradients with respect to the vertices and the rays
============================  ==============================================================================

The ratio column is the forward + backward time over the matching forward time. Each measurement is one
jitted function; the first call (compilation) is reported apart from the warm median.

Flags: ``--quick`` (tiny sizes, one repeat: a smoke test), ``--triangles``, ``--rays``, ``--repeats``,
``--backend`` (the intersector's), ``--json PATH`` (every number and the machine). Only jax and numpy are
needed.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

import jaxrt as rt

__all__ = ["main", "noisy_sphere", "camera_rays"]

_DEFAULTS = dict(triangles=100_000, rays=1 << 16, repeats=5)
_QUICK = dict(triangles=2_000, rays=1 << 10, repeats=1)


def noisy_sphere(triangles: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A closed UV sphere of radius about 1 with radial noise and about ``triangles`` triangles.

    Returns:
      ``(vertices, indices)``: ``(V, 3)`` float32 and ``(T, 3)`` int32, ``T = 2 * rings * segments`` (its pole
      triangles are degenerate, as in any UV sphere: they are never hit).
    """
    rings = max(2, int(round((triangles / 4) ** 0.5)))
    segments = 2 * rings
    theta, phi = np.meshgrid(
        np.linspace(0.0, np.pi, rings + 1), np.linspace(0.0, 2 * np.pi, segments, endpoint=False), indexing="ij"
    )
    radius = 1.0 + 0.02 * np.random.default_rng(seed).standard_normal(theta.shape)
    points = radius[..., None] * np.stack([np.sin(theta) * np.cos(phi), np.cos(theta), np.sin(theta) * np.sin(phi)], -1)
    i, j = np.meshgrid(np.arange(rings), np.arange(segments), indexing="ij")
    a, b = i * segments + j, i * segments + (j + 1) % segments
    faces = np.concatenate([np.stack([a, b, b + segments], -1), np.stack([a, b + segments, a + segments], -1)])
    return points.reshape(-1, 3).astype(np.float32), faces.reshape(-1, 3).astype(np.int32)


def camera_rays(count: int) -> rt.Ray:
    """About ``count`` primary rays (a square image) of a pinhole camera framing the unit sphere."""
    side = max(1, int(round(count**0.5)))
    return rt.shading.pinhole_rays(side, side, eye=(0.3, 0.4, 3.0), target=(0.0, 0.0, 0.0), fov_degrees=45.0)


def _timed(fn: Callable[..., Any], args: Sequence[Any], repeats: int) -> dict[str, float]:
    """First call (compilation and one run) and the median and best of ``repeats`` warm calls, in seconds."""
    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - start
    times = []
    for _ in range(max(1, repeats)):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - start)
    median = statistics.median(times)
    return {"first_s": first, "compile_s": max(0.0, first - median), "median_s": median, "best_s": min(times)}


def _machine() -> dict[str, Any]:
    device = jax.devices()[0]
    return {
        "jaxrt_version": rt.__version__,
        "jax_version": jax.__version__,
        "backend": jax.default_backend(),
        "device_kind": device.device_kind,
        "device_count": jax.device_count(),
        "cpu_count": os.cpu_count(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
    }


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m jaxrt.bench.gradients",
        description="Forward against forward + backward Mrays/s of jaxrt's differentiable intersections.",
    )
    parser.add_argument("--triangles", type=int, help=f"mesh triangles (default {_DEFAULTS['triangles']:,})")
    parser.add_argument("--rays", type=int, help=f"camera rays (default {_DEFAULTS['rays']:,})")
    parser.add_argument("--repeats", type=int, help=f"warm calls per measurement (default {_DEFAULTS['repeats']})")
    parser.add_argument("--backend", choices=["auto", "portable", "gpu"], default="auto", help="intersector backend")
    parser.add_argument("--quick", action="store_true", help="tiny sizes and one repeat: a smoke test")
    parser.add_argument("--json", metavar="PATH", help="also write every number and the machine info to PATH")
    return parser


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run the benchmark, print its table and return every number.

    Args:
      argv: command-line arguments (``sys.argv[1:]`` when ``None``); see ``--help``.

    Returns:
      ``{"machine", "config", "results"}``; ``results`` maps each measurement of the module docstring to its
      timings (seconds), ``mrays_s`` and ``ratio`` (its time over the matching forward time).

    Examples:
      >>> from jaxrt.bench import gradients
      >>> out = gradients.main(["--quick", "--triangles", "64", "--rays", "16"])  # doctest: +SKIP
    """
    args = _parser().parse_args(argv)
    sizes = dict(_QUICK if args.quick else _DEFAULTS)
    for name in sizes:
        if getattr(args, name) is not None:
            sizes[name] = getattr(args, name)

    vertices_np, indices_np = noisy_sphere(sizes["triangles"])
    vertices, indices = jnp.asarray(vertices_np), jnp.asarray(indices_np)
    rays = camera_rays(sizes["rays"])
    count = int(np.prod(rays.shape))
    intersector = rt.Intersector(rt.tags.triangle_data, backend=args.backend)
    key = jax.random.key(0)
    weight_distance = jax.random.normal(key, rays.shape)
    weight_bary = jax.random.normal(jax.random.split(key)[1], (*rays.shape, 2))

    def objective(result: rt.IntersectionResult) -> jax.Array:
        hit = result.type != 0
        distance = jnp.where(hit, result.distance, 0.0)
        return jnp.sum(weight_distance * distance) + jnp.sum(weight_bary * result.triangle_barycentric_coord)

    def traced(vertices, origin, direction):
        structure = rt.build_primitive_structure(rt.TriangleGeometry(vertices, indices))
        return objective(intersector.intersect(rt.Ray(origin, direction), structure))

    structure = jax.block_until_ready(rt.build_primitive_structure(rt.TriangleGeometry(vertices, indices)))

    def trace_only(structure, origin, direction):
        return objective(intersector.intersect(rt.Ray(origin, direction), structure))

    measurements = {
        "trace": (jax.jit(trace_only), (structure, rays.origin, rays.direction), None),
        "trace+grad(rays)": (
            jax.jit(jax.value_and_grad(trace_only, argnums=(1, 2))),
            (structure, rays.origin, rays.direction),
            "trace",
        ),
        "build+trace": (jax.jit(traced), (vertices, rays.origin, rays.direction), None),
        "build+trace+grad(vertices)": (
            jax.jit(jax.value_and_grad(traced)),
            (vertices, rays.origin, rays.direction),
            "build+trace",
        ),
        "build+trace+grad(all)": (
            jax.jit(jax.value_and_grad(traced, argnums=(0, 1, 2))),
            (vertices, rays.origin, rays.direction),
            "build+trace",
        ),
    }
    results: dict[str, dict[str, float]] = {}
    for name, (fn, fn_args, forward) in measurements.items():
        timing = _timed(fn, fn_args, sizes["repeats"])
        timing["mrays_s"] = count / timing["median_s"] / 1e6
        timing["ratio"] = timing["median_s"] / results[forward]["median_s"] if forward else 1.0
        results[name] = timing

    machine = _machine()
    config = {"triangles": int(len(indices_np)), "rays": count, "repeats": sizes["repeats"], "backend": args.backend}
    print(
        f"jaxrt gradient bench on {machine['backend']} ({machine['device_kind']}): noisy sphere, "
        f"{config['triangles']:,} triangles, {count:,} camera rays, median of {sizes['repeats']} warm calls"
    )
    print(f"  {'measurement':28s} {'median ms':>10s} {'Mrays/s':>9s} {'x forward':>10s} {'compile s':>10s}")
    for name, timing in results.items():
        print(
            f"  {name:28s} {timing['median_s'] * 1e3:10.2f} {timing['mrays_s']:9.3f} {timing['ratio']:10.2f} "
            f"{timing['compile_s']:10.1f}"
        )
    out = {"machine": machine, "config": config, "results": results}
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=2)
        print(f"  wrote {args.json}")
    return out


if __name__ == "__main__":
    main(sys.argv[1:])
