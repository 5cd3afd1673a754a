"""Gradients of hits through ``rt.build_primitive_structure`` + ``Intersector.intersect`` (triangle geometry).

Automatic derivatives (``jax.jvp``, ``jax.vjp``, ``jax.grad``) of the hit distance, the barycentrics
``triangle_barycentric_coord`` and the hit point ``rt.shading.hit_points`` with respect to the vertices of two
geometries (an indexed, connected grid patch and an unindexed soup), the ray origins and the ray directions,
checked against float64 central differences on random scenes and rays (hypothesis: random seed, scale
``10**[-2, 2]``, scene centre up to ``10**2`` scales from the origin; 64 rays aimed at random triangle
interiors from random directions at least 14 degrees off the plane).

A directional derivative along a random tangent ``t`` of one input group is compared, per ray, with the
five-point difference ``(8 (f(x + h t) - f(x - h t)) - (f(x + 2h t) - f(x - 2h t))) / 12h``, ``h = 1e-5``
(tangent entries are the scene scale, or the direction length, times a standard normal). Rays are compared
only where the same primitive is hit at all five points and the hit is at least ``1e-4`` (barycentric) from
an edge. The error of a ray is ``|ad - fd| / max(|fd|, 1e-3 * rms(|fd|))`` (vector norms over the
quantity's components, rms over the scene's rays). The table holds the largest error over all rays of 300
random scenes drawn like the hypothesis strategy below (CI runs 12 per test); the last column is what the
tests assert.

============  ==========  ================  ====================  ========
quantity      w.r.t.      float64 AD        float32 AD            asserted
============  ==========  ================  ====================  ========
distance      vertices    3.8e-7            1.9e-3                1e-6/1e-2
distance      origins     3.5e-7            1.4e-4                1e-6/1e-2
distance      directions  1.2e-8            4.0e-4                1e-6/1e-2
barycentrics  vertices    1.7e-8            8.7e-5                1e-6/1e-2
barycentrics  origins     2.6e-8            4.8e-6                1e-6/1e-2
barycentrics  directions  2.0e-9            1.3e-4                1e-6/1e-2
hit point     vertices    6.0e-7            1.9e-3                1e-6/1e-2
hit point     origins     2.4e-8            1.1e-5                1e-6/1e-2
hit point     directions  6.0e-8            3.0e-5                1e-6/1e-2
============  ==========  ================  ====================  ========

The float64 column is limited by the differences themselves (it moves with ``h``). The float32 column is
what users get by default (float32 scene and rays, the primitive chosen in float32) against the float64
differences at the same float32-rounded inputs; its largest errors are rays whose derivative is a sum of
nearly cancelling per-vertex terms (float32 cancellation, not a formula error).

``jax.grad`` and ``jax.vjp`` are checked along the same tangents through a random weighting of the rays
(``<grad, t>`` against the differences of the weighted sum, and ``<vjp(c), t> = <c, jvp(t)>``).
"""

from __future__ import annotations

import contextlib

import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

import jaxrt as rt

GRID_CELLS = 4  # a 4 x 4 patch: 25 vertices, 32 triangles sharing edges and vertices
SOUP_TRIANGLES = 16
RAYS = 64
STEP = 1e-5
EDGE_MARGIN = 1e-4
FLOOR = 1e-3
QUANTITIES = ("distance", "barycentrics", "point")
GROUPS = {"vertices": ("grid", "soup"), "origins": ("origin",), "directions": ("direction",)}
#: Largest accepted per-ray relative error (see the module docstring): float64 AD, float32 AD.
TOLERANCE = {"float64": 1e-6, "float32": 1e-2}


def grid_indices(cells: int) -> np.ndarray:
    """Two triangles per cell of a ``cells x cells`` grid of ``(cells + 1) ** 2`` vertices."""
    i, j = np.meshgrid(np.arange(cells), np.arange(cells), indexing="ij")
    a = i * (cells + 1) + j
    b, c = a + 1, a + cells + 1
    d = c + 1
    quads = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    return quads.astype(np.int32)


GRID_INDICES = grid_indices(GRID_CELLS)
INTERSECTOR = rt.Intersector(rt.tags.triangle_data)


