"""Ray/curve-segment intersection: round (swept-sphere) and flat (ray-facing ribbon) cubic Bezier segments.

Every basis is first converted to cubic Bezier form (:mod:`jaxrt._src.curves`); a segment is then its four
control points ``b0..b3`` with a radius each, and the curve ``C(u)``, radius ``r(u)``, ``u`` in ``[0, 1]``.

**Shapes.** A round segment is the part of the surface swept by the spheres ``S(u)`` (centre ``C(u)``,
radius ``r(u)``) whose points touch a sphere of ``u`` in ``[0, 1]`` (as Metal and Embree): the envelope of
the spheres, where ``(P - C(u)) . C'(u) + r(u) r'(u) = 0``. Along a ray, the entry into ``S(u)`` is at
``t_enter(u) = z(u) - sqrt(r(u)^2 - x(u)^2 - y(u)^2)`` in *ray space* (the ray along ``+z`` from the origin),
and the envelope points it enters are the local minima of ``t_enter``: an interior minimum is a hit on the
tube, a minimum at ``u = 0`` or ``1`` lies on an end sphere (a cap, or the joint with a neighbour). A flat
segment is a ribbon whose cross-section at ``u`` is the segment of half-width ``r(u)`` through ``C(u)``,
perpendicular to the curve and to the ray: in ray space, the ray hits it where ``p(u) . p'(u) = 0`` for
``p = (x, y)`` with ``|p(u)| <= r(u)``, at depth ``z(u)``. Only entries count: a ray that starts inside a
round tube does not hit that tube. Interpolated radii are used as ``|r(u)|`` (a Catmull-Rom radius can
undershoot below zero between non-negative control radii).

**Joints and caps.** Segments meeting at a joint share the sphere there. It is drawn only where neither
tube covers it (a kink of a Bezier or linear chain), and then by the segment that starts at the joint, so a
ray crosses a joint once: no gap, no second hit. The free ends of a chain get the end caps: none (open),
a disk spanning the tube's end circle, or the end sphere.

**Method** (chosen by measurement, see ``docs/curves.md``): the segment is sampled at ``pieces + 1``
parameters in ray space; each piece is a round cone (a linearly varying sphere swept along the chord) whose
entry is found exactly in closed form. Pieces whose chord passes within a bound of the curve's distance to its
chords (``0.75 h^2`` times the largest second difference of the Bezier control points, ``h = 1 / pieces``)
run a few safeguarded Newton steps towards the ray's closest approach to the true curve, which decides
whether the curve is touched there and gives an entry estimate (exact for a straight tube). ``iterations``
Newton steps on the true cubic then refine two starts side by side (the nearest chord hit and the nearest
closest-approach entry), on the two equations above in ``(u, t)``; a solution counts when it is on the
sphere and the envelope and the step Newton would still take is within ``tolerance`` of the radius. Where
Newton fails but the curve is touched, the exact hit of the chord is the answer (an error of at most the
chord bound). Ribbons run Newton on ``p . p' = 0`` from every candidate crossing of the chords at once and
keep the nearest. Caps and joints are exact sphere, disk or ribbon-end tests. With ``iterations = 0`` the
method is the chord approximation (a linear curve is exact with one piece and no iteration).

**Gradients.** :func:`smooth_hit` recomputes the chosen hit in world space, differentiably: a Newton step
from the (detached) solution with a detached Jacobian gives the implicit-function derivative of ``(u, t)``
with respect to control points, radii and the ray, and leaves the value unchanged. The solution is first
polished by two detached Newton steps: the test accepts a hit within its tolerance of the root, and the
derivative taken there would be off by about that much (a float64 gradient off by 1.4e-2 relative on one
ray of three random scenes of tests/test_gradients_curves.py).

References:
  Reshetov, Luebke, "Phantom Ray-Hair Intersector", Proc. ACM CGIT 1(2), 2018 (ray-space curve tests).
  Woop, Benthin, Wald, Johnson, Tabellion, "Exploiting Local Orientation Similarity for Efficient Ray
  Traversal of Hair and Fur", HPG 2014 (ray-space projection and subdivision of hair segments).
  Duff et al., "Building an Orthonormal Basis, Revisited", JCGT 6(1), 2017 (the ray frame).
  van Wijk, "Ray tracing objects defined by sweeping a sphere", Computers & Graphics 9(3), 1985.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

__all__ = [
    "CurveOptions",
    "CurveRay",
    "CurveHit",
    "DEFAULT_OPTIONS",
    "ROUND",
    "FLAT",
    "CAP_NONE",
    "CAP_DISK",
    "CAP_SPHERE",
    "curve_ray",
    "intersect",
    "smooth_hit",
    "segment_bounds",
    "world_bezier",
    "pack_flags",
]

# Per-segment flag bits (an int32 per leaf).
HAS_PREVIOUS = 1
HAS_NEXT = 2
_CAP_SHIFT = 2  # two bits: 0 none, 1 disk, 2 sphere
FLAT_BIT = 16
IS_CURVE = 32  # marks curve leaves in a structure that also holds triangles
UNROLL = False  # rolled loops: a smaller program, compiled about 15% faster, as fast to run
ROUND, FLAT = 0, 1
CAP_NONE, CAP_DISK, CAP_SPHERE = 0, 1, 2

# Which part of the segment was hit (returned by :func:`intersect`, read by :func:`smooth_hit`).
PART_TUBE, PART_SPHERE, PART_DISK, PART_RIBBON, PART_FACING_DISK = 0, 1, 2, 3, 4


@dataclasses.dataclass(frozen=True)
class CurveOptions:
    """Static accuracy knobs of the ray/curve test (hashable; part of the compiled code).

    Attributes:
      pieces: chord pieces the segment is split into to find the start of the Newton iteration (and the
        answer where Newton fails). More pieces: a closer start and a smaller fallback error, more work.
      iterations: Newton steps on the true cubic. 0 keeps the chord answer (error about the chord distance).
      tolerance: convergence test of Newton, relative to the radius: a solution whose distance to the sphere
        surface, and whose offset from the envelope, is within ``tolerance * radius`` (plus float rounding)
        is accepted; otherwise the chord answer is used.
      approach_iterations: Newton steps towards the ray's closest approach to the centre line, which decide
        whether a thin curve is touched at all where no chord is hit, and start the entry search there.
    """

    pieces: int = 8
    iterations: int = 3
    tolerance: float = 1e-3
    approach_iterations: int = 3

    def __post_init__(self):
        if not isinstance(self.pieces, int) or self.pieces < 1:
            raise ValueError(f"CurveOptions: pieces must be a positive int, got {self.pieces!r}")
        if not isinstance(self.iterations, int) or self.iterations < 0:
            raise ValueError(f"CurveOptions: iterations must be a non-negative int, got {self.iterations!r}")
        if not isinstance(self.approach_iterations, int) or self.approach_iterations < 0:
            raise ValueError(
                f"CurveOptions: approach_iterations must be a non-negative int, got {self.approach_iterations!r}"
            )
        if not self.tolerance > 0:
            raise ValueError(f"CurveOptions: tolerance must be positive, got {self.tolerance!r}")


DEFAULT_OPTIONS = CurveOptions()


def pack_flags(has_previous, has_next, end_caps: int, flat: bool) -> jax.Array:
    """The per-segment int32 flags read by :func:`intersect`."""
    flags = jnp.where(has_previous, HAS_PREVIOUS, 0) | jnp.where(has_next, HAS_NEXT, 0)
    return (flags | (int(end_caps) << _CAP_SHIFT) | (FLAT_BIT if flat else 0)).astype(jnp.int32)


class CurveRay(NamedTuple):
    """Per-ray constants: the origin, an orthonormal frame whose third row is the unit direction, 1/|d|."""

    origin: jax.Array
    frame: jax.Array
    inv_length: jax.Array


def curve_ray(origin: jax.Array, direction: jax.Array) -> CurveRay:
    """The ray-space frame of one ray (Duff et al. 2017); ``direction`` must be non-zero.

    The squared length is written as multiply-adds, not ``jnp.sum``: XLA 0.11's CPU YNNPACK reduce fusion
    returns ``1 / length = inf`` for this reduce-sqrt-divide pattern on batches of 4096 rays or more.
    """
    length = jnp.sqrt(direction[0] * direction[0] + direction[1] * direction[1] + direction[2] * direction[2])
    n = direction / length
    sign = jnp.where(n[2] >= 0, 1.0, -1.0).astype(n.dtype)
    a = -1.0 / (sign + n[2])
    b = n[0] * n[1] * a
    e1 = jnp.stack([1.0 + sign * n[0] * n[0] * a, sign * b, -sign * n[0]])
    e2 = jnp.stack([b, sign + n[1] * n[1] * a, -n[1]])
    return CurveRay(origin, jnp.stack([e1, e2, n]), 1.0 / length)


class CurveHit(NamedTuple):
    hit: jax.Array
    distance: jax.Array  # ray parameter t (hit = origin + t * direction); inf on a miss
    u: jax.Array  # segment-local curve parameter in [0, 1]; 0 on a miss
    part: jax.Array  # PART_* code of the part hit


def segment_bounds(segment: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Box of packed segments ``(..., 6, 4)``: the convex hull of their Bezier control points grown by the
    largest radius, and by the rounding of adding the local points to the base point (so it stays a bound)."""
    local, base = segment[..., :4, :], segment[..., 4, :3]
    reach = jnp.max(jnp.abs(local[..., 3]), axis=-1)[..., None]
    lower = base + jnp.min(local[..., :3], axis=-2)
    upper = base + jnp.max(local[..., :3], axis=-2)
    slack = 2.0 * float(jnp.finfo(segment.dtype).eps) * jnp.maximum(jnp.abs(lower), jnp.abs(upper))
    return lower - reach - slack, upper + reach + slack


