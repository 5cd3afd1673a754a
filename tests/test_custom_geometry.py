"""Bounding-box primitives, filters on non-opaque triangles and primitive data, against float64 brute force.

Every random scene has one layout (:data:`COUNTS`): opaque triangles, alpha-tested triangles, and spheres,
disks and capped cylinders as :class:`rt.BoundingBoxGeometry` decided by ``rt.intersection_functions``. All
geometries carry one primitive-data pytree of mixed dtypes and trailing shapes (shape parameters, texture
coordinates, a 4x4 alpha texture, a cutoff, integer keys, nested bools), so the tests here and in
``test_multi_hit.py`` share one build and a few compiled intersectors.

The float64 reference describes each (ray, primitive) pair by *where* a correct float32 implementation may
report a hit:

* triangles: the watertight oracle of ``reference.py`` (certain / possible hits, derived distance tolerance);
* analytic shapes: a backward-error model. The float32 functions return the exact intersection of the shape
  inflated or deflated by at most ``delta = SHAPE_ERROR * eps32 * M`` (radius and caps moved by ``delta``),
  where ``M`` (:func:`round_magnitude`, :func:`cylinder_magnitude`) sums the magnitudes the function
  subtracts and the hit's distance from the origin, plus, for the capped cylinder, the loss of its
  squared-length formulation, ``(|o - p0| + L + r) (|o - p0| + L) / r``. The backward error of a hit is the
  distance of its float64 point ``o + t d`` from the surface (a signed-distance function). Measured over
  2.4 million random rays and shapes (log-uniform sizes, distances up to 3000, grazing rays and origins
  inside; 330k, 145k and 406k hits), the largest ``backward error / (eps32 M)`` was 1.37 (sphere), 0.82
  (disk) and 1.70 (capped cylinder), the 99.99% quantiles 0.87, 0.77 and 1.28;
  :func:`test_shape_error_model_bounds_the_analytic_functions` re-measures it on every run.
  :data:`SHAPE_ERROR` = 4 leaves a factor of at least 2.3. A hit is *certain* when the deflated shape is
  crossed inside the ray interval, *possible* when the inflated one is; the reported distance must lie
  between the entries of the inflated and deflated shapes (or between their exits);
* the alpha filter: texel lookups at interpolated texture coordinates, decided when the whole rectangle of
  coordinates the float32 barycentrics allow (the oracle's barycentric tolerance) falls in texels that agree.

A ray is *ambiguous* when another possible hit overlaps the nearest certain one within these tolerances
(near-ties, grazing hits, texel edges); such rays are counted and only checked for hitting something real,
and every test asserts that they stay a small minority.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from reference import brute_force, ray_enabled

import jaxrt as rt

EPS32 = float(np.finfo(np.float32).eps)
#: Primitives per geometry: opaque triangles, alpha-tested triangles, spheres, disks, capped cylinders.
COUNTS = (80, 16, 8, 4, 4)
TRIANGLES = COUNTS[0] + COUNTS[1]
PRIMITIVES = sum(COUNTS)
CAPACITY = 128
RAYS = 256
OPAQUE, ALPHA, SPHERES, DISKS, CYLINDERS = range(5)
FUNCTIONS = {
    SPHERES: rt.intersection_functions.sphere,
    DISKS: rt.intersection_functions.disk,
    CYLINDERS: rt.intersection_functions.capped_cylinder,
}
#: Backward error of the analytic functions in units of ``eps32 * M`` (see the module docstring).
SHAPE_ERROR = 4.0
TEXELS = 4
#: Alpha cutoffs of alpha-tested triangles: accept everything, the texture's mask, reject everything.
CUTOFFS = np.array([-1.0, 0.5, 2.0], np.float32)
#: At most this fraction of rays may be ambiguous (measured over 400 random batches of each test: 6% on
#: average, at most 28 of 256 rays).
AMBIGUOUS_LIMIT = 0.15


def alpha_filter(candidate: rt.TriangleCandidate) -> jax.Array:
    """Alpha test: the texel of the interpolated texture coordinates against the primitive's cutoff."""
    data = candidate.primitive_data
    u, v = candidate.barycentric_coord[0], candidate.barycentric_coord[1]
    uv = (1 - u - v) * data["uv"][0] + u * data["uv"][1] + v * data["uv"][2]
    texel = jnp.clip(jnp.floor(uv * TEXELS).astype(jnp.int32), 0, TEXELS - 1)
    return data["texture"][texel[0], texel[1]] >= data["cutoff"]


NEAREST = rt.Intersector(
    rt.tags.primitive_data, rt.tags.triangle_data, intersection_functions=FUNCTIONS, filter=alpha_filter
)
#: Any-hit with culling (front faces, counterclockwise winding): traced inside ``jax.jit`` and ``jax.vmap``.
ANY = rt.Intersector(
    accept_any_intersection=True,
    triangle_cull_mode="front",
    front_facing_winding="counterclockwise",
    intersection_functions=FUNCTIONS,
    filter=alpha_filter,
)
ANY_CULL = dict(cull="front", front_facing_winding="counterclockwise")


@jax.jit
def trace_any(rays: rt.Ray, structure) -> rt.IntersectionResult:
    """``ANY`` over two halves of the batch under ``jax.vmap``, inside ``jax.jit`` with the structure as an
    argument (one compilation for all scenes of the layout); the result has the batch's shape."""
    halves = rays.reshape(2, -1)
    result = jax.vmap(lambda r: ANY.intersect(r, structure))(halves)
    return jax.tree_util.tree_map(lambda a: a.reshape(-1, *a.shape[2:]), result)


# --- scenes -----------------------------------------------------------------------------------------------------


@dataclasses.dataclass
class Scene:
    geometries: list
    triangles: np.ndarray  # (TRIANGLES, 3, 3) float32, opaque then alpha-tested
    sphere: tuple  # center (N, 3), radius (N,)
    disk: tuple  # center, normal, radius
    cylinder: tuple  # p0, p1, radius
    data: list  # per geometry: the primitive-data pytree (numpy)
    center: np.ndarray
    scale: float


@dataclasses.dataclass
class Rays:
    origin: np.ndarray
    direction: np.ndarray
    min_distance: np.ndarray
    max_distance: np.ndarray
    mask: np.ndarray

    def ray(self) -> rt.Ray:
        return rt.Ray(self.origin, self.direction, self.min_distance, self.max_distance, self.mask)

    @property
    def enabled(self) -> np.ndarray:
        return ray_enabled(self.origin, self.direction, self.min_distance, self.max_distance, self.mask)


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _log_uniform(rng, lo, hi, size=None):
    return 10.0 ** rng.uniform(lo, hi, size)


def _f32(a):
    return np.asarray(a, np.float32)


def primitive_data(rng, count: int, offset: int, **shape) -> dict:
    """One geometry's primitive data: every field of the shared layout, shape parameters where given."""
    data = {
        "center": rng.normal(size=(count, 3)),
        "normal": _unit(rng.normal(size=(count, 3))),
        "p0": rng.normal(size=(count, 3)),
        "p1": rng.normal(size=(count, 3)),
        "radius": rng.uniform(0.1, 1.0, count),
        "uv": rng.uniform(0, 1, (count, 3, 2)),
        "texture": rng.integers(0, 2, (count, TEXELS, TEXELS)),
        "cutoff": np.full(count, CUTOFFS[2]),  # would reject, were the filter asked (opaque and boxes)
    }
    data.update(shape)
    data = {k: _f32(v) for k, v in data.items()}
    data["key"] = (offset + np.arange(count) * 7919 + 1).astype(np.int32)
    data["extra"] = (rng.uniform(size=(count, 2)) < 0.5, {"code": rng.integers(0, 256, (count, 2, 2)).astype(np.uint8)})
    return data


