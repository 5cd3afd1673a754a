"""Keyframe motion: the time range and border modes, and linear interpolation between keyframes.

``K >= 2`` keyframes are evenly spaced over ``[start_time, end_time]``: keyframe ``k`` is at
``start_time + k (end_time - start_time) / (K - 1)``. At time ``t`` a moving primitive is the linear blend of
its two neighbouring keyframes (as Metal interpolates vertices, control points, boxes and instance
transforms, component by component). Outside the range a border mode decides: ``"clamp"`` holds the
first (last) keyframe, ``"vanish"`` removes the primitive (no hit).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

__all__ = [
    "BORDERS",
    "KeyframePosition",
    "LeafKeys",
    "MotionSpec",
    "at_time",
    "interpolate",
    "keyframe_position",
    "keyframe_times",
    "motion_bounds",
    "spec_position",
]

#: Border modes: what a moving primitive is outside ``[start_time, end_time]``.
BORDERS = ("clamp", "vanish")


@dataclasses.dataclass(frozen=True)
class MotionSpec:
    """The time range of keyframe motion and what happens outside it (Metal's motion start/end time and
    border modes).

    Args:
      start_time, end_time: the times of the first and last keyframe (``end_time > start_time``).
      start_border, end_border: ``"clamp"`` (hold the first/last keyframe) or ``"vanish"`` (no hit before
        ``start_time`` / after ``end_time``).

    The spec is static (hashable): structures with different specs compile separately.

    Raises:
      ValueError: non-finite times, ``end_time <= start_time``, or an unknown border mode.

    Examples:
      >>> import jaxrt as rt
      >>> rt.MotionSpec(0.0, 1.0, end_border="vanish")
      MotionSpec(start_time=0.0, end_time=1.0, start_border='clamp', end_border='vanish')
    """

    start_time: float = 0.0
    end_time: float = 1.0
    start_border: str = "clamp"
    end_border: str = "clamp"

    def __post_init__(self):
        owner = "MotionSpec"
        for name in ("start_time", "end_time"):
            value = getattr(self, name)
            try:
                number = float(value)
            except (TypeError, ValueError):
                raise TypeError(f"{owner}: {name} must be a float, got {value!r}") from None
            if not math.isfinite(number):
                raise ValueError(f"{owner}: {name} must be finite, got {number}")
            object.__setattr__(self, name, number)
        if self.end_time <= self.start_time:
            raise ValueError(f"{owner}: end_time={self.end_time} must be greater than start_time={self.start_time}")
        for name in ("start_border", "end_border"):
            value = getattr(self, name)
            if value not in BORDERS:
                raise ValueError(f"{owner}: {name} must be one of {BORDERS}, got {value!r}")

    def interpolate(self, keys: Any, time: Any) -> jax.Array:
        """Keyframes ``keys`` ``(K, ...)`` blended at a scalar ``time`` as the traversal blends them (clamped
        outside the range): e.g. the vertices a ray at ``time`` sees.

        Examples:
          >>> import jaxrt as rt
          >>> float(rt.MotionSpec(0.0, 1.0).interpolate([0.0, 2.0, 4.0], 0.25))
          1.0
        """
        return at_time(keys, self, time)


class KeyframePosition(NamedTuple):
    """Where a time falls among the keyframes: blend ``keys[index]`` and ``keys[index + 1]`` by ``weight``."""

    index: jax.Array  # int32 in [0, K - 2]
    weight: jax.Array  # float in [0, 1]
    visible: jax.Array  # bool: False outside the range on a "vanish" border


def keyframe_position(
    time: jax.Array, count: Any, start: Any, end: Any, vanish_start: Any = False, vanish_end: Any = False
) -> KeyframePosition:
    """The keyframe segment, blend weight and visibility at ``time`` (elementwise; parameters may be arrays).

    Args:
      time: the ray's time.
      count: keyframes ``K >= 2``.
      start, end: the times of the first and last keyframe.
      vanish_start, vanish_end: whether the border before ``start`` / after ``end`` is ``"vanish"``.
    """
    time = jnp.asarray(time)
    segments = jnp.asarray(count, jnp.int32) - 1
    # Position in keyframe units; NaN times (never enabled rays) take keyframe 0.
    position = (time - start) / (end - start) * segments.astype(time.dtype)
    position = jnp.where(jnp.isnan(position), 0.0, position)
    clamped = jnp.clip(position, 0.0, segments.astype(time.dtype))
    index = jnp.clip(jnp.floor(clamped).astype(jnp.int32), 0, segments - 1)
    weight = clamped - index.astype(time.dtype)
    visible = ~((time < start) & vanish_start) & ~((time > end) & vanish_end)
    return KeyframePosition(index, weight, visible)


def spec_position(spec: MotionSpec, count: int, time: jax.Array) -> KeyframePosition:
    """:func:`keyframe_position` for a static :class:`MotionSpec` with ``count`` keyframes."""
    return keyframe_position(
        time, count, spec.start_time, spec.end_time, spec.start_border == "vanish", spec.end_border == "vanish"
    )


def blend(a: jax.Array, b: jax.Array, weight: jax.Array) -> jax.Array:
    """``(1 - weight) a + weight b``: exactly ``a`` at weight 0 and exactly ``b`` at weight 1."""
    return (1.0 - weight) * a + weight * b


def keyframe_times(spec: MotionSpec, count: int) -> list[float]:
    """The times of ``count`` evenly spaced keyframes over the spec's range."""
    return [spec.start_time + k * (spec.end_time - spec.start_time) / (count - 1) for k in range(count)]


