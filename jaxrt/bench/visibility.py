"""``python -m jaxrt.bench.visibility``: visibility-aware gradients, their error, variance and cost.

Three measurements (pick with the first argument; default all):

- ``compare``: on the scenes of :mod:`jaxrt.bench.visibility_scenes` (exact pixel integrals; float64), the
  relative error ``|g - g_ref| / |g_ref|`` of the whole gradient against central differences of the exact
  images, for plain autodiff, edge sampling (``rt.pixel_integral`` with edge samples) and Gaussian smoothing
  of the parameters (a zeroth-order baseline: ``mean_k [L(x + s e_k) - L(x - s e_k)] / (2 s) e_k``, antithetic
  pairs, the same renderer without edge samples; Le Lidec et al. 2021, Fischer and Ritschel 2023), each with
  its camera-ray count per gradient; mean over ``--seeds`` keys.
- ``variance``: edge sampling's relative error (mean over seeds) and relative standard deviation against
  samples per pixel, with ``samples per pixel * 16 * 16 * 2`` edge samples (and as many again per light).
- ``cost``: a 512 x 512 image of the Stanford bunny (``../shared/data`` or ``$JAXRT_DATA_DIR``; skipped with a
  message when absent): the forward pixel integral against ``jax.value_and_grad`` of an image loss with respect
  to the bunny's translation, with plain autodiff and with edge samples. Target: gradient at most 3x forward.

Flags: ``--quick`` (fewer seeds and configurations, a 64 x 64 image: a smoke test), ``--seeds``, ``--size``,
``--edge-samples`` (comma-separated counts), ``--scenes``, ``--backend``, ``--repeats``, ``--json PATH``.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

import jaxrt as rt
from jaxrt.bench import visibility_scenes
from jaxrt.bench.timing import timed

__all__ = ["main"]


def _relative(estimate: dict, reference: dict) -> float:
    e, _ = visibility_scenes.flatten({k: np.asarray(v) for k, v in estimate.items()})
    r, _ = visibility_scenes.flatten(reference)
    return float(np.linalg.norm(e - r) / np.linalg.norm(r))


def _smoothing_gradient(scene, samples_per_pixel: int, pairs: int, sigma: float):
    """A jitted ``(params, key) -> gradient`` by antithetic Gaussian smoothing of the rendered loss."""
    weights = jnp.asarray(scene.weights())
    _, unflatten = visibility_scenes.flatten(scene.params)

    def loss(x, key):
        return jnp.sum(weights * scene.render(unflatten(x), key, samples_per_pixel, 0, 0))

    def gradient(params, key):
        x = jnp.concatenate([jnp.ravel(params[name]) for name in sorted(params)])
        noise_key, pixel_key = jax.random.split(key)
        e = jax.random.normal(noise_key, (pairs, x.shape[0]), x.dtype)
        up = jax.vmap(lambda d: loss(x + sigma * d, pixel_key))(e)
        down = jax.vmap(lambda d: loss(x - sigma * d, pixel_key))(e)
        g = jnp.mean(((up - down) / (2 * sigma))[:, None] * e, axis=0)
        return unflatten(g)

    return jax.jit(gradient)


def _seeds_stats(fn, params, reference, seeds: int) -> tuple[float, float]:
    """``(mean relative error, relative standard deviation)`` over ``seeds`` keys."""
    r, _ = visibility_scenes.flatten(reference)
    estimates = []
    for seed in range(seeds):
        g = fn(params, jax.random.key(seed))
        estimates.append(visibility_scenes.flatten({k: np.asarray(v) for k, v in g.items()})[0])
    estimates = np.array(estimates)
    errors = np.linalg.norm(estimates - r, axis=1) / np.linalg.norm(r)
    spread = np.sqrt(np.mean(np.sum((estimates - estimates.mean(0)) ** 2, axis=1))) / np.linalg.norm(r)
    return float(errors.mean()), float(spread)


def _chosen(names: Sequence[str] | None) -> dict:
    every = visibility_scenes.scenes()
    unknown = sorted(set(names or ()) - set(every))
    if unknown:
        raise SystemExit(f"python -m jaxrt.bench.visibility: unknown scenes {unknown}; known: {sorted(every)}")
    return {k: v for k, v in every.items() if not names or k in names}


def compare(seeds: int, quick: bool, names: Sequence[str] | None = None) -> list[dict[str, Any]]:
    """Plain autodiff, edge sampling and Gaussian smoothing on every exact scene."""
    rows = []
    pixels = visibility_scenes.SIZE**2
    spp, edges = 4, 8192
    with jax.enable_x64(True):
        for name, scene in _chosen(names).items():
            reference = visibility_scenes.exact_gradient(scene)
            params = {k: jnp.asarray(v) for k, v in scene.params.items()}
            shadows = 4096 if name.startswith("shadow") else 0
            methods = [
                ("plain autodiff", visibility_scenes.estimator_gradient(scene, None, spp, 0, 0), spp * pixels),
                (
                    f"edge sampling ({edges} + {shadows} edge samples)" if shadows else f"edge sampling ({edges})",
                    visibility_scenes.estimator_gradient(scene, None, spp, edges, shadows),
                    spp * pixels + 2 * (edges + shadows),
                ),
            ]
            for pairs, sigma in ((8, 0.01), (8, 0.03)) if quick else ((8, 0.01), (8, 0.03), (64, 0.01), (64, 0.03)):
                methods.append(
                    (
                        f"Gaussian smoothing ({pairs} pairs, sigma {sigma})",
                        _smoothing_gradient(scene, spp, pairs, sigma),
                        2 * pairs * spp * pixels,
                    )
                )
            for method, fn, rays in methods:
                error, spread = _seeds_stats(fn, params, reference, seeds)
                row = dict(scene=name, method=method, rays=rays, relative_error=error, relative_std=spread)
                rows.append(row)
                print(f"{name:14s} {method:44s} rays {rays:7d}  error {error:8.4f}  std {spread:8.4f}", flush=True)
    return rows


def variance(seeds: int, quick: bool, names: Sequence[str] | None = None) -> list[dict[str, Any]]:
    """Edge sampling's error and spread against samples per pixel (edge samples scaled with them)."""
    rows = []
    pixels = visibility_scenes.SIZE**2
    with jax.enable_x64(True):
        for name, scene in _chosen(names).items():
            reference = visibility_scenes.exact_gradient(scene)
            params = {k: jnp.asarray(v) for k, v in scene.params.items()}
            for spp in (1, 4) if quick else (1, 4, 16, 64):
                edges = 2 * spp * pixels
                shadows = edges if name.startswith("shadow") else 0
                fn = visibility_scenes.estimator_gradient(scene, None, spp, edges, shadows)
                error, spread = _seeds_stats(fn, params, reference, seeds)
                rows.append(
                    dict(
                        scene=name, samples_per_pixel=spp, edge_samples=edges, relative_error=error, relative_std=spread
                    )
                )
                print(
                    f"{name:14s} spp {spp:3d} edge samples {edges:6d}  error {error:.4f}  std {spread:.4f}", flush=True
                )
    return rows