def random_scene(seed: int, far_exp: float | None = None, scale_exp: float = 0.0, *, spread: float = 1.0) -> Scene:
    """A scene of the shared layout around a centre ``10**far_exp`` from the origin (``None``: at it), with
    triangles ``spread`` times the usual size (a denser scene: more hits along each ray)."""
    rng = np.random.default_rng(seed)
    center = np.zeros(3) if far_exp is None else _unit(rng.normal(size=3)) * 10.0**far_exp
    scale = max(10.0**scale_exp, 1e-3 * float(np.linalg.norm(center)))

    def around(count):
        return center + rng.uniform(-scale, scale, (count, 3))

    def soup(count, lo, hi):
        extent = spread * scale * _log_uniform(rng, lo, hi, (count, 1, 1))
        return _f32(around(count)[:, None] + extent * rng.normal(size=(count, 3, 3)))

    opaque = soup(COUNTS[OPAQUE], -1.5, -0.5)
    alpha = soup(COUNTS[ALPHA], -1.0, -0.2)
    s_center, s_radius = _f32(around(COUNTS[SPHERES])), _f32(scale * _log_uniform(rng, -1.3, -0.6, COUNTS[SPHERES]))
    d_center, d_normal = _f32(around(COUNTS[DISKS])), _f32(_unit(rng.normal(size=(COUNTS[DISKS], 3))))
    d_radius = _f32(scale * _log_uniform(rng, -1.0, -0.4, COUNTS[DISKS]))
    c_p0 = _f32(around(COUNTS[CYLINDERS]))
    c_p1 = _f32(
        c_p0
        + _unit(rng.normal(size=(COUNTS[CYLINDERS], 3))) * scale * _log_uniform(rng, -1, -0.3, (COUNTS[CYLINDERS], 1))
    )
    c_radius = _f32(scale * _log_uniform(rng, -1.5, -0.8, COUNTS[CYLINDERS]))

    offsets = np.cumsum((0,) + COUNTS)
    alpha_data = primitive_data(
        rng, COUNTS[ALPHA], offsets[ALPHA], cutoff=rng.choice(CUTOFFS, COUNTS[ALPHA], p=[0.25, 0.55, 0.2])
    )
    data = [
        primitive_data(rng, COUNTS[OPAQUE], offsets[OPAQUE]),
        alpha_data,
        primitive_data(rng, COUNTS[SPHERES], offsets[SPHERES], center=s_center, radius=s_radius),
        primitive_data(rng, COUNTS[DISKS], offsets[DISKS], center=d_center, normal=d_normal, radius=d_radius),
        primitive_data(rng, COUNTS[CYLINDERS], offsets[CYLINDERS], p0=c_p0, p1=c_p1, radius=c_radius),
    ]
    functions = rt.intersection_functions
    geometries = [
        rt.TriangleGeometry(opaque.reshape(-1, 3), primitive_data=data[OPAQUE]),
        rt.TriangleGeometry(alpha.reshape(-1, 3), primitive_data=data[ALPHA], opaque=False),
        rt.BoundingBoxGeometry(*functions.sphere_bounds(s_center, s_radius), primitive_data=data[SPHERES]),
        rt.BoundingBoxGeometry(*functions.disk_bounds(d_center, d_normal, d_radius), primitive_data=data[DISKS]),
        rt.BoundingBoxGeometry(*functions.capped_cylinder_bounds(c_p0, c_p1, c_radius), primitive_data=data[CYLINDERS]),
    ]
    triangles = np.concatenate([opaque, alpha])
    return Scene(
        geometries,
        triangles,
        (s_center, s_radius),
        (d_center, d_normal, d_radius),
        (c_p0, c_p1, c_radius),
        data,
        center,
        scale,
    )


#: Where rays aim: opaque triangles, alpha-tested triangles, spheres, disks, cylinders, sphere surfaces, disk
#: rims (grazing), nowhere in particular.
AIM = [0.2, 0.2, 0.15, 0.1, 0.1, 0.05, 0.05, 0.15]


def random_rays(seed: int, scene: Scene, count: int = RAYS, *, intervals: bool = True, aim: int | None = None) -> Rays:
    """Rays aimed at points inside triangles and shapes, at shape rims (grazing), and at random (or all at
    the geometry ``aim``).

    With ``intervals`` some rays get a finite interval around their target (a few of them empty), some a
    negative ``min_distance``, and a few (the first among them) are disabled by a zero mask.
    """
    rng = np.random.default_rng(seed)
    kind = rng.choice(8, count, p=AIM) if aim is None else np.full(count, aim)
    tri = scene.triangles.astype(np.float64)
    k = np.where(kind == 0, rng.integers(0, COUNTS[OPAQUE], count), rng.integers(COUNTS[OPAQUE], TRIANGLES, count))
    target = np.einsum("rv,rvk->rk", rng.dirichlet(np.ones(3), count), tri[k])
    # Inside a sphere.
    sc, sr = (a.astype(np.float64) for a in scene.sphere)
    i = rng.integers(0, COUNTS[SPHERES], count)
    inside = sc[i] + _unit(rng.normal(size=(count, 3))) * (sr[i] * rng.uniform(0, 0.9, count))[:, None]
    target = np.where((kind == 2)[:, None], inside, target)
    # On a disk.
    dc, dn, dr = (a.astype(np.float64) for a in scene.disk)
    i = rng.integers(0, COUNTS[DISKS], count)
    in_plane = _unit(np.cross(dn[i], rng.normal(size=(count, 3))))
    on_disk = dc[i] + in_plane * (dr[i] * np.sqrt(rng.uniform(0, 0.95, count)))[:, None]
    target = np.where((kind == 3)[:, None], on_disk, target)
    # Inside a capped cylinder.
    p0, p1, cr = (a.astype(np.float64) for a in scene.cylinder)
    i = rng.integers(0, COUNTS[CYLINDERS], count)
    axis = p1[i] - p0[i]
    perp = _unit(np.cross(axis, rng.normal(size=(count, 3))))
    in_cylinder = (
        p0[i] + axis * rng.uniform(0.05, 0.95, (count, 1)) + perp * (cr[i] * rng.uniform(0, 0.9, count))[:, None]
    )
    target = np.where((kind == 4)[:, None], in_cylinder, target)
    # Rims: on a sphere's surface or a disk's edge (grazing rays, mostly ambiguous).
    i = rng.integers(0, COUNTS[SPHERES], count)
    target = np.where((kind == 5)[:, None], sc[i] + _unit(rng.normal(size=(count, 3))) * sr[i][:, None], target)
    i = rng.integers(0, COUNTS[DISKS], count)
    rim = dc[i] + _unit(np.cross(dn[i], rng.normal(size=(count, 3)))) * dr[i][:, None]
    target = np.where((kind == 6)[:, None], rim, target)

    unit = _unit(rng.normal(size=(count, 3)))
    length = _log_uniform(rng, -1, 1, (count, 1))
    along = scene.scale * _log_uniform(rng, -1.5, 0.7, count)
    origin = target - unit * along[:, None]
    wild = kind == 7
    origin = np.where(wild[:, None], scene.center + rng.uniform(-2, 2, (count, 3)) * scene.scale, origin)
    t_target = along / length[:, 0]
    tmin, tmax = np.zeros(count), np.full(count, np.inf)
    mask = np.full(count, 0xFFFFFFFF, np.uint32)
    if intervals:
        bounded = rng.uniform(size=count) < 0.3
        tmin = np.where(bounded, t_target * rng.uniform(0, 1.2, count), tmin)
        tmax = np.where(bounded, tmin + t_target * rng.uniform(-0.1, 2, count), tmax)
        tmin = np.where(rng.uniform(size=count) < 0.1, -t_target * rng.uniform(0, 2, count), tmin)
        mask[(rng.uniform(size=count) < 0.03) | (np.arange(count) == 0)] = 0
    return Rays(_f32(origin), _f32(unit * length), _f32(tmin), _f32(tmax), mask)


