"""Curve geometry (Metal's curve geometry descriptor): bases, curve types, end caps, validation.

A curve is a chain of segments; each segment is its own primitive. The index buffer holds the *first*
control point of each segment, so neighbouring segments share control points (Metal's convention): a
segment of a basis with ``n`` control points per segment uses ``control_points[i : i + n]``.

Every segment is converted to cubic Bezier form for bounds and intersection (see :func:`bezier_segments`):

==============  =====  =====================================================================================
basis           count  the part drawn, in the segment's own control points ``p0 .. p{n-1}``
==============  =====  =====================================================================================
Bezier          3, 4   from ``p0`` to ``p{n-1}`` (quadratic segments are degree-elevated, exactly)
B-spline        3, 4   the middle span: from ``(p0 + p1) / 2`` to ``(p1 + p2) / 2`` (quadratic), or from
                       ``(p0 + 4 p1 + p2) / 6`` to ``(p1 + 4 p2 + p3) / 6`` (cubic); uniform knots
Catmull-Rom     4      from ``p1`` to ``p2`` (uniform, tension 1/2)
linear          2      the straight line from ``p0`` to ``p1``
==============  =====  =====================================================================================

Radii are per control point and interpolated with the same basis as the positions. A segment is connected to
a predecessor when another segment starts ``step`` control points before it (``step`` is ``n - 1`` for Bezier
and linear segments, which share their end point, and 1 for B-spline and Catmull-Rom segments, which share
``n - 1`` points); end caps are drawn at the two ends of every connected chain (Metal's
``MTLCurveEndCaps``: "at the beginning and end of each connected sequence of curve segments").

References:
  Apple, "Your guide to Metal ray tracing", WWDC 2023 (curve geometry, bases, end caps).
  Catmull, Rom, "A class of local interpolating splines", 1974; de Boor, "A Practical Guide to Splines".
"""

from __future__ import annotations

import enum
import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxrt._src.geometry import (
    _as_float_array,
    _check_finite,
    _check_primitive_data,
    _gather_rows,
    _is_concrete,
    keyframe_error,
    keyframe_stack,
)
from jaxrt._src.kinds.curve import CURVE
from jaxrt._src.primitives import curve as primitive

__all__ = [
    "MotionCurveGeometry",
    "CurveBasis",
    "CurveType",
    "CurveEndCaps",
    "CurveGeometry",
    "CurveInfo",
    "bezier_matrix",
    "bezier_segments",
    "segment_links",
    "pack_segments",
    "VALID_COUNTS",
]


class CurveBasis(enum.Enum):
    """The basis that turns a segment's control points into a curve (Metal's ``MTLCurveBasis``)."""

    def __new__(cls, value: str, doc: str):
        member = object.__new__(cls)
        member._value_ = value
        member.__doc__ = doc
        return member

    BEZIER = (
        "bezier",
        "Bezier segments of 3 (quadratic) or 4 (cubic) control points; the curve passes through the first and "
        "last. Neighbouring segments share their end point.",
    )
    CATMULL_ROM = (
        "catmull_rom",
        "Uniform Catmull-Rom segments of 4 control points; the curve passes through every control point and a "
        "segment spans its second to third point. Neighbouring segments overlap by 3 points.",
    )
    BSPLINE = (
        "bspline",
        "Uniform B-spline segments of 3 or 4 control points (the middle span); smooth (C1 or C2) and inside "
        "the convex hull of the control points, which it does not interpolate.",
    )
    LINEAR = (
        "linear",
        "Straight segments of 2 control points (round: cones with spheres at the joints, as Embree's round "
        "linear curves).",
    )

    @classmethod
    def coerce(cls, value: Any, owner: str = "CurveGeometry", name: str = "basis") -> CurveBasis:
        """The member named by ``value`` (a member, or its value or name as a string, any case)."""
        return _coerce(cls, value, owner, name)


class CurveType(enum.Enum):
    """The cross-section of a curve (Metal's ``MTLCurveType``)."""

    def __new__(cls, value: str, doc: str):
        member = object.__new__(cls)
        member._value_ = value
        member.__doc__ = doc
        return member

    ROUND = (
        "round",
        "A tube: the surface swept by a sphere of the interpolated radius along the centre line (as Metal and "
        "Embree). Distances are those of the true surface; the ray enters it from outside.",
    )
    FLAT = (
        "flat",
        "A ribbon of width ``2 * radius`` that always faces the ray (cheaper; for thin hair seen from afar). "
        "The hit lies on the centre line's depth where the ray crosses the ribbon.",
    )

    @classmethod
    def coerce(cls, value: Any, owner: str = "CurveGeometry", name: str = "curve_type") -> CurveType:
        """The member named by ``value`` (a member, or its value or name as a string, any case)."""
        return _coerce(cls, value, owner, name)


