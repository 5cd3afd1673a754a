"""``python -m jaxrt.bench.sharded``: rays sharded over every device against one device.

Traces the same rays into a noisy 1M-triangle sphere (``--triangles``) with one plain
``Intersector.intersect`` call on the first device and with :func:`jaxrt.intersect_sharded` over the first
``--devices`` devices (default all; the structure replicated once beforehand), and reports Mrays/s of both,
the speed-up, and whether every result field is equal (hit ids exactly, distances to rounding). Any ray count
runs: the camera gives ``round(sqrt(rays))**2`` rays, and ``intersect_sharded`` pads them in equal rows, one
per device, and cuts the padding. Where the count divides by the devices the rays are placed on them before
timing (``placed``); otherwise they stay on the first device and each call spreads them (``spread per
call``). A camera's rays cost unequally (rows through the object against rows past it), so equal blocks of
image rows load the devices unequally: ``--layouts`` times the rays in image order and ``interleaved`` (rows
dealt to the devices in turn, as multi-GPU renderers interleave scanlines), the one device tracing the same
ordered rays. On a CPU, ``XLA_FLAGS=--xla_force_host_platform_device_count=N`` gives ``N`` devices.

Flags: ``--triangles``, ``--rays`` (comma-separated counts), ``--devices``, ``--layouts``, ``--repeats``, ``--json PATH``.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from typing import Any

import jax
import numpy as np
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

import jaxrt as rt
from jaxrt.bench.gradients import camera_rays, noisy_sphere
from jaxrt.bench.report import machine_info
from jaxrt.bench.timing import timed

__all__ = ["main"]


def _rays(count: int, layout: str, devices: int) -> rt.Ray:
    """The camera's rays, flat: image rows in order (``image``), or rows dealt to the devices in turn
    (``interleaved``: row ``r`` in the block of device ``r % devices``, so every device traces rows from all
    over the image)."""
    rays = camera_rays(count)
    if layout == "interleaved":
        order = np.concatenate([np.arange(k, rays.shape[0], devices) for k in range(devices)])
        rays = jax.tree_util.tree_map(lambda a: a[order], rays)
    return rays.reshape(-1)


def _run(
    count: int, layout: str, structure: Any, intersector: rt.Intersector, single: Any, mesh: Any, repeats: int
) -> dict[str, Any]:
    """One ray count and layout: one device, then the mesh; the numbers and whether the hits agree."""
    rays = _rays(count, layout, mesh.size)
    n = int(rays.origin.shape[0])
    one, reference = timed(lambda: single(rays, structure), repeats)
    devices = mesh.size
    # One device's share traced alone on one device: the speed-up cannot pass (time of all the rays) / (time of
    # one share), and a smaller batch pays the per-call work over fewer rays.
    share_rays = jax.tree_util.tree_map(lambda a: a[: -(-n // devices)], rays)
    share, _ = timed(lambda: single(share_rays, structure), repeats)
    replicated = rt.replicate(structure, mesh)
    placed = n % devices == 0
    if placed:
        rays = jax.device_put(rays, NamedSharding(mesh, P(mesh.axis_names)))
    many, out = timed(lambda: rt.intersect_sharded(intersector, rays, replicated, mesh=mesh), repeats)
    same_ids = all(
        np.array_equal(np.asarray(out[name]), np.asarray(reference[name])) for name in ("type", "primitive_id")
    )
    hit = np.asarray(reference.primitive_id) >= 0
    distance_gap = float(np.max(np.abs(np.asarray(out.distance)[hit] - np.asarray(reference.distance)[hit]), initial=0))
    results = {
        "layout": layout,
        "devices": devices,
        "rays_placed": placed,
        "device_kinds": sorted({d.device_kind for d in jax.devices()}),
        "rays": n,
        "one_device": one.as_dict(n),
        "one_device_share": share.as_dict(-(-n // devices)),
        "all_devices": many.as_dict(n),
        "speedup": one.median_s / many.median_s if many.median_s > 0 else float("inf"),
        "same_hits": same_ids,
        "max_distance_difference": distance_gap,
        "hits": int(hit.sum()),
    }
    print(f"{n:,} rays in {layout} order, {devices} device(s) of {results['device_kinds']}")
    print(f"  one device: {results['one_device']['mrays_s']:.1f} Mrays/s (compile {one.compile_s:.1f} s)")
    ceiling = one.median_s / share.median_s if share.median_s > 0 else float("inf")
    print(
        f"  one device, 1/{devices} of the rays: {results['one_device_share']['mrays_s']:.1f} Mrays/s "
        f"(speed-up ceiling {ceiling:.2f}x)"
    )
    where = "placed on the devices" if placed else "on the first device, spread per call"
    print(
        f"  {devices} devices: {results['all_devices']['mrays_s']:.1f} Mrays/s (compile {many.compile_s:.1f} s; "
        f"rays {where})"
    )
    print(f"  speed-up {results['speedup']:.2f}x; same hits: {same_ids}; max distance difference {distance_gap:.2e}")
    return results


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run, print the lines of each ray count, and write the JSON file if asked; returns the results (those of
    the first ray count, and every count's under ``runs``)."""
    parser = argparse.ArgumentParser(prog="python -m jaxrt.bench.sharded", description=__doc__.splitlines()[0])
    parser.add_argument("--triangles", type=int, default=1_000_000)
    parser.add_argument("--rays", default=str(1 << 24), help="ray counts, comma-separated")
    parser.add_argument("--devices", type=int, help="devices to split the rays over (default: all)")
    parser.add_argument("--layouts", default="image,interleaved", help="ray orders: image and/or interleaved")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--json", metavar="PATH")
    args = parser.parse_args(argv)
    vertices, indices = noisy_sphere(args.triangles)
    structure = rt.build_primitive_structure(rt.TriangleGeometry(vertices, indices))
    print(f"{int(indices.shape[0]):,} triangles (noisy sphere)")
    intersector = rt.Intersector(rt.tags.triangle_data)
    mesh = rt.device_mesh(args.devices)
    single = jax.jit(intersector.intersect)  # one device: compiled once per ray count
    layouts = [x.strip() for x in args.layouts.split(",")]
    for layout in layouts:
        if layout not in ("image", "interleaved"):
            raise ValueError(f"--layouts: expected image and/or interleaved, got {layout!r}")
    runs = [
        _run(int(c), layout, structure, intersector, single, mesh, args.repeats)
        for c in args.rays.split(",")
        for layout in layouts
    ]
    results = dict(runs[0], machine=machine_info(), triangles=int(indices.shape[0]), runs=runs)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)
    return results


if __name__ == "__main__":
    main(sys.argv[1:])
    sys.exit(0)
