"""Shape from silhouettes: fit an ellipsoid's centre and radii to two silhouette images (optax, Adam).

Needs the ``diff`` extra (optax, matplotlib) beyond the README's ``.[demo]`` environment:
``pip install -e ".[diff]"``.

The ellipsoid is a triangle mesh (a UV sphere scaled by three radii and moved to a centre), seen by two pinhole
cameras (front and side). The images are silhouettes: 1 where a ray hits the mesh, 0 elsewhere, integrated over
each pixel. Only the silhouettes carry the signal, so plain autodiff (the hit held fixed) has a zero gradient:
starting from a wrong centre and radii it does not move. ``rt.pixel_integral`` with edge samples on the mesh's
silhouette edges gives the derivative of the pixel integrals, and Adam recovers the shape. Both runs are made
from the same start with the same steps; the script prints their errors and wall times.

Run: ``python examples/shape_from_silhouette.py [--size 64] [--iterations 150] [--out out/shape_from_silhouette]``
Writes ``silhouettes.png`` (targets, start, and both results for each view) and ``loss.png`` under ``--out``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
from _progress import progress

import jaxrt as rt

VIEWS = (((0.0, 0.0, 3.0), (0.0, 0.0, 0.0)), ((3.0, 0.4, 0.0), (0.0, 0.0, 0.0)))
TRUE_CENTRE = np.array([0.15, -0.1, 0.05])
TRUE_RADII = np.array([0.55, 0.3, 0.4])
START_CENTRE = np.array([-0.35, 0.25, -0.3])
START_RADII = np.array([0.3, 0.3, 0.3])


def unit_sphere(rings: int = 16, segments: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """A closed UV sphere of radius 1 with single pole vertices: ``(vertices, faces)``."""
    theta = np.linspace(0.0, np.pi, rings + 1)[1:-1]
    phi = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    ring = np.stack([np.sin(t) * np.cos(p), np.cos(t), np.sin(t) * np.sin(p)], -1).reshape(-1, 3)
    vertices = np.concatenate([[[0.0, 1.0, 0.0]], ring, [[0.0, -1.0, 0.0]]])
    faces = []
    bottom = len(vertices) - 1
    for j in range(segments):
        k = (j + 1) % segments
        faces.append([0, 1 + k, 1 + j])
        for i in range(rings - 3):
            a, b = 1 + i * segments + j, 1 + i * segments + k
            faces += [[a, b, b + segments], [a, b + segments, a + segments]]
        last = 1 + (rings - 2) * segments
        faces.append([bottom, last + j, last + k])
    return vertices.astype(np.float32), np.asarray(faces, np.int32)


def main(argv: list[str] | None = None) -> dict:
    """Run both fits; returns their errors and times (also printed)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=64, help="image width and height in pixels")
    parser.add_argument("--iterations", type=int, default=150)
    parser.add_argument("--learning-rate", type=float, default=0.02)
    parser.add_argument("--samples-per-pixel", type=int, default=4)
    parser.add_argument("--edge-samples", type=int, default=4096, help="silhouette edge samples per view")
    parser.add_argument("--out", default="out/shape_from_silhouette")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    sphere, faces = unit_sphere()
    sphere = jnp.asarray(sphere)
    cameras = [rt.PinholeCamera(args.size, args.size, eye=e, target=t, fov_degrees=35.0) for e, t in VIEWS]
    intersector = rt.Intersector()

    def images(shape: dict, key: jax.Array, samples_per_pixel: int, edge_samples: int) -> list[jax.Array]:
        vertices = sphere * jnp.exp(shape["log_radii"]) + shape["centre"]
        structure = rt.build_primitive_structure(rt.TriangleGeometry(vertices, faces))

        def shade(rays):
            return (intersector.intersect(rays, structure).type != 0).astype(vertices.dtype)

        mesh = rt.SilhouetteMesh(vertices, faces)
        keys = jax.random.split(key, len(cameras))
        return [
            rt.pixel_integral(
                shade, c, k, samples_per_pixel=samples_per_pixel, meshes=[mesh], edge_samples=edge_samples
            )
            for c, k in zip(cameras, keys, strict=True)
        ]

    truth = {
        "centre": jnp.asarray(TRUE_CENTRE, jnp.float32),
        "log_radii": jnp.log(jnp.asarray(TRUE_RADII, jnp.float32)),
    }
    start = {
        "centre": jnp.asarray(START_CENTRE, jnp.float32),
        "log_radii": jnp.log(jnp.asarray(START_RADII, jnp.float32)),
    }
    render = jax.jit(lambda shape: images(shape, jax.random.key(1), 16, 0))
    targets = render(truth)

    def fit(edge_samples: int) -> tuple[dict, list[float], float]:
        def loss_fn(shape, key):
            rendered = images(shape, key, args.samples_per_pixel, edge_samples)
            return sum(jnp.mean((a - b) ** 2) for a, b in zip(rendered, targets, strict=True)) / len(cameras)

        optimizer = optax.adam(args.learning_rate)

        @jax.jit
        def step(shape, state, key):
            loss, gradient = jax.value_and_grad(loss_fn)(shape, key)
            updates, state = optimizer.update(gradient, state)
            return optax.apply_updates(shape, updates), state, loss

        shape, state, losses = start, optimizer.init(start), []
        clock = time.perf_counter()
        label = "edge sampling" if edge_samples else "plain autodiff"
        for i in progress(range(args.iterations), quiet=args.quiet, desc=label):
            shape, state, loss = step(shape, state, jax.random.fold_in(jax.random.key(0), i))
            losses.append(float(loss))
        return shape, losses, time.perf_counter() - clock

    def errors(shape: dict) -> dict:
        rendered = [np.asarray(a) for a in render(shape)]
        masks = [(a > 0.5, np.asarray(t) > 0.5) for a, t in zip(rendered, targets, strict=True)]
        return {
            "centre_error": float(np.linalg.norm(np.asarray(shape["centre"]) - TRUE_CENTRE)),
            "radii_error": float(np.linalg.norm(np.exp(np.asarray(shape["log_radii"])) - TRUE_RADII)),
            "silhouette_iou": float(np.mean([(a & b).sum() / max((a | b).sum(), 1) for a, b in masks])),
        }

    result = {"start": errors(start)}
    fitted, seconds = {}, {}
    losses = {}
    for name, edges in (("edge_sampling", args.edge_samples), ("plain_autodiff", 0)):
        fitted[name], losses[name], seconds[name] = fit(edges)
        result[name] = dict(errors(fitted[name]), seconds=seconds[name], final_loss=losses[name][-1])
    print(
        f"shape_from_silhouette: ellipsoid mesh ({len(faces)} triangles), {len(cameras)} views of {args.size}x"
        f"{args.size} pixels, {args.samples_per_pixel} samples per pixel, {args.iterations} Adam steps -> {out}/"
    )
    print(f"  true centre {TRUE_CENTRE}, radii {TRUE_RADII}; start centre {START_CENTRE}, radii {START_RADII}")
    print(f"  {'':34s} {'centre error':>12s} {'radii error':>12s} {'IoU':>6s} {'loop':>8s}")
    print(
        f"  {'start':34s} {result['start']['centre_error']:12.4f} {result['start']['radii_error']:12.4f} "
        f"{result['start']['silhouette_iou']:6.3f}"
    )
    for name, label in (
        ("edge_sampling", f"edge sampling ({args.edge_samples} per view)"),
        ("plain_autodiff", "plain autodiff"),
    ):
        r = result[name]
        print(
            f"  {label:34s} {r['centre_error']:12.4f} {r['radii_error']:12.4f} {r['silhouette_iou']:6.3f} "
            f"{r['seconds']:7.1f}s"
        )
    for name in fitted:
        c, radii = np.asarray(fitted[name]["centre"]), np.exp(np.asarray(fitted[name]["log_radii"]))
        print(f"  {name}: centre {np.round(c, 4)}, radii {np.round(radii, 4)}")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [("target", targets), ("start", render(start))]
    rows += [("edge sampling", render(fitted["edge_sampling"])), ("plain autodiff", render(fitted["plain_autodiff"]))]
    fig, axes = plt.subplots(len(cameras), len(rows), figsize=(2.2 * len(rows), 2.3 * len(cameras)), dpi=80)
    for col, (title, views) in enumerate(rows):
        for row, image in enumerate(views):
            ax = axes[row, col]
            ax.imshow(np.asarray(image), cmap="gray", vmin=0, vmax=1, interpolation="nearest")
            ax.contour(np.asarray(targets[row]), levels=[0.5], colors="tab:orange", linewidths=0.8)
            ax.set_axis_off()
            ax.set_title(f"{title}, view {row + 1}", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / "silhouettes.png")
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(4, 3), dpi=80)
    for name, label in (("edge_sampling", "edge sampling"), ("plain_autodiff", "plain autodiff")):
        ax.semilogy(losses[name], label=label)
    ax.set_xlabel("iteration")
    ax.set_ylabel("silhouette loss")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "loss.png")
    plt.close(fig)
    return result


if __name__ == "__main__":
    main()
