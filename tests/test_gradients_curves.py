"""Gradients of curve hits through ``rt.build_primitive_structure`` + ``Intersector.intersect``.

Per-ray ``jax.grad`` of the hit ``distance`` and ``curve_parameter`` with respect to the control points and
radii of every geometry, the ray origins and the ray directions, against float64 five-point central
differences of the same intersect call, on random scenes (random seed, scale ``10**[-1, 1]``, centre up to 10
scales from the origin): one structure holding every basis (cubic Bezier, Catmull-Rom, cubic B-spline,
linear) as round tubes and as flat ribbons, with each kind of end cap, 2 strands of 2 segments per geometry
(the first Bezier segment starts with a zero tangent, ``b1 = b0``), and one holding only linear curves (its
default is the exact round cone, no iteration). 6 rays are aimed at points within 0.8 radii of each
geometry's centre line, at least 30 degrees off its tangent; 8 more miss or are disabled.

The per-ray gradients are ``jax.vmap(jax.grad(loss of one ray))`` over the rays (:func:`per_ray_gradients`),
projected on a random tangent of one input group (points of every geometry, radii, origins or directions;
entries a standard normal times the scene scale, the point's radius, the scene scale, the direction's
length) and compared, per ray, with ``(8 (f(x + h t) - f(x - h t)) - (f(x + 2h t) - f(x - 2h t))) / 12h``,
``h = STEP``. The call runs Newton to convergence (:data:`CONVERGED`; see there why the default's 3 steps give
no usable differences); its gradients equal the default's.

A ray is compared only where its hit is the same segment at all five points and on the same part of it (a
cap or joint sphere reports ``u`` exactly 0 or 1, a tube or ribbon hit an interior ``u``): a stencil that
crosses a silhouette or the rim between a tube and its cap straddles a visibility (or first-derivative)
discontinuity, which autodiff does not see by design; and only where the hit is not grazing
(:data:`INCIDENCE`). Most aimed rays must be compared. The error of a ray is ``|ad - fd| / max(|fd|, FLOOR *
rms(fd))`` (rms over the compared rays of the scene), separately for the distance and the curve parameter.

The largest errors over 100 random scenes per structure, in float64 and float32, are tabulated in
``docs/differentiable.md`` by ``python tests/test_gradients_curves.py --scenes 100``; :data:`TOLERANCE` is set
from them. Rays that miss, and disabled rays (mask 0, ``max_distance < min_distance``, zero direction, NaN
origin), get exactly zero gradient in every input and no NaN anywhere, in both precisions; ``jax.jit(
jax.grad(...))`` of a batch agrees with the per-ray gradients.
"""

from __future__ import annotations

import functools
import sys

import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

import jaxrt as rt
from jaxrt._src.curves import bezier_matrix

#: (basis, control points per segment, type, end caps) of the geometries of each structure.
MIXED = (
    ("bezier", 4, "round", "sphere"),
    ("catmull_rom", 4, "round", "disk"),
    ("bspline", 4, "round", "none"),
    ("linear", 2, "round", "sphere"),
    ("bezier", 4, "flat", "disk"),
    ("catmull_rom", 4, "flat", "sphere"),
    ("bspline", 4, "flat", "none"),
    ("linear", 2, "flat", "disk"),
)
LINEAR = (("linear", 2, "round", "sphere"), ("linear", 2, "flat", "disk"))
STRANDS = 2  # per geometry
SEGMENTS = 2  # per strand
AIMED = 6  # rays aimed at each geometry
QUIET = 8  # misses and disabled rays, after the aimed ones
STEP = 1e-5
FLOOR = 1e-3
#: Rays compared only where they hit at least 14.5 degrees off the surface (:func:`incidence`), as in the
#: triangle tests: a grazing hit's derivative grows like 1 / cos, and the hit itself is accepted at the test's
#: tolerance, ill conditioned there (the differences then measure the test's convergence, not the derivative).
INCIDENCE = 0.25
QUANTITIES = ("distance", "u")
GROUPS = ("points", "radii", "origin", "direction")
#: Largest accepted per-ray relative error, float64: the largest measured over 100 scenes per structure is
#: 5.8e-7 (docs/differentiable.md; the differences' own error: over 30 scenes it is 1.2e-5 with a step of
#: 1e-4 and 7.6e-7 with 1e-6), times 3.4.
TOLERANCE = 2e-6
#: Largest accepted error of a float32 batch gradient against the float64 per-ray gradients, relative to the
#: largest entry (:func:`batch_gradient_errors`): measured at most 6.2e-6 over seeds 0-99, times 3.2.
TOLERANCE_FLOAT32 = 2e-5