def world_bezier(segment: jax.Array) -> jax.Array:
    """``(..., 4, 4)`` world-space Bezier control points (x, y, z, radius) of packed segments."""
    base = jnp.concatenate([segment[..., 4:5, :3], jnp.zeros_like(segment[..., 4:5, 3:])], axis=-1)
    return segment[..., :4, :] + base


# --- polynomials ---------------------------------------------------------------------------------------------

_TO_POWER = np.array([[1, 0, 0, 0], [-3, 3, 0, 0], [3, -6, 3, 0], [-1, 3, -3, 1]], np.float64)


def _bernstein(u: np.ndarray) -> np.ndarray:
    u = np.asarray(u, np.float64)[:, None]
    k = np.arange(4)
    return np.array([1, 3, 3, 1]) * u**k * (1 - u) ** (3 - k)


def _combine(weights: np.ndarray, points: jax.Array) -> jax.Array:
    """``weights @ points`` for a constant ``(m, 4)`` matrix, as a sum of scaled rows.

    (XLA on the CPU runs tiny batched matrix products far slower than the same multiply-adds written out.)
    """
    weights = np.asarray(weights, np.float64)
    rows = [
        sum(float(weights[i, k]) * points[k] for k in range(weights.shape[1]) if weights[i, k] != 0)
        for i in range(weights.shape[0])
    ]
    return jnp.stack([r if not isinstance(r, int) else jnp.zeros_like(points[0]) for r in rows])


def _rotate(v: jax.Array, frame: jax.Array) -> jax.Array:
    """``v @ frame.T`` for ``v`` ``(..., 3)`` written as multiply-adds (see :func:`_combine`)."""
    return jnp.stack([v[..., 0] * f[0] + v[..., 1] * f[1] + v[..., 2] * f[2] for f in frame], axis=-1)


def _evaluate(c: jax.Array, u: jax.Array):
    """Value, first and second derivative at ``u`` of power-basis coefficients ``c`` ``(4, k)``."""
    value = c[0] + u * (c[1] + u * (c[2] + u * c[3]))
    first = c[1] + u * (2.0 * c[2] + 3.0 * u * c[3])
    second = 2.0 * c[2] + 6.0 * u * c[3]
    return value, first, second


def _norm2(v):
    return jnp.sum(v * v, axis=-1)


def _diff_of_squares(a, b):
    """``a^2 - b^2`` as ``(a - b)(a + b)`` for non-negative ``a, b`` (no cancellation when they are close)."""
    return (a - b) * (a + b)


# --- round cones (pieces and linear segments) --------------------------------------------------------------------