class CurveEndCaps(enum.Enum):
    """What closes the two ends of each connected chain of segments (Metal's ``MTLCurveEndCaps``)."""

    def __new__(cls, value: str, doc: str):
        member = object.__new__(cls)
        member._value_ = value
        member.__doc__ = doc
        return member

    NONE = (
        "none",
        "Open ends: a round curve is a tube cut at the end parameter, through which a ray can see inside.",
    )
    DISK = (
        "disk",
        "A flat disk closes each end of a round curve (a ray-facing disk for a flat curve).",
    )
    SPHERE = (
        "sphere",
        "A sphere of the end radius closes each end (for a flat curve, a ray-facing disk at the end).",
    )

    @classmethod
    def coerce(cls, value: Any, owner: str = "CurveGeometry", name: str = "end_caps") -> CurveEndCaps:
        """The member named by ``value`` (a member, or its value or name as a string, any case)."""
        return _coerce(cls, value, owner, name)


def _coerce(cls, value, owner, name):
    if isinstance(value, cls):
        return value
    if isinstance(value, str):
        key = value.strip().lower().replace("-", "_")
        for member in cls:
            if key in (member.value, member.name.lower()):
                return member
    choices = ", ".join(repr(m.value) for m in cls)
    raise ValueError(f"{owner}: {name} must be one of {choices} (or rt.{cls.__name__}), got {value!r}")


#: Control points per segment allowed for each basis (Metal's combinations).
VALID_COUNTS = {
    CurveBasis.BEZIER: (3, 4),
    CurveBasis.BSPLINE: (3, 4),
    CurveBasis.CATMULL_ROM: (4,),
    CurveBasis.LINEAR: (2,),
}

_ELEVATE = np.array([[1, 0, 0], [1 / 3, 2 / 3, 0], [0, 2 / 3, 1 / 3], [0, 0, 1]])
_MATRICES = {
    (CurveBasis.BEZIER, 4): np.eye(4),
    (CurveBasis.BEZIER, 3): _ELEVATE,
    (CurveBasis.BSPLINE, 4): np.array([[1, 4, 1, 0], [0, 4, 2, 0], [0, 2, 4, 0], [0, 1, 4, 1]]) / 6.0,
    (CurveBasis.BSPLINE, 3): _ELEVATE @ np.array([[0.5, 0.5, 0], [0, 1, 0], [0, 0.5, 0.5]]),
    (CurveBasis.CATMULL_ROM, 4): np.array([[0, 6, 0, 0], [-1, 6, 1, 0], [0, 1, 6, -1], [0, 0, 6, 0]]) / 6.0,
    (CurveBasis.LINEAR, 2): np.array([[1, 0], [2 / 3, 1 / 3], [1 / 3, 2 / 3], [0, 1]]),
}


def bezier_matrix(basis: CurveBasis, count: int) -> np.ndarray:
    """The ``(4, count)`` matrix taking a segment's control points to its cubic Bezier control points.

    Examples:
      >>> import numpy as np
      >>> from jaxrt._src.curves import CurveBasis, bezier_matrix
      >>> (bezier_matrix(CurveBasis.CATMULL_ROM, 4) * 6).astype(int).tolist()
      [[0, 6, 0, 0], [-1, 6, 1, 0], [0, 1, 6, -1], [0, 0, 6, 0]]
    """
    return _MATRICES[(CurveBasis.coerce(basis), int(count))]


def _link_step(basis: CurveBasis, count: int) -> int:
    """How many control points separate the first points of two connected segments."""
    return count - 1 if basis in (CurveBasis.BEZIER, CurveBasis.LINEAR) else 1


class CurveInfo(NamedTuple):
    """The static description of a curve geometry (part of a structure's static data)."""

    basis: CurveBasis
    control_point_count: int
    curve_type: CurveType
    end_caps: CurveEndCaps