#: The knobs of the differentiated call: Newton run to convergence in float64. The default (3 steps) stops
#: once a hit is within its tolerance (1e-3 of the radius), and 6 steps do not always converge where the curve
#: slows down (near a zero tangent): differences of such a call differentiate its truncated iteration (for the
#: default, they differ from the gradients by up to 8.5e-2 over 100 scenes, docs/differentiable.md), while the
#: gradients, taken at the hit polished to the root, are the same with either knobs. Linear-only structures
#: keep their default, the exact round cone.
CONVERGED = rt.CurveOptions(iterations=12)


def _rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.diag(r))


def _strand(rng, basis: str, count: int, offset: np.ndarray, radius: float):
    """A smooth random strand of ``SEGMENTS`` connected segments with unit control polygon legs."""
    step = count - 1 if basis in ("bezier", "linear") else 1
    points = count + (SEGMENTS - 1) * step
    direction, legs = rng.normal(size=3), []
    for _ in range(points - 1):
        direction = direction / np.linalg.norm(direction)
        legs.append(direction)
        direction = direction + 0.4 * rng.normal(size=3)
    position = np.concatenate([np.zeros((1, 3)), np.cumsum(legs, axis=0)]) + offset
    return position, radius * rng.uniform(0.3, 1.0, points), np.arange(SEGMENTS) * step


def _bezier(points: np.ndarray, radii: np.ndarray, indices: np.ndarray, basis: str, count: int) -> np.ndarray:
    """``(S, 4, 4)`` float64 cubic Bezier control points (x, y, z, radius) of every segment."""
    window = np.concatenate([points, radii[:, None]], axis=1)[indices[:, None] + np.arange(count)]
    return np.einsum("ij,sjk->sik", bezier_matrix(rt.CurveBasis.coerce(basis), count), window)


