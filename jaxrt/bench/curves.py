"""``python -m jaxrt.bench.curves``: ray/curve speed against error, and against triangle tubes.

Two parts:

* A float64 NumPy **reference** for rays against curve segments (:func:`reference_hits`), independent of the
  library's method: it evaluates each basis from its own polynomial form (no Bezier conversion), finds every
  closest approach of the ray to the centre line by bisection on a dense grid, and the local minima of the
  sphere-entry distance ``t_enter(u)`` inside each hit interval by bisection on its derivative, all in
  double precision. It applies the same shape rules as the library (swept-sphere tube, ray-facing ribbon,
  end caps, joints) and flags rays whose answer is undecidable within a band (near-tangent rays, hits at the
  end parameter of open tubes, sign decisions at joints), where any answer is accepted.
* The **bench** (:func:`main`): for hair assets (TressFX ponytail and bear fur when the data folder has them,
  a procedural hair ball otherwise), Mrays/s and error against the reference for each setting of the curve
  test's knobs, and for the same strands tessellated into triangle tubes at several rates (memory per
  segment included): the table that decides the defaults.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

__all__ = [
    "main",
    "hair_ball",
    "tessellate",
    "camera_rays",
    "reference_scene",
    "ReferenceHits",
    "reference_hits",
    "reference_nearest",
    "host_segments",
    "HostSegments",
]

# Power-basis matrices, rows = coefficient of u^k, columns = the segment's control points: the textbook
# polynomial forms of each basis (deliberately not the Bezier conversion the library uses).
_POWER = {
    ("linear", 2): np.array([[1, 0], [-1, 1]], np.float64),
    ("bezier", 3): np.array([[1, 0, 0], [-2, 2, 0], [1, -2, 1]], np.float64),
    ("bezier", 4): np.array([[1, 0, 0, 0], [-3, 3, 0, 0], [3, -6, 3, 0], [-1, 3, -3, 1]], np.float64),
    ("catmull_rom", 4): 0.5 * np.array([[0, 2, 0, 0], [-1, 0, 1, 0], [2, -5, 4, -1], [-1, 3, -3, 1]], np.float64),
    ("bspline", 4): np.array([[1, 4, 1, 0], [-3, 0, 3, 0], [3, -6, 3, 0], [-1, 3, -3, 1]], np.float64) / 6,
    ("bspline", 3): 0.5 * np.array([[1, 1, 0], [-2, 2, 0], [1, -2, 1]], np.float64),
}
_GRID = 512
#: The grid reaches this far past both ends, so that minima just outside a segment are seen (and flagged).
_EXTEND = 1e-3
#: Curve-parameter slack of the library's in-segment test, plus its float32 rounding.
_U_SLACK = 1e-5
#: Flat ribbons whose tangent is within this sine of the ray direction are seen end-on: undecidable.
END_ON_SINE = 0.1
_BISECT = 64


class HostSegments(NamedTuple):
    """A curve geometry's segments on the host in float64, in their own basis."""

    points: np.ndarray  # (S, n, 4) control points (x, y, z, radius) of each segment
    previous: np.ndarray  # (S, n, 4) control points of the predecessor (the segment's own where none)
    has_previous: np.ndarray  # (S,) bool
    has_next: np.ndarray  # (S,) bool
    basis: str
    count: int
    curve_type: str
    end_caps: str


def host_segments(geometry) -> HostSegments:
    """The segments of a ``jaxrt.CurveGeometry`` as float64 arrays, with the chain links found on the host."""
    points = np.concatenate(
        [np.asarray(geometry.control_points, np.float64), np.asarray(geometry.radii, np.float64)[:, None]], axis=1
    )
    first = np.asarray(geometry.indices, np.int64)
    n = geometry.control_point_count
    basis = geometry.basis.value
    step = n - 1 if basis in ("bezier", "linear") else 1
    segments = points[first[:, None] + np.arange(n)]
    lookup = {int(f): i for i, f in enumerate(first)}
    prev_index = np.array([lookup.get(int(f) - step, -1) for f in first])
    has_next = np.array([int(f) + step in lookup for f in first])
    previous = np.where((prev_index >= 0)[:, None, None], segments[np.maximum(prev_index, 0)], segments)
    return HostSegments(
        segments, previous, prev_index >= 0, has_next, basis, n, geometry.curve_type.value, geometry.end_caps.value
    )