@jax.tree_util.register_pytree_node_class
class CurveGeometry:
    """Curves from control points, per-point radii and a segment index buffer (Metal's curve geometry).

    Args:
      control_points: ``(P, 3)`` float32 (or float64 under x64) control point positions.
      radii: ``(P,)`` non-negative radius per control point, interpolated with the curve's basis.
      indices: ``(S,)`` integer index of the first control point of each segment (Metal's convention).
      basis: static; a :class:`CurveBasis` (or its name): ``"bezier"``, ``"catmull_rom"``, ``"bspline"``,
        ``"linear"``.
      control_point_count: static; control points per segment: Bezier 3 or 4, B-spline 3 or 4,
        Catmull-Rom 4, linear 2.
      curve_type: static; :class:`CurveType` ``"round"`` (swept-sphere tube) or ``"flat"`` (ray-facing ribbon).
      end_caps: static; :class:`CurveEndCaps` ``"none"``, ``"disk"`` or ``"sphere"``.
      primitive_data: optional pytree whose leaves have leading dimension ``S`` (per-segment user data).
      opaque: static; ``False`` marks the geometry as alpha-tested.

    Raises:
      TypeError: a non-float ``control_points``/``radii`` or non-integer ``indices`` dtype.
      ValueError: a basis/count combination Metal does not have, wrong shapes, empty geometry, non-finite
        control points, negative or non-finite radii, indices whose segment runs past the control points,
        or primitive data whose leading dimension is not ``S``. Messages name the argument and the value.

    Examples:
      >>> import jaxrt as rt
      >>> points = [[0., 0, 0], [1, 0, 0], [2, 1, 0], [3, 1, 0], [4, 0, 0]]
      >>> hair = rt.CurveGeometry(points, [.1] * 5, [0, 1], basis="catmull_rom", control_point_count=4)
      >>> hair.primitive_count, hair.basis
      (2, <CurveBasis.CATMULL_ROM: 'catmull_rom'>)
    """

    kind = CURVE.name

    def __init__(
        self,
        control_points: Any,
        radii: Any,
        indices: Any,
        *,
        basis: CurveBasis | str,
        control_point_count: int,
        curve_type: CurveType | str = "round",
        end_caps: CurveEndCaps | str = "none",
        primitive_data: Any = None,
        opaque: bool = True,
    ):
        owner = "CurveGeometry"
        basis = CurveBasis.coerce(basis, owner)
        curve_type = CurveType.coerce(curve_type, owner)
        end_caps = CurveEndCaps.coerce(end_caps, owner)
        if isinstance(control_point_count, bool) or not isinstance(control_point_count, (int, np.integer)):
            raise TypeError(f"{owner}: control_point_count must be an int, got {control_point_count!r}")
        count = int(control_point_count)
        if count not in VALID_COUNTS[basis]:
            allowed = " or ".join(str(c) for c in VALID_COUNTS[basis])
            raise ValueError(
                f"{owner}: control_point_count={count} is not valid for basis {basis.value!r}; it takes {allowed} "
                "control points per segment"
            )
        points = _as_float_array(control_points, "control_points", owner)
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"{owner}: control_points must have shape (P, 3), got {tuple(points.shape)}")
        if points.shape[0] == 0:
            raise ValueError(f"{owner}: control_points is empty (shape {tuple(points.shape)}); a curve needs points")
        _check_finite(points, "control_points", owner)
        radii = _as_float_array(radii, "radii", owner)
        if radii.shape != (points.shape[0],):
            raise ValueError(
                f"{owner}: radii must have shape (P,) = ({points.shape[0]},) like control_points, got "
                f"{tuple(radii.shape)}"
            )
        _check_finite(radii, "radii", owner)
        if _is_concrete(radii):
            host = np.asarray(radii)
            if (host < 0).any():
                i = int(np.argmax(host < 0))
                raise ValueError(f"{owner}: radii must be non-negative, got radii[{i}] = {host[i]}")
        if isinstance(indices, (list, tuple)) and len(indices) == 0:
            raise ValueError(f"{owner}: indices is empty (length 0); a geometry needs a segment")
        dtype = np.dtype(getattr(indices, "dtype", None) or np.asarray(indices).dtype)
        if not np.issubdtype(dtype, np.integer):
            raise TypeError(f"{owner}: indices must have an integer dtype, got {dtype}")
        if _is_concrete(indices):
            host = np.asarray(indices)
            if host.ndim != 1:
                raise ValueError(f"{owner}: indices must have shape (S,), got {host.shape}")
            if host.shape[0] == 0:
                raise ValueError(f"{owner}: indices is empty (shape {host.shape}); a geometry needs a segment")
            bad = (host < 0) | (host.astype(np.int64) + count > points.shape[0])
            if bad.any():
                s = int(np.argmax(bad))
                raise ValueError(
                    f"{owner}: indices[{s}] = {int(host[s])} starts a {count}-point segment that runs past the "
                    f"{points.shape[0]} control points (the last valid first index is {points.shape[0] - count})"
                )
        elif indices.ndim != 1 or indices.shape[0] == 0:
            raise ValueError(f"{owner}: indices must have shape (S,) with S > 0, got {tuple(indices.shape)}")
        indices = jnp.asarray(indices, jnp.int32)
        if primitive_data is not None:
            _check_primitive_data(primitive_data, indices.shape[0], owner)
        self.control_points = points
        self.radii = radii
        self.indices = indices
        self.primitive_data = primitive_data
        self.basis = basis
        self.control_point_count = count
        self.curve_type = curve_type
        self.end_caps = end_caps
        self.opaque = bool(opaque)

    @property
    def primitive_count(self) -> int:
        """Number of segments (static)."""
        return int(self.indices.shape[0])

    @property
    def info(self) -> CurveInfo:
        """The static description (basis, count, type, caps)."""
        return CurveInfo(self.basis, self.control_point_count, self.curve_type, self.end_caps)

    def segment_control_points(self) -> jax.Array:
        """``(S, n, 4)`` control points of each segment in its own basis, radius in the last column."""
        window = self.indices[:, None] + jnp.arange(self.control_point_count, dtype=jnp.int32)
        points = jnp.concatenate([self.control_points, self.radii[:, None]], axis=-1)
        # A segment running past the control points (traced indices only) gets zero rows, not clamped ones;
        # ``curve_leaves`` gives it an empty box (``segments_in_range``).
        return _gather_rows(points, window)

    def segments_in_range(self) -> jax.Array:
        """``(S,)`` whether each segment's control points all exist (the constructor checks concrete indices;
        traced ones may run past the end, and such segments are never hit)."""
        last = self.indices + (self.control_point_count - 1)
        return (self.indices >= 0) & (last < self.control_points.shape[0])

    def tree_flatten(self):
        children = (self.control_points, self.radii, self.indices, self.primitive_data)
        return children, (self.basis, self.control_point_count, self.curve_type, self.end_caps, self.opaque)

    @classmethod
    def tree_unflatten(cls, aux, children):
        obj = object.__new__(cls)
        obj.control_points, obj.radii, obj.indices, obj.primitive_data = children
        obj.basis, obj.control_point_count, obj.curve_type, obj.end_caps, obj.opaque = aux
        return obj

    def __repr__(self) -> str:
        return (
            f"CurveGeometry(control_points={tuple(self.control_points.shape)}, segments={self.primitive_count}, "
            f"basis={self.basis.value!r}, control_point_count={self.control_point_count}, "
            f"curve_type={self.curve_type.value!r}, end_caps={self.end_caps.value!r}, opaque={self.opaque})"
        )