def build(scene: Scene) -> rt.PrimitiveAccelerationStructure:
    return rt.build_primitive_structure(scene.geometries, capacity=CAPACITY)


# --- the float64 reference ----------------------------------------------------------------------------------------


def _dot(a, b):
    return np.sum(a * b, axis=-1)


def sphere_span(o, d, center, radius):
    """Entry and exit distances of rays ``(R, 1, 3)`` through solid spheres ``(1, N, 3)``, ``(1, N)`` (NaN: miss)."""
    norm = np.linalg.norm(d, axis=-1)
    unit = d / norm[..., None]
    f = o - center
    s = -_dot(f, unit)
    closest = f + s[..., None] * unit  # the centre-to-ray vector at closest approach: no cancellation
    h2 = radius**2 - _dot(closest, closest)
    h = np.sqrt(np.maximum(h2, 0))
    hit = h2 >= 0
    return np.where(hit, (s - h) / norm, np.nan), np.where(hit, (s + h) / norm, np.nan)


def cylinder_span(o, d, base, axis, length, radius):
    """Entry and exit distances of rays through solid capped cylinders (``axis`` unit, NaN: miss)."""
    oc = o - base
    da, oa = _dot(d, axis), _dot(oc, axis)
    with np.errstate(divide="ignore", invalid="ignore"):
        z0, z1 = -oa / da, (length - oa) / da
    parallel = da == 0
    in_slab = (oa >= 0) & (oa <= length)
    z_lo = np.where(parallel, np.where(in_slab, -np.inf, np.inf), np.minimum(z0, z1))
    z_hi = np.where(parallel, np.where(in_slab, np.inf, -np.inf), np.maximum(z0, z1))
    dp = d - da[..., None] * axis
    op = oc - oa[..., None] * axis
    a = _dot(dp, dp)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -_dot(op, dp) / a
        closest = op + np.nan_to_num(s)[..., None] * dp
        h = np.sqrt(np.maximum(radius**2 - _dot(closest, closest), 0) / a)
    wall_hit = radius**2 - _dot(closest, closest) >= 0
    along_axis = a == 0
    inside = _dot(op, op) <= radius**2
    w_lo = np.where(along_axis, np.where(inside, -np.inf, np.inf), np.where(wall_hit, s - h, np.inf))
    w_hi = np.where(along_axis, np.where(inside, np.inf, -np.inf), np.where(wall_hit, s + h, -np.inf))
    t_in, t_out = np.maximum(z_lo, w_lo), np.minimum(z_hi, w_hi)
    hit = t_in <= t_out
    return np.where(hit, t_in, np.nan), np.where(hit, t_out, np.nan), (z_lo, z_hi, w_lo, w_hi)


def round_magnitude(o, center, radius):
    """``M`` of the sphere and disk functions: the coordinates they subtract, the shape's size and the
    distance of any of its points from the origin (which bounds the hit's ``|t d|``)."""
    norm = functools.partial(np.linalg.norm, axis=-1)
    return norm(o) + norm(center) + 2 * radius + norm(o - center)


def cylinder_magnitude(o, p0, p1, radius):
    """``M`` of the capped-cylinder function: the rounding of ``o - p0`` plus the squared-length
    formulation's loss, ``(|o - p0| + L + r) (|o - p0| + L) / r``."""
    norm = functools.partial(np.linalg.norm, axis=-1)
    length, oc = norm(p1 - p0), norm(o - p0)
    return norm(o) + norm(p0) + 2 * (radius + length) + oc + (oc + length + radius) * (oc + length) / radius


@dataclasses.dataclass
class Expected:
    """What a correct float32 implementation may report, per ray and primitive ``(R, P)``.

    ``hit``: it must report a hit on the primitive within ``[lo, hi]`` (when nothing nearer is hit);
    ``maybe``: it may report one within ``[lo, hi]``; neither: it must not report one.
    """

    hit: np.ndarray
    maybe: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    barycentric: np.ndarray  # (R, T, 2) of the triangles
    barycentric_tolerance: np.ndarray  # (R, T)
    kind: np.ndarray  # (P,) the result type of each primitive
    offsets: np.ndarray  # global index of each geometry's first primitive

    @property
    def possible(self) -> np.ndarray:
        return self.hit | self.maybe


#: Result type and geometry of each global primitive index, and each geometry's first global index.
KIND = np.array(
    [int(rt.IntersectionType.TRIANGLE)] * TRIANGLES + [int(rt.IntersectionType.BOUNDING_BOX)] * (PRIMITIVES - TRIANGLES)
)
GEOMETRY = np.repeat(np.arange(len(COUNTS)), COUNTS)
OFFSETS = np.cumsum((0,) + COUNTS)[:-1]


def _filter_decision(scene: Scene, bary, bary_tol):
    """``(accept_certain, reject_certain)`` of the alpha filter per (ray, alpha-tested triangle)."""
    data = scene.data[ALPHA]
    uv = data["uv"].astype(np.float64)  # (T, 3, 2)
    u, v = bary[..., 0], bary[..., 1]
    weights = np.stack([1 - u - v, u, v], axis=-1)  # (R, T, 3)
    point = np.einsum("rtv,tvk->rtk", weights, uv)
    spread = np.abs(uv[:, 1] - uv[:, 0]) + np.abs(uv[:, 2] - uv[:, 0])  # (T, 2)
    tol = bary_tol[..., None] * spread + 8 * EPS32 * (1 + 2 * (np.abs(u) + np.abs(v)))[..., None]
    decided = np.isfinite(tol).all(-1) & np.isfinite(point).all(-1)
    point, tol = np.nan_to_num(point), np.nan_to_num(tol)
    first = np.clip(np.floor((point - tol) * TEXELS), 0, TEXELS - 1).astype(int)
    last = np.clip(np.floor((point + tol) * TEXELS), 0, TEXELS - 1).astype(int)
    index = np.arange(TEXELS)
    rows = (index >= first[..., 0, None]) & (index <= last[..., 0, None])  # (R, T, 4)
    cols = (index >= first[..., 1, None]) & (index <= last[..., 1, None])
    covered = rows[..., :, None] & cols[..., None, :]  # (R, T, 4, 4)
    accepted = data["texture"] >= data["cutoff"][:, None, None]  # (T, 4, 4)
    some_accept = (covered & accepted).any((-1, -2))
    some_reject = (covered & ~accepted).any((-1, -2))
    return decided & ~some_reject, decided & ~some_accept