def cost(size: int, edge_samples: Sequence[int], backend: str, repeats: int) -> dict[str, Any] | None:
    """Forward against value-and-gradient of a bunny image loss; ``None`` (with a message) without the data."""
    from jaxrt.bench.scenes import shared_mesh

    try:
        mesh = shared_mesh("bunny")
    except (FileNotFoundError, ImportError) as error:
        print(f"cost: skipped, the bunny is not available ({error})")
        return None
    vertices = np.asarray(mesh.vertices, np.float32)
    lower, upper = vertices.min(0), vertices.max(0)
    vertices = jnp.asarray((vertices - (lower + upper) / 2) / (upper - lower).max())
    faces = np.asarray(mesh.indices)
    camera = rt.PinholeCamera(size, size, eye=(0.0, 0.1, 2.4), target=(0.0, 0.0, 0.0), fov_degrees=30.0)
    intersector = rt.Intersector(rt.tags.triangle_data, backend=backend)
    light = jnp.array([-0.4, 0.7, 0.6])
    key = jax.random.key(0)

    def render(translation, edges):
        v = vertices + translation
        structure = rt.build_primitive_structure(rt.TriangleGeometry(v, faces))
        normals = rt.shading.vertex_normals(v, faces)

        def shade(rays):
            hits = intersector.intersect(rays, structure)
            n = rt.shading.interpolate_normals(normals, faces, hits.primitive_id, hits.triangle_barycentric_coord)
            n = rt.shading.face_forward(n, rays.direction)
            return jnp.where(hits.type != 0, 0.1 + 0.9 * rt.shading.lambert(n, light), 0.0)

        meshes = [rt.SilhouetteMesh(v, faces)] if edges else ()
        return rt.pixel_integral(shade, camera, key, samples_per_pixel=1, meshes=meshes, edge_samples=edges)

    translation = jnp.array([0.01, -0.02, 0.0], jnp.float32)
    target = jax.jit(lambda t: render(t, 0))(jnp.zeros(3, jnp.float32))

    def loss(t, edges):
        return jnp.mean((render(t, edges) - target) ** 2)

    measurements = [
        ("forward", jax.jit(lambda t: render(t, 0))),
        ("grad, plain autodiff", jax.jit(jax.value_and_grad(lambda t: loss(t, 0)))),
    ]
    for count in edge_samples:
        measurements.append(
            (f"grad, {count} edge samples", jax.jit(jax.value_and_grad(lambda t, count=count: loss(t, count))))
        )
    result: dict[str, Any] = {"size": size, "triangles": int(len(faces)), "device": jax.devices()[0].device_kind}
    base = None
    for label, fn in measurements:
        timing, out = timed(lambda fn=fn: fn(translation), repeats)
        base = base or timing.median_s
        result[label] = dict(timing.as_dict(), ratio=timing.median_s / base)
        extra = "" if label == "forward" else f"  gradient {np.asarray(out[1])}"
        print(
            f"{label:22s} first {timing.first_s:7.2f} s  median {timing.median_s:7.3f} s  "
            f"x forward {timing.median_s / base:5.2f}{extra}",
            flush=True,
        )
    return result


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m jaxrt.bench.visibility", description=__doc__.splitlines()[0])
    parser.add_argument("what", nargs="*", help="any of compare, variance, cost (default: all)")
    parser.add_argument("--quick", action="store_true", help="few seeds and configurations, a 64 x 64 bunny")
    parser.add_argument("--seeds", type=int, default=None, help="keys per estimate (default 16; quick 4)")
    parser.add_argument("--size", type=int, default=None, help="bunny image width and height (default 512)")
    parser.add_argument(
        "--edge-samples", default="4096,16384", help="edge samples of the bunny image, comma-separated (one row each)"
    )
    parser.add_argument("--backend", default="auto", help="the bunny intersector's backend")
    parser.add_argument("--repeats", type=int, default=3, help="warm calls per cost measurement")
    parser.add_argument("--scenes", help="comma-separated scenes for compare and variance (default: all)")
    parser.add_argument("--json", metavar="PATH", help="also write every number to PATH")
    return parser


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    args = _parser().parse_args(argv)
    what = args.what or ["compare", "variance", "cost"]
    unknown = sorted(set(what) - {"compare", "variance", "cost"})
    if unknown:
        raise SystemExit(
            f"python -m jaxrt.bench.visibility: unknown measurement {unknown}; use compare, variance, cost"
        )
    seeds = args.seeds or (4 if args.quick else 16)
    names = [n for n in (args.scenes or "").split(",") if n]
    size = args.size or (64 if args.quick else 512)
    print(f"jax {jax.__version__} on {jax.devices()[0].device_kind}, {platform.processor() or platform.machine()}")
    out: dict[str, Any] = {"jax": jax.__version__, "device": jax.devices()[0].device_kind}
    if "compare" in what:
        out["compare"] = compare(seeds, args.quick, names)
    if "variance" in what:
        out["variance"] = variance(seeds, args.quick, names)
    if "cost" in what:
        counts = [int(c) for c in str(args.edge_samples).split(",") if c]
        out["cost"] = cost(size, counts, args.backend, 1 if args.quick else args.repeats)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)
    return out


if __name__ == "__main__":
    main(sys.argv[1:])
