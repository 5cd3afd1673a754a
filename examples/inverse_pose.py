"""Pose estimation: fit the rigid transform of a known object to a depth image (optax, Adam).

Needs the ``diff`` extra (optax, matplotlib) beyond the README's ``.[demo]`` environment:
``pip install -e ".[diff]"``.

The object (the Stanford bunny from ``../shared/data``, or a procedural blob when the data or trimesh is
absent) is seen by a pinhole camera at an unknown pose. Starting from the identity, Adam fits a rotation
vector and a translation so that the rendered depth matches the target depth. Each step applies the
transform to the vertices, rebuilds the acceleration structure and traces; the gradient reaches the pose
through the hit distances. Only pixels hit in both images contribute: moving silhouettes are not
differentiated (docs/differentiable.md), so the initial pose must overlap the target.

An instance transform (``rt.Instances``) is the other way to pose the object: its structure is then built
once and only the instance transform is differentiated (docs/instancing.md).

Run: ``python examples/inverse_pose.py [--size 64] [--iterations 200] [--procedural] [--out out/inverse_pose]``
Writes ``target.png``, ``before.png``, ``after.png`` (depth maps) and ``loss.png`` under ``--out``, and prints
the pose and depth errors before and after.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
from _progress import progress

import jaxrt as rt

EYE, TARGET, FOV = (0.0, 0.1, 2.4), (0.0, 0.0, 0.0), 30.0
TRUE_ROTATION = 0.3 * np.array([1.0, 2.0, 0.5]) / np.linalg.norm([1.0, 2.0, 0.5])  # about 17 degrees
TRUE_TRANSLATION = np.array([0.06, -0.04, 0.05])


def data_dir() -> Path:
    """``$JAXRT_DATA_DIR``, or ``../shared/data`` next to the repository."""
    default = Path(__file__).resolve().parents[1].parent / "shared" / "data"
    return Path(os.environ.get("JAXRT_DATA_DIR", default))


def blob(segments: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """A lumpy, asymmetric closed surface (a displaced UV sphere), so that every pose looks different."""
    theta, phi = np.meshgrid(
        np.linspace(0.0, np.pi, segments // 2 + 1), np.linspace(0.0, 2 * np.pi, segments, endpoint=False), indexing="ij"
    )
    radius = 1.0 + 0.2 * np.sin(3 * theta) * np.cos(2 * phi) + 0.1 * np.cos(theta) + 0.08 * np.sin(5 * phi + theta)
    stretch = np.array([1.0, 0.8, 0.6])
    vertices = (
        stretch
        * radius[..., None]
        * np.stack([np.sin(theta) * np.cos(phi), np.cos(theta), np.sin(theta) * np.sin(phi)], -1)
    )
    rings, count = theta.shape
    i, j = np.meshgrid(np.arange(rings - 1), np.arange(count), indexing="ij")
    a, b = i * count + j, i * count + (j + 1) % count
    faces = np.concatenate([np.stack([a, b, b + count], -1), np.stack([a, b + count, a + count], -1)]).reshape(-1, 3)
    return vertices.reshape(-1, 3), faces


def load_object(procedural: bool) -> tuple[np.ndarray, np.ndarray, str]:
    """``(vertices, faces, name)`` centred at the origin, largest extent 1."""
    path = data_dir() / "stanford-bunny" / "bun_zipper.binary.ply"
    vertices = faces = None
    name = "procedural blob"
    if not procedural and path.exists():
        try:
            import trimesh
        except ImportError:
            print("trimesh is not installed: using a procedural mesh instead of the bunny")
        else:
            mesh = trimesh.load(path, process=False)
            vertices, faces, name = np.asarray(mesh.vertices), np.asarray(mesh.faces), "Stanford bunny"
    if vertices is None:
        vertices, faces = blob()
    lower, upper = vertices.min(0), vertices.max(0)
    vertices = (vertices - (lower + upper) / 2) / (upper - lower).max()
    return vertices.astype(np.float32), faces.astype(np.int32), name


def rotation_matrix(rotation: jax.Array) -> jax.Array:
    """Rodrigues' formula, smooth at the zero rotation (no NaN gradient there)."""
    angle = jnp.sqrt(jnp.sum(rotation**2) + 1e-20)
    k = jnp.array(
        [[0.0, -rotation[2], rotation[1]], [rotation[2], 0.0, -rotation[0]], [-rotation[1], rotation[0], 0.0]]
    )
    a = jnp.sinc(angle / jnp.pi)  # sin(angle) / angle
    b = 0.5 * jnp.sinc(angle / (2 * jnp.pi)) ** 2  # (1 - cos(angle)) / angle^2
    return jnp.eye(3) + a * k + b * (k @ k)


def posed(vertices: jax.Array, pose: dict) -> jax.Array:
    """The object rotated about its centre (the origin) and translated."""
    return vertices @ rotation_matrix(pose["rotation"]).T + pose["translation"]