def _shape_status(t_in_out, deflated, tmin, tmax):
    """Status of sphere or cylinder hits from inflated ``(in, out)`` and deflated spans (see module doc)."""
    (in_hi, out_hi), (in_lo, out_lo) = t_in_out, deflated  # inflated enters earlier and leaves later
    inflated_hit = ~np.isnan(in_hi)
    deflated_hit = ~np.isnan(in_lo)
    entry = (in_hi, np.where(deflated_hit, in_lo, out_hi))  # a tangent ray: anywhere along the inflated chord
    exit_ = (np.where(deflated_hit, out_lo, in_hi), out_hi)

    def inside(r):
        return (r[0] >= tmin) & (r[1] <= tmax)

    def outside(r):
        return (r[1] < tmin) | (r[0] > tmax)

    with np.errstate(invalid="ignore"):
        e_in, e_out, x_in, x_out = inside(entry), outside(entry), inside(exit_), outside(exit_)
        before = entry[1] < tmin
    hit_entry = inflated_hit & deflated_hit & e_in
    hit_exit = inflated_hit & deflated_hit & before & x_in
    hit = hit_entry | hit_exit
    none = ~inflated_hit | (e_out & ~before) | (before & x_out)
    lo = np.where(hit_exit, exit_[0], entry[0])
    hi = np.where(hit_entry, entry[1], exit_[1])  # maybe: the hull of both ranges
    return hit, ~hit & ~none, lo, hi


def expected(scene: Scene, rays: Rays, *, cull: str = "none", front_facing_winding: str = "clockwise") -> Expected:
    """The float64 reference for every ray and primitive of ``scene`` (see :class:`Expected`)."""
    o64, d64 = rays.origin.astype(np.float64), rays.direction.astype(np.float64)
    tmin = rays.min_distance.astype(np.float64)[:, None]
    tmax = rays.max_distance.astype(np.float64)[:, None]
    enabled = rays.enabled[:, None]
    ref = brute_force(
        rays.origin,
        rays.direction,
        rays.min_distance,
        rays.max_distance,
        scene.triangles,
        cull=cull,
        front_facing_winding=front_facing_winding,
    )
    accept, reject = _filter_decision(
        scene, ref.barycentric[:, COUNTS[OPAQUE] :], ref.barycentric_tolerance[:, COUNTS[OPAQUE] :]
    )
    opaque = np.arange(TRIANGLES) < COUNTS[OPAQUE]
    accept = np.concatenate([np.ones((len(o64), COUNTS[OPAQUE]), bool), accept], axis=1)
    reject = np.concatenate([np.zeros((len(o64), COUNTS[OPAQUE]), bool), reject], axis=1)
    tri_hit = ref.certain & (opaque | accept)
    tri_maybe = ref.possible & ~tri_hit & (opaque | ~reject)
    tri_lo, tri_hi = ref.distance - ref.tolerance, ref.distance + ref.tolerance

    o, d = o64[:, None], d64[:, None]
    parts = []
    # Spheres.
    c, r = (a.astype(np.float64) for a in scene.sphere)
    delta = SHAPE_ERROR * EPS32 * round_magnitude(o, c, r)
    parts.append(
        _shape_status(sphere_span(o, d, c, r + delta), sphere_span(o, d, c, np.maximum(r - delta, 0)), tmin, tmax)
    )
    # Capped cylinders.
    p0, p1, r = (a.astype(np.float64) for a in scene.cylinder)
    length = np.linalg.norm(p1 - p0, axis=-1)
    axis = (p1 - p0) / length[:, None]
    delta = SHAPE_ERROR * EPS32 * cylinder_magnitude(o, p0, p1, r)
    inflated = cylinder_span(o, d, p0 - delta[..., None] * axis, axis, length + 2 * delta, r + delta)[:2]
    deflated = cylinder_span(
        o, d, p0 + delta[..., None] * axis, axis, np.maximum(length - 2 * delta, 0), np.maximum(r - delta, 0)
    )[:2]
    cylinders = _shape_status(inflated, deflated, tmin, tmax)
    # Disks: a slab of half-thickness delta around the plane; certain when the ray's whole slab segment lies
    # within radius r - delta, possible when it meets radius r + delta.
    c, n, r = (a.astype(np.float64) for a in scene.disk)
    delta = SHAPE_ERROR * EPS32 * round_magnitude(o, c, r)
    base = c - delta[..., None] * n
    t_in, t_out, _ = cylinder_span(o, d, base, n, 2 * delta, r + delta)
    _, _, (z_lo, z_hi, w_lo, w_hi) = cylinder_span(o, d, base, n, 2 * delta, np.maximum(r - delta, 0))
    with np.errstate(invalid="ignore"):
        crossed = (w_lo <= z_lo) & (z_hi <= w_hi) & np.isfinite(z_lo) & np.isfinite(z_hi)
        inside = (t_in >= tmin) & (t_out <= tmax)
        outside = np.isnan(t_in) | (t_out < tmin) | (t_in > tmax)
    disk_hit = crossed & inside & ~np.isnan(t_in)
    parts.append((disk_hit, ~disk_hit & ~outside, t_in, t_out))
    parts.append(cylinders)

    hit = np.concatenate([tri_hit] + [p[0] for p in parts], axis=1) & enabled
    maybe = np.concatenate([tri_maybe] + [p[1] for p in parts], axis=1) & enabled
    lo = np.concatenate([tri_lo] + [p[2] for p in parts], axis=1)
    hi = np.concatenate([tri_hi] + [p[3] for p in parts], axis=1)
    return Expected(hit, maybe, lo, hi, ref.barycentric, ref.barycentric_tolerance, KIND, OFFSETS)


def nearest_expectation(exp: Expected) -> np.ndarray:
    """Per ray: the global index of the hit a nearest-hit query must report, -1 for a miss, -2 when ambiguous
    (no certain hit, or another possible hit within the tolerances of the nearest certain one)."""
    lo = np.where(exp.hit, exp.lo, np.inf)
    first = np.argmin(lo, axis=1)
    rows = np.arange(len(first))
    first_hi = exp.hi[rows, first]
    others = exp.possible.copy()
    others[rows, first] = False
    clear = ~(others & (exp.lo <= first_hi[:, None])).any(axis=1)
    answer = np.where(exp.hit.any(axis=1) & clear, first, -2)
    return np.where(~exp.possible.any(axis=1), -1, answer)


def global_index(result_geometry, result_primitive, offsets=OFFSETS):
    g = np.asarray(result_geometry)
    return np.where(g >= 0, offsets[np.maximum(g, 0)] + np.asarray(result_primitive), -1)


def _is_real_hit(exp: Expected, r: int, k: int, distance: float) -> bool:
    return 0 <= k < exp.hit.shape[1] and exp.possible[r, k] and exp.lo[r, k] <= distance <= exp.hi[r, k]


def check_nearest(result, exp: Expected) -> tuple[list[str], int]:
    """Failures of a nearest-hit result, and the number of ambiguous rays."""
    answer = nearest_expectation(exp)
    kind, distance = np.asarray(result.type), np.asarray(result.distance, np.float64)
    k_all = global_index(result.geometry_id, result.primitive_id, exp.offsets)
    failures = []
    for r in range(len(answer)):
        k, want = k_all[r], answer[r]
        if kind[r] == int(rt.IntersectionType.NONE):
            if not (np.isposinf(distance[r]) and k == -1):
                failures.append(f"ray {r}: miss with distance {distance[r]} and primitive {k}")
            if exp.hit[r].any():
                failures.append(f"ray {r}: missed, but primitives {np.flatnonzero(exp.hit[r])} are certainly hit")
            continue
        if not (0 <= k < exp.hit.shape[1] and kind[r] == exp.kind[k]):
            failures.append(f"ray {r}: type {kind[r]} with primitive {k}")
            continue
        if want >= 0 and k != want:
            failures.append(
                f"ray {r}: hit primitive {k} at {distance[r]!r}, expected {want} in [{exp.lo[r, want]!r}, {exp.hi[r, want]!r}]"
            )
        elif want == -1 or not _is_real_hit(exp, r, k, distance[r]):
            failures.append(f"ray {r}: hit primitive {k} at {distance[r]!r}, which is not a hit in float64")
        elif want == -2 and distance[r] > np.min(np.where(exp.hit[r], exp.hi[r], np.inf)):
            failures.append(f"ray {r}: hit primitive {k} at {distance[r]!r} behind a certain hit")
    return failures, int(np.sum(answer == -2))