def outputs(params: dict, settings: dict):
    """The differentiable hit quantities (misses give 0) and, as auxiliary data, the hit primitive.

    ``params`` holds the differentiated inputs (``grid`` and ``soup`` vertices, ray ``origin`` and
    ``direction``), ``settings`` the others (``min_distance``, ``max_distance``, ``mask``).
    """
    geometries = [rt.TriangleGeometry(params["grid"], GRID_INDICES), rt.TriangleGeometry(params["soup"])]
    structure = rt.build_primitive_structure(geometries)
    rays = rt.Ray(params["origin"], params["direction"], **settings)
    hits = INTERSECTOR.intersect(rays, structure)
    hit = hits.type != 0
    values = {
        "distance": jnp.where(hit, hits.distance, 0.0),
        "barycentrics": hits.triangle_barycentric_coord,
        "point": rt.shading.hit_points(rays, hits, miss_value=0.0),
    }
    primitive = jnp.where(hit, hits.geometry_id * 1000 + hits.primitive_id, -1)
    return values, primitive


def loss(params: dict, settings: dict, cotangent: dict) -> jax.Array:
    """A scalar: the hit quantities weighted by ``cotangent``."""
    values, _ = outputs(params, settings)
    return sum(jnp.sum(cotangent[k] * values[k]) for k in QUANTITIES)


def derivatives(params: dict, settings: dict, tangent: dict, cotangent: dict):
    """``(values, primitive, jvp(tangent), vjp(cotangent))`` of :func:`outputs` in one program."""
    values, tangents, primitive = jax.jvp(lambda q: outputs(q, settings), (params,), (tangent,), has_aux=True)
    _, pullback, _ = jax.vjp(lambda q: outputs(q, settings), params, has_aux=True)
    return values, primitive, tangents, pullback(cotangent)[0]


# Module-level jitted functions with fixed shapes, so that each compiles once per dtype for the whole module
# (compiling the traversal dominates the run time of these tests).
derivatives_jit = jax.jit(derivatives)
grad_jit = jax.jit(jax.grad(loss))


def float64():
    """Run jaxrt in float64 (geometry and rays are stored in float64 under ``jax_enable_x64``)."""
    return jax.enable_x64(True)


def _rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.diag(r))


def default_settings() -> dict:
    return dict(
        min_distance=np.zeros(RAYS), max_distance=np.full(RAYS, np.inf), mask=np.full(RAYS, 0xFFFFFFFF, np.uint32)
    )


def random_scene(seed: int, scale_exp: float, offset_exp: float) -> tuple[dict, float]:
    """Random grid patch and soup, and rays aimed at random triangle interiors; returns (params, scale)."""
    rng = np.random.default_rng(seed)
    scale = 10.0**scale_exp
    direction = rng.normal(size=3)
    center = scale * 10.0**offset_exp * direction / np.linalg.norm(direction)
    rotation = _rotation(rng)
    g = np.linspace(-1.0, 1.0, GRID_CELLS + 1)
    x, y = np.meshgrid(g, g, indexing="ij")
    grid = np.stack([x, y, 0.3 * rng.normal(size=x.shape)], -1).reshape(-1, 3)
    soup = rng.uniform(-1.5, 1.5, (SOUP_TRIANGLES, 1, 3)) + 0.6 * rng.normal(size=(SOUP_TRIANGLES, 3, 3))
    grid, soup = (center + scale * p @ rotation.T for p in (grid, soup.reshape(-1, 3)))
    triangles = np.concatenate([grid[GRID_INDICES], soup.reshape(-1, 3, 3)])
    origin, direction = np.empty((RAYS, 3)), np.empty((RAYS, 3))
    for i in range(RAYS):
        tri = triangles[rng.integers(len(triangles))]
        normal = np.cross(tri[1] - tri[0], tri[2] - tri[0])
        normal /= np.linalg.norm(normal)
        weights = rng.dirichlet([2.0, 2.0, 2.0])
        while weights.min() < 0.1:
            weights = rng.dirichlet([2.0, 2.0, 2.0])
        w = rng.normal(size=3)
        while abs(w @ normal) < 0.25 * np.linalg.norm(w):
            w = rng.normal(size=3)
        w /= np.linalg.norm(w)
        origin[i] = weights @ tri - w * scale * rng.uniform(0.5, 3.0)
        direction[i] = w * rng.uniform(0.5, 2.0)
    return dict(grid=grid, soup=soup, origin=origin, direction=direction), scale


