"""The ray pytree."""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxrt._src.geometry import float_dtype

__all__ = ["Ray"]


def _float(value: Any, name: str) -> jax.Array:
    dtype = getattr(value, "dtype", None)
    if dtype is None:
        value = np.asarray(value)
        dtype = value.dtype
    if not (np.issubdtype(np.dtype(dtype), np.floating) or np.issubdtype(np.dtype(dtype), np.integer)):
        raise TypeError(f"Ray: {name} must be a float array, got dtype {dtype}")
    return jnp.asarray(value, float_dtype())


def _mask(value: Any) -> jax.Array:
    if isinstance(value, jax.Array):
        return value.astype(jnp.uint32)
    host = np.asarray(value)
    if host.size and ((host < 0).any() or (host > 0xFFFFFFFF).any()):
        raise ValueError(f"Ray: mask values must be in [0, 2**32), got {host.min()}..{host.max()}")
    return jnp.asarray(host.astype(np.uint32))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True, init=False)
class Ray:
    """A batch of rays with any leading batch shape (Metal's ``ray``).

    Args:
      origin: ``(..., 3)`` ray origins.
      direction: ``(..., 3)`` directions. They need not be unit length: distances are measured in units
        of the direction's length (the hit point is ``origin + distance * direction``).
      min_distance, max_distance: the accepted hit interval, broadcast to the batch shape.
      mask: uint32 ray mask, tested against instance masks; 0 disables the ray.
      time: the ray's time for motion blur (ignored by static geometry).

    A ray is disabled (it misses, at no cost and with no NaN in the result) when ``max_distance <
    min_distance``, its mask is 0, its direction is zero, or any component is NaN.

    Examples:
      >>> import jaxrt as rt
      >>> r = rt.Ray([0., 0, -1], [0., 0, 1])
      >>> r.shape
      ()
    """

    origin: jax.Array
    direction: jax.Array
    min_distance: jax.Array
    max_distance: jax.Array
    mask: jax.Array
    time: jax.Array

    def __init__(
        self,
        origin: Any,
        direction: Any,
        min_distance: Any = 0.0,
        max_distance: Any = jnp.inf,
        mask: Any = 0xFFFFFFFF,
        time: Any = 0.0,
    ):
        origin = _float(origin, "origin")
        direction = _float(direction, "direction")
        if origin.ndim < 1 or origin.shape[-1] != 3:
            raise ValueError(f"Ray: origin must have shape (..., 3), got {tuple(origin.shape)}")
        if direction.ndim < 1 or direction.shape[-1] != 3:
            raise ValueError(f"Ray: direction must have shape (..., 3), got {tuple(direction.shape)}")
        try:
            batch = jnp.broadcast_shapes(origin.shape[:-1], direction.shape[:-1])
        except ValueError:
            raise ValueError(
                f"Ray: origin {tuple(origin.shape)} and direction {tuple(direction.shape)} batch shapes do not broadcast"
            ) from None
        mask_dtype = np.dtype(getattr(mask, "dtype", None) or np.asarray(mask).dtype)
        if not np.issubdtype(mask_dtype, np.integer):
            raise TypeError(f"Ray: mask must be an integer array, got dtype {mask_dtype}")
        fields = dict(
            origin=jnp.broadcast_to(origin, (*batch, 3)),
            direction=jnp.broadcast_to(direction, (*batch, 3)),
            min_distance=_float(min_distance, "min_distance"),
            max_distance=_float(max_distance, "max_distance"),
            mask=_mask(mask),
            time=_float(time, "time"),
        )
        for name in ("min_distance", "max_distance", "mask", "time"):
            try:
                fields[name] = jnp.broadcast_to(fields[name], batch)
            except ValueError:
                raise ValueError(
                    f"Ray: {name} of shape {tuple(fields[name].shape)} does not broadcast to {batch}"
                ) from None
        for name, value in fields.items():
            object.__setattr__(self, name, value)

    @property
    def shape(self) -> tuple[int, ...]:
        """The batch shape."""
        return tuple(self.origin.shape[:-1])

    def reshape(self, *shape: int) -> Ray:
        """The same rays with another batch shape."""
        return jax.tree_util.tree_map(lambda a: a.reshape(*shape, *a.shape[len(self.shape) :]), self)