def check_any(result, exp: Expected) -> tuple[list[str], int]:
    """Failures of an any-hit result: a hit iff the reference has one, and only real hits."""
    kind, distance = np.asarray(result.type), np.asarray(result.distance, np.float64)
    k_all = global_index(result.geometry_id, result.primitive_id, exp.offsets)
    must_hit, may_hit = exp.hit.any(axis=1), exp.possible.any(axis=1)
    failures = []
    for r in range(len(kind)):
        if kind[r] == int(rt.IntersectionType.NONE):
            if must_hit[r]:
                failures.append(f"ray {r}: missed, but primitives {np.flatnonzero(exp.hit[r])} are certainly hit")
        elif not (_is_real_hit(exp, r, k_all[r], distance[r]) and kind[r] == exp.kind[k_all[r]]):
            failures.append(f"ray {r}: hit primitive {k_all[r]} (type {kind[r]}) at {distance[r]!r}, not a float64 hit")
    return failures, int(np.sum(may_hit & ~must_hit))


def data_rows(scene: Scene, k: np.ndarray):
    """The primitive-data pytree rows of global primitive indices ``k`` (zeros where ``k < 0``)."""
    leaves = [jax.tree_util.tree_leaves(d) for d in scene.data]
    treedef = jax.tree_util.tree_structure(scene.data[0])
    columns = []
    for i in range(len(leaves[0])):
        column = np.concatenate([g[i] for g in leaves])
        row = column[np.maximum(k, 0)]
        columns.append(np.where((k >= 0).reshape(k.shape + (1,) * (row.ndim - k.ndim)), row, np.zeros_like(row)))
    return jax.tree_util.tree_unflatten(treedef, columns)


def assert_data_round_trip(result, scene: Scene) -> None:
    """Every hit carries exactly the data of its (geometry, primitive); misses carry zeros."""
    k = global_index(result.geometry_id, result.primitive_id)
    got, want = result.primitive_data, data_rows(scene, k)
    assert jax.tree_util.tree_structure(got) == jax.tree_util.tree_structure(want)
    for path, g, w in zip(
        [jax.tree_util.keystr(p) for p, _ in jax.tree_util.tree_leaves_with_path(want)],
        jax.tree_util.tree_leaves(got),
        jax.tree_util.tree_leaves(want),
        strict=True,
    ):
        assert g.dtype == w.dtype and g.shape == w.shape, (path, g.dtype, g.shape, w.dtype, w.shape)
        np.testing.assert_array_equal(np.asarray(g), w, err_msg=path)


def assert_nearest(result, exp: Expected) -> int:
    failures, ambiguous = check_nearest(result, exp)
    assert not failures, f"{len(failures)} rays disagree with the float64 reference:\n" + "\n".join(failures[:20])
    assert ambiguous <= AMBIGUOUS_LIMIT * len(exp.hit), f"{ambiguous} ambiguous rays"
    return ambiguous


seeds = st.integers(0, 2**32 - 1)
far_exponents = st.one_of(st.none(), st.floats(0.0, 3.0))
scale_exponents = st.floats(-0.5, 1.0)


# --- the error model -----------------------------------------------------------------------------------------------


@jax.jit
def _call_functions(origin, direction, data):
    """Every analytic function on its own ray and shape: ``{name: (accept, distance)}``."""

    def one(fn, o, d, data):
        candidate = rt.BoundingBoxCandidate(jnp.int32(0), jnp.int32(0), jnp.zeros(3), jnp.ones(3), data)
        return fn(rt.Ray(o, d), candidate)

    return {
        name: jax.vmap(functools.partial(one, fn))(origin, direction, data) for name, fn in FUNCTIONS_BY_NAME.items()
    }


FUNCTIONS_BY_NAME = {"sphere": FUNCTIONS[SPHERES], "disk": FUNCTIONS[DISKS], "capped_cylinder": FUNCTIONS[CYLINDERS]}


def test_shape_error_model_bounds_the_analytic_functions():
    """The backward error of every hit (the distance of its float64 point from the surface) is within half
    the ``delta`` the reference allows, on random shapes and rays like those the measurement used."""
    rng = np.random.default_rng(7)
    n = 20000
    center = _unit(rng.normal(size=(n, 3))) * 10.0 ** rng.uniform(-1, 3.5, (n, 1)) * (rng.uniform(size=(n, 1)) < 0.7)
    size = 10.0 ** rng.uniform(-1.5, 1, (n, 1))
    radius = size[:, 0] * 10 ** rng.uniform(-1.5, 0, n)
    normal = _unit(rng.normal(size=(n, 3)))
    p1 = center + _unit(rng.normal(size=(n, 3))) * size * 2
    target = center + rng.normal(size=(n, 3)) * size * 0.7
    direction = _unit(rng.normal(size=(n, 3))) * 10.0 ** rng.uniform(-2, 2, (n, 1))
    origin = target - _unit(direction) * (size[:, 0] * 10.0 ** rng.uniform(-2, 2.5, n))[:, None]
    origin = np.where((rng.uniform(size=n) < 0.1)[:, None], center + rng.normal(size=(n, 3)) * size * 0.2, origin)
    o, d, c, r, nrm, p1 = (_f32(a) for a in (origin, direction, center, radius, normal, p1))
    data = {"center": c, "normal": nrm, "p0": c, "p1": p1, "radius": r}
    out = {k: [np.asarray(x) for x in v] for k, v in _call_functions(o, d, data).items()}
    o, d, c, r, nrm, p1 = (a.astype(np.float64) for a in (o, d, c, r, nrm, p1))

    def point(name):
        accept, t = out[name]
        return accept, o + np.where(accept, t, 0)[:, None] * d

    def radial(p, axis):
        along = _dot(p - c, axis)
        return along, np.linalg.norm(p - c - along[:, None] * axis, axis=-1)

    accept, p = point("sphere")
    errors = {"sphere": (accept, np.abs(np.linalg.norm(p - c, axis=-1) - r) / round_magnitude(o, c, r))}
    accept, p = point("disk")
    along, rho = radial(p, nrm)
    errors["disk"] = (accept, np.maximum(np.abs(along), rho - r) / round_magnitude(o, c, r))
    accept, p = point("capped_cylinder")
    length = np.linalg.norm(p1 - c, axis=-1)
    along, rho = radial(p, (p1 - c) / length[:, None])
    outside = np.maximum(np.maximum(rho - r, -along), along - length)
    errors["capped_cylinder"] = (accept, np.abs(outside) / cylinder_magnitude(o, c, p1, r))
    for name, (accept, error) in errors.items():
        assert accept.sum() > n // 20, name
        assert np.max(error[accept]) / EPS32 <= SHAPE_ERROR / 2, (name, np.max(error[accept]) / EPS32)


# --- nearest and any hit ------------------------------------------------------------------------------------------


