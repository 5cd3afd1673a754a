"""Traversal heatmaps of the Stanford bunny and Sponza (Xcode's acceleration-structure viewer, "traversal" mode).

Renders ``nodes_visited`` per primary ray for the LBVH, for the clustering build (``quality="high"``) and for
the LBVH refit after a twist of the mesh (whose boxes overlap), on one colour scale, and prints the mean work.
Needs the shared data folder (``$JAXRT_DATA_DIR`` or ``../shared/data``); exits with a message without it.

Run: ``python examples/heatmap.py [--size 192] [--out docs/img]``
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

import jaxrt as rt
from jaxrt import debug
from jaxrt.bench.refit import twist
from jaxrt.bench.scenes import shared_mesh


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--size", type=int, default=192, help="image width and height in pixels")
    parser.add_argument("--twist", type=float, default=2.0, help="twist of the refit mesh, radians")
    parser.add_argument("--out", default="docs/img", help="folder for heatmap_*.png")
    args = parser.parse_args()
    try:
        bunny = shared_mesh("bunny")
    except FileNotFoundError as error:
        print(f"heatmap: the bunny is not available ({error}); nothing rendered", file=sys.stderr)
        return 0
    vertices, indices = np.asarray(bunny.vertices), np.asarray(bunny.indices)
    lower, upper = vertices.min(axis=0), vertices.max(axis=0)
    centre, radius = (lower + upper) / 2, float(np.linalg.norm(upper - lower)) / 2
    rays = rt.shading.pinhole_rays(
        args.size, args.size, eye=centre + np.array([0.3, 0.2, 2.6]) * radius, target=centre, fov_degrees=40.0
    )
    fast = rt.build_primitive_structure(rt.TriangleGeometry(vertices, indices))
    structures = {
        "fast": fast,
        "high": rt.build_primitive_structure(rt.TriangleGeometry(vertices, indices), quality="high"),
        "refit": rt.refit(fast, rt.TriangleGeometry(twist(vertices, args.twist), indices)),
    }
    counts = {name: debug.traversal_heatmap(s, rays)[1] for name, s in structures.items()}
    vmax = max(float(c.max()) for c in counts.values())  # one scale for all three images
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for name, c in counts.items():
        image = np.concatenate([debug.heatmap(c, vmax=vmax), debug.colorbar(args.size, 6)], axis=0)
        debug.write_png(out / f"heatmap_{name}.png", image)
        print(
            f"{name:>5}: SAH {rt.sah_cost(structures[name]):6.1f}, nodes visited per ray: mean {c.mean():5.1f}, "
            f"max {c.max():4d} -> {out / f'heatmap_{name}.png'}"
        )
    print(f"colour scale: 0 (dark blue) to {vmax:.0f} (dark red) nodes")
    _interior(args.size, out)
    return 0


def _interior(size: int, out: Path) -> None:
    """The same view of an interior: Sponza from its bench camera, on a scale of its own."""
    try:
        sponza = shared_mesh("sponza")
    except FileNotFoundError as error:
        print(f"heatmap: Sponza is not available ({error}); no interior rendered", file=sys.stderr)
        return
    rays = rt.shading.pinhole_rays(size, size, eye=sponza.eye, target=sponza.target, fov_degrees=60.0)
    structure = rt.build_primitive_structure(rt.TriangleGeometry(sponza.vertices, sponza.indices))
    c = debug.traversal_heatmap(structure, rays)[1]
    image = np.concatenate([debug.heatmap(c), debug.colorbar(size, 6)], axis=0)
    debug.write_png(out / "heatmap_sponza.png", image)
    print(f"sponza: nodes visited per ray: mean {c.mean():5.1f}, max {c.max():4d} -> {out / 'heatmap_sponza.png'}")


if __name__ == "__main__":
    raise SystemExit(main())