def _round_cone_tube(a: jax.Array, b: jax.Array):
    """Entry into the lateral surface of round cones from ``a`` to ``b`` (``(..., 4)`` ray-space x, y, z, r).

    Returns ``(valid, t, s)``: the local minimum of ``t_enter(s) = z(s) - sqrt(D(s))`` over the infinite cone,
    ``D = r^2 - |p|^2`` quadratic in ``s``. Its stationarity condition ``2 z' sqrt(D) = D'`` is the quadratic
    ``A k s^2 + 2 B k s + (z1^2 C - B^2) = 0`` with ``D = C + 2 B s + A s^2`` and ``k = |b - a|^2 - dr^2``
    (the cone exists when ``k > 0``; then the stationary point is a minimum). ``B^2 - A C`` is evaluated as
    ``|dr p0 - r0 p1|^2 - (p0 x p1)^2`` to avoid the cancellation of the expanded form.
    """
    p0, z0, r0 = a[..., :2], a[..., 2], a[..., 3]
    p1, z1, dr = b[..., :2] - p0, b[..., 2] - z0, b[..., 3] - r0
    big_a = dr * dr - _norm2(p1)
    big_b = r0 * dr - jnp.sum(p0 * p1, axis=-1)
    k = z1 * z1 - big_a
    mixed = jnp.sqrt(_norm2(dr[..., None] * p0 - r0[..., None] * p1))
    cross = jnp.abs(p0[..., 0] * p1[..., 1] - p0[..., 1] * p1[..., 0])
    disc = _diff_of_squares(mixed, cross)
    exists = (k > 0) & (disc >= 0)
    root = z1 * jnp.sqrt(jnp.where(exists, disc / jnp.where(k > 0, k, 1.0), 0.0))
    # s = (-B + root) / A, or the same root from the product of the two roots when -B and root differ in sign.
    first = -big_b + root
    numerator_2 = z1 * z1 * (r0 * r0 - _norm2(p0)) - big_b * big_b
    denominator_2 = k * (-big_b - root)
    same = (-big_b) * root >= 0
    num = jnp.where(same, first, numerator_2)
    den = jnp.where(same, big_a, denominator_2)
    ok = exists & (den != 0)
    s = jnp.where(ok, num / jnp.where(den != 0, den, 1.0), -1.0)
    p = p0 + s[..., None] * p1
    r = jnp.abs(r0 + s * dr)
    depth = _diff_of_squares(r, jnp.sqrt(_norm2(p)))
    valid = ok & (s >= 0) & (s <= 1) & (depth >= 0)
    t = z0 + s * z1 - jnp.sqrt(jnp.maximum(depth, 0.0))
    return valid, t, s


def _sphere_entry(q: jax.Array):
    """Entry ``(valid, t)`` of the +z ray into spheres ``q`` ``(..., 4)`` (ray-space centre and radius)."""
    depth = _diff_of_squares(jnp.abs(q[..., 3]), jnp.sqrt(_norm2(q[..., :2])))
    return depth >= 0, q[..., 2] - jnp.sqrt(jnp.maximum(depth, 0.0))


def _chord_bound(control: jax.Array, pieces: int) -> jax.Array:
    """Bound on the distance between the curve (with its radius) and the pieces' chords (and linear radii)."""
    second = control[:-2] - 2.0 * control[1:-1] + control[2:]
    position = jnp.max(jnp.sqrt(_norm2(second[:, :3])))
    radius = jnp.max(jnp.abs(second[:, 3]))
    return 0.75 * (position + radius) / (pieces * pieces)


# --- the segment test --------------------------------------------------------------------------------------------


def _enter_slope(q: jax.Array, dq: jax.Array) -> jax.Array:
    """Sign-carrying slope of ``t_enter`` at a sphere ``q`` along the derivative ``dq`` (times sqrt(D) > 0)."""
    depth = _diff_of_squares(jnp.abs(q[3]), jnp.sqrt(_norm2(q[:2])))
    root = jnp.sqrt(jnp.maximum(depth, 0.0))
    return dq[2] * root - (q[3] * dq[3] - q[0] * dq[0] - q[1] * dq[1])


def intersect(
    ray: CurveRay,
    segment: jax.Array,
    flags: jax.Array,
    t_min: jax.Array,
    t_max: jax.Array,
    *,
    curve_types: tuple[int, ...] = (ROUND,),
    end_caps: tuple[int, ...] = (CAP_NONE,),
    options: CurveOptions = DEFAULT_OPTIONS,
) -> CurveHit:
    """Nearest entry of one ray into one curve segment within ``[t_min, t_max]`` (batch it with ``vmap``).

    Args:
      ray: from :func:`curve_ray`.
      segment: ``(6, 4)`` packed segment (:func:`jaxrt._src.curves.pack_segments`): rows 0-3 the cubic Bezier
        control points (``x, y, z, radius``) relative to the base point in row 4 (which keeps their
        precision far from the origin), row 5 the derivative of the predecessor at the shared joint.
      flags: int32 from :func:`pack_flags`.
      t_min, t_max: accepted interval of the ray parameter.
      curve_types: static; the curve types the code handles (``ROUND``, ``FLAT``); with both, ``flags``
        selects per segment.
      end_caps: static; the cap kinds the code handles (``CAP_*``).
      options: static accuracy knobs.

    Returns:
      A :class:`CurveHit`: distance in units of the ray direction's length, the curve parameter ``u``.
    """
    dtype = segment.dtype
    scale_t = ray.inv_length
    # Ray space: x, y across the ray, z along the unit direction (world length units), r unchanged.
    rel = _rotate((segment[4, :3] - ray.origin) + segment[:4, :3], ray.frame)
    q = jnp.concatenate([rel, segment[:4, 3:]], axis=-1)
    dprev = jnp.concatenate([_rotate(segment[5, :3], ray.frame), segment[5, 3:]])
    lo, hi = t_min / scale_t, t_max / scale_t  # interval in world length along the unit direction
    has_previous = (flags & HAS_PREVIOUS) != 0
    has_next = (flags & HAS_NEXT) != 0
    caps = (flags >> _CAP_SHIFT) & 3
    scale = jnp.max(jnp.abs(q[:, :3])) + jnp.max(jnp.abs(q[:, 3]))
    noise = 16.0 * float(jnp.finfo(dtype).eps) * scale  # rounding of ray-space coordinates

    results = []
    if ROUND in curve_types:
        results.append(_round(q, dprev, has_previous, has_next, caps, lo, hi, noise, end_caps, options))
    if FLAT in curve_types:
        results.append(_flat(q, dprev, has_previous, has_next, caps, lo, hi, noise, end_caps, options))
    if len(results) == 1:
        hit, t, u, part = results[0]
    else:
        flat = (flags & FLAT_BIT) != 0
        hit, t, u, part = (jnp.where(flat, f, r) for r, f in zip(*results, strict=True))
    return CurveHit(hit, jnp.where(hit, t * scale_t, jnp.inf), jnp.where(hit, u, 0.0), part)