@settings(max_examples=8, deadline=None)
@given(seeds, far_exponents, scale_exponents)
def test_nearest_hit_on_triangles_and_analytic_shapes_matches_float64(seed, far_exp, scale_exp):
    scene = random_scene(seed, far_exp, scale_exp)
    rays = random_rays(seed ^ 0x5EED, scene)
    result = NEAREST.intersect(rays.ray(), build(scene))
    exp = expected(scene, rays)
    assert_nearest(result, exp)
    # Every kind of primitive is hit (the scene and rays are made so), and triangle barycentrics are right.
    answer = nearest_expectation(exp)
    assert set(GEOMETRY[answer[answer >= 0]]) == set(range(len(COUNTS))), np.bincount(GEOMETRY[answer[answer >= 0]])
    k = global_index(result.geometry_id, result.primitive_id)
    rows = np.flatnonzero((answer >= 0) & (answer < TRIANGLES))
    bary = np.asarray(result.triangle_barycentric_coord, np.float64)[rows]
    error = np.abs(bary - exp.barycentric[rows, k[rows]]).max(axis=-1)
    assert np.all(error <= exp.barycentric_tolerance[rows, k[rows]]), error
    disabled = ~rays.enabled
    assert disabled.any() and np.all(np.asarray(result.type)[disabled] == 0)
    assert_data_round_trip(result, scene)


@settings(max_examples=6, deadline=None)
@given(seeds, far_exponents, scale_exponents)
def test_any_hit_under_jit_and_vmap_reports_a_real_hit_iff_the_reference_has_one(seed, far_exp, scale_exp):
    """``accept_any_intersection`` with culling, the filter and intersection functions, vmapped over ray
    batches inside ``jax.jit`` (see :func:`trace_any`)."""
    scene = random_scene(seed, far_exp, scale_exp)
    rays = random_rays(seed ^ 0xA11, scene)
    result = trace_any(rays.ray(), build(scene))
    exp = expected(scene, rays, **ANY_CULL)
    failures, undecided = check_any(result, exp)
    assert not failures, f"{len(failures)} rays disagree with the float64 reference:\n" + "\n".join(failures[:20])
    assert undecided <= AMBIGUOUS_LIMIT * RAYS
    kinds = set(np.asarray(result.type).tolist())
    assert kinds == {0, int(rt.IntersectionType.TRIANGLE), int(rt.IntersectionType.BOUNDING_BOX)}


@settings(max_examples=6, deadline=None)
@given(seeds, far_exponents, scale_exponents)
def test_alpha_tested_triangles_match_brute_force_filtering(seed, far_exp, scale_exp):
    """Rays at alpha-tested triangles: candidates the filter rejects do not end the search, accepted ones
    do, the alpha comes from primitive data and a texture at interpolated coordinates, and the filter never
    decides opaque triangles (their data would reject them)."""
    scene = random_scene(seed, far_exp, scale_exp)
    rays = random_rays(seed ^ 0xA1FA, scene, aim=ALPHA)
    result = NEAREST.intersect(rays.ray(), build(scene))
    exp = expected(scene, rays)
    assert_nearest(result, exp)
    # The filter matters for these rays: the nearest geometric hit of many is rejected, of many accepted.
    ref = brute_force(rays.origin, rays.direction, rays.min_distance, rays.max_distance, scene.triangles)
    nearest = np.argmin(np.where(ref.certain, ref.distance, np.inf), axis=1)
    on_alpha = ref.certain.any(axis=1) & (nearest >= COUNTS[OPAQUE])
    rows = np.arange(RAYS)
    rejected = on_alpha & ~exp.possible[rows, nearest]
    accepted = on_alpha & exp.hit[rows, nearest]
    assert rejected.sum() >= 10 and accepted.sum() >= 10, (rejected.sum(), accepted.sum())
    texture_decided = accepted & (scene.data[ALPHA]["cutoff"][np.maximum(nearest - COUNTS[OPAQUE], 0)] == CUTOFFS[1])
    assert texture_decided.sum() >= 3


# --- filters on triangle-only scenes ----------------------------------------------------------------------------

#: A scene of opaque and alpha-tested triangle soups, and the same scene without the alpha-tested geometry.
FILTER_COUNTS = (16, 16)
REJECT = rt.Intersector(rt.tags.triangle_data, filter=lambda candidate: jnp.zeros((), bool))
PLAIN = rt.Intersector(rt.tags.triangle_data)
#: A filter runs the portable traversal; bit-for-bit comparisons trace the reference with it too (on a GPU the
#: kernel's distances can differ from it by an ulp).
PLAIN_PORTABLE = rt.Intersector(rt.tags.triangle_data, backend="portable")


#: Alpha-tested primitives the checker filter always rejects (by ``candidate.primitive_id``).
CHECKER_SKIPS = np.zeros(FILTER_COUNTS[1], bool)
CHECKER_SKIPS[[2, 11]] = True


def checker_filter(candidate: rt.TriangleCandidate) -> jax.Array:
    """Accept a candidate on the even squares of a 4x4 checkerboard over its barycentrics, unless its
    primitive is one of :data:`CHECKER_SKIPS`. The candidate must come from geometry 1 and, with back faces
    culled, face the front: a wrong ``geometry_id`` or ``front_facing`` would reject it."""
    cells = jnp.floor(candidate.barycentric_coord * 4).astype(jnp.int32)
    even = (cells[0] + cells[1]) % 2 == 0
    skip = jnp.asarray(CHECKER_SKIPS)[candidate.primitive_id]
    return even & ~skip & candidate.front_facing & (candidate.geometry_id == 1)


CHECKER = rt.Intersector(
    rt.tags.triangle_data, rt.tags.primitive_data, filter=checker_filter, triangle_cull_mode="back"
)


def filter_scene(seed: int):
    """Opaque triangles without primitive data and alpha-tested ones with it, and rays at both."""
    rng = np.random.default_rng(seed)
    scale = _log_uniform(rng, -1, 2)
    soup = [
        _f32(
            rng.uniform(-scale, scale, (n, 1, 3))
            + scale * _log_uniform(rng, -1.2, -0.3, (n, 1, 1)) * rng.normal(size=(n, 3, 3))
        )
        for n in FILTER_COUNTS
    ]
    data = {
        "weight": _f32(rng.normal(size=(FILTER_COUNTS[1], 2))),
        "id": np.arange(FILTER_COUNTS[1], dtype=np.int32) + 100,
    }
    geometries = [
        rt.TriangleGeometry(soup[0].reshape(-1, 3)),
        rt.TriangleGeometry(soup[1].reshape(-1, 3), primitive_data=data, opaque=False),
    ]
    triangles = np.concatenate(soup).astype(np.float64)
    count = RAYS
    target = np.einsum(
        "rv,rvk->rk", rng.dirichlet(np.ones(3), count), triangles[rng.integers(0, len(triangles), count)]
    )
    unit = _unit(rng.normal(size=(count, 3)))
    origin = target - unit * (scale * _log_uniform(rng, -1, 0.7, count))[:, None]
    rays = Rays(
        _f32(origin),
        _f32(unit),
        np.zeros(count, np.float32),
        np.full(count, np.inf, np.float32),
        np.ones(count, np.uint32),
    )
    return geometries, np.concatenate(soup), data, rays


def _assert_equal_results(a, b):
    assert set(a) == set(b)
    for name in a:
        np.testing.assert_array_equal(np.asarray(a[name]), np.asarray(b[name]), err_msg=name)


@settings(max_examples=4, deadline=None)
@given(seeds)
def test_filter_rejecting_everything_equals_removing_the_geometry(seed):
    geometries, _, _, rays = filter_scene(seed)
    with_alpha = REJECT.intersect(rays.ray(), rt.build_primitive_structure(geometries, capacity=32))
    without = PLAIN_PORTABLE.intersect(rays.ray(), rt.build_primitive_structure(geometries[:1], capacity=32))
    _assert_equal_results(with_alpha, without)
    assert np.isfinite(np.asarray(without.distance)).sum() > RAYS // 4