def random_scene(seed: int, combos: tuple, scale_exp: float, offset_exp: float):
    """``(params, settings, indices, scale)``: the geometries of ``combos`` side by side, ``AIMED`` rays aimed
    at points within 0.8 radii of each geometry's centre line (at least 30 degrees off its tangent), then the
    ``QUIET`` rays; float64 numpy arrays."""
    rng = np.random.default_rng(seed)
    scale = 10.0**scale_exp
    centre = scale * 10.0**offset_exp * rng.normal(size=3)
    rotation = _rotation(rng)
    points, radii, indices, origin, direction = [], [], [], [], []
    for g, (basis, count, _, _) in enumerate(combos):
        parts = [_strand(rng, basis, count, np.array([4.0 * g, 3.0 * s, 0.0]), 0.2) for s in range(STRANDS)]
        if basis == "bezier":  # a first segment that starts with a zero tangent (b1 = b0): a valid curve
            parts[0][0][1] = parts[0][0][0]
        p = np.concatenate([q[0] for q in parts])
        r = np.concatenate([q[1] for q in parts])
        i = np.concatenate([q[2] + k * len(parts[0][0]) for k, q in enumerate(parts)])
        bezier = _bezier(p, r, i, basis, count)
        for k in range(AIMED):
            # (The first ray at a Bezier geometry: at the start of its first segment, the zero tangent.)
            first = basis == "bezier" and k == 0
            b = bezier[0 if first else rng.integers(len(bezier))]
            u = rng.uniform(0.1, 0.4) if first else rng.uniform(0.0, 1.0)
            c = np.array([(1 - u) ** 3, 3 * u * (1 - u) ** 2, 3 * u**2 * (1 - u), u**3]) @ b
            tangent = np.array([-3 * (1 - u) ** 2, 3 - 12 * u + 9 * u**2, 6 * u - 9 * u**2, 3 * u**2]) @ b[:, :3]
            tangent /= np.linalg.norm(tangent)
            w = rng.normal(size=3)  # at least 30 degrees off the tangent
            while abs(w @ tangent) > np.cos(np.radians(30.0)) * np.linalg.norm(w):
                w = rng.normal(size=3)
            w /= np.linalg.norm(w)
            side = rng.normal(size=3)
            side -= (side @ w) * w
            target = c[:3] + side / np.linalg.norm(side) * rng.uniform(0.0, 0.8) * abs(c[3])
            origin.append(target - w * rng.uniform(3.0, 6.0))
            direction.append(w * rng.uniform(0.5, 2.0))
        points.append(p)
        radii.append(r)
        indices.append(i)
    # Misses and disabled rays.
    every = np.concatenate(points)
    middle = every.mean(axis=0)
    reach = np.linalg.norm(every - middle, axis=1).max() + 1.0
    min_distance, max_distance, mask = np.zeros(QUIET), np.full(QUIET, np.inf), np.full(QUIET, 0xFFFFFFFF)
    quiet_origin, quiet_direction = np.array(origin[:QUIET]), np.array(direction[:QUIET])
    for k in (0, 1):  # pointing away from the scene
        away = rng.normal(size=3)
        quiet_origin[k], quiet_direction[k] = middle + 2.0 * reach * away / np.linalg.norm(away), away
    mask[2] = 0
    min_distance[3], max_distance[3] = 1.0, 0.5
    quiet_direction[4] = 0.0
    quiet_origin[5] = np.nan
    max_distance[6] = 1e-3  # ends before anything
    min_distance[7] = 1e3 * reach / np.linalg.norm(quiet_direction[7])  # starts past everything
    origin = np.concatenate([np.array(origin), quiet_origin])
    direction = np.concatenate([np.array(direction), quiet_direction])
    rays = len(origin)
    settings = dict(
        min_distance=np.concatenate([np.zeros(rays - QUIET), min_distance]),
        max_distance=np.concatenate([np.full(rays - QUIET, np.inf), max_distance]),
        mask=np.concatenate([np.full(rays - QUIET, 0xFFFFFFFF), mask]).astype(np.uint32),
    )
    world = lambda p: centre + scale * p @ rotation.T  # noqa: E731
    params = dict(
        points=[world(p) for p in points],
        radii=[scale * r for r in radii],
        origin=world(origin),
        direction=scale * direction @ rotation.T,
    )
    return params, settings, tuple(indices), scale


def hit_values(params: dict, settings: dict, indices: tuple, combos: tuple, options=None):
    """``({"distance", "u"}, primitive)`` of every ray: 0 for misses; ``1000 * geometry + segment`` or -1."""
    geometries = [
        rt.CurveGeometry(p, r, i, basis=basis, control_point_count=count, curve_type=kind, end_caps=caps)
        for p, r, i, (basis, count, kind, caps) in zip(params["points"], params["radii"], indices, combos, strict=True)
    ]
    structure = rt.build_primitive_structure(geometries)
    intersector = rt.Intersector(rt.tags.curve_data, curve_options=options)
    hits = intersector.intersect(rt.Ray(params["origin"], params["direction"], **settings), structure)
    hit = hits.type == rt.IntersectionType.CURVE
    values = {"distance": jnp.where(hit, hits.distance, 0.0), "u": hits.curve_parameter}
    return values, jnp.where(hit, hits.geometry_id * 1000 + hits.primitive_id, -1)


def weighted_loss(params, settings, indices, weights, combos, options=None):
    """``sum(weights[0] * distance + weights[1] * u)`` (and the values, primitives as auxiliary data)."""
    values, primitive = hit_values(params, settings, indices, combos, options)
    return jnp.sum(weights[0] * values["distance"]) + jnp.sum(weights[1] * values["u"]), (values, primitive)