def cast(tree: dict, dtype) -> dict:
    """Float arrays to ``dtype`` (JAX arrays); other arrays unchanged."""
    return {k: jnp.asarray(v, dtype) if np.asarray(v).dtype.kind == "f" else jnp.asarray(v) for k, v in tree.items()}


def tangent_for(group: str, params: dict, scale: float, rng: np.random.Generator) -> dict:
    """A random tangent in one input group (zero elsewhere), in the units of that group."""
    tangent = {k: np.zeros_like(v) for k, v in params.items()}
    for name in GROUPS[group]:
        size = np.linalg.norm(params["direction"], axis=-1, keepdims=True) if name == "direction" else scale
        tangent[name] = size * rng.normal(size=np.shape(params[name]))
    return tangent


def relative_errors(ad: dict, fd: dict, valid: np.ndarray) -> dict:
    """Largest per-ray error of each quantity (see the module docstring)."""
    errors = {}
    for name in QUANTITIES:
        a = np.asarray(ad[name], np.float64).reshape(RAYS, -1)[valid]
        f = np.asarray(fd[name], np.float64).reshape(RAYS, -1)[valid]
        size = np.linalg.norm(f, axis=-1)
        floor = FLOOR * np.sqrt(np.mean(size**2))
        errors[name] = float(np.max(np.linalg.norm(a - f, axis=-1) / np.maximum(size, floor)))
    return errors


def zeros_like(tree: dict) -> dict:
    return {k: np.zeros_like(v) for k, v in tree.items()}


def output_shaped(fill) -> dict:
    return {"distance": fill((RAYS,)), "barycentrics": fill((RAYS, 2)), "point": fill((RAYS, 3))}


def central_differences(params: dict, tangent: dict) -> tuple[dict, np.ndarray, np.ndarray]:
    """Float64 differences along ``tangent`` (five-point stencil), the rays where they are valid (the module
    docstring), and the primitive each ray hits (``1000 * geometry + primitive``, -1 for a miss)."""
    values, primitives = {}, []
    for sign in (0, 1, -1, 2, -2):
        moved = {k: v + sign * STEP * tangent[k] for k, v in params.items()}
        with float64():
            settings = cast(default_settings(), jnp.float64)
            value, primitive, _, _ = derivatives_jit(
                cast(moved, jnp.float64), settings, zeros_like(moved), output_shaped(np.zeros)
            )
        values[sign] = {k: np.asarray(v) for k, v in value.items()}
        primitives.append(np.asarray(primitive))
    bary = values[0]["barycentrics"]
    margin = np.minimum(np.minimum(bary[:, 0], bary[:, 1]), 1.0 - bary[:, 0] - bary[:, 1])
    valid = (primitives[0] >= 0) & (margin > EDGE_MARGIN)
    for other in primitives[1:]:
        valid &= other == primitives[0]
    fd = {
        k: (8.0 * (values[1][k] - values[-1][k]) - (values[2][k] - values[-2][k])) / (12.0 * STEP) for k in QUANTITIES
    }
    return fd, valid, primitives[0]


def masked(cotangent: dict, valid: np.ndarray) -> dict:
    return {k: np.where(valid.reshape(-1, *([1] * (np.ndim(v) - 1))), v, 0.0) for k, v in cotangent.items()}


def scalar_check(gradient: dict, tangent: dict, cotangent: dict, fd: dict) -> tuple[float, float]:
    """``(<gradient, tangent> - <cotangent, fd>, sum |cotangent * fd|)``: the error of a gradient along
    ``tangent`` against the differences of the weighted sum, and its scale."""
    along = sum(float(np.sum(np.asarray(gradient[k], np.float64) * tangent[k])) for k in tangent)
    differences = sum(float(np.sum(cotangent[k] * fd[k])) for k in QUANTITIES)
    return along - differences, sum(float(np.sum(np.abs(cotangent[k] * fd[k]))) for k in QUANTITIES)


scenes = st.tuples(st.integers(0, 2**31 - 1), st.floats(-2.0, 2.0), st.floats(-1.0, 2.0))


