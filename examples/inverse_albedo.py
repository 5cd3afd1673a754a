"""Recover an albedo texture and a light direction from one shaded image (optax, Adam).

Needs the ``diff`` extra (optax, matplotlib) beyond the README's ``.[demo]`` environment:
``pip install -e ".[diff]"``.

The object (the Stanford bunny from ``../shared/data``, or a procedural blob when the data or trimesh is
absent) is known and does not move, so its camera rays are traced once: the hit triangles and barycentrics
then give, through ``rt.shading.interpolate_normals`` and ``rt.shading.interpolate``, smooth shading normals
and planar texture coordinates per pixel. The image model is

    image = texture(uv) * (ambient + (1 - ambient) * max(0, n . l))

and Adam fits a 16 x 16 texture and the light direction ``l`` to a target rendered with a hidden texture
and light, with a small smoothness prior on the texture (texels no pixel sees are set by the prior alone).

Run: ``python examples/inverse_albedo.py [--size 64] [--iterations 300] [--procedural] [--out out/inverse_albedo]``
Writes ``target.png``, ``before.png``, ``after.png``, ``texture.png`` (true and recovered) and ``loss.png``
under ``--out``, and prints the image, texture and light errors before and after.
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
TEXELS = 16
AMBIENT = 0.2
TRUE_LIGHT = np.array([-0.6, 0.7, 0.4]) / np.linalg.norm([-0.6, 0.7, 0.4])


def data_dir() -> Path:
    """``$JAXRT_DATA_DIR``, or ``../shared/data`` next to the repository."""
    default = Path(__file__).resolve().parents[1].parent / "shared" / "data"
    return Path(os.environ.get("JAXRT_DATA_DIR", default))


def blob(segments: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """A lumpy closed surface (a displaced UV sphere)."""
    theta, phi = np.meshgrid(
        np.linspace(0.0, np.pi, segments // 2 + 1), np.linspace(0.0, 2 * np.pi, segments, endpoint=False), indexing="ij"
    )
    radius = 1.0 + 0.2 * np.sin(3 * theta) * np.cos(2 * phi) + 0.1 * np.cos(theta) + 0.08 * np.sin(5 * phi + theta)
    sphere = np.stack([np.sin(theta) * np.cos(phi), np.cos(theta), np.sin(theta) * np.sin(phi)], -1)
    rings, count = theta.shape
    i, j = np.meshgrid(np.arange(rings - 1), np.arange(count), indexing="ij")
    a, b = i * count + j, i * count + (j + 1) % count
    faces = np.concatenate([np.stack([a, b, b + count], -1), np.stack([a, b + count, a + count], -1)]).reshape(-1, 3)
    return (radius[..., None] * sphere).reshape(-1, 3), faces


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


def true_texture() -> np.ndarray:
    """The hidden albedo: smooth stripes and blobs in [0.15, 0.9]."""
    v, u = np.meshgrid((np.arange(TEXELS) + 0.5) / TEXELS, (np.arange(TEXELS) + 0.5) / TEXELS, indexing="ij")
    pattern = 0.5 + 0.25 * np.sin(2 * np.pi * 2 * u) * np.cos(2 * np.pi * 1.5 * v) + 0.15 * np.cos(6 * (u + v))
    return np.clip(pattern, 0.15, 0.9).astype(np.float32)


def shade(texture: jax.Array, light: jax.Array, normals: jax.Array, uv: jax.Array, hit: jax.Array) -> jax.Array:
    """The image model of the module docstring (0 where no surface is hit)."""
    albedo = rt.shading.texture_lookup(texture, uv)
    return jnp.where(hit, albedo * (AMBIENT + (1.0 - AMBIENT) * rt.shading.lambert(normals, light)), 0.0)


def save_images(out: Path, images: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    for name, image in images.items():
        plt.imsave(out / f"{name}.png", np.asarray(image), cmap="gray", vmin=0.0, vmax=1.0)


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
    parser.add_argument("--learning-rate", type=float, default=0.05)
    parser.add_argument("--smoothness", type=float, default=1e-3, help="weight of the texture smoothness prior")
    parser.add_argument("--procedural", action="store_true", help="use the procedural blob, not the bunny")
    parser.add_argument("--out", default="out/inverse_albedo")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    vertices, faces, name = load_object(args.procedural)
    texture_true = jnp.asarray(true_texture())

    @jax.jit
    def prepare(vertices, faces):
        """Trace the camera rays once: per-pixel hit mask, shading normals, texture coordinates, target."""
        rays = rt.shading.pinhole_rays(args.size, args.size, eye=EYE, target=TARGET, fov_degrees=FOV)
        structure = rt.build_primitive_structure(rt.TriangleGeometry(vertices, faces))
        hits = rt.Intersector(rt.tags.triangle_data).intersect(rays, structure)
        hit, primitive, bary = hits.type != 0, hits.primitive_id, hits.triangle_barycentric_coord
        smooth = rt.shading.interpolate_normals(rt.shading.vertex_normals(vertices, faces), faces, primitive, bary)
        normals = rt.shading.face_forward(smooth, rays.direction)
        lower, upper = vertices.min(0), vertices.max(0)
        planar = jnp.stack([vertices[:, 0] - lower[0], upper[1] - vertices[:, 1]], -1) / (upper - lower)[:2]
        uv = rt.shading.interpolate(planar, faces, primitive, bary)
        target = shade(texture_true, jnp.asarray(TRUE_LIGHT, jnp.float32), normals, uv, hit)
        # Texels that pixels see: the bilinear weights of all visible lookups, summed per texel.
        coverage = jax.grad(lambda t: jnp.sum(jnp.where(hit, rt.shading.texture_lookup(t, uv), 0.0)))(texture_true)
        return hit, normals, uv, target, coverage

    hit, normals, uv, target, coverage = prepare(vertices, faces)
    seen = np.asarray(coverage) > 0.5

    def loss_fn(params):
        image = shade(params["texture"], params["light"], normals, uv, hit)
        t = params["texture"]
        prior = jnp.mean((t[1:] - t[:-1]) ** 2) + jnp.mean((t[:, 1:] - t[:, :-1]) ** 2)
        return jnp.mean((image - target) ** 2) + args.smoothness * prior

    optimizer = optax.adam(args.learning_rate)
    params = {"texture": jnp.full((TEXELS, TEXELS), 0.5), "light": jnp.array([0.0, 0.0, 1.0])}  # light at the camera
    state = optimizer.init(params)

    @jax.jit
    def step(params, state):
        loss, gradient = jax.value_and_grad(loss_fn)(params)
        updates, state = optimizer.update(gradient, state)
        return optax.apply_updates(params, updates), state, loss

    @jax.jit
    def render(params):
        image = shade(params["texture"], params["light"], normals, uv, hit)
        return image, jnp.sqrt(jnp.mean((image - target) ** 2))

    def errors(params) -> tuple[dict, np.ndarray]:
        image, rmse = render(params)
        light = np.asarray(params["light"]) / np.linalg.norm(np.asarray(params["light"]))
        return {
            "image_rmse": float(rmse),
            "texture_rmse_seen": float(np.sqrt(np.mean((np.asarray(params["texture"]) - true_texture())[seen] ** 2))),
            "light_error_degrees": float(np.degrees(np.arccos(np.clip(light @ TRUE_LIGHT, -1.0, 1.0)))),
        }, np.asarray(image)

    before, image_before = errors(params)
    losses, clock = [], time.perf_counter()
    for _ in progress(range(args.iterations), quiet=args.quiet, desc="optimising"):
        params, state, loss = step(params, state)
        losses.append(float(loss))
    seconds = time.perf_counter() - clock
    after, image_after = errors(params)

    save_images(out, {"target": np.asarray(target), "before": image_before, "after": image_after})
    gap = np.ones((TEXELS, 1), np.float32)
    save_images(out, {"texture": np.concatenate([true_texture(), gap, np.asarray(params["texture"])], 1)})
    save_loss(out / "loss.png", losses, "image error + smoothness")
    result = {"object": name, "triangles": int(len(faces)), "iterations": args.iterations, "seconds": seconds}
    result.update({f"{k}_before": v for k, v in before.items()})
    result.update({f"{k}_after": v for k, v in after.items()})
    print(
        f"inverse_albedo: {name} ({len(faces)} triangles), {args.size}x{args.size} pixels, {args.iterations} Adam "
        f"steps in {seconds:.1f} s (first includes compilation) -> {out}/"
    )
    for key, label in (
        ("image_rmse", "image RMSE"),
        ("texture_rmse_seen", f"texture RMSE ({int(seen.sum())} seen texels)"),
        ("light_error_degrees", "light error (deg)"),
    ):
        print(f"  {label:32s} {before[key]:.4f} -> {after[key]:.4f}")
    return result


if __name__ == "__main__":
    main()