@functools.partial(jax.jit, static_argnames=("combos", "options"))
def per_ray_gradients(params, settings, indices, combos, options=None):
    """``(values, primitive, rows)``: ``rows[k]`` is, for every input, the gradient of the distance of ray
    ``k`` (``k < R``) or the curve parameter of ray ``k - R``: ``jax.vmap(jax.grad(loss of one ray))`` over
    the rays, twice (``rows["origin"]`` and ``rows["direction"]`` are ``(2R, 3)``, the gradients with respect
    to the ray's own origin and direction)."""
    rays = params["origin"].shape[0]

    def one_ray(points, radii, origin, direction, settings, weights):
        mine = dict(points=points, radii=radii, origin=origin, direction=direction)
        return weighted_loss(mine, settings, indices, weights, combos, options)

    twice = lambda a: jnp.concatenate([a, a])  # noqa: E731
    weights = jnp.repeat(jnp.eye(2, dtype=params["origin"].dtype), rays, axis=0)  # (2R, 2)
    grad = jax.grad(one_ray, argnums=(0, 1, 2, 3), has_aux=True)
    (points, radii, origin, direction), (values, primitive) = jax.vmap(grad, in_axes=(None, None, 0, 0, 0, 0))(
        params["points"],
        params["radii"],
        twice(params["origin"]),
        twice(params["direction"]),
        jax.tree_util.tree_map(twice, settings),
        weights,
    )
    rows = dict(points=points, radii=radii, origin=origin, direction=direction)
    return jax.tree_util.tree_map(lambda a: a[:rays], values), primitive[:rays], rows


def cast(tree, dtype):
    """Float arrays to ``dtype``; others to JAX arrays unchanged."""
    return jax.tree_util.tree_map(
        lambda v: jnp.asarray(v, dtype) if np.asarray(v).dtype.kind == "f" else jnp.asarray(v), tree
    )


def evaluate(params, settings, indices, combos, options=None, dtype=jnp.float64):
    """:func:`per_ray_gradients` in ``dtype`` (float64 under x64), as numpy arrays."""
    with jax.enable_x64(dtype == jnp.float64):
        args = cast(params, dtype), cast(settings, dtype), cast(indices, jnp.int32)
        out = per_ray_gradients(*args, combos=combos, options=options)
        return jax.tree_util.tree_map(lambda a: np.asarray(a, np.float64), out)


def tangent_for(group: str, params: dict, scale: float, rng: np.random.Generator) -> dict:
    """A random tangent in one input group (zero elsewhere), in the units of that group."""
    tangent = jax.tree_util.tree_map(np.zeros_like, params)
    if group == "points":
        tangent["points"] = [scale * rng.normal(size=p.shape) for p in params["points"]]
    elif group == "radii":
        tangent["radii"] = [r * rng.normal(size=r.shape) for r in params["radii"]]
    elif group == "origin":
        tangent["origin"] = scale * rng.normal(size=params["origin"].shape)
    else:
        length = np.linalg.norm(params["direction"], axis=-1, keepdims=True)
        tangent["direction"] = length * rng.normal(size=params["direction"].shape)
    return tangent


def along(rows: dict, tangent: dict) -> np.ndarray:
    """``(2R,)``: each row of gradients projected on ``tangent``."""
    total = 0.0
    for name in ("points", "radii"):
        for leaf, t in zip(rows[name], tangent[name], strict=True):
            total = total + leaf.reshape(len(leaf), -1) @ t.reshape(-1)
    for name in ("origin", "direction"):
        total = total + np.sum(rows[name] * np.concatenate([tangent[name], tangent[name]]), axis=-1)
    return total


def _on_end(u: np.ndarray) -> np.ndarray:
    return (u == 0.0) | (u == 1.0)


def central_differences(params, settings, indices, combos, tangent, options=None):
    """Float64 five-point differences along ``tangent`` of the values, the rays where they are valid (the
    module docstring), and the base evaluation ``(values, primitive, rows)``."""
    base = evaluate(params, settings, indices, combos, options)
    values, primitive = {}, base[1]
    valid = primitive >= 0
    for sign in (1, -1, 2, -2):
        moved = jax.tree_util.tree_map(lambda v, t, sign=sign: v + sign * STEP * t, params, tangent)
        values[sign], other, _ = evaluate(moved, settings, indices, combos, options)
        valid &= (other == primitive) & (_on_end(values[sign]["u"]) == _on_end(base[0]["u"]))
    with np.errstate(invalid="ignore"):  # the NaN-origin ray
        fd = {
            k: (8.0 * (values[1][k] - values[-1][k]) - (values[2][k] - values[-2][k])) / (12.0 * STEP)
            for k in QUANTITIES
        }
    return fd, valid, base