@settings(max_examples=4, deadline=None)
@given(seeds)
def test_filter_on_an_all_opaque_scene_changes_nothing(seed):
    geometries, _, _, rays = filter_scene(seed)
    structure = rt.build_primitive_structure(geometries[:1], capacity=32)
    _assert_equal_results(REJECT.intersect(rays.ray(), structure), PLAIN.intersect(rays.ray(), structure))


@settings(max_examples=4, deadline=None)
@given(seeds)
def test_filter_with_back_face_culling_matches_brute_force(seed):
    """Culled triangles are skipped before the filter; the filter decides the rest of the alpha-tested ones
    from the candidate's barycentrics, primitive and geometry ids and facing. Primitive data of the geometry
    without any comes back as zeros."""
    geometries, triangles, data, rays = filter_scene(seed)
    result = CHECKER.intersect(rays.ray(), rt.build_primitive_structure(geometries, capacity=32))
    ref = brute_force(rays.origin, rays.direction, rays.min_distance, rays.max_distance, triangles, cull="back")
    # The checkerboard, decided where the barycentrics are further than their tolerance from a cell edge.
    cells = ref.barycentric * 4
    margin = np.abs(cells - np.round(cells)).min(axis=-1) > 4 * ref.barycentric_tolerance
    even = np.nan_to_num(np.floor(cells)).astype(np.int64).sum(axis=-1) % 2 == 0
    opaque = np.arange(len(triangles)) < FILTER_COUNTS[0]
    skip = np.concatenate([np.zeros(FILTER_COUNTS[0], bool), CHECKER_SKIPS])
    hit = ref.certain & (opaque | (margin & even & ~skip))
    maybe = ref.possible & ~hit & (opaque | ((~margin | even) & ~skip))
    exp = Expected(
        hit,
        maybe,
        ref.distance - ref.tolerance,
        ref.distance + ref.tolerance,
        ref.barycentric,
        ref.barycentric_tolerance,
        np.full(len(triangles), int(rt.IntersectionType.TRIANGLE)),
        np.array([0, FILTER_COUNTS[0]]),
    )
    assert_nearest(result, exp)
    front = np.asarray(result.triangle_front_facing)
    assert np.all(front[np.asarray(result.type) != 0]), "back faces are culled"
    geometry, primitive = np.asarray(result.geometry_id), np.asarray(result.primitive_id)
    alpha = geometry == 1
    np.testing.assert_array_equal(np.asarray(result.primitive_data["id"]), np.where(alpha, data["id"][primitive], 0))
    np.testing.assert_array_equal(
        np.asarray(result.primitive_data["weight"]), np.where(alpha[:, None], data["weight"][primitive], 0)
    )
    assert alpha.sum() > 10 and (geometry == 0).sum() > 10


# --- primitive data -----------------------------------------------------------------------------------------------


def moved(scene: Scene, seed: int) -> Scene:
    """The scene translated a little, with new primitive data of the same layout (and the same cutoffs)."""
    rng = np.random.default_rng(seed)
    shift = rng.normal(size=3) * scene.scale * 0.3
    other = random_scene(seed)  # new data values (and shapes we do not use)
    triangles = _f32(scene.triangles + shift)
    s_center = _f32(scene.sphere[0] + shift)
    d_center = _f32(scene.disk[0] + shift)
    c_p0, c_p1 = _f32(scene.cylinder[0] + shift), _f32(scene.cylinder[1] + shift)
    data = [dict(d) for d in other.data]
    data[SPHERES].update(center=s_center, radius=scene.sphere[1])
    data[DISKS].update(center=d_center, normal=scene.disk[1], radius=scene.disk[2])
    data[CYLINDERS].update(p0=c_p0, p1=c_p1, radius=scene.cylinder[2])
    data[ALPHA].update(cutoff=scene.data[ALPHA]["cutoff"])
    functions = rt.intersection_functions
    geometries = [
        rt.TriangleGeometry(triangles[: COUNTS[OPAQUE]].reshape(-1, 3), primitive_data=data[OPAQUE]),
        rt.TriangleGeometry(triangles[COUNTS[OPAQUE] :].reshape(-1, 3), primitive_data=data[ALPHA], opaque=False),
        rt.BoundingBoxGeometry(*functions.sphere_bounds(s_center, scene.sphere[1]), primitive_data=data[SPHERES]),
        rt.BoundingBoxGeometry(*functions.disk_bounds(d_center, *scene.disk[1:]), primitive_data=data[DISKS]),
        rt.BoundingBoxGeometry(
            *functions.capped_cylinder_bounds(c_p0, c_p1, scene.cylinder[2]), primitive_data=data[CYLINDERS]
        ),
    ]
    return Scene(
        geometries,
        triangles,
        (s_center, scene.sphere[1]),
        (d_center, *scene.disk[1:]),
        (c_p0, c_p1, scene.cylinder[2]),
        data,
        scene.center + shift,
        scene.scale,
    )


@settings(max_examples=3, deadline=None)
@given(seeds)
def test_primitive_data_round_trip_through_build_and_refit(seed):
    """Hits return exactly their primitive's row of a pytree of float32, int32, uint8 and bool leaves with
    trailing shapes in nested dicts and tuples; misses return zeros; a refit takes the new geometries' data."""
    scene = random_scene(seed, None, 0.0)
    structure = build(scene)
    rays = random_rays(seed ^ 0xDA7A, scene)
    result = NEAREST.intersect(rays.ray(), structure)
    assert_data_round_trip(result, scene)
    hit = np.asarray(result.type) != 0
    assert hit.sum() > RAYS // 2 and (~hit).sum() > 10
    assert set(np.asarray(result.geometry_id)[hit].tolist()) == set(range(len(COUNTS)))

    after = moved(scene, seed ^ 0x4EF1)
    refit = rt.refit(structure, after.geometries)
    rays = random_rays(seed ^ 0x4EF1, after)
    result = NEAREST.intersect(rays.ray(), refit)
    assert_nearest(result, expected(after, rays))
    assert_data_round_trip(result, after)


# --- jit -------------------------------------------------------------------------------------------------------


@functools.cache
def fixed_scene():
    scene = random_scene(2024, 1.0, 0.0)
    rays = random_rays(2025, scene)
    return scene, rays, build(scene)


def test_intersect_closed_over_inside_jit_equals_eager():
    """The structure as a constant of a jitted function (the any-hit test passes it as an argument)."""
    scene, rays, structure = fixed_scene()
    distance = jax.jit(lambda r: NEAREST.intersect(r, structure).distance)(rays.ray())
    eager = NEAREST.intersect(rays.ray(), structure)
    np.testing.assert_array_equal(np.asarray(distance), np.asarray(eager.distance))
    assert_nearest(eager, expected(scene, rays))


