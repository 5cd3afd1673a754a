"""Move the vertices of a mesh to match a target depth map, with a smoothness prior (optax, Adam).

Needs the ``diff`` extra (optax, matplotlib) beyond the README's ``.[demo]`` environment:
``pip install -e ".[diff]"``.

A height-field mesh starts flat; the target is the depth map of a bumpy version of it, seen from above by a
pinhole camera that sees only the inside of the mesh (no silhouettes: see docs/differentiable.md). Each step
rebuilds the acceleration structure from the current vertices, traces the camera rays and differentiates
the depth error with respect to every vertex position through ``rt.build_primitive_structure`` and
``Intersector.intersect``. A Laplacian prior on the vertex offsets keeps the mesh smooth and regular (depth
alone does not say where along the surface a vertex should slide).

Run: ``python examples/inverse_depth.py [--size 64] [--iterations 300] [--cells 24] [--out out/inverse_depth]``
Writes ``target.png``, ``before.png``, ``after.png`` (depth maps) and ``loss.png`` under ``--out``, and prints
the depth and height errors before and after.
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

EYE, TARGET, FOV = (0.0, 0.0, 3.0), (0.0, 0.0, 0.0), 30.0


def height(x, y):
    """The target surface: a bump, a dent and a gentle wave."""
    bump = 0.25 * jnp.exp(-((x - 0.3) ** 2 + (y - 0.2) ** 2) / 0.1)
    dent = -0.15 * jnp.exp(-((x + 0.35) ** 2 + (y + 0.3) ** 2) / 0.05)
    return bump + dent + 0.05 * jnp.sin(3.0 * x) * jnp.cos(2.0 * y)


def grid(cells: int) -> tuple[np.ndarray, np.ndarray]:
    """A flat ``cells x cells`` grid over ``[-1, 1]^2`` in the plane z = 0, facing +z."""
    g = np.linspace(-1.0, 1.0, cells + 1)
    x, y = np.meshgrid(g, g, indexing="ij")
    vertices = np.stack([x, y, np.zeros_like(x)], -1).reshape(-1, 3).astype(np.float32)
    i, j = np.meshgrid(np.arange(cells), np.arange(cells), indexing="ij")
    a = i * (cells + 1) + j
    b, c = a + cells + 1, a + 1
    faces = np.concatenate([np.stack([a, b, b + 1], -1).reshape(-1, 3), np.stack([a, b + 1, c], -1).reshape(-1, 3)])
    return vertices, faces.astype(np.int32)


def laplacian(faces: np.ndarray, count: int) -> jax.Array:
    """The uniform graph Laplacian ``L x = mean(neighbours) - x`` as a dense ``(V, V)`` matrix (small meshes)."""
    adjacency = np.zeros((count, count), np.float32)
    for a, b in ((0, 1), (1, 2), (2, 0)):
        adjacency[faces[:, a], faces[:, b]] = adjacency[faces[:, b], faces[:, a]] = 1.0
    return jnp.asarray(adjacency / adjacency.sum(1, keepdims=True) - np.eye(count, dtype=np.float32))


def render_depth(vertices: jax.Array, faces: np.ndarray, rays: rt.Ray) -> tuple[jax.Array, jax.Array]:
    """(distance along each unit ray, hit mask): build the structure from ``vertices`` and trace."""
    structure = rt.build_primitive_structure(rt.TriangleGeometry(vertices, faces))
    hits = rt.Intersector().intersect(rays, structure)
    hit = hits.type != 0
    return jnp.where(hit, hits.distance, 0.0), hit


def save_depth(path: Path, depth: np.ndarray, hit: np.ndarray, limits: tuple[float, float]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    image = np.where(hit, depth, np.nan)
    plt.imsave(path, image, cmap="viridis", vmin=limits[0], vmax=limits[1])


def save_loss(path: Path, losses: list[float], title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(4, 3), dpi=80)
    ax.semilogy(losses)
    ax.set_xlabel("iteration")
    ax.set_ylabel("loss")
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main(argv: list[str] | None = None) -> dict:
    """Run the example; returns the errors before and after (also printed)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=64, help="image width and height in pixels")
    parser.add_argument("--iterations", type=int, default=300)
    parser.add_argument("--cells", type=int, default=24, help="grid cells per side")
    parser.add_argument("--learning-rate", type=float, default=0.005)
    parser.add_argument("--smoothness", type=float, default=1.0, help="weight of the Laplacian prior")
    parser.add_argument("--out", default="out/inverse_depth")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    start, faces = grid(args.cells)
    vertices0 = jnp.asarray(start)
    truth = vertices0.at[:, 2].set(height(vertices0[:, 0], vertices0[:, 1]))
    rays = jax.jit(lambda: rt.shading.pinhole_rays(args.size, args.size, eye=EYE, target=TARGET, fov_degrees=FOV))()
    lap = laplacian(faces, len(start))

    @jax.jit
    def measure(offsets):
        """Depth map and hit mask, and per-vertex height errors, for the current offsets."""
        vertices = vertices0 + offsets
        depth, hit = render_depth(vertices, faces, rays)
        seen = (jnp.abs(vertices[:, 0]) < 0.6) & (jnp.abs(vertices[:, 1]) < 0.6)  # in the camera's view
        return depth, hit, vertices[:, 2] - height(vertices[:, 0], vertices[:, 1]), seen

    target, target_hit, _, _ = measure(truth - vertices0)

    def loss_fn(offsets):
        depth, hit = render_depth(vertices0 + offsets, faces, rays)
        both = hit & target_hit
        data = jnp.sum(jnp.where(both, (depth - target) ** 2, 0.0)) / jnp.maximum(jnp.sum(both), 1)
        prior = jnp.mean(jnp.sum((lap @ offsets) ** 2, axis=-1))
        return data + args.smoothness * prior, data

    optimizer = optax.adam(args.learning_rate)
    offsets = jnp.zeros_like(vertices0)
    state = optimizer.init(offsets)

    @jax.jit
    def step(offsets, state):
        (loss, data), gradient = jax.value_and_grad(loss_fn, has_aux=True)(offsets)
        updates, state = optimizer.update(gradient, state)
        return optax.apply_updates(offsets, updates), state, loss, data

    def errors(offsets) -> tuple[float, float, np.ndarray, np.ndarray]:
        depth, hit, height_error, seen = (np.asarray(a) for a in measure(offsets))
        both = hit & np.asarray(target_hit)
        depth_rmse = float(np.sqrt(np.mean((depth - np.asarray(target))[both] ** 2)))
        return depth_rmse, float(np.sqrt(np.mean(height_error[seen] ** 2))), depth, hit

    *before, depth_before, hit_before = errors(offsets)
    losses, clock = [], time.perf_counter()
    for _ in progress(range(args.iterations), quiet=args.quiet, desc="optimising"):
        offsets, state, loss, _ = step(offsets, state)
        losses.append(float(loss))
    seconds = time.perf_counter() - clock
    *after, depth_after, hit_after = errors(offsets)

    limits = (float(np.min(np.asarray(target)[np.asarray(target_hit)])), float(np.max(np.asarray(target))))
    save_depth(out / "target.png", np.asarray(target), np.asarray(target_hit), limits)
    save_depth(out / "before.png", depth_before, hit_before, limits)
    save_depth(out / "after.png", depth_after, hit_after, limits)
    save_loss(out / "loss.png", losses, "depth + smoothness")
    result = {
        "triangles": int(len(faces)),
        "pixels": args.size * args.size,
        "iterations": args.iterations,
        "seconds": seconds,
        "depth_rmse_before": before[0],
        "depth_rmse_after": after[0],
        "height_rmse_before": before[1],
        "height_rmse_after": after[1],
        "final_loss": losses[-1] if losses else float("nan"),
    }
    print(
        f"inverse_depth: {result['triangles']} triangles, {args.size}x{args.size} pixels, {args.iterations} Adam "
        f"steps in {seconds:.1f} s (first includes compilation) -> {out}/"
    )
    print(f"  depth RMSE  {before[0]:.4f} -> {after[0]:.4f}   (camera 3 units away)")
    print(f"  height RMSE {before[1]:.4f} -> {after[1]:.4f}   (vertices in the camera's view)")
    return result


if __name__ == "__main__":
    main()