def incidence(params: dict, indices: tuple, combos: tuple, values: dict, primitive: np.ndarray) -> np.ndarray:
    """Per ray, the cosine of the angle between the ray and the normal of the surface it hits (tube: the
    normal of the touching sphere; end disk: the curve's end tangent) or, on a flat ribbon, the sine of the
    angle between the ray and the curve's tangent (a ribbon seen end-on is ill defined); 1 for ray-facing
    disks, 0 for misses."""
    cosine = np.zeros(len(primitive))
    origin, direction = np.asarray(params["origin"]), np.asarray(params["direction"])
    for r in np.nonzero(primitive >= 0)[0]:
        g, segment = divmod(int(primitive[r]), 1000)
        basis, count, kind, _ = combos[g]
        b = _bezier(np.asarray(params["points"][g]), np.asarray(params["radii"][g]), indices[g], basis, count)[segment]
        u, t = values["u"][r], values["distance"][r]
        centre = np.array([(1 - u) ** 3, 3 * u * (1 - u) ** 2, 3 * u**2 * (1 - u), u**3]) @ b
        tangent = np.array([-3 * (1 - u) ** 2, 3 - 12 * u + 9 * u**2, 6 * u - 9 * u**2, 3 * u**2]) @ b[:, :3]
        ray = direction[r] / np.linalg.norm(direction[r])
        offset = origin[r] + t * direction[r] - centre[:3]
        on_sphere = abs(np.linalg.norm(offset) - abs(centre[3])) <= 1e-6 * abs(centre[3])
        if 0 < u < 1 and kind == "flat":
            cosine[r] = np.sqrt(max(0.0, 1.0 - (ray @ tangent / np.linalg.norm(tangent)) ** 2))
        elif 0 < u < 1 or on_sphere:  # the tube, or an end sphere
            cosine[r] = abs(ray @ offset) / np.linalg.norm(offset)
        elif kind == "flat":  # the ray-facing end disk
            cosine[r] = 1.0
        else:  # the end disk
            cosine[r] = abs(ray @ tangent) / np.linalg.norm(tangent)
    return cosine