@given(scenes)
@settings(deadline=None, derandomize=True)
def test_float64_jvp_and_vjp_match_central_differences(scene):
    """Per ray, ``jax.jvp`` against the differences (the table); ``jax.vjp`` of a random weighting of the
    rays where the differences are valid, along the tangent, against the differences of that weighting."""
    params, scale = random_scene(*scene)
    rng = np.random.default_rng(scene[0] + 1)
    for group in GROUPS:
        tangent = tangent_for(group, params, scale, rng)
        fd, valid, _ = central_differences(params, tangent)
        assert valid.sum() >= RAYS // 4, f"only {valid.sum()} rays usable for the check"
        cotangent = masked(output_shaped(lambda shape: rng.normal(size=shape)), valid)
        with float64():
            p, s = cast(params, jnp.float64), cast(default_settings(), jnp.float64)
            _, _, ad, pulled = derivatives_jit(p, s, tangent, cotangent)
        for name, error in relative_errors(ad, fd, valid).items():
            assert error < TOLERANCE["float64"], f"{name} w.r.t. {group}: relative error {error:.2e}"
        error, size = scalar_check(pulled, tangent, cotangent, fd)
        assert abs(error) <= TOLERANCE["float64"] * size, (group, error, size)
        # The adjoint identity <vjp(c), t> = <c, jvp(t)>.
        backward = sum(float(np.sum(np.asarray(pulled[k]) * tangent[k])) for k in tangent)
        forward = sum(float(np.sum(cotangent[k] * np.asarray(ad[k]))) for k in QUANTITIES)
        assert abs(backward - forward) <= 1e-12 * size


@given(scenes)
@settings(deadline=None, derandomize=True)
def test_float32_jvp_and_grad_close_to_float64_central_differences(scene):
    """What users get by default: float32 inputs, the primitive chosen in float32, float32 derivatives."""
    params, scale = random_scene(*scene)
    params = {k: np.asarray(v, np.float32).astype(np.float64) for k, v in params.items()}
    rng = np.random.default_rng(scene[0] + 1)
    p, s = cast(params, jnp.float32), cast(default_settings(), jnp.float32)
    for group in GROUPS:
        tangent = tangent_for(group, params, scale, rng)
        fd, valid, primitive64 = central_differences(params, tangent)
        cotangent = output_shaped(lambda shape: rng.normal(size=shape))
        _, primitive, ad, pulled = derivatives_jit(p, s, cast(tangent, jnp.float32), cast(cotangent, jnp.float32))
        valid &= np.asarray(primitive) == primitive64
        assert valid.sum() >= RAYS // 4, f"only {valid.sum()} rays usable for the check"
        for name, error in relative_errors(ad, fd, valid).items():
            assert error < TOLERANCE["float32"], f"{name} w.r.t. {group}: relative error {error:.2e}"
        gradient = grad_jit(p, s, cast(cotangent, jnp.float32))
        for name in params:  # jax.grad and jax.vjp: the same program, the same numbers
            np.testing.assert_allclose(np.asarray(gradient[name]), np.asarray(pulled[name]), rtol=1e-5, atol=1e-6)
        weights = masked(cotangent, valid)
        error, size = scalar_check(grad_jit(p, s, cast(weights, jnp.float32)), tangent, weights, fd)
        assert abs(error) <= TOLERANCE["float32"] * size, (group, error, size)