def render_depth(vertices: jax.Array, faces: np.ndarray, rays: rt.Ray) -> tuple[jax.Array, jax.Array]:
    structure = rt.build_primitive_structure(rt.TriangleGeometry(vertices, faces))
    hits = rt.Intersector().intersect(rays, structure)
    hit = hits.type != 0
    return jnp.where(hit, hits.distance, 0.0), hit


def save_depth(path: Path, depth: np.ndarray, hit: np.ndarray, limits: tuple[float, float]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.imsave(path, np.where(hit, depth, np.nan), cmap="viridis", vmin=limits[0], vmax=limits[1])


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
    """Run the example; returns the pose and depth errors before and after (also printed)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=64, help="image width and height in pixels")
    parser.add_argument("--iterations", type=int, default=200)
    parser.add_argument("--learning-rate", type=float, default=0.01)
    parser.add_argument("--procedural", action="store_true", help="use the procedural blob, not the bunny")
    parser.add_argument("--out", default="out/inverse_pose")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    vertices, faces, name = load_object(args.procedural)
    vertices = jnp.asarray(vertices)
    rays = jax.jit(lambda: rt.shading.pinhole_rays(args.size, args.size, eye=EYE, target=TARGET, fov_degrees=FOV))()
    truth = {
        "rotation": jnp.asarray(TRUE_ROTATION, jnp.float32),
        "translation": jnp.asarray(TRUE_TRANSLATION, jnp.float32),
    }
    render = jax.jit(lambda pose: render_depth(posed(vertices, pose), faces, rays))
    target, target_hit = render(truth)

    def loss_fn(pose):
        depth, hit = render_depth(posed(vertices, pose), faces, rays)
        both = hit & target_hit
        return jnp.sum(jnp.where(both, (depth - target) ** 2, 0.0)) / jnp.maximum(jnp.sum(both), 1)

    optimizer = optax.adam(args.learning_rate)
    pose = {"rotation": jnp.zeros(3), "translation": jnp.zeros(3)}
    state = optimizer.init(pose)

    @jax.jit
    def step(pose, state):
        loss, gradient = jax.value_and_grad(loss_fn)(pose)
        updates, state = optimizer.update(gradient, state)
        return optax.apply_updates(pose, updates), state, loss

    rotations = jax.jit(lambda a, b: rotation_matrix(a).T @ rotation_matrix(b))

    def errors(pose) -> dict:
        relative = np.asarray(rotations(pose["rotation"], truth["rotation"]))
        angle = np.degrees(np.arccos(np.clip((np.trace(relative) - 1) / 2, -1.0, 1.0)))
        depth, hit = render(pose)
        hit, seen = np.asarray(hit), np.asarray(target_hit)
        both, either = hit & seen, hit | seen
        rmse = float(np.sqrt(np.mean((np.asarray(depth) - np.asarray(target))[both] ** 2)))
        return {
            "rotation_error_degrees": float(angle),
            "translation_error": float(np.linalg.norm(np.asarray(pose["translation"]) - TRUE_TRANSLATION)),
            "depth_rmse": rmse,
            "silhouette_iou": float(both.sum() / max(either.sum(), 1)),
        }

    before = errors(pose)
    depth_before, hit_before = render(pose)
    losses, clock = [], time.perf_counter()
    for _ in progress(range(args.iterations), quiet=args.quiet, desc="optimising"):
        pose, state, loss = step(pose, state)
        losses.append(float(loss))
    seconds = time.perf_counter() - clock
    after = errors(pose)
    depth_after, hit_after = render(pose)

    seen = np.asarray(target)[np.asarray(target_hit)]
    limits = (float(seen.min()), float(seen.max()))
    save_depth(out / "target.png", np.asarray(target), np.asarray(target_hit), limits)
    save_depth(out / "before.png", np.asarray(depth_before), np.asarray(hit_before), limits)
    save_depth(out / "after.png", np.asarray(depth_after), np.asarray(hit_after), limits)
    save_loss(out / "loss.png", losses, "depth error (pixels hit in both)")
    result = {"object": name, "triangles": int(len(faces)), "iterations": args.iterations, "seconds": seconds}
    result.update({f"{k}_before": v for k, v in before.items()})
    result.update({f"{k}_after": v for k, v in after.items()})
    print(
        f"inverse_pose: {name} ({len(faces)} triangles), {args.size}x{args.size} pixels, {args.iterations} Adam "
        f"steps in {seconds:.1f} s (first includes compilation) -> {out}/"
    )
    for key, label in (
        ("rotation_error_degrees", "rotation error (deg)"),
        ("translation_error", "translation error"),
        ("depth_rmse", "depth RMSE"),
        ("silhouette_iou", "silhouette IoU"),
    ):
        print(f"  {label:21s} {before[key]:.4f} -> {after[key]:.4f}")
    return result


if __name__ == "__main__":
    main()
