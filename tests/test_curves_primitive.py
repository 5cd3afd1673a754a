"""The ray/curve-segment test against the float64 reference (``jaxrt.bench.curves.reference_hits``).

Tolerances (relative to the largest control radius ``r`` of the curve, plus float32 rounding of ray-space
coordinates, ``ROUNDING eps |scale|`` with ``scale`` the distance of the curve from the ray origin):

* hit/miss: equal for every (ray, segment) pair the reference does not flag as undecidable within the band
  ``BAND * r``: rays passing within the band of tangency, tube minima within the band of a segment end,
  cap and joint decisions within the band;
* distance: ``|t - t_ref| |d| <= DISTANCE * r``;
* curve parameter: ``|u - u_ref| <= PARAMETER`` where the entry is well conditioned (the ray is not within 30
  degrees of the tangent), and ``|u - u_ref| |C'| / chord <= PARAMETER`` where the curve slows down (cusps).

Flat ribbons seen within ``END_ON`` of their axis have several crossings of nearly equal depth; their
distances are compared with the looser ``END_ON_DISTANCE``.
"""

from __future__ import annotations

import functools

import hypothesis
import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrt as rt
from jaxrt._src.curves import bezier_segments, pack_segments
from jaxrt._src.primitives import curve as primitive
from jaxrt.bench.curves import host_segments, reference_hits

BAND = 1e-2
DISTANCE = 1e-2
PARAMETER = 2e-3
END_ON = np.cos(np.radians(10.0))
END_ON_DISTANCE = 10.0
EPS32 = float(np.finfo(np.float32).eps)
#: Float32 rounding of ray-space coordinates, in units of eps times the curve's distance from the ray origin.
ROUNDING = 32

COMBOS = [("bezier", 4), ("bezier", 3), ("catmull_rom", 4), ("bspline", 4), ("bspline", 3), ("linear", 2)]
RAYS = 64
SEGMENTS = 3


@functools.cache
def _tester(options: primitive.CurveOptions = primitive.DEFAULT_OPTIONS):
    """One compiled (rays x segments) test covering both curve types and all caps (selected by flags)."""

    def one(origin, direction, t_min, t_max, segment, flags):
        ray = primitive.curve_ray(origin, direction)
        return primitive.intersect(
            ray,
            segment,
            flags,
            t_min,
            t_max,
            curve_types=(primitive.ROUND, primitive.FLAT),
            end_caps=(primitive.CAP_NONE, primitive.CAP_DISK, primitive.CAP_SPHERE),
            options=options,
        )

    per_segment = jax.vmap(one, in_axes=(None, None, None, None, 0, 0))
    return jax.jit(jax.vmap(per_segment, in_axes=(0, 0, 0, 0, None, None)))


def run(geometry: rt.CurveGeometry, origin, direction, t_min=None, t_max=None, options=primitive.DEFAULT_OPTIONS):
    """The library's answer for every (ray, segment) pair, ``(R, S)`` arrays."""
    segments, flags = pack_segments(geometry)
    n, s = len(origin), segments.shape[0]
    t_min = np.zeros(n, np.float32) if t_min is None else np.asarray(t_min, np.float32)
    t_max = np.full(n, np.inf, np.float32) if t_max is None else np.asarray(t_max, np.float32)
    # Pad to fixed shapes (repeating the first ray and segment) so that every test compiles the same code.
    rays = max(RAYS, n)
    pad_rays = lambda a: np.concatenate([a, np.repeat(a[:1], rays - n, axis=0)])  # noqa: E731
    pad_segments = lambda a: jnp.concatenate([a, jnp.repeat(a[:1], max(0, 4 - s), axis=0)])  # noqa: E731
    out = _tester(options)(
        *(jnp.asarray(pad_rays(np.asarray(a, np.float32))) for a in (origin, direction, t_min, t_max)),
        pad_segments(segments),
        pad_segments(flags),
    )
    return jax.tree_util.tree_map(lambda a: np.asarray(a)[:n, :s], out)


def strand(rng, basis, count, segments, *, radius, turn, offset=0.0, taper=True):
    """A smooth random strand of ``segments`` connected segments with unit-length control polygon legs."""
    step = count - 1 if basis in ("bezier", "linear") else 1
    points = count + (segments - 1) * step
    direction = rng.normal(size=3)
    legs = []
    for _ in range(points - 1):
        direction = direction / np.linalg.norm(direction)
        legs.append(direction)
        direction = direction + turn * rng.normal(size=3)
    position = np.concatenate([np.zeros((1, 3)), np.cumsum(legs, axis=0)]) + offset
    radii = radius * (rng.uniform(0.3, 1.0, points) if taper else np.ones(points))
    return position.astype(np.float32), radii.astype(np.float32), np.arange(segments) * step