def _samples(q: jax.Array, pieces: int) -> jax.Array:
    return _combine(_bernstein(np.linspace(0.0, 1.0, pieces + 1)), q)


def _nearest(valid, t, u, lo, hi, margin):
    """The candidate (flattened) with the smallest ``t`` in ``[lo - margin, hi]``."""
    key = jnp.where(valid & (t >= lo - margin) & (t <= hi), t, jnp.inf).reshape(-1)
    best = jnp.argmin(key)
    return jnp.isfinite(key[best]), t.reshape(-1)[best], u.reshape(-1)[best]


def _round(q, dprev, has_previous, has_next, caps, lo, hi, noise, end_caps, options: CurveOptions):
    n = options.pieces
    h = 1.0 / n
    power = _combine(_TO_POWER, q)
    sample = _samples(q, n)
    sample = sample.at[:, 3].set(jnp.abs(sample[:, 3]))
    grow = _chord_bound(q, n) if options.iterations > 0 else jnp.zeros((), q.dtype)
    index = jnp.arange(n, dtype=q.dtype)

    # The chords: exact hits of the round cones through the samples (spheres at the inner samples).
    cone_ok, cone_t, cone_s = _round_cone_tube(sample[:-1], sample[1:])
    sphere_ok, sphere_t = _sphere_entry(sample[1:-1])
    # An inner sphere is on the chords' surface only where it fills a kink: t_enter decreases towards it
    # along both neighbouring chords (else its entry lies inside a cone).
    chord = sample[1:] - sample[:-1]
    inner_slopes = jax.vmap(_enter_slope, in_axes=(0, 0))
    sphere_ok &= (inner_slopes(sample[1:-1], chord[:-1]) <= 0) & (inner_slopes(sample[1:-1], chord[1:]) >= 0)
    # A ray starting just outside the tube may start inside a chord's: keep such pieces as candidates.
    margin = 2.0 * (jnp.max(sample[:, 3]) + grow) if options.iterations > 0 else 0.0
    chord_ok, chord_t, chord_u = _nearest(
        jnp.concatenate([cone_ok, sphere_ok]),
        jnp.concatenate([cone_t, sphere_t]),
        jnp.concatenate([(index + cone_s) * h, index[1:] * h]),
        lo,
        hi,
        margin,
    )

    if options.iterations > 0:
        # Pieces whose chord passes within the chord bound of the ray may hold a hit of the true curve even
        # where no chord is hit (a thin curve bending away from its chords): each runs a few steps towards
        # the ray's closest approach to the true curve, which decides whether the curve is touched there
        # (well conditioned, unlike the entry point near a silhouette), and gives an entry estimate.
        p0, p1 = sample[:-1, :2], sample[1:, :2] - sample[:-1, :2]
        length2 = _norm2(p1)
        s = jnp.clip(-jnp.sum(p0 * p1, axis=-1) / jnp.where(length2 > 0, length2, 1.0), 0.0, 1.0)
        reach = sample[:-1, 3] + s * (sample[1:, 3] - sample[:-1, 3]) + grow
        near = _norm2(p0 + s[:, None] * p1) <= reach * reach
        power_n = power[:, :, None]

        def closest(u):
            """h(u) = p . p' - r r' (half the derivative of |p|^2 - r^2) and its derivative."""
            (x, y, _z, r), (dx, dy, _dz, dr), (ddx, ddy, _ddz, ddr) = _evaluate(power_n, u)
            return x * dx + y * dy - r * dr, dx * dx + dy * dy + x * ddx + y * ddy - dr * dr - r * ddr

        def approach(_, carry):
            # Safeguarded Newton on h = 0 in a bracket [a, b] with h(a) < 0 < h(b): bisect where the Newton
            # step leaves the bracket or the slope has the wrong sign.
            u, a, b = carry
            value, slope = closest(u)
            a = jnp.where(value < 0, u, a)
            b = jnp.where(value > 0, u, b)
            step = u - value / jnp.where(slope > 0, slope, 1.0)
            good = (slope > 0) & (step >= a) & (step <= b)  # (a converged step may land on a bracket end)
            return jnp.where(good, step, 0.5 * (a + b)), a, b

        u = (index + s) * h
        a, b = jnp.clip(u - h, 0.0, 1.0), jnp.clip(u + h, 0.0, 1.0)
        u_close, _, _ = lax.fori_loop(0, options.approach_iterations, approach, (u, a, b), unroll=UNROLL)
        # Without a sign change in the bracket the iteration drifts; the closest of it and the two ends wins.
        tries = jnp.stack([u_close, a, b])
        (x, y, _z, r), _, _ = _evaluate(power[:, :, None, None], tries)
        u_close = jnp.take_along_axis(tries, jnp.argmin(x * x + y * y - r * r, axis=0)[None], axis=0)[0]
        (x, y, z, r), (dx, dy, dz, _), _ = _evaluate(power_n, u_close)
        depth = _diff_of_squares(jnp.abs(r), jnp.sqrt(x * x + y * y))
        touching = near & (depth >= -2.0 * noise * (jnp.abs(r) + noise))
        # The entry into a straight tube through the closest approach: u_close + shift (exact for lines).
        across2 = dx * dx + dy * dy
        shift = -dz * jnp.sqrt(jnp.maximum(depth, 0.0)) / jnp.sqrt(jnp.maximum(across2 * (across2 + dz * dz), 1e-30))
        u_entry = jnp.clip(u_close + jnp.clip(shift, -h, h), 0.0, 1.0)
        (x, y, z, r), _, _ = _evaluate(power_n, u_entry)
        t_entry = z - jnp.sqrt(jnp.maximum(_diff_of_squares(jnp.abs(r), jnp.sqrt(x * x + y * y)), 0.0))
        touch_ok, t_entry, u_entry = _nearest(touching, t_entry, u_entry, lo, hi, margin)
        touches = jnp.any(touching)
        found = chord_ok | touch_ok
        (x, y, z, r), _, _ = _evaluate(power, chord_u)
        t_chord = z - jnp.sqrt(jnp.maximum(_diff_of_squares(jnp.abs(r), jnp.sqrt(x * x + y * y)), 0.0))
        # Two starts, refined side by side: the chord's hit (good for thick curves) and the entry through the
        # closest approach (good for thin ones, where the chord's point may sit on the true curve's silhouette).
        u = jnp.stack([jnp.where(chord_ok, chord_u, u_entry), u_entry])
        t = jnp.stack([jnp.where(chord_ok, t_chord, t_entry), t_entry])
        # Newton stays near its start (as Embree keeps it in the sub-curve it refines): a far solution is
        # another local minimum of t_enter, whose entry is not the first. It also stays in the segment: past
        # its ends, the cubic's extension is not the neighbouring segment.
        window_lo, window_hi = jnp.maximum(u - h, 0.0), jnp.minimum(u + h, 1.0)

        def newton(_, carry):
            u, t = carry
            (x, y, z, r), (dx, dy, dz, dr), (ddx, ddy, ddz, ddr) = _evaluate(power[:, :, None], u)
            w = t - z
            f = x * x + y * y + w * w - r * r
            g = -x * dx - y * dy + w * dz + r * dr
            f_u, f_t = -2.0 * g, 2.0 * w
            g_u = -(dx * dx + dy * dy + dz * dz) - x * ddx - y * ddy + w * ddz + dr * dr + r * ddr
            det = f_u * dz - f_t * g_u
            safe = jnp.where(det == 0, 1.0, det)
            du = jnp.where(det == 0, 0.0, (-f * dz + f_t * g) / safe)
            dt = jnp.where(det == 0, 0.0, (-f_u * g + f * g_u) / safe)
            return jnp.clip(u + du, window_lo, window_hi), t + dt

        u, t = lax.fori_loop(0, options.iterations, newton, (u, t), unroll=UNROLL)
        (x, y, z, r), (dx, dy, dz, dr), (ddx, ddy, ddz, ddr) = _evaluate(power[:, :, None], u)
        w = t - z
        speed = jnp.sqrt(dx * dx + dy * dy + dz * dz)
        radius = jnp.abs(r)
        tol = options.tolerance * radius + noise
        off_sphere = jnp.abs(jnp.sqrt(x * x + y * y + w * w) - radius)
        off_envelope = jnp.abs(-x * dx - y * dy + w * dz + r * dr)
        g_u = -(dx * dx + dy * dy + dz * dz) - x * ddx - y * ddy + w * ddz + dr * dr + r * ddr
        # The step Newton would still take in t: near a silhouette t changes much for a small residual, so a
        # slow iterate can be close to the sphere and the envelope and still far from the entry.
        f = x * x + y * y + w * w - r * r
        g = -x * dx - y * dy + w * dz + r * dr
        det = -2.0 * g * dz - 2.0 * w * g_u
        remaining = jnp.abs(2.0 * g * g + f * g_u) / jnp.maximum(jnp.abs(det), jnp.finfo(q.dtype).tiny)
        converged = found & (off_sphere <= tol) & (off_envelope <= tol * (speed + jnp.abs(dr))) & (remaining <= tol)
        slack = 1e-6
        valid = converged & (w <= 0) & (g_u <= 0) & (u >= -slack) & (u <= 1 + slack) & (t >= lo) & (t <= hi)
        pick = jnp.argmin(jnp.where(valid, t, jnp.inf))
        tube, t, u = valid[pick], t[pick], u[pick]
        # Newton failed but the curve is touched: the chord's hit (not where Newton is leaving the segment:
        # the entry is then beyond its end, on a neighbour or a cap).
        leaving = jnp.any((u <= 0) | (u >= 1))
        fallback = chord_ok & touches & ~jnp.any(converged) & ~leaving & (chord_t >= lo) & (chord_t <= hi)
        tube_ok = tube | fallback
        tube_t = jnp.where(tube, t, chord_t)
        tube_u = jnp.clip(jnp.where(tube, u, chord_u), 0.0, 1.0)
    else:
        tube_ok, tube_t, tube_u = chord_ok & (chord_t >= lo), chord_t, chord_u

    # The end spheres: a cap, or the fill of a kink at a joint (drawn by the segment that starts there).
    start, end = q[0], q[3]
    d_start, d_end = 3.0 * (q[1] - q[0]), 3.0 * (q[3] - q[2])
    (start_ok, start_t), (end_ok, end_t) = _sphere_entry(start), _sphere_entry(end)
    start_surface = _enter_slope(start, d_start) >= 0  # t_enter does not decrease into the segment
    end_surface = _enter_slope(end, d_end) <= 0
    joint_open = _enter_slope(start, dprev) <= 0  # nor into the predecessor: a gap between the tubes
    start_accept = has_previous & joint_open
    end_accept = jnp.zeros((), bool)
    if CAP_SPHERE in end_caps:
        start_accept |= ~has_previous & (caps == CAP_SPHERE)
        end_accept |= ~has_next & (caps == CAP_SPHERE)
    start_ok &= start_accept & start_surface
    end_ok &= end_accept & end_surface
    candidates = [(tube_ok, tube_t, tube_u, PART_TUBE), (start_ok, start_t, 0.0, PART_SPHERE)]
    candidates.append((end_ok, end_t, 1.0, PART_SPHERE))
    if CAP_DISK in end_caps:
        ends = ((0.0, start, d_start, ~has_previous, 1.0), (1.0, end, d_end, ~has_next, -1.0))
        for which, point, derivative, free, sign in ends:
            ok, t = _disk(point, derivative, q, sign)
            candidates.append((ok & free & (caps == CAP_DISK), t, which, PART_DISK))
    return _pick(candidates, lo, hi)