@jax.tree_util.register_pytree_node_class
class MotionCurveGeometry:
    """Curves whose control points and radii move through ``K >= 2`` keyframes (Metal's motion curve geometry).

    A ray with time ``t`` sees the control points and radii blended linearly between its two neighbouring
    keyframes (over the structure's :class:`~jaxrt.MotionSpec` range); the segment indices, basis, type and
    end caps are shared by every keyframe.

    Args:
      control_points: ``(K, P, 3)`` float control points per keyframe (or a sequence of ``K`` ``(P, 3)``).
      radii: ``(K, P)`` non-negative radii per keyframe.
      indices, basis, control_point_count, curve_type, end_caps, primitive_data, opaque: as
        :class:`CurveGeometry`.

    Raises:
      TypeError, ValueError: fewer than 2 keyframes, keyframe shapes that differ (between keyframes or between
        points and radii), non-finite values, or any error of :class:`CurveGeometry` on a keyframe.

    Examples:
      >>> import jaxrt as rt
      >>> points = [[[0., 0, 0], [1, 0, 0]], [[0., 1, 0], [1, 1, 0]]]
      >>> g = rt.MotionCurveGeometry(points, [[.1, .1], [.1, .1]], [0], basis="linear", control_point_count=2)
      >>> g.keyframe_count, g.primitive_count
      (2, 1)
    """

    kind = CURVE.name
    motion = True

    def __init__(
        self,
        control_points: Any,
        radii: Any,
        indices: Any,
        *,
        basis: CurveBasis | str,
        control_point_count: int,
        curve_type: CurveType | str = "round",
        end_caps: CurveEndCaps | str = "none",
        primitive_data: Any = None,
        opaque: bool = True,
    ):
        owner = "MotionCurveGeometry"
        points = keyframe_stack(control_points, "control_points", owner, (-1, 3))
        radii = keyframe_stack(radii, "radii", owner, (-1,))
        if radii.shape != points.shape[:2]:
            raise ValueError(
                f"{owner}: radii must have shape (K, P) = {tuple(points.shape[:2])} like control_points, got "
                f"{tuple(radii.shape)}"
            )
        options = dict(
            basis=basis,
            control_point_count=control_point_count,
            curve_type=curve_type,
            end_caps=end_caps,
            opaque=opaque,
        )
        for k in range(points.shape[0]):
            try:
                frame = CurveGeometry(
                    points[k], radii[k], indices, primitive_data=primitive_data if k == 0 else None, **options
                )
            except (TypeError, ValueError) as error:
                raise keyframe_error(owner, k, error) from None
        self.control_points = points
        self.radii = radii
        self.indices = frame.indices
        self.primitive_data = primitive_data
        self.basis = frame.basis
        self.control_point_count = frame.control_point_count
        self.curve_type = frame.curve_type
        self.end_caps = frame.end_caps
        self.opaque = frame.opaque

    @property
    def keyframe_count(self) -> int:
        """``K`` (static)."""
        return int(self.control_points.shape[0])

    @property
    def primitive_count(self) -> int:
        """Number of segments (static)."""
        return int(self.indices.shape[0])

    @property
    def info(self) -> CurveInfo:
        """The static description (basis, count, type, caps)."""
        return CurveInfo(self.basis, self.control_point_count, self.curve_type, self.end_caps)

    def keyframe(self, k: int) -> CurveGeometry:
        """The static geometry of keyframe ``k`` (differentiable; no validation, so usable inside ``jit``)."""
        children, aux = self.tree_flatten()
        points, radii, indices, data = children
        return CurveGeometry.tree_unflatten(aux, (points[k], radii[k], indices, data))

    def tree_flatten(self):
        children = (self.control_points, self.radii, self.indices, self.primitive_data)
        return children, (self.basis, self.control_point_count, self.curve_type, self.end_caps, self.opaque)

    @classmethod
    def tree_unflatten(cls, aux, children):
        obj = object.__new__(cls)
        obj.control_points, obj.radii, obj.indices, obj.primitive_data = children
        obj.basis, obj.control_point_count, obj.curve_type, obj.end_caps, obj.opaque = aux
        return obj

    def __repr__(self) -> str:
        return (
            f"MotionCurveGeometry(keyframes={self.keyframe_count}, segments={self.primitive_count}, "
            f"basis={self.basis.value!r}, control_point_count={self.control_point_count})"
        )