def test_vmap_over_ray_batches_equals_one_batch():
    _, rays, structure = fixed_scene()
    batched = jax.vmap(lambda r: NEAREST.intersect(r, structure))(rays.ray().reshape(4, RAYS // 4))
    eager = NEAREST.intersect(rays.ray(), structure)
    flat = jax.tree_util.tree_map(lambda a: np.asarray(a).reshape(RAYS, *a.shape[2:]), dict(batched))
    assert jax.tree_util.tree_structure(flat) == jax.tree_util.tree_structure(dict(eager))
    for (path, a), b in zip(
        jax.tree_util.tree_leaves_with_path(flat), jax.tree_util.tree_leaves(dict(eager)), strict=True
    ):
        name = jax.tree_util.keystr(path)
        if "barycentric" in name:
            # Recomputed after the traversal in a differently batched program: XLA may contract the edge
            # functions' multiply-adds differently (seen with jax 0.12), a few 1e-6 on ill-conditioned hits.
            np.testing.assert_allclose(a, np.asarray(b), rtol=0, atol=1e-5, err_msg=name)
        else:  # decisions, ids and distances come from the traversal: identical
            np.testing.assert_array_equal(a, np.asarray(b), err_msg=name)


# --- bad inputs ---------------------------------------------------------------------------------------------------


def _boxes(count=3):
    lower = np.zeros((count, 3), np.float32) + np.arange(count, dtype=np.float32)[:, None]
    return lower, lower + 0.5


def test_primitive_data_with_the_wrong_leading_dimension_is_refused():
    vertices = np.random.default_rng(0).normal(size=(9, 3)).astype(np.float32)
    with pytest.raises(
        ValueError,
        match=r"TriangleGeometry: primitive_data leaf \['alpha'\] has shape \(4,\); its leading dimension must equal the primitive count 3",
    ):
        rt.TriangleGeometry(vertices, primitive_data={"alpha": np.zeros(4, np.float32)})
    with pytest.raises(
        ValueError, match=r"BoundingBoxGeometry: primitive_data leaf \['x'\]\[1\] has shape \(2, 5\).*primitive count 3"
    ):
        rt.BoundingBoxGeometry(*_boxes(), primitive_data={"x": (np.zeros(3), np.zeros((2, 5)))})
    with pytest.raises(ValueError, match=r"has shape \(\); its leading dimension"):
        rt.BoundingBoxGeometry(*_boxes(), primitive_data=np.float32(1.0))


def test_inverted_and_non_finite_boxes_are_refused():
    lower, upper = _boxes()
    upper[1, 2] = lower[1, 2] - 1
    with pytest.raises(ValueError, match=r"BoundingBoxGeometry: box 1 is inverted on axis 2: lower 1.0 > upper 0.0"):
        rt.BoundingBoxGeometry(lower, upper)
    lower, upper = _boxes()
    lower[2, 0] = np.nan
    with pytest.raises(ValueError, match=r"BoundingBoxGeometry: lower has a non-finite value nan at index \(2, 0\)"):
        rt.BoundingBoxGeometry(lower, upper)
    lower, upper = _boxes()
    upper[0, 1] = np.inf
    with pytest.raises(ValueError, match=r"upper has a non-finite value inf at index \(0, 1\)"):
        rt.BoundingBoxGeometry(lower, upper)


def test_differing_primitive_data_layouts_are_refused():
    vertices = np.random.default_rng(0).normal(size=(6, 3)).astype(np.float32)
    base = {"a": np.zeros(2, np.float32), "b": np.zeros((2, 3), np.int32)}
    variants = {
        "dtype": {"a": np.zeros(2, np.int32), "b": base["b"]},
        "trailing shape": {"a": base["a"], "b": np.zeros((2, 4), np.int32)},
        "structure": {"a": base["a"], "c": base["b"]},
        "nesting": {"a": base["a"], "b": (base["b"],)},
    }
    for other in variants.values():
        geometries = [
            rt.TriangleGeometry(vertices, primitive_data=base),
            rt.TriangleGeometry(vertices, primitive_data=other),
        ]
        with pytest.raises(
            ValueError,
            match=r"primitive_data of geometries\[1\] has layout .* but geometries\[0\] has .*share one layout",
        ):
            rt.build_primitive_structure(geometries)


def test_intersection_functions_must_cover_exactly_the_box_geometries():
    _, rays, structure = fixed_scene()
    with pytest.raises(
        ValueError,
        match=r"geometry 2 is a BoundingBoxGeometry but the intersector has no intersection function for it \(pass intersection_functions=\{2: fn\}\)",
    ):
        rt.Intersector().intersect(rays.ray(), structure)
    partial = {SPHERES: FUNCTIONS[SPHERES], CYLINDERS: FUNCTIONS[CYLINDERS]}
    with pytest.raises(ValueError, match=r"geometry 3 is a BoundingBoxGeometry"):
        rt.Intersector(intersection_functions=partial).intersect(rays.ray(), structure)
    for index, what in ((OPAQUE, "a triangle geometry"), (ALPHA, "a triangle geometry"), (9, "absent")):
        functions = {**FUNCTIONS, index: rt.intersection_functions.sphere}
        with pytest.raises(
            ValueError,
            match=rf"intersection_functions names geometry {index}, which is {what}; intersection functions apply to BoundingBoxGeometry only",
        ):
            rt.Intersector(intersection_functions=functions, filter=alpha_filter).intersect(rays.ray(), structure)


_SPHERE = rt.intersection_functions.sphere


@pytest.mark.parametrize(
    "fn",
    [
        lambda ray, candidate: _SPHERE(ray, candidate)[1],
        lambda ray, candidate: jnp.stack([x.astype(jnp.float32) for x in _SPHERE(ray, candidate)]),
        lambda ray, candidate: (jnp.ones(2, bool), jnp.ones(2)),
        lambda ray, candidate: (*_SPHERE(ray, candidate), 0.0),
    ],
    ids=["a single value", "one array of shape (2,)", "a pair of arrays of shape (2,)", "a triple"],
)
def test_intersection_functions_must_return_a_pair_of_scalars(fn):
    _, rays, structure = fixed_scene()
    functions = {**FUNCTIONS, SPHERES: fn}
    with pytest.raises(
        TypeError, match=r"the intersection function of geometry 2 must return a pair \(accept, distance\) of scalars"
    ):
        rt.Intersector(intersection_functions=functions, filter=alpha_filter).intersect(rays.ray(), structure)


def test_filters_must_return_a_scalar():
    _, rays, structure = fixed_scene()
    bad_filter = lambda candidate: candidate.barycentric_coord > 0.5  # noqa: E731
    with pytest.raises(TypeError, match=r"the filter must return one scalar accept flag per candidate"):
        rt.Intersector(intersection_functions=FUNCTIONS, filter=bad_filter).intersect(rays.ray(), structure)


def test_primitive_data_tag_needs_a_structure_with_data():
    geometries, _, _, rays = filter_scene(0)
    structure = rt.build_primitive_structure(geometries[:1], capacity=32)
    with pytest.raises(
        ValueError, match=r"tags.primitive_data needs a structure built from geometries with primitive_data"
    ):
        rt.Intersector(rt.tags.primitive_data).intersect(rays.ray(), structure)


def test_bad_intersector_options_are_refused():
    for value in (0, -1, True, 2.0, "4"):
        with pytest.raises(ValueError, match=rf"Intersector: max_hits must be a positive int, got {value!r}"):
            rt.Intersector(max_hits=value)
    with pytest.raises(ValueError, match=r"max_hits and accept_any_intersection exclude each other"):
        rt.Intersector(max_hits=2, accept_any_intersection=True)
    sphere = rt.intersection_functions.sphere
    with pytest.raises(TypeError, match=r"intersection_functions must be a dict \{geometry index: fn\}, got list"):
        rt.Intersector(intersection_functions=[(2, sphere)])
    with pytest.raises(TypeError, match=r"intersection_functions must be a dict .* got function"):
        rt.Intersector(intersection_functions=sphere)
    with pytest.raises(ValueError, match=r"intersection_functions keys must be geometry indices, got '2'"):
        rt.Intersector(intersection_functions={"2": sphere})
    with pytest.raises(ValueError, match=r"keys must be geometry indices, got -1"):
        rt.Intersector(intersection_functions={-1: sphere})
    with pytest.raises(TypeError, match=r"the intersection function of geometry 2 is not callable"):
        rt.Intersector(intersection_functions={2: "sphere"})
    with pytest.raises(TypeError, match=r"filter must be a callable fn\(candidate\) -> accept"):
        rt.Intersector(filter=0.5)