def _disk(point, derivative, q, sign):
    """Entry through the flat disk spanning the tube's end circle (``sign`` +1 at the start, -1 at the end)."""
    speed = jnp.sqrt(_norm2(derivative[:3]))
    fallback = q[3, :3] - q[0, :3]
    axis = jnp.where(speed > 0, derivative[:3], fallback)
    axis = axis / jnp.maximum(jnp.sqrt(_norm2(axis)), jnp.finfo(q.dtype).tiny)
    radius = jnp.abs(point[3])
    # The end circle lies in the plane (P - C) . T = -r r' / |C'|, with radius sqrt(r^2 - (r r' / |C'|)^2).
    offset = jnp.clip(-point[3] * derivative[3] / jnp.maximum(speed, jnp.finfo(q.dtype).tiny), -radius, radius)
    centre = point[:3] + offset * axis
    facing = sign * axis[2] > 0  # the ray enters the tube through the disk
    t = jnp.dot(centre, axis) / jnp.where(axis[2] == 0, 1.0, axis[2])
    hit_point = jnp.array([0.0, 0.0, 1.0], q.dtype) * t
    inside = _norm2(hit_point - centre) <= _diff_of_squares(radius, jnp.abs(offset))
    return facing & inside, t


def _pick(candidates, lo, hi):
    ok = jnp.stack([c[0] & (c[1] >= lo) & (c[1] <= hi) for c in candidates])
    t = jnp.stack([jnp.asarray(c[1]) for c in candidates])
    key = jnp.where(ok, t, jnp.inf)
    best = jnp.argmin(key)
    u = jnp.stack([jnp.asarray(c[2], t.dtype) for c in candidates])
    part = jnp.array([c[3] for c in candidates], jnp.int32)
    return jnp.any(ok), key[best], u[best], part[best]