def relative_errors(ad: np.ndarray, fd: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Per-ray error (the module docstring); 0 where not ``valid``."""
    floor = FLOOR * np.sqrt(np.mean(fd[valid] ** 2)) if valid.any() else 1.0
    error = np.abs(ad - fd) / np.maximum(np.abs(fd), floor)
    return np.where(valid, error, 0.0)


def check_quiet(base, rays: int) -> None:
    """Misses and disabled rays: values 0, every gradient exactly 0; no NaN in any gradient."""
    values, primitive, rows = base
    quiet = np.arange(rays) >= rays - QUIET
    assert (primitive[quiet] == -1).all(), primitive[quiet]
    missed = np.concatenate([primitive < 0, primitive < 0])
    for name in GROUPS:
        for leaf in jax.tree_util.tree_leaves(rows[name]):
            assert np.isfinite(leaf).all(), f"non-finite gradient w.r.t. {name}"
            assert (leaf[missed] == 0).all(), f"a miss has a non-zero gradient w.r.t. {name}"
    for k in QUANTITIES:
        assert (values[k][primitive < 0] == 0).all(), k


def measure(scene: tuple, combos: tuple, options=None, reference=None, dtype=jnp.float64) -> dict:
    """Per ``(geometry, group, quantity)``: ``(largest error, rays compared, rays aimed)``.

    Autodiff in ``dtype`` with the knobs ``options`` against float64 differences with the knobs ``reference``
    (default: ``options``). Float32: the inputs are rounded to float32 first, and rays are compared where the
    float32 hit is the segment and part (cap or not) of the float64 one.
    """
    seed = scene[0]
    params, settings, indices, scale = random_scene(seed, combos, *scene[1:])
    if dtype != jnp.float64:
        params = jax.tree_util.tree_map(lambda v: np.asarray(v, np.float32).astype(np.float64), params)
    reference = options if reference is None else reference
    rays = len(params["origin"])
    aimed_at = np.concatenate([np.repeat(np.arange(len(combos)), AIMED), np.full(QUIET, -1)])
    rng = np.random.default_rng(seed + 1)
    result = {}
    for group in GROUPS:
        tangent = tangent_for(group, params, scale, rng)
        fd, valid, base = central_differences(params, settings, indices, combos, tangent, reference)
        check_quiet(base, rays)
        valid &= incidence(params, indices, combos, base[0], base[1]) >= INCIDENCE
        if dtype != jnp.float64 or options != reference:
            fd_base, base = base, evaluate(params, settings, indices, combos, options, dtype)
            check_quiet(base, rays)
            valid &= (base[1] == fd_base[1]) & (_on_end(base[0]["u"]) == _on_end(fd_base[0]["u"]))
        ad = along(base[2], tangent)
        primitive = base[1]
        hit_geometry = np.where(primitive >= 0, primitive // 1000, -1)
        for q, name in enumerate(QUANTITIES):
            error = relative_errors(ad[q * rays : (q + 1) * rays], fd[name], valid)
            for g in range(len(combos)):
                mine = hit_geometry == g
                result[g, group, name] = (
                    float(error[mine].max(initial=0.0)),
                    int((valid & mine).sum()),
                    int((aimed_at == g).sum()),
                )
    return result


scenes = st.tuples(st.integers(0, 2**31 - 1), st.floats(-1.0, 1.0), st.floats(-1.0, 1.0))


def _check(scene, combos, options):
    result = measure(scene, combos, options)
    compared = {}
    for (g, group, name), (error, count, _) in result.items():
        basis, _, kind, caps = combos[g]
        assert error < TOLERANCE, f"{name} w.r.t. {group}, {kind} {basis} ({caps} caps): relative error {error:.2e}"
        compared[group] = compared.get(group, 0) + count
    aimed = AIMED * len(combos)
    for group, count in compared.items():  # per quantity and group: most aimed rays are compared
        assert count >= len(QUANTITIES) * aimed // 2, f"only {count // 2} of {aimed} rays compared ({group})"
    for g, combo in enumerate(combos):  # and every geometry has some
        count = sum(result[g, group, name][1] for group in GROUPS for name in QUANTITIES)
        assert count >= len(GROUPS) * len(QUANTITIES), f"{combo}: {count} comparisons"


@given(scenes)
@settings(deadline=None, derandomize=True)
def test_float64_gradients_of_every_basis_and_type_match_central_differences(scene):
    _check(scene, MIXED, CONVERGED)


@given(scenes)
@settings(deadline=None, derandomize=True, max_examples=4)
def test_float64_gradients_of_linear_curves_match_central_differences(scene):
    """Linear-only structures take the exact round-cone test (one piece, no Newton iteration)."""
    _check(scene, LINEAR, None)


def _root(b: np.ndarray, origin: np.ndarray, direction: np.ndarray, u: float, t: float, flat: bool):
    """The tube's ``(u, t)`` (or the ribbon's ``u``) solved by Newton in float64 from ``(u, t)``."""
    for _ in range(30):
        c = np.array([(1 - u) ** 3, 3 * u * (1 - u) ** 2, 3 * u**2 * (1 - u), u**3]) @ b
        dc = np.array([-3 * (1 - u) ** 2, 3 - 12 * u + 9 * u**2, 6 * u - 9 * u**2, 3 * u**2]) @ b
        ddc = np.array([6 * (1 - u), -12 + 18 * u, 6 - 18 * u, 6 * u]) @ b
        if flat:
            across = lambda v: v - (v @ direction) / (direction @ direction) * direction  # noqa: E731
            p, dp, ddp = across(c[:3] - origin), across(dc[:3]), across(ddc[:3])
            u -= (p @ dp) / (dp @ dp + p @ ddp)
            continue
        w = origin + t * direction - c[:3]
        value = np.array([w @ w - c[3] ** 2, w @ dc[:3] + c[3] * dc[3]])
        g_u = -dc[:3] @ dc[:3] + w @ ddc[:3] + dc[3] ** 2 + c[3] * ddc[3]
        jac = np.array([[-2 * value[1], 2 * w @ direction], [g_u, direction @ dc[:3]]])
        u, t = np.array([u, t]) - np.linalg.solve(jac, value)
    return u, t


@jax.jit
def _smooth_jacobian(segment, origin, direction, part, u, t):
    """The Jacobian of :func:`~jaxrt._src.primitives.curve.smooth_hit`'s ``(t, u)`` w.r.t. the segment and ray."""
    from jaxrt._src.primitives import curve as primitive

    hit = lambda s, o, d: jnp.stack(primitive.smooth_hit(o, d, s, part, u, t))  # noqa: E731
    return jax.jacobian(hit, argnums=(0, 1, 2))(segment, origin, direction)