def aimed_rays(rng, geometry, count, *, spread=1.5, distance=(5.0, 20.0)):
    """Rays from afar at points within ``spread`` radii of the centre line, in random directions."""
    bezier = np.asarray(bezier_segments(geometry), np.float64)
    segment = rng.integers(0, bezier.shape[0], count)
    u = rng.uniform(0.0, 1.0, count)
    weights = np.stack([(1 - u) ** 3, 3 * u * (1 - u) ** 2, 3 * u**2 * (1 - u), u**3], axis=1)
    centre = np.einsum("rk,rkc->rc", weights, bezier[segment])
    offset = rng.normal(size=(count, 3))
    offset /= np.linalg.norm(offset, axis=1, keepdims=True)
    target = centre[:, :3] + offset * (rng.uniform(0.0, spread, (count, 1)) * np.abs(centre[:, 3:]))
    direction = rng.normal(size=(count, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    origin = target - direction * rng.uniform(*distance, (count, 1))
    direction *= rng.uniform(0.5, 2.0, (count, 1))
    return origin.astype(np.float32), direction.astype(np.float32)


def compare(geometry, origin, direction, t_min=None, t_max=None, *, options=primitive.DEFAULT_OPTIONS, band=BAND):
    """Assert the library agrees with the reference; return counts.

    The contract: per ray, the nearest hit over all segments equals the reference's (hit/miss, distance);
    per (ray, segment) pair, no hit the reference does not have (no hit on a joint sphere inside a
    neighbour's tube), and the reference's hit unless it is hidden behind a nearer hit of the ray (a segment
    may skip a second local minimum of its entry distance that lies inside the chain).
    """
    got = run(geometry, origin, direction, t_min, t_max, options)
    segments = host_segments(geometry)
    r, s = len(origin), segments.points.shape[0]
    ray_index, segment_index = np.repeat(np.arange(r), s), np.tile(np.arange(s), r)
    radius = float(np.max(np.asarray(geometry.radii)))
    scale = np.max(
        np.linalg.norm(np.asarray(geometry.control_points, np.float64)[None] - origin[:, None], axis=-1), axis=1
    )
    rounding = ROUNDING * EPS32 * scale[ray_index]
    t_lo = np.zeros(r) if t_min is None else np.asarray(t_min, np.float64)
    t_hi = np.full(r, np.inf) if t_max is None else np.asarray(t_max, np.float64)
    ref = reference_hits(
        origin, direction, t_lo, t_hi, segments, ray_index, segment_index, band=band * radius + rounding
    )
    hit, distance, u = got.hit.reshape(-1), got.distance.reshape(-1).astype(np.float64), got.u.reshape(-1)
    length = np.linalg.norm(np.asarray(direction, np.float64), axis=1)[ray_index]
    allowed = (DISTANCE * radius + rounding) / length  # in units of the ray parameter
    if geometry.curve_type == rt.CurveType.FLAT:
        chord = np.asarray(bezier_segments(geometry), np.float64)
        axis = chord[:, 3, :3] - chord[:, 0, :3]
        axis /= np.maximum(np.linalg.norm(axis, axis=1, keepdims=True), 1e-30)
        cosine = np.abs(np.einsum("ni,ni->n", np.asarray(direction, np.float64)[ray_index], axis[segment_index]))
        allowed = np.where(cosine / length > END_ON, (END_ON_DISTANCE * radius + rounding) / length, allowed)
    decided = ~ref.ambiguous
    nearest = np.full(r, np.inf)
    np.minimum.at(nearest, ray_index, np.where(hit, distance, np.inf))
    ray_nearest = nearest[ray_index]
    ref_t = np.where(ref.hit, ref.distance, np.inf)

    false_hit = decided & hit & ~ref.hit
    assert not false_hit.any(), _report(
        "hit/miss (extra hit)", false_hit, ray_index, segment_index, hit, distance, u, ref
    )
    hidden = ray_nearest < ref_t - allowed
    missed = decided & ref.hit & ~hit & ~hidden
    assert not missed.any(), _report("hit/miss (missed)", missed, ray_index, segment_index, hit, distance, u, ref)
    both = decided & hit & ref.hit
    close = np.abs(np.where(both, distance - np.where(both, ref_t, 0.0), 0.0)) <= allowed
    farther_hidden = (distance > ref_t) & (ray_nearest <= ref_t + allowed)
    far = both & ~close & ~farther_hidden
    assert not far.any(), _report("distance", far, ray_index, segment_index, hit, distance, u, ref)
    conditioned, speed = _conditioned(geometry, ref, direction, ray_index, segment_index)
    off = both & close & conditioned & (np.abs(u - ref.u) * np.minimum(speed, 1.0) > PARAMETER)
    assert not off.any(), _report("curve parameter", off, ray_index, segment_index, hit, distance, u, ref)

    # Per ray: the nearest hit.
    ray_decided = np.ones(r, bool)
    np.logical_and.at(ray_decided, ray_index, decided)
    ref_nearest = np.full(r, np.inf)
    np.minimum.at(ref_nearest, ray_index, ref_t)
    tolerance = np.full(r, np.inf)
    np.minimum.at(tolerance, ray_index, allowed)
    wrong = ray_decided & (np.isfinite(nearest) != np.isfinite(ref_nearest))
    both_rays = ray_decided & np.isfinite(nearest) & np.isfinite(ref_nearest)
    gap = np.where(both_rays, nearest, 0.0) - np.where(both_rays, ref_nearest, 0.0)
    wrong |= both_rays & (np.abs(gap) > tolerance)
    assert not wrong.any(), f"{int(wrong.sum())} rays differ in their nearest hit: rays {np.nonzero(wrong)[0][:6]}"
    return dict(pairs=int(decided.sum()), hits=int(both.sum()), ambiguous=int(ref.ambiguous.sum()))


def _conditioned(geometry, ref, direction, ray_index, segment_index):
    """``(well_conditioned, speed)`` per pair: the ray is not within 30 degrees of the curve's tangent, and the
    curve's speed ``|C'(u)|`` relative to its chord (where the curve slows down, as at a cusp, the parameter
    of a point is ill defined and is compared as a distance along the curve instead)."""
    bezier = np.asarray(bezier_segments(geometry), np.float64)[segment_index]
    u = ref.u
    tangent = (
        3 * (1 - u)[:, None] ** 2 * (bezier[:, 1, :3] - bezier[:, 0, :3])
        + 6 * ((1 - u) * u)[:, None] * (bezier[:, 2, :3] - bezier[:, 1, :3])
        + 3 * u[:, None] ** 2 * (bezier[:, 3, :3] - bezier[:, 2, :3])
    )
    d = np.asarray(direction, np.float64)[ray_index]
    speed = np.linalg.norm(tangent, axis=1)
    cosine = np.abs(np.einsum("ni,ni->n", d, tangent)) / np.maximum(np.linalg.norm(d, axis=1) * speed, 1e-300)
    chord = np.linalg.norm(bezier[:, 3, :3] - bezier[:, 0, :3], axis=1) + np.abs(bezier[:, :, 3]).max(axis=1)
    return cosine < np.cos(np.radians(30.0)), speed / np.maximum(chord, 1e-300)


def _report(what, bad, ray_index, segment_index, hit, distance, u, ref):
    k = np.nonzero(bad)[0][:4]
    rows = [
        f"ray {ray_index[i]} segment {segment_index[i]}: got hit={hit[i]} t={distance[i]:.7g} u={u[i]:.5g}; "
        f"reference hit={ref.hit[i]} t={ref.distance[i]:.7g} u={ref.u[i]:.5g} clearance={ref.clearance[i]:.3g}"
        for i in k
    ]
    return f"{int(bad.sum())} pairs differ in {what} (ray-space scale in the message's units):\n" + "\n".join(rows)


@st.composite
def curves(draw):
    basis, count = draw(st.sampled_from(COMBOS))
    curve_type = draw(st.sampled_from(["round", "flat"]))
    caps = draw(st.sampled_from(["none", "disk", "sphere"]))
    seed = draw(st.integers(0, 2**31 - 1))
    radius = 10.0 ** draw(st.floats(-3.0, -0.7))
    turn = draw(st.floats(0.0, 0.6))
    far = draw(st.sampled_from([0.0, 0.0, 1e3]))
    rng = np.random.default_rng(seed)
    points, radii, indices = strand(rng, basis, count, SEGMENTS, radius=radius, turn=turn, offset=far)
    geometry = rt.CurveGeometry(
        points, radii, indices, basis=basis, control_point_count=count, curve_type=curve_type, end_caps=caps
    )
    return geometry, rng


@hypothesis.given(curves())
def test_matches_reference(case):
    geometry, rng = case
    origin, direction = aimed_rays(rng, geometry, RAYS)
    compare(geometry, origin, direction)


@pytest.mark.parametrize("curve_type", ["round", "flat"])
@pytest.mark.parametrize("basis,count", COMBOS)
def test_each_basis(basis, count, curve_type):
    rng = np.random.default_rng(7)
    points, radii, indices = strand(rng, basis, count, SEGMENTS, radius=0.08, turn=0.4)
    geometry = rt.CurveGeometry(points, radii, indices, basis=basis, control_point_count=count, curve_type=curve_type)
    stats = compare(geometry, *aimed_rays(rng, geometry, RAYS))
    assert stats["hits"] > RAYS // 4


def test_options_are_validated():
    with pytest.raises(ValueError, match="pieces"):
        primitive.CurveOptions(pieces=0)
    with pytest.raises(ValueError, match="iterations"):
        primitive.CurveOptions(iterations=-1)
    with pytest.raises(ValueError, match="tolerance"):
        primitive.CurveOptions(tolerance=0.0)