def _flat(q, dprev, has_previous, has_next, caps, lo, hi, noise, end_caps, options: CurveOptions):
    n = options.pieces
    h = 1.0 / n
    power = _combine(_TO_POWER, q)
    sample = _samples(q, n)
    grow = _chord_bound(q, n) if options.iterations > 0 else jnp.zeros((), q.dtype)
    # The chords in ray space: the ray's closest point on each, its depth, and the chord's half-width there.
    a, b = sample[:-1], sample[1:]
    p0, p1 = a[:, :2], b[:, :2] - a[:, :2]
    length2 = _norm2(p1)
    s = jnp.clip(-jnp.sum(p0 * p1, axis=-1) / jnp.where(length2 > 0, length2, 1.0), 0.0, 1.0)
    closest2 = _norm2(p0 + s[:, None] * p1)
    reach = jnp.abs(a[:, 3]) + s * (jnp.abs(b[:, 3]) - jnp.abs(a[:, 3]))
    t_piece = a[:, 2] + s * (b[:, 2] - a[:, 2])
    u_piece = (jnp.arange(n, dtype=q.dtype) + s) * h
    # The ray crosses the polyline's ribbon inside a chord (closest point inside it) or at an inner sample
    # where the closest points of both neighbouring chords are that sample (the outer side of a kink).
    interior = (s > 0) & (s < 1)
    kink = (s[:-1] >= 1) & (s[1:] <= 0)
    vertex2 = _norm2(sample[1:-1, :2])
    vertex_r = jnp.abs(sample[1:-1, 3])
    index = jnp.arange(1, n, dtype=q.dtype)
    t_all = jnp.concatenate([t_piece, sample[1:-1, 2]])
    u_all = jnp.concatenate([u_piece, index * h])
    crossing = jnp.concatenate([interior & (closest2 <= reach * reach), kink & (vertex2 <= vertex_r * vertex_r)])
    chord_ok, chord_t, chord_u = _nearest(crossing, t_all, u_all, lo, hi, 0.0)

    if options.iterations > 0:
        # Within the chord bound of the polyline, also where the closest point is a segment end (the curve's
        # own crossing may lie just inside it).
        grown, vertex_grown = reach + grow, vertex_r + grow
        ends = jnp.stack([s[0] <= 0, s[-1] >= 1])
        near = jnp.concatenate(
            [interior | ((jnp.arange(n) == 0) & ends[0]) | ((jnp.arange(n) == n - 1) & ends[1]), kink]
        )
        near &= jnp.concatenate([closest2 <= grown * grown, vertex2 <= vertex_grown**2])
        # Newton on every candidate at once (it is one-dimensional and cheap): every crossing near the
        # polyline is found, and the nearest valid one wins.
        start = u_all
        window_lo, window_hi = jnp.maximum(start - h, 0.0), jnp.minimum(start + h, 1.0)
        power_n = power[:, :, None]

        def newton(_, u):
            # Newton on g(u) = p . p' = 0: the ray lies on the ribbon's cross-section line at u.
            (x, y, _z, _r), (dx, dy, _dz, _dr), (ddx, ddy, _ddz, _ddr) = _evaluate(power_n, u)
            g = x * dx + y * dy
            g_u = dx * dx + dy * dy + x * ddx + y * ddy
            step = jnp.where(g_u == 0, 0.0, -g / jnp.where(g_u == 0, 1.0, g_u))
            return jnp.clip(u + step, window_lo, window_hi)

        u = lax.fori_loop(0, options.iterations, newton, start, unroll=UNROLL)
        (x, y, z, r), (dx, dy, _dz, _dr), _ = _evaluate(power_n, u)
        speed = jnp.sqrt(dx * dx + dy * dy)
        converged = near & (jnp.abs(x * dx + y * dy) <= (options.tolerance * jnp.abs(r) + noise) * speed)
        slack = 1e-6
        inside = (x * x + y * y <= r * r) & (u >= -slack) & (u <= 1 + slack) & (z >= lo) & (z <= hi)
        ribbon_ok, z, u = _nearest(converged & inside, z, u, lo, hi, 0.0)
        # No chord fallback: where Newton does not converge the true ribbon is usually not crossed there
        # (a chord crossing within the chord bound of the curve's silhouette).
        ribbon_t, ribbon_u = z, jnp.clip(u, 0.0, 1.0)
    else:
        ribbon_ok, ribbon_t, ribbon_u = chord_ok & (chord_t >= lo), chord_t, chord_u

    start, end = q[0], q[3]
    d_start, d_end = 3.0 * (q[1] - q[0]), 3.0 * (q[3] - q[2])
    start_in = _norm2(start[:2]) <= start[3] * start[3]
    end_in = _norm2(end[:2]) <= end[3] * end[3]
    start_free = jnp.dot(start[:2], d_start[:2]) >= 0  # the ribbon's closest point lies before u = 0
    end_free = jnp.dot(end[:2], d_end[:2]) <= 0
    joint_open = jnp.dot(start[:2], dprev[:2]) <= 0
    start_disk = has_previous & joint_open
    end_disk = jnp.zeros((), bool)
    start_sphere = jnp.zeros((), bool)
    end_sphere = jnp.zeros((), bool)
    if CAP_DISK in end_caps:
        start_disk |= ~has_previous & (caps == CAP_DISK)
        end_disk |= ~has_next & (caps == CAP_DISK)
    if CAP_SPHERE in end_caps:
        start_sphere = ~has_previous & (caps == CAP_SPHERE)
        end_sphere = ~has_next & (caps == CAP_SPHERE)
    (_, start_sphere_t), (_, end_sphere_t) = _sphere_entry(start), _sphere_entry(end)
    candidates = [
        (ribbon_ok, ribbon_t, ribbon_u, PART_RIBBON),
        (start_in & start_free & start_disk, start[2], 0.0, PART_FACING_DISK),
        (start_in & start_free & start_sphere, start_sphere_t, 0.0, PART_SPHERE),
        (end_in & end_free & end_disk, end[2], 1.0, PART_FACING_DISK),
        (end_in & end_free & end_sphere, end_sphere_t, 1.0, PART_SPHERE),
    ]
    return _pick(candidates, lo, hi)