def bezier_segments(geometry: CurveGeometry) -> jax.Array:
    """``(S, 4, 4)`` cubic Bezier control points of every segment (``x, y, z, radius``); differentiable."""
    matrix = jnp.asarray(bezier_matrix(geometry.basis, geometry.control_point_count), geometry.control_points.dtype)
    return jnp.einsum("ij,sjk->sik", matrix, geometry.segment_control_points())


def segment_links(geometry: CurveGeometry, bezier: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Connectivity of every segment: ``(has_previous, has_next, previous_end_derivative)``.

    ``previous_end_derivative`` ``(S, 4)`` is the derivative (position and radius) of the predecessor at its
    end, ``3 (b3 - b2)`` in Bezier form (zeros without a predecessor): the intersector needs it to decide
    whether a ray hitting the sphere at a joint sees a gap between two segments that meet at an angle.

    Works on traced indices (a sort and a binary search).
    """
    step = _link_step(geometry.basis, geometry.control_point_count)
    first = geometry.indices
    order = jnp.argsort(first)
    ordered = first[order]

    def find(target):
        position = jnp.clip(jnp.searchsorted(ordered, target), 0, ordered.shape[0] - 1)
        return ordered[position] == target, order[position]

    has_previous, previous = find(first - step)
    has_next, _ = find(first + step)
    derivative = 3.0 * (bezier[previous, 3] - bezier[previous, 2])
    derivative = jnp.where(has_previous[:, None], derivative, 0.0)
    return has_previous, has_next, derivative


def pack_segments(geometry: CurveGeometry) -> tuple[jax.Array, jax.Array]:
    """The per-segment payload the intersector reads: ``(segments (S, 6, 4), flags (S,) int32)``.

    ``segments`` rows 0-3 are the cubic Bezier control points relative to the segment's first control point
    (row 4), so the basis conversion keeps full precision far from the origin; row 5 is the derivative of the
    predecessor at the joint (:func:`segment_links`). ``flags`` holds the links, the end caps and the type
    (:func:`jaxrt._src.primitives.curve.pack_flags`). Differentiable with respect to points and radii.
    """
    window = geometry.segment_control_points()
    base = window[:, 0, :3]
    relative = window - jnp.concatenate([base, jnp.zeros_like(base[:, :1])], axis=-1)[:, None, :]
    matrix = jnp.asarray(bezier_matrix(geometry.basis, geometry.control_point_count), window.dtype)
    local = jnp.einsum("ij,sjk->sik", matrix, relative)
    has_previous, has_next, previous = segment_links(geometry, local)
    caps = {CurveEndCaps.NONE: primitive.CAP_NONE, CurveEndCaps.DISK: primitive.CAP_DISK}
    flags = primitive.pack_flags(
        has_previous, has_next, caps.get(geometry.end_caps, primitive.CAP_SPHERE), geometry.curve_type == CurveType.FLAT
    )
    base_row = jnp.concatenate([base, jnp.zeros_like(base[:, :1])], axis=-1)[:, None, :]
    return jnp.concatenate([local, base_row, previous[:, None, :]], axis=1), flags


# --- structures and the intersector ---------------------------------------------------------------------------


class CurveLeafArrays(NamedTuple):
    """The curve part of a structure's leaves, in unsorted slot order, padded to the capacity."""

    segments: jax.Array  # (C, 6, 4) packed segments (zeros for triangles and padding)
    flags: jax.Array  # (C,) int32 (IS_CURVE set on curve leaves)
    lower: jax.Array  # (C, 3) segment boxes (meaningful where is_curve)
    upper: jax.Array
    is_curve: jax.Array  # (C,) bool


def curve_leaves(geometries: tuple[Any, ...], capacity: int) -> CurveLeafArrays | None:
    """Packed segments, flags and boxes of the curve geometries among ``geometries`` (``None`` without any).

    Triangle geometries take zero rows, so that row ``i`` is the ``i``-th primitive over all geometries.
    """
    if not any(isinstance(g, CurveGeometry) for g in geometries):
        return None
    dtype = next(g.control_points.dtype for g in geometries if isinstance(g, CurveGeometry))
    segments, flags, in_range = [], [], []
    for g in geometries:
        if isinstance(g, CurveGeometry):
            packed, packed_flags = pack_segments(g)
            segments.append(packed.astype(dtype))
            flags.append(packed_flags | primitive.IS_CURVE)
            in_range.append(g.segments_in_range())
        else:
            segments.append(jnp.zeros((g.primitive_count, 6, 4), dtype))
            flags.append(jnp.zeros((g.primitive_count,), jnp.int32))
            in_range.append(jnp.ones((g.primitive_count,), bool))
    segments = jnp.concatenate(segments)
    flags = jnp.concatenate(flags)
    pad = capacity - segments.shape[0]
    segments = jnp.pad(segments, ((0, pad), (0, 0), (0, 0)))
    flags = jnp.pad(flags, (0, pad))
    in_range = jnp.pad(jnp.concatenate(in_range), (0, pad), constant_values=True)
    is_curve = (flags & primitive.IS_CURVE) != 0
    lower, upper = CURVE.bounds(segments)
    # segments with indices out of range: an empty box, so no ray enters them
    lower = jnp.where(in_range[:, None], lower, jnp.inf)
    upper = jnp.where(in_range[:, None], upper, -jnp.inf)
    return CurveLeafArrays(segments, flags, lower, upper, is_curve)


def curve_configuration(infos: tuple[CurveInfo, ...], curve_type: CurveType | None, options: Any) -> dict:
    """Static code choices for the curve geometries of a structure: ``curve_types``, ``end_caps``, ``options``.

    Only the types and caps present are compiled; linear-only structures use one exact round cone per segment
    (one piece, no iteration) unless ``options`` is given.
    """
    types = {i.curve_type for i in infos} if curve_type is None else {curve_type}
    curve_types = tuple(sorted(primitive.FLAT if t == CurveType.FLAT else primitive.ROUND for t in types))
    code = {CurveEndCaps.NONE: primitive.CAP_NONE, CurveEndCaps.DISK: primitive.CAP_DISK}
    end_caps = tuple(sorted({code.get(i.end_caps, primitive.CAP_SPHERE) for i in infos}))
    if options is None:
        linear = all(i.basis == CurveBasis.LINEAR for i in infos)
        options = primitive.CurveOptions(pieces=1, iterations=0) if linear else primitive.DEFAULT_OPTIONS
    return dict(curve_types=curve_types, end_caps=end_caps, options=options)


class CurveLeaves:
    """Ray/curve tests of BVH leaves (a :class:`~jaxrt._src.traversal.step.LeafTester`; curves have no
    facing, so the per-level ``facing`` of a traversal below instances is ignored)."""

    def __init__(self, leaf_curve: jax.Array, leaf_flags: jax.Array, curve_types, end_caps, options):
        self.leaf_curve = leaf_curve
        self.leaf_flags = leaf_flags
        self.config = dict(curve_types=curve_types, end_caps=end_caps, options=options)

    def prepare(self, origin, direction, facing=None):
        del facing  # culling applies to triangles only
        return primitive.curve_ray(origin, direction)

    def __call__(self, context, leaves, t_min, t_max):
        index = jnp.maximum(leaves, 0)
        test = lambda segment, flags: primitive.intersect(context, segment, flags, t_min, t_max, **self.config)  # noqa: E731
        hit = jax.vmap(test)(self.leaf_curve[index], self.leaf_flags[index])
        return hit.hit & (leaves >= 0), hit.distance


def curve_hit_fields(
    leaf_curve, leaf_curve_flags, leaf, hit, origin, direction, t_min, t_max, distance, config, exact=None
):
    """For every ray, whether its hit is a curve, that hit's differentiable ``(distance, u)``, and the part of
    the segment it lies on (a ``PART_*`` code of :mod:`jaxrt._src.primitives.curve`).

    ``leaf_curve`` and ``leaf_curve_flags`` are a scene's global curve leaves indexed by ``leaf``; ``origin``
    and ``direction`` are the ray in the hit's object space. The traversal only picks the leaf: the chosen segment is tested again
    (exactly, for ``u``), then :func:`jaxrt._src.primitives.curve.smooth_hit` polishes a tube or ribbon hit
    to its root and attaches derivatives with respect to the segment's control points and radii and to the
    ray. ``exact``: the exact test's ``(u, part)`` for every ray where the traversal computed them (the CPU
    traversal, with the shared curve formula), which then replace the test made here.
    """
    stop = jax.lax.stop_gradient
    flags = leaf_curve_flags[leaf]
    is_curve = hit & ((flags & primitive.IS_CURVE) != 0)
    segment = leaf_curve[leaf]
    # Lanes without a curve hit get a dummy segment and ray (no NaN in their zero gradients).
    dummy = jnp.zeros((6, 4), segment.dtype).at[:4, 0].set(jnp.array([0.0, 1 / 3, 2 / 3, 1.0])).at[:4, 3].set(0.5)
    segment = jnp.where(is_curve[:, None, None], segment, dummy)
    unit_z = jnp.array([0.0, 0.0, 1.0], origin.dtype)
    ray_origin = jnp.where(is_curve[:, None], origin, jnp.array([0.5, 0.0, -1.0], origin.dtype))
    ray_direction = jnp.where(is_curve[:, None], direction, unit_z)

    def test(o, d, s, f, lo, hi):
        return primitive.intersect(primitive.curve_ray(o, d), s, f, lo, hi, **config)

    if exact is None:
        again = jax.vmap(test)(stop(ray_origin), stop(ray_direction), stop(segment), flags, t_min, t_max)
        exact = again.u, again.part
    exact_t = jnp.where(is_curve, distance, 0.5)
    part = jnp.where(is_curve, exact[1], primitive.PART_TUBE)
    u = jnp.where(is_curve, stop(exact[0]), 0.5)
    smooth = functools.partial(primitive.smooth_hit, curve_types=config["curve_types"])
    t, u = jax.vmap(smooth)(ray_origin, ray_direction, segment, part, u, exact_t, t_min, t_max)
    return is_curve, t, u, part