def interpolate(keys: jax.Array, position: KeyframePosition, rows: Any = None) -> jax.Array:
    """The blend of keyframes ``keys`` ``(K, ...)`` at ``position`` (optionally of rows ``keys[:, rows]``).

    ``rows`` (integer array) gathers rows of the second axis; the position's arrays broadcast against the
    gathered rows' leading shape.
    """
    a = keys[position.index] if rows is None else keys[position.index, rows]
    b = keys[position.index + 1] if rows is None else keys[position.index + 1, rows]
    w = position.weight.reshape(position.weight.shape + (1,) * (a.ndim - position.weight.ndim))
    return blend(a, b, w)


def at_time(keys: jax.Array, spec: MotionSpec, time: Any) -> jax.Array:
    """Keyframes ``keys`` ``(K, ...)`` interpolated at one scalar ``time`` (clamped outside the range).

    Examples:
      >>> import jax.numpy as jnp
      >>> from jaxrt._src.motion import MotionSpec, at_time
      >>> float(at_time(jnp.array([0.0, 2.0, 4.0]), MotionSpec(0.0, 1.0), 0.25))
      1.0
    """
    keys = jnp.asarray(keys)
    position = spec_position(spec, keys.shape[0], jnp.asarray(time, keys.dtype))
    return interpolate(keys, position)


@jax.tree_util.register_pytree_node_class
class LeafKeys:
    """Leaf keyframes ``(K, C, ...)`` read at one ray's keyframe position, indexed like a ``(C, ...)`` array.

    Leaf tests index their leaf arrays with ``array[leaves]``; a ``LeafKeys`` in their place returns the rows
    blended at the ray's time, so the same tests run on moving primitives.
    """

    def __init__(self, keys: jax.Array, position: KeyframePosition):
        self.keys = keys
        self.position = position

    def tree_flatten(self):
        return (self.keys, self.position), None

    @classmethod
    def tree_unflatten(cls, aux, children):
        return cls(*children)

    @property
    def dtype(self):
        return self.keys.dtype

    @property
    def shape(self):
        return self.keys.shape[1:]

    def __getitem__(self, rows):
        rows = jnp.asarray(rows)
        a = self.keys[self.position.index, rows]
        b = self.keys[self.position.index + 1, rows]
        w = jnp.broadcast_to(self.position.weight, rows.shape)
        w = w.reshape(w.shape + (1,) * (a.ndim - w.ndim))
        return blend(a, b, w)


def motion_bounds(lower: jax.Array, upper: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The union over keyframes of boxes ``(K, ..., 3)``: bounds of the primitive at any time.

    Linear interpolation keeps every point of a blended primitive inside the blend of its keyframe boxes,
    which lies inside their union, so the union bounds every time in the range (and the clamped borders).
    """
    return jnp.min(lower, axis=0), jnp.max(upper, axis=0)