# --- differentiable re-computation -----------------------------------------------------------------------------


#: Newton steps that polish an accepted tube or ribbon hit before it is linearised (:func:`smooth_hit`).
POLISH_STEPS = 2


@jax.custom_jvp
def _attach(exact, smooth):
    """``exact``'s value with ``smooth``'s derivative. A custom JVP rather than ``exact + (smooth -
    stop(smooth))``: the value does not depend on ``smooth``, so a call that takes no derivative never computes
    it (XLA drops it as dead code), and a non-finite ``smooth`` cannot turn the value into NaN."""
    del smooth
    return lax.stop_gradient(exact)


@_attach.defjvp
def _attach_jvp(primals, tangents):
    return _attach(*primals), tangents[1]


def _tube_system(origin, direction, power, u, t):
    """The round tube's equations ``(F, G)`` at ``(u, t)`` and their Jacobian ``d(F, G) / d(u, t)``."""
    c, dc, ddc = _evaluate(power, u)
    w = origin + t * direction - c[:3]
    value = jnp.stack([jnp.dot(w, w) - c[3] * c[3], jnp.dot(w, dc[:3]) + c[3] * dc[3]])
    f_u = -2.0 * value[1]
    f_t = 2.0 * jnp.dot(w, direction)
    g_u = -jnp.dot(dc[:3], dc[:3]) + jnp.dot(w, ddc[:3]) + dc[3] * dc[3] + c[3] * ddc[3]
    g_t = jnp.dot(direction, dc[:3])
    return value, jnp.stack([jnp.stack([f_u, f_t]), jnp.stack([g_u, g_t])])


def _solve2(jac, value):
    """The Newton step ``-jac^-1 value`` of a 2 x 2 system (0 where ``jac`` is singular)."""
    det = jac[0, 0] * jac[1, 1] - jac[0, 1] * jac[1, 0]
    inverse = jnp.stack([jnp.stack([jac[1, 1], -jac[0, 1]]), jnp.stack([-jac[1, 0], jac[0, 0]])])
    return jnp.where(det == 0, 0.0, -(inverse @ value) / jnp.where(det == 0, 1.0, det))


def _ribbon_system(origin, direction, power, u):
    """The ribbon's equation ``g(u) = p . p'`` (``p`` the part of ``C - O`` across the ray) and ``g'(u)``."""
    c, dc, ddc = _evaluate(power, u)
    dd = jnp.dot(direction, direction)

    def across(v):
        return v - jnp.dot(v, direction) / dd * direction

    rel, first = across(c[:3] - origin), across(dc[:3])
    return jnp.dot(rel, first), jnp.dot(first, first) + jnp.dot(rel, across(ddc[:3]))


def _polish_tube(origin, direction, power, u, t):
    """A few Newton steps on the tube's equations from an accepted hit (no derivatives): each is taken only
    where it moves the point by less than the radius and reduces the scaled residual, so it stays on the
    root the test found (and leaves hits that are not on the tube alone: their part ignores the result)."""

    def residual(value, u):
        c, dc, _ = _evaluate(power, u)
        r2 = c[3] * c[3]
        scale = jnp.sqrt(r2 * (jnp.dot(dc[:3], dc[:3]) + dc[3] * dc[3]))
        return jnp.abs(value[0]) / jnp.where(r2 > 0, r2, 1.0) + jnp.abs(value[1]) / jnp.where(scale > 0, scale, 1.0)

    for _ in range(POLISH_STEPS):
        value, jac = _tube_system(origin, direction, power, u, t)
        step = _solve2(jac, value)
        c, dc, _ = _evaluate(power, u)
        new_u, new_t = jnp.clip(u + step[0], 0.0, 1.0), t + step[1]
        new_value, _ = _tube_system(origin, direction, power, new_u, new_t)
        small = (jnp.abs(step[0]) * jnp.sqrt(jnp.dot(dc[:3], dc[:3])) <= jnp.abs(c[3])) & (
            jnp.abs(step[1]) * jnp.sqrt(jnp.dot(direction, direction)) <= jnp.abs(c[3])
        )
        better = small & (residual(new_value, new_u) < residual(value, u))
        u, t = jnp.where(better, new_u, u), jnp.where(better, new_t, t)
    return u, t


def _polish_ribbon(origin, direction, power, u):
    """A few Newton steps on the ribbon's equation from an accepted hit, kept like :func:`_polish_tube`'s."""
    for _ in range(POLISH_STEPS):
        g, g_prime = _ribbon_system(origin, direction, power, u)
        c, dc, _ = _evaluate(power, u)
        du = jnp.where(g_prime == 0, 0.0, -g / jnp.where(g_prime == 0, 1.0, g_prime))
        new_u = jnp.clip(u + du, 0.0, 1.0)
        new_g, _ = _ribbon_system(origin, direction, power, new_u)
        small = jnp.abs(du) * jnp.sqrt(jnp.dot(dc[:3], dc[:3])) <= jnp.abs(c[3])
        u = jnp.where(small & (jnp.abs(new_g) < jnp.abs(g)), new_u, u)
    return u