def hard_scene() -> tuple[dict, dict, dict]:
    """A flat grid in z = 0 over [0, 1]^2, degenerate soup triangles, and rays through hard cases.

    Returns the parameters, the ray settings and a dict of ray index arrays: ``hits`` (interior, shared edge, shared diagonal,
    shared vertex, grazing, starting on the surface, from below), ``misses`` (beside, away, in the plane,
    through degenerate triangles only, a huge origin, beyond ``max_distance``) and ``disabled``.
    """
    g = np.linspace(0.0, 1.0, GRID_CELLS + 1)
    x, y = np.meshgrid(g, g, indexing="ij")
    grid = np.stack([x, y, np.zeros_like(x)], -1).reshape(-1, 3)
    soup = [[[3, 0, 0], [3.5, 0, 0], [4, 0, 0]], [[3, 2, 0]] * 3, [[3, 4, 0], [3, 4, 0], [4, 5, 0]]]
    soup += [[[10 + k, 0, 0], [10.5 + k, 0, 0], [10 + k, 0.5, 0]] for k in range(SOUP_TRIANGLES - 3)]
    inf, nan = np.inf, np.nan
    down = (0.0, 0.0, -1.0)
    rays = [  # origin, direction, min_distance, max_distance, mask
        ((0.3, 0.4, 1), down, 0, inf, 1),
        ((0.5, 0.4, 1), down, 0, inf, 1),  # shared grid edge x = 0.5
        ((0.3, 0.3, 1), down, 0, inf, 1),  # shared cell diagonal
        ((0.5, 0.5, 1), down, 0, inf, 1),  # shared vertex
        ((-1, 0.4, 1e-3), (1.3, 0, -1e-3), 0, inf, 1),  # grazing, 1e-3 rad
        ((-1, 0.4, 1e-6), (1.3, 0, -1e-6), 0, inf, 1),  # grazing, 1e-6 rad
        ((0.3, 0.6, 0), (0, 0.1, -1), 0, inf, 1),  # starts on the surface
        ((0.6, 0.7, -2), (0.1, 0, 1), 0, inf, 1),  # from below
        ((5, 5, 1), down, 0, inf, 1),  # misses: beside the scene
        ((0.3, 0.4, 1), (0, 0, 1), 0, inf, 1),  # away from it
        ((-1, 0.4, 0), (1, 0, 0), 0, inf, 1),  # in its plane
        ((3.5, 0, 1), down, 0, inf, 1),  # through a collinear triangle
        ((3, 2, 1), down, 0, inf, 1),  # through a point-like triangle
        ((3.5, 4.5, 1), down, 0, inf, 1),  # through a zero-area triangle
        ((3e38, 3e38, 3e38), (1, 0.5, -1), 0, inf, 1),  # a huge origin
        ((0.3, 0.4, 1), down, 0, 0.5, 1),  # the hit is beyond max_distance
        ((0.3, 0.4, 1), down, 2, 1, 1),  # disabled: max < min
        ((0.3, 0.4, 1), down, 0, inf, 0),  # mask 0
        ((0.3, 0.4, 1), (0, 0, 0), 0, inf, 1),  # zero direction
        ((0.3, 0.4, 1), (nan, 0, -1), 0, inf, 1),
        ((nan, 0.4, 1), down, 0, inf, 1),
        ((inf, 0.4, 1), down, 0, inf, 1),
        ((0.3, 0.4, 1), (0, -inf, -1), 0, inf, 1),
    ]
    rng = np.random.default_rng(7)
    while len(rays) < RAYS:
        rays.append(((*rng.uniform(0.05, 0.95, 2), 2.0), (*rng.uniform(-0.2, 0.2, 2), -1.0), 0, inf, 1))
    origin, direction, t_min, t_max, mask = (np.asarray(a, np.float64) for a in zip(*rays, strict=True))
    params = dict(grid=grid, soup=np.asarray(soup, np.float64).reshape(-1, 3), origin=origin, direction=direction)
    settings = dict(min_distance=t_min, max_distance=t_max, mask=np.where(mask > 0, 0xFFFFFFFF, 0).astype(np.uint32))
    cases = dict(hits=np.arange(0, 8), misses=np.arange(8, 16), disabled=np.arange(16, 23))
    return params, settings, cases


