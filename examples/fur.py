"""Render the TressFX bear's fur: 48k short strands as round Catmull-Rom curves, Kajiya-Kay shading.

Run: ``python examples/fur.py [--width 320] [--height 320] [--width-of-strand 0.35] [--data DIR]
[--out out/fur.png]`` (``DIR`` holds ``tressfx-fur-bear/bear.tfx``). Without the data, a procedural hair
ball stands in. Prints the segment count and the build and trace times.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from hair import LIGHT, catmull_rom_tangent, data_folder, kajiya_kay

import jaxrt as rt


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=320)
    parser.add_argument("--width-of-strand", type=float, default=0.35, help="strand width (bear units)")
    parser.add_argument("--data", help="shared data folder")
    parser.add_argument("--out", default="out/fur.png")
    args = parser.parse_args(argv)

    data = data_folder(args.data)
    path = data / "tressfx-fur-bear" / "bear.tfx" if data else None
    if path and path.is_file():
        curves, name = rt.io.load_hair(path, basis="catmull_rom", width=args.width_of_strand), "bear"
    else:
        from jaxrt.bench.curves import hair_ball

        curves, name = hair_ball(20000), "hair ball"
    geometry = curves.geometry(end_caps="sphere")
    points = np.asarray(curves.control_points)
    lower, upper = points.min(0), points.max(0)
    centre, size = 0.5 * (lower + upper), float(np.linalg.norm(upper - lower))

    start = time.perf_counter()
    structure = jax.block_until_ready(rt.build_primitive_structure(geometry))
    build_s = time.perf_counter() - start
    eye = centre + size * np.array([0.75, 0.35, 0.55])
    rays = rt.shading.pinhole_rays(args.width, args.height, eye=tuple(eye), target=tuple(centre), fov_degrees=40)
    intersector = rt.Intersector(rt.tags.curve_data)
    start = time.perf_counter()
    hits = jax.block_until_ready(intersector.intersect(rays, structure))
    trace_s = time.perf_counter() - start
    start = time.perf_counter()  # again: the compiled program alone
    jax.block_until_ready(intersector.intersect(rays, structure))
    again_s = time.perf_counter() - start

    is_curve = hits.type == rt.IntersectionType.CURVE
    first = jnp.asarray(curves.indices)[jnp.maximum(hits.primitive_id, 0)]
    tangent = catmull_rom_tangent(curves.control_points, first, hits.curve_parameter)
    diffuse, specular = kajiya_kay(tangent, rays.direction, jnp.asarray(LIGHT, jnp.float32), shininess=20.0)
    # Darker towards the strand roots (curve parameter of the first segment of a 3-segment strand ~ 0).
    root = jnp.clip((hits.primitive_id % 3 + hits.curve_parameter) / 3.0, 0, 1)[..., None]
    fur = jnp.asarray([0.28, 0.17, 0.09]) * (0.2 + 0.8 * root) * (0.3 + 0.7 * diffuse[..., None])
    fur = fur + 0.15 * specular[..., None]
    image = jnp.where(is_curve[..., None], fur, jnp.asarray([0.8, 0.85, 0.9]))
    image = np.asarray(jnp.clip(image, 0, 1) ** (1 / 2.2) * 255).astype(np.uint8)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    from PIL import Image

    Image.fromarray(image, "RGB").save(out)
    stats = dict(scene=name, curve_segments=geometry.primitive_count, rays=args.width * args.height)
    stats.update(build_s=build_s, trace_s=trace_s, again_s=again_s, fur_pixels=int(is_curve.sum()))
    print(
        f"{name}: {stats['curve_segments']} curve segments; build {build_s:.2f} s, trace {stats['rays']} rays "
        f"{trace_s:.2f} s (first call, compile included), {again_s * 1e3:.0f} ms again; {stats['fur_pixels']} fur pixels -> {out}"
    )
    return stats


if __name__ == "__main__":
    main()