def smooth_hit(
    origin: jax.Array,
    direction: jax.Array,
    segment: jax.Array,
    part: jax.Array,
    u: jax.Array,
    distance: jax.Array,
    t_min: jax.Array | float = -np.inf,
    t_max: jax.Array | float = np.inf,
    curve_types: tuple[int, ...] = (ROUND, FLAT),
) -> tuple[jax.Array, jax.Array]:
    """``(distance, u)`` of a hit found by :func:`intersect`, with derivatives.

    Tube and ribbon hits take the implicit-function derivative of their defining equations; cap hits the
    derivative of the sphere, disk or ray-facing disk they lie on. Misses must be given a dummy segment.

    Values: a tube or ribbon hit is reported at its polished root (:data:`POLISH_STEPS` guarded Newton steps
    in the hit's space from the test's answer, which stops within its tolerance of the root: on the bench's
    fur about three times closer to the float64 reference, ``docs/curves.md``) where that root lies in
    ``[t_min, t_max]``; other hits keep the test's values. ``curve_types``: the types that can have been hit
    (static; the tube or ribbon equations of an absent type are not solved).
    """
    stop = lax.stop_gradient
    bezier = world_bezier(segment)
    power = jnp.asarray(_TO_POWER, bezier.dtype) @ bezier
    u0, t0 = stop(u), stop(distance)
    fixed = stop(origin), stop(direction), stop(power)

    # Round tube: F = |O + t d - C|^2 - r^2 = 0, G = (O + t d - C) . C' + r r' = 0, linearised at the hit
    # polished to the root (the test accepts a hit within its tolerance, where the linearisation is off).
    tube_u0, tube_t0 = tube_u, tube_t = u0, t0  # (never selected where no round curve can be hit)
    if ROUND in curve_types:
        tube_u0, tube_t0 = _polish_tube(*fixed, u0, t0)
        value, jac = _tube_system(origin, direction, power, tube_u0, tube_t0)
        step = _solve2(stop(jac), value)
        tube_u, tube_t = tube_u0 + step[0], tube_t0 + step[1]

    # Flat ribbon: g(u) = p . p' = 0 with p the part of C - O across the ray; t = (C(u) - O) . d / |d|^2.
    dd = jnp.dot(direction, direction)
    ribbon_u0 = ribbon_u = u0  # (never selected where no flat curve can be hit)
    ribbon_t0 = ribbon_t = t0
    if FLAT in curve_types:
        ribbon_u0 = _polish_ribbon(*fixed, u0)
        g, g_prime = _ribbon_system(origin, direction, power, ribbon_u0)
        g_prime = stop(g_prime)
        ribbon_u = ribbon_u0 - g / jnp.where(g_prime == 0, 1.0, g_prime)
        along = lambda c: jnp.dot(c[:3] - origin, direction) / dd  # noqa: E731
        ribbon_t = along(_evaluate(power, ribbon_u)[0])
        ribbon_t0 = along(_evaluate(power, ribbon_u0)[0])  # the polished root's distance (used as a value only)

    # Caps at the end u0 (0 or 1): sphere entry, end disk, ray-facing disk.
    end = jnp.where(u0 > 0.5, bezier[3], bezier[0])
    d_end = jnp.where(u0 > 0.5, 3.0 * (bezier[3] - bezier[2]), 3.0 * (bezier[1] - bezier[0]))
    rel_end = end[:3] - origin
    b = jnp.dot(direction, rel_end)
    # Entry into the end sphere, b / |d|^2 - sqrt((r^2 - |p|^2) / |d|^2) with p the centre's offset across the
    # ray (not b^2 - |d|^2 (|rel|^2 - r^2): its cancellation for a far sphere costs float32 gradients digits).
    across_end = rel_end - b / dd * direction
    depth = jnp.maximum(end[3] * end[3] - jnp.dot(across_end, across_end), 0.0) / dd
    sphere_t = b / dd - jnp.sqrt(depth + jnp.where(depth == 0, 1e-30, 0.0))
    # An end tangent of zero length (b1 = b0, or b3 = b2) is a valid curve: the square roots below are taken of
    # 1 there, since the derivative of sqrt at 0 is infinite and the zero cotangent of an unselected branch
    # times it would make every gradient of the segment NaN. The offset is the forward test's (clipped to the
    # radius, see _disk).
    speed2 = jnp.dot(d_end[:3], d_end[:3])
    moving = speed2 > 0
    speed = jnp.sqrt(jnp.where(moving, speed2, 1.0))
    axis = jnp.where(moving, d_end[:3], bezier[3, :3] - bezier[0, :3])
    axis2 = jnp.dot(axis, axis)
    axis = axis / jnp.sqrt(jnp.where(axis2 > 0, axis2, 1.0))
    radius = jnp.abs(end[3])
    offset = jnp.where(
        moving, jnp.clip(-end[3] * d_end[3] / speed, -radius, radius), -jnp.sign(end[3] * d_end[3]) * radius
    )
    denominator = jnp.dot(direction, axis)
    disk_t = (jnp.dot(rel_end, axis) + offset) / jnp.where(denominator == 0, 1.0, denominator)
    facing_t = b / dd

    t_out = jnp.select(
        [part == PART_TUBE, part == PART_RIBBON, part == PART_SPHERE, part == PART_DISK],
        [tube_t, ribbon_t, sphere_t, disk_t],
        facing_t,
    )
    on_curve = [part == PART_TUBE, part == PART_RIBBON]
    u_out = jnp.select(on_curve, [tube_u, ribbon_u], u0)
    # The values: the polished root of a tube or ribbon hit where it lies in the ray's interval, else the test's.
    polished_t = stop(jnp.select(on_curve, [tube_t0, ribbon_t0], t0))
    polished_u = jnp.select(on_curve, [tube_u0, ribbon_u0], u0)
    inside = (polished_t >= t_min) & (polished_t <= t_max)
    value_t, value_u = jnp.where(inside, polished_t, t0), jnp.where(inside, polished_u, u0)
    return _attach(value_t, t_out), _attach(value_u, u_out)