def test_gradients_are_taken_at_the_root_not_at_the_accepted_hit():
    """The test accepts a hit within its tolerance of the root (with the default knobs, ``1e-3`` of the radius):
    :func:`~jaxrt._src.primitives.curve.smooth_hit` polishes it first, so its gradients are the root's (a
    linearisation at the accepted point is off by up to 1.9e-4 here, 2% of some entries)."""
    from jaxrt._src.curves import pack_segments
    from jaxrt._src.primitives import curve as primitive

    points = np.array([[0.0, 0.0, 0.0], [1.0, 0.6, 0.2], [2.0, -0.4, 0.1], [3.0, 0.3, 0.0]])
    radii = np.array([0.3, 0.25, 0.2, 0.3])
    origin, direction = np.array([1.3, 0.05, 3.0]), np.array([0.1, 0.05, -1.0])
    b = _bezier(points, radii, np.array([0]), "bezier", 4)[0]
    with jax.enable_x64(True):
        for flat, part in ((False, primitive.PART_TUBE), (True, primitive.PART_RIBBON)):
            geometry = rt.CurveGeometry(
                points, radii, [0], basis="bezier", control_point_count=4, curve_type="flat" if flat else "round"
            )
            segment = pack_segments(geometry)[0][0]
            u, t = _root(b, origin, direction, 0.45, 2.7, flat)
            if flat:
                c = np.array([(1 - u) ** 3, 3 * u * (1 - u) ** 2, 3 * u**2 * (1 - u), u**3]) @ b
                t = (c[:3] - origin) @ direction / (direction @ direction)

            args = segment, jnp.asarray(origin), jnp.asarray(direction), jnp.asarray(part)
            at_root = _smooth_jacobian(*args, jnp.asarray(u), jnp.asarray(t))
            accepted = _smooth_jacobian(*args, jnp.asarray(u + 2e-4), jnp.asarray(t - 1e-4))  # ~1e-3 r away
            for want, got in zip(at_root, accepted, strict=True):
                np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-9, atol=1e-9 * np.abs(want).max())


_batch_grad = jax.jit(jax.grad(weighted_loss, has_aux=True), static_argnames=("combos", "options"))


def batch_gradient_errors(seed: int) -> dict:
    """``jax.jit(jax.grad(loss))`` of a batch in float32 (the default), on a linear-only scene: asserts no NaN,
    and exactly zero gradient for a loss of the misses and disabled rays only; returns, per input group, the
    largest error of the gradient of a random weighting of the rays that hit the same segment, well off grazing,
    in both precisions, against the float64 per-ray gradients (``jax.vmap(jax.grad(...))``) weighted alike,
    relative to the group's largest entry."""
    params, settings, indices, _ = random_scene(seed, LINEAR, 0.0, 0.0)
    params = jax.tree_util.tree_map(lambda v: np.asarray(v, np.float32).astype(np.float64), params)
    rays = len(params["origin"])
    values64, primitive64, rows = evaluate(params, settings, indices, LINEAR)
    p, s, i = cast(params, jnp.float32), cast(settings, jnp.float32), cast(indices, jnp.int32)

    quiet = np.zeros((2, rays), np.float32)
    quiet[:, primitive64 < 0] = 1.0
    assert quiet[0, -QUIET:].all() and (primitive64 >= 0).sum() >= (rays - QUIET) // 2
    gradient, (_, primitive) = _batch_grad(p, s, i, jnp.asarray(quiet), combos=LINEAR)
    same = np.asarray(primitive) == primitive64
    for name in GROUPS:
        for leaf in jax.tree_util.tree_leaves(gradient[name]):
            assert (np.asarray(leaf) == 0).all(), f"a miss has a gradient w.r.t. {name}"

    compared = same & (primitive64 >= 0) & (incidence(params, indices, LINEAR, values64, primitive64) >= INCIDENCE)
    weights = np.random.default_rng(seed).normal(size=(2, rays)) * compared
    gradient, _ = _batch_grad(p, s, i, jnp.asarray(weights, jnp.float32), combos=LINEAR)
    flat, errors = weights.reshape(-1), {}
    for name in GROUPS:
        if name in ("points", "radii"):
            expected = [np.tensordot(flat, leaf, axes=1) for leaf in rows[name]]
        else:
            expected = [weights[0, :, None] * rows[name][:rays] + weights[1, :, None] * rows[name][rays:]]
        got = [np.asarray(leaf, np.float64) for leaf in jax.tree_util.tree_leaves(gradient[name])]
        assert all(np.isfinite(leaf).all() for leaf in got), name
        scale = max(np.abs(want).max() for want in expected)  # (a ribbon's distance has no radius gradient)
        errors[name] = max(np.abs(a - b).max() for a, b in zip(got, expected, strict=True)) / scale
    return errors