def _frame(direction: np.ndarray) -> np.ndarray:
    """``(R, 3, 3)`` orthonormal frames whose last row is the unit direction."""
    d = direction / np.linalg.norm(direction, axis=-1, keepdims=True)
    helper = np.where((np.abs(d[:, 0]) < 0.6)[:, None], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    e1 = np.cross(helper, d)
    e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
    e2 = np.cross(d, e1)
    return np.stack([e1, e2, d], axis=1)


class _Curves:
    """Ray-space polynomials of (ray, segment) pairs: value and derivatives at any ``u``."""

    def __init__(self, coefficients: np.ndarray):
        self.c = coefficients  # (N, degree + 1, 4) power basis, ray space

    def __call__(self, pair: np.ndarray, u: np.ndarray, order: int = 0) -> np.ndarray:
        """``(..., 4)`` derivative ``order`` at ``u`` (same shape as ``pair``)."""
        c = self.c[pair]
        degree = c.shape[-2] - 1
        out = np.zeros((*u.shape, 4))
        for k in range(order, degree + 1):
            factor = np.prod(np.arange(k - order + 1, k + 1)) if order else 1.0
            out += factor * c[..., k, :] * (u ** (k - order))[..., None]
        return out


def _bisect(fn, pair, lo, hi):
    """Roots of ``fn(pair, u)`` in brackets ``[lo, hi]`` whose ends have opposite signs."""
    f_lo = fn(pair, lo)
    for _ in range(_BISECT):
        mid = 0.5 * (lo + hi)
        f_mid = fn(pair, mid)
        left = np.sign(f_mid) == np.sign(f_lo)
        lo = np.where(left, mid, lo)
        f_lo = np.where(left, f_mid, f_lo)
        hi = np.where(left, hi, mid)
    return 0.5 * (lo + hi)


class ReferenceHits(NamedTuple):
    """Per (ray, segment) pair: the reference answer and whether it is decidable."""

    hit: np.ndarray
    distance: np.ndarray  # ray parameter; inf on a miss
    u: np.ndarray
    ambiguous: np.ndarray  # some decision is within the band: any answer is accepted
    clearance: np.ndarray  # smallest | |p| - r | over closest approaches (distance to tangency)


def reference_hits(
    origin: np.ndarray,
    direction: np.ndarray,
    t_min: np.ndarray,
    t_max: np.ndarray,
    segments: HostSegments,
    ray_index: np.ndarray,
    segment_index: np.ndarray,
    *,
    band: float | np.ndarray = 0.0,
) -> ReferenceHits:
    """Float64 reference for (ray, segment) pairs.

    Args:
      origin, direction, t_min, t_max: ``(R, 3)``, ``(R, 3)``, ``(R,)``, ``(R,)`` rays.
      segments: from :func:`host_segments`.
      ray_index, segment_index: ``(N,)`` the pairs to test.
      band: absolute length (scalar or per pair): decisions closer than this to flipping are ambiguous.

    Returns:
      :class:`ReferenceHits` per pair.
    """
    origin = np.asarray(origin, np.float64)[ray_index]
    direction = np.asarray(direction, np.float64)[ray_index]
    length = np.linalg.norm(direction, axis=-1)
    lo = np.asarray(t_min, np.float64)[ray_index] * length
    hi = np.asarray(t_max, np.float64)[ray_index] * length
    band = np.broadcast_to(np.asarray(band, np.float64), ray_index.shape)
    frame = _frame(direction)
    power = _POWER[(segments.basis, segments.count)]

    def to_ray_space(points):
        rel = points[..., :3] - origin[:, None, :]
        local = np.einsum("nij,npj->npi", frame, rel)
        return np.einsum("kp,npc->nkc", power, np.concatenate([local, points[..., 3:]], axis=-1))

    curve = _Curves(to_ray_space(segments.points[segment_index]))
    before = _Curves(to_ray_space(segments.previous[segment_index]))
    n = ray_index.shape[0]
    pair = np.arange(n)
    caps = segments.end_caps
    has_previous = segments.has_previous[segment_index]
    has_next = segments.has_next[segment_index]

    candidates_t, candidates_u, candidates_ok = [], [], []
    ambiguous = np.zeros(n, bool)
    grid = np.linspace(-_EXTEND, 1.0 + _EXTEND, _GRID + 1)
    grid_pair = np.repeat(pair[:, None], grid.size, axis=1)
    grid_u = np.broadcast_to(grid, grid_pair.shape)
    value = curve(grid_pair, grid_u)
    first = curve(grid_pair, grid_u, 1)

    def add(p, t, u, ok):
        full_t = np.full(n, np.inf)
        full_u = np.zeros(n)
        full_ok = np.zeros(n, bool)
        np.minimum.at(full_t, p[ok], t[ok])
        take = ok & (t <= full_t[p])
        full_u[p[take]] = u[take]
        full_ok[p[ok]] = True
        candidates_t.append(full_t)
        candidates_u.append(full_u)
        candidates_ok.append(full_ok)

    def radius(v):
        return np.abs(v[..., 3])

    def ends():
        start, end = curve(pair, np.zeros(n)), curve(pair, np.ones(n))
        d_start, d_end = curve(pair, np.zeros(n), 1), curve(pair, np.ones(n), 1)
        d_prev = before(pair, np.ones(n), 1)
        return start, end, d_start, d_end, d_prev

    clearance = np.full(n, np.inf)
    if segments.curve_type == "round":
        # Closest approaches: minima of m(u) = |p|^2 - r^2, roots of h = m'/2 from - to +.
        def h(p, u):
            v, d = curve(p, u), curve(p, u, 1)
            return v[..., 0] * d[..., 0] + v[..., 1] * d[..., 1] - v[..., 3] * d[..., 3]

        def m(p, u):
            v = curve(p, u)
            return v[..., 0] ** 2 + v[..., 1] ** 2 - v[..., 3] ** 2

        hv = value[..., 0] * first[..., 0] + value[..., 1] * first[..., 1] - value[..., 3] * first[..., 3]
        mv = value[..., 0] ** 2 + value[..., 1] ** 2 - value[..., 3] ** 2
        rise = (hv[:, :-1] < 0) & (hv[:, 1:] >= 0)
        p_idx, j_idx = np.nonzero(rise)
        u_c = _bisect(h, p_idx, grid[j_idx], grid[j_idx + 1])
        # Ends where m is increasing into the segment are minima too.
        p_idx = np.concatenate([p_idx, pair[hv[:, 0] >= 0], pair[hv[:, -1] <= 0]])
        u_c = np.concatenate(
            [u_c, np.full(int((hv[:, 0] >= 0).sum()), grid[0]), np.full(int((hv[:, -1] <= 0).sum()), grid[-1])]
        )
        j_idx = np.clip(np.floor((u_c - grid[0]) / (grid[1] - grid[0])).astype(int), 0, _GRID - 1)
        v_c = curve(p_idx, u_c)
        gap = np.sqrt(v_c[:, 0] ** 2 + v_c[:, 1] ** 2) - radius(v_c)
        np.minimum.at(clearance, p_idx, np.abs(gap))
        inside = gap <= 0
        p_idx, u_c, j_idx = p_idx[inside], u_c[inside], j_idx[inside]
        # The hit interval [a, b] around each closest approach, from the grid and bisection on m.
        positive = mv > 0
        index = np.arange(grid.size)
        last_pos = np.maximum.accumulate(np.where(positive, index, -1), axis=1)
        next_pos = np.minimum.accumulate(np.where(positive, index, grid.size)[:, ::-1], axis=1)[:, ::-1]
        left = last_pos[p_idx, j_idx]
        right = next_pos[p_idx, np.minimum(j_idx + 1, _GRID)]
        a = np.where(left >= 0, _bisect(m, p_idx, grid[np.maximum(left, 0)], u_c), grid[0])
        b = np.where(right <= _GRID, _bisect(m, p_idx, u_c, grid[np.minimum(right, _GRID)]), grid[-1])

        def slope(p, u):  # t_enter'(u) * sqrt(-m) (sign-carrying, finite at the interval ends)
            v, d = curve(p, u), curve(p, u, 1)
            root = np.sqrt(np.maximum(-(v[..., 0] ** 2 + v[..., 1] ** 2 - v[..., 3] ** 2), 0.0))
            return d[..., 2] * root + (v[..., 0] * d[..., 0] + v[..., 1] * d[..., 1] - v[..., 3] * d[..., 3])

        def t_enter(p, u):
            v = curve(p, u)
            return v[..., 2] - np.sqrt(np.maximum(v[..., 3] ** 2 - v[..., 0] ** 2 - v[..., 1] ** 2, 0.0))

        k = 128
        # Sample [a, b] including its ends: the multiplied slope is finite there (it is h, - at a, + at b).
        sub = a[:, None] + (b - a)[:, None] * np.linspace(0.0, 1.0, k)[None, :]
        sub_p = np.repeat(p_idx[:, None], k, axis=1)
        sv = slope(sub_p, sub)
        fall = (sv[:, :-1] < 0) & (sv[:, 1:] >= 0)
        ci, si = np.nonzero(fall)
        u_min = _bisect(slope, p_idx[ci], sub[ci, si], sub[ci, si + 1])
        tube_p = p_idx[ci]
        t_tube = t_enter(tube_p, u_min)
        # The band: a local minimum within band of the segment's ends may flip to the neighbour's side.
        speed = np.linalg.norm(curve(tube_p, u_min, 1)[:, :3], axis=-1)
        slack = band[tube_p] / np.maximum(speed, 1e-300) + _U_SLACK
        near_end = np.minimum(np.abs(u_min), np.abs(1 - u_min)) <= slack
        ok = (t_tube >= lo[tube_p]) & (t_tube <= hi[tube_p])
        add(tube_p, t_tube, u_min, ok & ~near_end & (u_min >= 0) & (u_min <= 1))
        ambiguous[tube_p[ok & near_end]] = True
        within_t = (np.abs(t_tube - lo[tube_p]) <= band[tube_p]) | (np.abs(t_tube - hi[tube_p]) <= band[tube_p])
        ambiguous[tube_p[within_t]] = True

        # End spheres and disks.
        start, end, d_start, d_end, d_prev = ends()

        def sphere(v):
            depth = radius(v) ** 2 - v[:, 0] ** 2 - v[:, 1] ** 2
            return depth >= 0, v[:, 2] - np.sqrt(np.maximum(depth, 0.0)), depth

        def enter_slope(v, d):
            root = np.sqrt(np.maximum(radius(v) ** 2 - v[:, 0] ** 2 - v[:, 1] ** 2, 0.0))
            return d[:, 2] * root - (v[:, 3] * d[:, 3] - v[:, 0] * d[:, 0] - v[:, 1] * d[:, 1])

        s_ok, s_t, s_depth = sphere(start)
        e_ok, e_t, e_depth = sphere(end)
        own_start, own_end, prev_start = (
            enter_slope(start, d_start),
            enter_slope(end, d_end),
            enter_slope(start, d_prev),
        )
        scale_start = radius(start) * (np.linalg.norm(d_start, axis=-1) + np.linalg.norm(d_prev, axis=-1))
        scale_end = radius(end) * np.linalg.norm(d_end, axis=-1)
        start_accept = has_previous & (prev_start <= 0)
        end_accept = np.zeros(n, bool)
        start_decisive = np.abs(own_start) > band * scale_start / np.maximum(radius(start), 1e-300)
        start_decisive &= ~has_previous | (np.abs(prev_start) > band * scale_start / np.maximum(radius(start), 1e-300))
        end_decisive = np.abs(own_end) > band * scale_end / np.maximum(radius(end), 1e-300)
        if caps == "sphere":
            start_accept |= ~has_previous
            end_accept |= ~has_next
        s_hit = s_ok & start_accept & (own_start >= 0)
        e_hit = e_ok & end_accept & (own_end <= 0)
        add(pair, s_t, np.zeros(n), s_hit & (s_t >= lo) & (s_t <= hi))
        add(pair, e_t, np.ones(n), e_hit & (e_t >= lo) & (e_t <= hi))
        # A nearly stationary t_enter at an end: the tube's minimum may lie on either side of it.
        ambiguous |= s_ok & ~start_decisive
        ambiguous |= e_ok & ~end_decisive
        ambiguous |= (np.abs(s_depth) <= 2 * band * radius(start)) & (start_accept | (caps != "none"))
        ambiguous |= (np.abs(e_depth) <= 2 * band * radius(end)) & (end_accept | (caps != "none"))
        if caps == "disk":
            for which, v, d, free, sign in (
                (0.0, start, d_start, ~has_previous, 1.0),
                (1.0, end, d_end, ~has_next, -1.0),
            ):
                speed = np.linalg.norm(d[:, :3], axis=-1)
                axis = d[:, :3] / np.maximum(speed, 1e-300)[:, None]
                offset = np.clip(-v[:, 3] * d[:, 3] / np.maximum(speed, 1e-300), -radius(v), radius(v))
                centre = v[:, :3] + offset[:, None] * axis
                t = np.einsum("ni,ni->n", centre, axis) / np.where(axis[:, 2] == 0, 1.0, axis[:, 2])
                rim2 = radius(v) ** 2 - offset**2
                dist2 = np.sum((np.stack([np.zeros(n), np.zeros(n), t], axis=1) - centre) ** 2, axis=-1)
                ok = free & (sign * axis[:, 2] > 0) & (dist2 <= rim2) & (t >= lo) & (t <= hi)
                add(pair, t, np.full(n, which), ok)
                rim = np.abs(np.sqrt(dist2) - np.sqrt(np.maximum(rim2, 0))) <= band
                ambiguous |= free & rim
    else:
        # Ribbon: roots of g = p . p' (the ray on the cross-section's line), hit where |p| <= r, t = z.
        def g(p, u):
            v, d = curve(p, u), curve(p, u, 1)
            return v[..., 0] * d[..., 0] + v[..., 1] * d[..., 1]

        gv = value[..., 0] * first[..., 0] + value[..., 1] * first[..., 1]
        change = np.sign(gv[:, :-1]) != np.sign(gv[:, 1:])
        p_idx, j_idx = np.nonzero(change)
        u_r = _bisect(g, p_idx, grid[j_idx], grid[j_idx + 1])
        v = curve(p_idx, u_r)
        gap = np.sqrt(v[:, 0] ** 2 + v[:, 1] ** 2) - radius(v)
        np.minimum.at(clearance, p_idx, np.abs(gap))
        tangent = curve(p_idx, u_r, 1)
        speed = np.linalg.norm(tangent[:, :2], axis=-1)
        slack = band[p_idx] / np.maximum(speed, 1e-300) + _U_SLACK
        near_end = np.minimum(np.abs(u_r), np.abs(1 - u_r)) <= slack
        ok = (gap <= 0) & (v[:, 2] >= lo[p_idx]) & (v[:, 2] <= hi[p_idx])
        add(p_idx, v[:, 2], u_r, ok & ~near_end & (u_r >= 0) & (u_r <= 1))
        ambiguous[p_idx[ok & near_end]] = True
        # A ribbon seen end-on (tangent within END_ON_SINE of the ray) has no well-defined cross-section line.
        end_on = speed < END_ON_SINE * np.linalg.norm(tangent[:, :3], axis=-1)
        ambiguous[p_idx[(gap <= band[p_idx]) & end_on]] = True
        start, end, d_start, d_end, d_prev = ends()
        for which, e, d, free, sign in ((0.0, start, d_start, ~has_previous, 1.0), (1.0, end, d_end, ~has_next, -1.0)):
            inside = e[:, 0] ** 2 + e[:, 1] ** 2 <= e[:, 3] ** 2
            own = sign * (e[:, 0] * d[:, 0] + e[:, 1] * d[:, 1]) >= 0
            accept = np.zeros(n, bool)
            if which == 0.0:
                accept |= has_previous & ((e[:, 0] * d_prev[:, 0] + e[:, 1] * d_prev[:, 1]) <= 0)
            if caps != "none":
                accept |= free
            if caps == "sphere":
                t = np.where(
                    free, e[:, 2] - np.sqrt(np.maximum(e[:, 3] ** 2 - e[:, 0] ** 2 - e[:, 1] ** 2, 0)), e[:, 2]
                )
            else:
                t = e[:, 2]
            add(pair, t, np.full(n, which), inside & own & accept & (t >= lo) & (t <= hi))
            rim = np.abs(np.sqrt(e[:, 0] ** 2 + e[:, 1] ** 2) - radius(e)) <= band
            ambiguous |= rim & (accept | has_previous)

    ambiguous |= clearance <= band
    t_all = np.stack(candidates_t) if candidates_t else np.full((1, n), np.inf)
    u_all = np.stack(candidates_u) if candidates_u else np.zeros((1, n))
    best = np.argmin(t_all, axis=0)
    t = t_all[best, pair]
    hit = np.isfinite(t)
    u = np.where(hit, u_all[best, pair], 0.0)
    return ReferenceHits(hit, np.where(hit, t / length, np.inf), u, ambiguous, clearance)


def reference_nearest(origin, direction, t_min, t_max, segments: HostSegments, *, band=0.0, candidates=None):
    """Nearest reference hit of every ray over all segments (or over ``candidates``: a list of pair arrays).

    Returns ``(hit, distance, segment, u, ambiguous)`` per ray; ``ambiguous`` also marks rays whose two
    nearest hits (on different segments) are within ``band`` of each other (either id is right).
    """
    r = np.asarray(origin).shape[0]
    s = segments.points.shape[0]
    if candidates is None:
        ray_index = np.repeat(np.arange(r), s)
        segment_index = np.tile(np.arange(s), r)
    else:
        ray_index, segment_index = candidates
    out = reference_hits(origin, direction, t_min, t_max, segments, ray_index, segment_index, band=band)
    distance = np.full(r, np.inf)
    np.minimum.at(distance, ray_index, out.distance)
    best = out.hit & (out.distance == distance[ray_index])
    segment = np.full(r, -1)
    u = np.zeros(r)
    segment[ray_index[best]] = segment_index[best]
    u[ray_index[best]] = out.u[best]
    ambiguous = np.zeros(r, bool)
    np.logical_or.at(ambiguous, ray_index, out.ambiguous)
    length = np.linalg.norm(np.asarray(direction, np.float64), axis=-1)
    close = out.hit & ~best & (np.abs(out.distance - distance[ray_index]) * length[ray_index] <= np.max(band))
    np.logical_or.at(ambiguous, ray_index, close)
    return np.isfinite(distance), distance, segment, u, ambiguous


# --- the bench -------------------------------------------------------------------------------------------------

#: Curve-test settings measured: ``(pieces, iterations)``; iterations 0 is the chord approximation.
CURVE_SETTINGS = ((4, 0), (16, 0), (4, 2), (8, 3), (16, 4))
#: Triangle tubes: ``(sides, rings per segment)``.
TUBE_RATES = ((4, 1), (6, 2), (8, 4))
_DEFAULTS = dict(rays=1 << 16, reference_rays=256, repeats=3, strands=None)
_QUICK = dict(rays=1 << 12, reference_rays=256, repeats=1, strands=600)
SCENES = ("ponytail", "bear", "ball")
_PONYTAIL = ("back.tfx", "front_top.tfx", "side.tfx", "tail.tfx")


class HairScene(NamedTuple):
    name: str
    geometry: object  # jaxrt.CurveGeometry
    width: float
    source: str


def hair_ball(strands: int = 2000, points: int = 8, *, seed: int = 0):
    """A procedural hair ball: curly strands growing out of a unit sphere (``HairCurves``)."""
    from jaxrt._src.io.hair import HairStrands, strands_to_curves

    rng = np.random.default_rng(seed)
    root = rng.normal(size=(strands, 3))
    root /= np.linalg.norm(root, axis=1, keepdims=True)
    direction = root + 0.4 * rng.normal(size=(strands, 3))
    polyline = [root]
    for _ in range(points - 1):
        direction = direction + 0.5 * rng.normal(size=(strands, 3))
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        polyline.append(polyline[-1] + 0.08 * direction)
    pts = np.stack(polyline, axis=1).reshape(-1, 3).astype(np.float32)
    return strands_to_curves(HairStrands(pts, np.full(strands, points), None), width=0.008)


def load_scene(name: str, data_dir, strands: int | None, seed: int = 0) -> HairScene | None:
    """A bench scene, or ``None`` when its files are not in ``data_dir``."""
    from pathlib import Path

    from jaxrt._src.io.hair import HairStrands, read_tfx, strands_to_curves

    if name == "ball":
        curves = hair_ball(strands or 2000, seed=seed)
        return HairScene(name, curves.geometry(), 0.008, "procedural")
    files = [f"tressfx-hair-ponytail/{f}" for f in _PONYTAIL] if name == "ponytail" else ["tressfx-fur-bear/bear.tfx"]
    if data_dir is None or not all((Path(data_dir) / f).is_file() for f in files):
        return None
    parts = [read_tfx(Path(data_dir) / f) for f in files]
    points = np.concatenate([p.points for p in parts])
    counts = np.concatenate([p.counts for p in parts])
    if strands is not None and strands < len(counts):  # an even subset of the strands
        keep = np.linspace(0, len(counts) - 1, strands).astype(int)
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        points = np.concatenate([points[starts[k] : starts[k] + counts[k]] for k in keep])
        counts = counts[keep]
    # Strand width: a fifth of the mean distance between neighbouring points (TressFX stores none).
    spacing = float(np.median(np.linalg.norm(np.diff(points[: counts[0]], axis=0), axis=1)))
    width = 0.2 * spacing
    curves = strands_to_curves(HairStrands(points, counts, None), width=width)
    return HairScene(name, curves.geometry(), width, ", ".join(files))


def camera_rays(geometry, count: int, *, seed: int = 0):
    """Pinhole rays over the hair's bounding box, from the front and a little above (``(origin, direction)``)."""
    points = np.asarray(geometry.control_points, np.float64)
    lower, upper = points.min(0), points.max(0)
    centre, size = 0.5 * (lower + upper), float(np.linalg.norm(upper - lower))
    eye = centre + size * np.array([0.3, 0.4, 1.2])
    forward = centre - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    side = int(np.sqrt(count))
    s = (np.arange(side) + 0.5) / side * 2 - 1
    x, y = np.meshgrid(s, -s)
    half = 0.5 * size / np.linalg.norm(centre - eye) * 1.1
    direction = forward + half * (x.reshape(-1, 1) * right + y.reshape(-1, 1) * up)
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    origin = np.broadcast_to(eye, direction.shape)
    return origin.astype(np.float32), direction.astype(np.float32)


def _candidates(origin, direction, segments: HostSegments):
    """(ray, segment) pairs whose float64 segment box the ray enters (the reference's broad phase)."""
    from jaxrt._src.curves import CurveBasis, bezier_matrix

    matrix = bezier_matrix(CurveBasis.coerce(segments.basis), segments.count)
    bezier = np.einsum("ij,sjk->sik", matrix, segments.points)
    reach = np.abs(bezier[..., 3]).max(axis=1, keepdims=True) * (1 + 1e-6)
    lower = bezier[..., :3].min(axis=1) - reach
    upper = bezier[..., :3].max(axis=1) + reach
    rays, segs = [], []
    d = np.asarray(direction, np.float64)
    inv = 1.0 / np.where(d == 0, 1e-300, d)
    o = np.asarray(origin, np.float64)
    chunk = max(1, (1 << 22) // max(len(lower), 1))  # rays per pass: a few tens of MB of temporaries
    for start in range(0, len(o), chunk):
        oo, ii = o[start : start + chunk, None], inv[start : start + chunk, None]
        t0, t1 = (lower[None] - oo) * ii, (upper[None] - oo) * ii
        near = np.minimum(t0, t1).max(axis=-1)
        far = np.maximum(t0, t1).min(axis=-1)
        r, s = np.nonzero((near <= far) & (far >= 0))
        rays.append(r + start)
        segs.append(s)
    return np.concatenate(rays), np.concatenate(segs)


def reference_scene(origin, direction, geometry, *, band: float, chunk: int = 8192):
    """Float64 nearest hits (``hit, distance, ambiguous``) of rays against a curve geometry."""
    segments = host_segments(geometry)
    ray_index, segment_index = _candidates(origin, direction, segments)
    r = len(origin)
    distance = np.full(r, np.inf)
    ambiguous = np.zeros(r, bool)
    t_min, t_max = np.zeros(r), np.full(r, np.inf)
    for start in range(0, len(ray_index), chunk):
        ri, si = ray_index[start : start + chunk], segment_index[start : start + chunk]
        out = reference_hits(origin, direction, t_min, t_max, segments, ri, si, band=band)
        np.minimum.at(distance, ri, out.distance)
        np.logical_or.at(ambiguous, ri, out.ambiguous)
    return np.isfinite(distance), distance, ambiguous


def tessellate(geometry, sides: int, rings: int):
    """The segments as triangle tubes: ``rings`` pieces along each segment, ``sides`` around (open ends)."""
    from jaxrt._src.curves import pack_segments
    from jaxrt._src.primitives.curve import world_bezier

    segments, _ = pack_segments(geometry)
    bezier = np.asarray(world_bezier(segments), np.float64)
    u = np.linspace(0.0, 1.0, rings + 1)
    w = np.stack([(1 - u) ** 3, 3 * u * (1 - u) ** 2, 3 * u**2 * (1 - u), u**3], axis=1)
    dw = np.stack([-3 * (1 - u) ** 2, 3 * (1 - u) ** 2 - 6 * u * (1 - u), 6 * u * (1 - u) - 3 * u**2, 3 * u**2], 1)
    centre = np.einsum("uk,skc->suc", w, bezier)
    tangent = np.einsum("uk,skc->suc", dw, bezier[..., :3])
    tangent /= np.maximum(np.linalg.norm(tangent, axis=-1, keepdims=True), 1e-30)
    helper = np.where((np.abs(tangent[..., :1]) < 0.6), [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    normal = np.cross(tangent, helper)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    binormal = np.cross(tangent, normal)
    angle = 2 * np.pi * np.arange(sides) / sides
    ring = centre[..., None, :3] + np.abs(centre[..., 3])[..., None, None] * (
        np.cos(angle)[:, None] * normal[..., None, :] + np.sin(angle)[:, None] * binormal[..., None, :]
    )  # (S, rings + 1, sides, 3)
    a, b = ring[:, :-1], ring[:, 1:]
    a2, b2 = np.roll(a, -1, axis=2), np.roll(b, -1, axis=2)
    quads = np.stack([np.stack([a, b, b2], axis=-2), np.stack([a, b2, a2], axis=-2)], axis=3)
    return quads.reshape(-1, 3, 3).astype(np.float32)


def _structure_bytes(structure) -> int:
    return int(sum(np.asarray(leaf).nbytes for leaf in jax_leaves(structure)))


def jax_leaves(tree):
    import jax

    return jax.tree_util.tree_leaves(tree)


def _errors(hit, distance, ref_hit, ref_distance, ambiguous, length, radius):
    decided = ~ambiguous
    mismatch = decided & (hit != ref_hit)
    both = decided & hit & ref_hit
    error = np.abs(distance[both].astype(np.float64) - ref_distance[both]) * length[both] / radius
    pick = lambda q: float(np.percentile(error, q)) if error.size else 0.0  # noqa: E731
    return dict(
        decided_rays=int(decided.sum()),
        mismatches=int(mismatch.sum()),
        mismatch_fraction=float(mismatch.sum() / max(decided.sum(), 1)),
        error_median=pick(50),
        error_p99=pick(99),
        error_max=float(error.max()) if error.size else 0.0,
    )


def bench_scene(scene: HairScene, config: dict, *, seed: int = 0, log=print) -> dict:
    """Every curve setting and tube rate on one scene: speed, error against the reference, memory."""
    import jax
    import jax.numpy as jnp

    import jaxrt as rt
    from jaxrt.bench.timing import timed

    geometry = scene.geometry
    radius = 0.5 * scene.width
    origin, direction = camera_rays(geometry, config["rays"], seed=seed)
    rays = rt.Ray(jnp.asarray(origin), jnp.asarray(direction))
    # Reference rays: an even sample of the rays that enter some segment's box, drawn from an even sample of
    # four times as many rays of the image (the rest of the image misses the hair anyway).
    start = time.perf_counter()
    want = min(config["reference_rays"], len(origin))
    pool = np.linspace(0, len(origin) - 1, min(4 * want, len(origin))).astype(int)
    near = pool[np.unique(_candidates(origin[pool], direction[pool], host_segments(geometry))[0])]
    near = near if len(near) else pool
    pick = near[np.linspace(0, len(near) - 1, min(want, len(near))).astype(int)]
    ref_hit, ref_distance, ambiguous = reference_scene(origin[pick], direction[pick], geometry, band=1e-2 * radius)
    reference_s = time.perf_counter() - start
    length = np.linalg.norm(direction[pick], axis=1).astype(np.float64)
    out = dict(
        scene=scene.name,
        source=scene.source,
        segments=geometry.primitive_count,
        radius=radius,
        rays=len(origin),
        reference_rays=len(pick),
        reference_hit_fraction=float(ref_hit.mean()),
        reference_s=reference_s,
        rows=[],
    )
    log(f"{scene.name}: {geometry.primitive_count} segments, radius {radius:.4g}, {len(origin)} rays "
        f"({len(pick)} checked, reference {reference_s:.1f} s, {ref_hit.mean():.0%} hit)")  # fmt: skip

    def measure(method, setting, structure, intersector, segments, same_as=None):
        timing, result = timed(lambda: intersector.intersect(rays, structure).distance, config["repeats"])
        full = np.asarray(result)
        distance = full[pick]
        row = dict(
            method=method,
            setting=setting,
            mrays_s=len(origin) / timing.median_s / 1e6,
            compile_s=timing.compile_s,
            bytes_per_segment=_structure_bytes(structure) / segments,
            **_errors(np.isfinite(distance), distance, ref_hit, ref_distance, ambiguous, length, radius),
        )
        if same_as is not None:  # every distance bit for bit against an earlier row's
            row["bitwise_equal"] = bool(np.array_equal(full.view(np.uint32), same_as.view(np.uint32)))
        out["rows"].append(row)
        log(_row_text(row))
        return row, full

    build = jax.jit(rt.build_primitive_structure)
    structure = build(geometry)
    batches = config.get("curve_batch") or (None,)
    for pieces, iterations in config["settings"]:
        options = rt.CurveOptions(pieces=pieces, iterations=iterations)
        name = "chord" if iterations == 0 else "newton"
        first = None
        for batch in batches:
            suffix = "" if batch is None else f", batch {batch}"
            with _kernel_curve_batch(batch):
                _, full = measure(
                    f"curve {name}",
                    f"{pieces} pieces, {iterations} it{suffix}",
                    structure,
                    rt.Intersector(curve_options=options),
                    geometry.primitive_count,
                    same_as=first,
                )
            first = full if first is None else first
    # The gain of specialisation: the same hair in a structure that also holds a far-away flat segment with
    # disk caps, so that the compiled test handles both types and all caps present.
    if config.get("generic", True):
        far = np.asarray(geometry.control_points).max(0) + 1e3
        other = rt.CurveGeometry(far + np.eye(3, dtype=np.float32)[:2], [0.1, 0.1], [0], basis="linear",
                                 control_point_count=2, curve_type="flat", end_caps="disk")  # fmt: skip
        generic = build([geometry, other])
        measure("curve generic", "8 pieces, 3 it", generic, rt.Intersector(), geometry.primitive_count)
        del generic
    for sides, rings in config["tubes"]:
        triangles = rt.TriangleGeometry(tessellate(geometry, sides, rings).reshape(-1, 3))
        tube = rt.build_primitive_structure(triangles)
        measure("triangle tube", f"{sides} sides x {rings} rings", tube, rt.Intersector(), geometry.primitive_count)
        del tube
    return out


@contextlib.contextmanager
def _kernel_curve_batch(batch: int | None):
    """Trace with the GPU kernel's ``curve_batch`` set to ``batch`` (``None``: the default), compiled afresh."""
    if batch is None:
        yield
        return
    import dataclasses

    import jax

    from jaxrt._src.traversal import gpu

    default = gpu.DEFAULT_OPTIONS
    gpu.DEFAULT_OPTIONS = dataclasses.replace(default, curve_batch=batch)
    jax.clear_caches()  # the intersect functions are compiled per intersector, not per kernel option
    try:
        yield
    finally:
        gpu.DEFAULT_OPTIONS = default
        jax.clear_caches()


def _row_text(row: dict) -> str:
    same = {True: "  bitwise equal to the first", False: "  DIFFERS from the first"}.get(row.get("bitwise_equal"), "")
    return (
        f"  {row['method']:<14} {row['setting']:<20} {row['mrays_s']:8.3f} Mrays/s  compile {row['compile_s']:5.1f} s  "
        f"mismatch {row['mismatches']:4d}/{row['decided_rays']:<5d} error/r median {row['error_median']:.1e} "
        f"p99 {row['error_p99']:.1e} max {row['error_max']:.1e}  {row['bytes_per_segment']:7.0f} B/segment{same}"
    )


def format_table(results: dict) -> str:
    """The Pareto table: one block per scene."""
    lines = []
    for scene in results["scenes"]:
        lines.append(
            f"{scene['scene']} ({scene['segments']} segments, radius {scene['radius']:.3g}, {scene['rays']} rays, "
            f"{scene['reference_rays']} against the float64 reference)"
        )
        lines.append(
            "| method | setting | Mrays/s | compile s | hit/miss mismatches | error/r median | p99 | max | bytes/segment |"
        )
        lines.append("|---|---|---|---|---|---|---|---|---|")
        for r in scene["rows"]:
            lines.append(
                f"| {r['method']} | {r['setting']} | {r['mrays_s']:.3f} | {r['compile_s']:.1f} | "
                f"{r['mismatches']}/{r['decided_rays']} | {r['error_median']:.1e} | {r['error_p99']:.1e} | "
                f"{r['error_max']:.1e} | {r['bytes_per_segment']:.0f} |"
            )
        lines.append("")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> dict:
    """Run the curve bench; print the table; return every number (also written with ``--json``)."""
    import argparse

    from jaxrt.bench.report import machine_info, write_json
    from jaxrt.bench.scenes import default_data_dir

    parser = argparse.ArgumentParser(prog="python -m jaxrt.bench.curves", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small sizes and one repeat (a smoke test)")
    parser.add_argument("--json", metavar="PATH", help="also write every number and the machine info to PATH")
    parser.add_argument("--data", metavar="DIR", help="shared data folder (default: $JAXRT_DATA_DIR or ../shared/data)")
    parser.add_argument("--scenes", nargs="+", choices=SCENES, help="default: ponytail and bear (ball without data)")
    parser.add_argument("--rays", type=int)
    parser.add_argument("--reference-rays", type=int)
    parser.add_argument("--strands", type=int, help="use an even subset of this many strands per scene")
    parser.add_argument("--repeats", type=int)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--settings", nargs="+", metavar="P,I", help="curve settings as pieces,iterations (default: the table's five)"
    )
    parser.add_argument("--tubes", nargs="+", metavar="S,R", help="tube rates as sides,rings (default: three)")
    parser.add_argument(
        "--curve-batch",
        nargs="+",
        type=int,
        metavar="N",
        help="a kernel row per setting for each GPU kernel curve_batch N (0: curve tests on sight); each row's "
        "distances are compared bit for bit with the first's",
    )
    parser.add_argument("--no-generic", action="store_true", help="skip the generic-code row")
    args = parser.parse_args(argv)
    config = dict(_QUICK if args.quick else _DEFAULTS)
    for key in ("rays", "reference_rays", "strands", "repeats"):
        if getattr(args, key) is not None:
            config[key] = getattr(args, key)
    pairs = lambda items: tuple(tuple(int(x) for x in item.split(",")) for item in items)  # noqa: E731
    config["settings"] = pairs(args.settings) if args.settings else CURVE_SETTINGS
    config["tubes"] = pairs(args.tubes) if args.tubes else TUBE_RATES
    config["curve_batch"] = tuple(args.curve_batch or ())
    config["generic"] = not args.no_generic
    data_dir = args.data or default_data_dir()
    names = args.scenes or (["ponytail"] if args.quick else ["ponytail", "bear"])
    start = time.perf_counter()
    results = dict(machine=machine_info(), config={k: v for k, v in config.items()}, scenes=[])
    for name in names:
        scene = load_scene(name, data_dir, config["strands"], args.seed)
        if scene is None:
            print(f"{name}: not in the data folder {data_dir}; the procedural hair ball instead", flush=True)
            scene = load_scene("ball", None, config["strands"], args.seed)
        results["scenes"].append(bench_scene(scene, config, seed=args.seed, log=lambda s: print(s, flush=True)))
    results["total_s"] = time.perf_counter() - start
    print()
    print(format_table(results))
    if args.json:
        write_json(results, args.json)
    return results


if __name__ == "__main__":
    main()