def test_misses_and_disabled_rays_get_exactly_zero_gradient():
    params, settings, cases = hard_scene()
    p, s = cast(params, jnp.float32), cast(settings, jnp.float32)
    zero_tangent = cast(zeros_like(params), jnp.float32)
    _, primitive, _, _ = derivatives_jit(p, s, zero_tangent, output_shaped(jnp.zeros))
    primitive = np.asarray(primitive)
    assert (primitive[cases["hits"]] >= 0).all(), primitive[cases["hits"]]
    quiet = np.concatenate([cases["misses"], cases["disabled"]])
    assert (primitive[quiet] == -1).all(), primitive[quiet]

    gradient = {k: np.asarray(v) for k, v in grad_jit(p, s, output_shaped(jnp.ones)).items()}
    for name, value in gradient.items():
        assert np.isfinite(value).all(), name
    for name in ("origin", "direction"):
        assert (gradient[name][quiet] == 0).all(), name
    assert (np.abs(gradient["origin"][cases["hits"]]).sum(-1) > 0).all()
    # A ray starting on the surface hits at distance 0: there the hit does not depend on its direction.
    moving = cases["hits"][cases["hits"] != 6]
    assert (np.abs(gradient["direction"][moving]).sum(-1) > 0).all()
    # Degenerate triangles are never hit: their vertices get no gradient (nor do the far soup triangles).
    assert (gradient["soup"] == 0).all()
    assert np.abs(gradient["grid"]).sum() > 0

    # Only misses and disabled rays in the loss: every gradient is exactly zero.
    mask = np.isin(np.arange(RAYS), quiet)
    only_quiet = {
        k: jnp.where(mask.reshape(-1, *([1] * (v.ndim - 1))), v, 0.0) for k, v in output_shaped(jnp.ones).items()
    }
    for name, value in grad_jit(p, s, only_quiet).items():
        assert (np.asarray(value) == 0).all(), name

    # Forward mode: tangents of misses are exactly zero, and finite everywhere.
    rng = np.random.default_rng(0)
    tangent = {k: jnp.asarray(rng.normal(size=np.shape(v)), jnp.float32) for k, v in params.items()}
    values, _, tangents, _ = derivatives_jit(p, s, tangent, output_shaped(jnp.zeros))
    for name in QUANTITIES:
        t = np.asarray(tangents[name])
        assert np.isfinite(t).all(), name
        assert (t[quiet] == 0).all(), name
        assert (np.asarray(values[name])[quiet] == 0).all(), name


COMPILE_EVENTS = ("/jax/core/compile/backend_compile_duration", "/jax/core/compile/jaxpr_trace_duration")


@contextlib.contextmanager
def compile_events():
    """The JAX compile and trace events (``jax.monitoring``) recorded inside the block."""
    events: list[str] = []

    def listener(event: str, duration: float, **kwargs) -> None:
        if event in COMPILE_EVENTS:
            events.append(event)

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        yield events
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)


def float32_scene(seed: int) -> tuple[dict, dict, dict]:
    params, _ = random_scene(seed, 0.0, 0.0)
    rng = np.random.default_rng(seed)
    cotangent = output_shaped(lambda shape: jnp.asarray(rng.normal(size=shape), jnp.float32))
    return cast(params, jnp.float32), cast(default_settings(), jnp.float32), cotangent


def test_jit_grad_equals_grad_and_neither_recompiles():
    eager_grad = jax.grad(loss)
    scenes = [float32_scene(seed) for seed in range(3)]
    jitted = grad_jit(*scenes[0])
    eager = eager_grad(*scenes[0])
    for name in jitted:
        np.testing.assert_allclose(np.asarray(jitted[name]), np.asarray(eager[name]), rtol=1e-5, atol=1e-5)
    with compile_events() as events:
        for scene in scenes[1:]:
            jax.block_until_ready(grad_jit(*scene))
    assert events == [], f"jax.jit(jax.grad(...)) recompiled for new values: {events}"
    with compile_events() as events:
        for scene in scenes[1:]:
            jax.block_until_ready(eager_grad(*scene))
    assert not [e for e in events if e == COMPILE_EVENTS[0]], f"jax.grad(...) recompiled for new values: {events}"


def per_ray_loss(grid, soup, origin, direction, cotangent):
    """:func:`loss` of a single ray (``origin`` and ``direction`` of shape ``(3,)``)."""
    params = dict(grid=grid, soup=soup, origin=origin, direction=direction)
    return loss(params, dict(min_distance=0.0, max_distance=jnp.inf, mask=0xFFFFFFFF), cotangent)


def test_vmap_grad_over_rays_matches_batched_grad():
    p, s, cotangent = float32_scene(5)
    per_ray = jax.jit(jax.vmap(jax.grad(per_ray_loss, argnums=(0, 1, 2, 3)), in_axes=(None, None, 0, 0, 0)))
    grid, soup, origin, direction = per_ray(p["grid"], p["soup"], p["origin"], p["direction"], cotangent)
    batched = grad_jit(p, s, cotangent)
    np.testing.assert_allclose(origin, batched["origin"], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(direction, batched["direction"], rtol=1e-5, atol=1e-6)
    scale = float(np.abs(np.asarray(batched["grid"])).max())
    np.testing.assert_allclose(grid.sum(0), batched["grid"], rtol=1e-4, atol=1e-5 * scale)
    np.testing.assert_allclose(soup.sum(0), batched["soup"], rtol=1e-4, atol=1e-5 * scale)