def test_jit_grad_in_float32_is_finite_zero_for_misses_and_matches_the_per_ray_gradients():
    for name, error in batch_gradient_errors(12).items():
        assert error < TOLERANCE_FLOAT32, f"w.r.t. {name}: {error:.1e}"


#: The columns of the table in the docs: (label, autodiff knobs, difference knobs, dtype of autodiff).
COLUMNS = (
    ("float64, converged (asserted)", CONVERGED, CONVERGED, jnp.float64),
    ("float64, default", None, CONVERGED, jnp.float64),
    ("float64, default, differences of the default", None, None, jnp.float64),
    ("float32, default", None, CONVERGED, jnp.float32),
)


def main(argv=None) -> None:
    """Print the largest per-ray errors over random scenes (the tables in docs/differentiable.md)."""
    import argparse
    import time

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("--scenes", type=int, default=20, help="random scenes per structure (default 20)")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    rng = np.random.default_rng(0)
    draws = [(int(rng.integers(2**31 - 1)), rng.uniform(-1, 1), rng.uniform(-1, 1)) for _ in range(args.scenes)]
    by_geometry, by_input = {}, {}
    for combos in (MIXED, LINEAR):
        for label, options, reference, dtype in COLUMNS:
            if combos is LINEAR:  # linear-only structures: their default (the exact cone) throughout
                if reference is None:
                    continue
                options = reference = None
            for scene in draws:
                for (g, group, name), (error, count, _) in measure(scene, combos, options, reference, dtype).items():
                    row = ("linear only" if combos is LINEAR else "mixed",) + combos[g]
                    for table, key in ((by_geometry, (row, label)), (by_input, ((group, name), label))):
                        old = table.get(key, (0.0, 0))
                        table[key] = (max(old[0], error), old[1] + count)
    labels = [c[0] for c in COLUMNS]
    for title, table in (("structure, basis, count, type, caps", by_geometry), ("input, quantity", by_input)):
        rows = list(dict.fromkeys(k[0] for k in table))
        print(f"| {title} | " + " | ".join(labels) + " | comparisons |")
        print("|---" * (len(labels) + 2) + "|")
        for row in rows:
            cells = [f"{table[row, label][0]:.1e}" if (row, label) in table else "-" for label in labels]
            print(f"| {', '.join(map(str, row))} | " + " | ".join(cells) + f" | {table[row, labels[0]][1]} |")
        print()
    batch = {}
    for seed in range(args.scenes):
        for name, error in batch_gradient_errors(seed).items():
            batch[name] = max(batch.get(name, 0.0), error)
    print("float32 jit(grad) of a batch, largest error / largest entry:", {k: f"{v:.1e}" for k, v in batch.items()})
    print(f"{args.scenes} scenes per structure, {time.perf_counter() - start:.0f} s; jax {jax.__version__}")


if __name__ == "__main__":
    main(sys.argv[1:])
