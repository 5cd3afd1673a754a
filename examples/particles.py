"""Translucent particles: depth-sorted any-hit compositing of built-in spheres, fitted to an image (optax, Adam).

Needs the ``diff`` extra (optax, matplotlib) beyond the README's ``.[demo]`` environment:
``pip install -e ".[diff]"``.

Each particle is an ``rt.SphereGeometry`` sphere with a colour and an opacity. A camera ray collects the ``K``
nearest spheres it crosses (``rt.Intersector(max_hits=K)``: a k-buffer, sorted by distance) and composites
them front to back; a particle's alpha falls off with the ray's distance to its centre (a Gaussian of a third
of the radius, as ray-traced Gaussian particles do), so the image differentiates with respect to the colours,
opacities and centres. A target image is rendered from one particle set; a second set, with shifted centres,
grey colours and uniform opacity, is fitted to it by gradient descent on colours, opacities and centres,
rebuilding the structure from the moving centres in every step.

Run: ``python examples/particles.py [--particles 4000] [--size 64] [--k 16] [--steps 100] [--out out/particles]``
(the default is small for a CPU; ``--particles 100000 --size 256`` is the full-size run). Writes
``target.png``, ``before.png``, ``after.png`` and ``loss.png`` under ``--out`` and prints the image error
before and after.
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

EYE, TARGET, FOV = (0.0, 0.0, 3.5), (0.0, 0.0, 0.0), 40.0


def particles(count: int, seed: int) -> dict[str, jax.Array]:
    """A cloud of particles in a torus-like shell, coloured by position."""
    rng = np.random.default_rng(seed)
    angle = rng.uniform(0, 2 * np.pi, count)
    tube = rng.normal(size=(count, 3)) * 0.18
    centre = np.stack([np.cos(angle), np.sin(angle), np.zeros(count)], 1) * 0.8 + tube
    colour = np.stack([0.5 + 0.5 * np.cos(angle), 0.5 + 0.5 * np.sin(angle), 0.5 + 0.4 * tube[:, 2] / 0.18], 1)
    return {
        "centre": jnp.asarray(centre, jnp.float32),
        "colour_logit": jnp.asarray(
            np.log(np.clip(colour, 0.02, 0.98) / (1 - np.clip(colour, 0.02, 0.98))), jnp.float32
        ),
        "opacity_logit": jnp.asarray(rng.normal(size=count) * 0.5 + 0.5, jnp.float32),
    }


def render(params: dict, radius: float, rays: rt.Ray, intersector: rt.Intersector) -> jax.Array:
    """Front-to-back compositing of the ``K`` nearest particles of each ray over a white background."""
    structure = rt.build_primitive_structure(rt.SphereGeometry(params["centre"], radius))
    hits = intersector.intersect(rays, structure)
    k = jnp.maximum(hits.primitive_id, 0)  # (n, K), sorted by distance
    found = hits.primitive_id >= 0
    centre = params["centre"][k]
    o, d = rays.origin[:, None, :], rays.direction[:, None, :]
    along = jnp.sum((centre - o) * d, -1) / jnp.sum(d * d, -1)
    gap = jnp.sum((o + along[..., None] * d - centre) ** 2, -1)  # squared ray-to-centre distance
    sigma = radius / 3
    alpha = jax.nn.sigmoid(params["opacity_logit"][k]) * jnp.exp(-0.5 * gap / sigma**2)
    alpha = jnp.where(found, alpha, 0.0)
    transmittance = jnp.cumprod(1 - alpha, axis=1)
    before = jnp.concatenate([jnp.ones_like(alpha[:, :1]), transmittance[:, :-1]], axis=1)
    colour = jax.nn.sigmoid(params["colour_logit"][k])
    image = jnp.sum((before * alpha)[..., None] * colour, axis=1)
    return image + transmittance[:, -1:]  # white behind the particles


def save(path: Path, image: np.ndarray) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.imsave(path, np.clip(image, 0, 1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--particles", type=int, default=4000)
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--k", type=int, default=16)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--out", default="out/particles")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    radius = float(4.0 / np.sqrt(args.particles))
    camera = rt.shading.pinhole_rays(args.size, args.size, eye=EYE, target=TARGET, fov_degrees=FOV)
    rays = rt.Ray(camera.origin.reshape(-1, 3), camera.direction.reshape(-1, 3))
    intersector = rt.Intersector(max_hits=args.k)
    shape = (args.size, args.size, 3)

    target_params = particles(args.particles, 0)
    target = jax.jit(render, static_argnums=(1, 3))(target_params, radius, rays, intersector)
    params = dict(target_params)
    rng = np.random.default_rng(1)
    params["centre"] = target_params["centre"] + jnp.asarray(rng.normal(size=(args.particles, 3)) * radius, jnp.float32)
    params["colour_logit"] = jnp.zeros_like(target_params["colour_logit"])
    params["opacity_logit"] = jnp.zeros_like(target_params["opacity_logit"])

    def loss(p):
        return jnp.mean((render(p, radius, rays, intersector) - target) ** 2)

    optimiser = optax.adam(0.05)
    scales = {"centre": 0.02, "colour_logit": 1.0, "opacity_logit": 1.0}  # positions move slower

    @jax.jit
    def step(p, state):
        value, grad = jax.value_and_grad(loss)(p)
        grad = {key: g * scales[key] for key, g in grad.items()}
        updates, state = optimiser.update(grad, state, p)
        return optax.apply_updates(p, updates), state, value

    before = np.asarray(jax.jit(lambda p: render(p, radius, rays, intersector))(params))
    state = optimiser.init(params)
    losses = []
    start = time.perf_counter()
    for _ in progress(range(args.steps), desc="fit"):
        params, state, value = step(params, state)
        losses.append(float(value))
    loop = time.perf_counter() - start
    after = np.asarray(jax.jit(lambda p: render(p, radius, rays, intersector))(params))
    target = np.asarray(target)
    rmse = lambda image: float(np.sqrt(np.mean((image - target) ** 2)))  # noqa: E731
    save(out / "target.png", target.reshape(shape))
    save(out / "before.png", before.reshape(shape))
    save(out / "after.png", after.reshape(shape))
    import matplotlib.pyplot as plt

    plt.figure(figsize=(4, 3))
    plt.semilogy(losses)
    plt.xlabel("step")
    plt.ylabel("image MSE")
    plt.tight_layout()
    plt.savefig(out / "loss.png")
    print(f"{args.particles:,} particles, {args.size} x {args.size} rays, k-buffer of {args.k} (max_hits)")
    print(f"image RMSE  {rmse(before):.4f} -> {rmse(after):.4f} in {args.steps} Adam steps ({loop:.1f} s)")
    print(f"wrote {out}/target.png, before.png, after.png, loss.png")


if __name__ == "__main__":
    main()
