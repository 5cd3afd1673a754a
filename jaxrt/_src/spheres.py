"""Sphere geometry (built-in spheres, as OptiX's and Embree's): a centre and a radius per primitive.

A ray that starts inside a sphere hits it where it leaves it (``sphere_front_facing`` false); see
:mod:`jaxrt._src.kinds.sphere` for the leaf layout and the test.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxrt._src.geometry import (
    _as_float_array,
    _check_finite,
    _check_primitive_data,
    _is_concrete,
    keyframe_error,
    keyframe_stack,
)
from jaxrt._src.kinds import sphere as kind

__all__ = ["MotionSphereGeometry", "SphereGeometry"]


def _float(value: Any, name: str, owner: str) -> jax.Array:
    """``value`` as the geometry's float type; a non-float dtype is a ``ValueError`` naming it."""
    try:
        return _as_float_array(value, name, owner)
    except TypeError as error:
        raise ValueError(str(error)) from None


def _radii(radii: Any, count: int, owner: str) -> jax.Array:
    """Radii ``(N,)`` from one per sphere or a scalar, checked: ``>= 0`` and finite (named ``ValueError``)."""
    radii = _float(radii, "radii", owner)
    if radii.ndim == 0:
        radii = jnp.broadcast_to(radii, (count,))
    if radii.shape != (count,):
        raise ValueError(
            f"{owner}: radii must be a scalar or have shape ({count},) (one per sphere), got {tuple(radii.shape)}"
        )
    if _is_concrete(radii):
        host = np.asarray(radii)
        bad = ~(host >= 0) | ~np.isfinite(host)
        if bad.any():
            index = int(np.argmax(bad))
            raise ValueError(f"{owner}: radii[{index}] = {host[index]} must be finite and >= 0")
    return radii


@jax.tree_util.register_pytree_node_class
class SphereGeometry:
    """Spheres from centres and radii (built-in spheres: no bounding box and intersection function needed).

    Args:
      centers: ``(N, 3)`` float32 (or float64 under x64) sphere centres.
      radii: ``(N,)`` float radii, one per sphere, or one scalar for all; each finite and ``>= 0``.
      primitive_data: optional pytree whose leaves have leading dimension ``N`` (per-sphere user data).
      opaque: static; ``False`` sends candidates to the intersector's filter (one candidate per sphere and ray:
        the hit described below; a rejected one drops the sphere for that ray).

    Hits report ``rt.IntersectionType.SPHERE``. A ray that starts inside a sphere (or enters it before its
    ``min_distance``) hits it where it leaves it, and ``sphere_front_facing`` (``rt.tags.sphere_data``) is
    false there; ``normal`` (``rt.tags.normal``) is the outward normal either way (OptiX's convention).

    Raises:
      ValueError: a non-float dtype, wrong shapes, an empty set, non-finite centres, negative, NaN or infinite
        radii, or primitive data whose leading dimension is not ``N``. The message names the argument and
        the offending value. Inside ``jax.jit`` only shapes and dtypes are checked: build with
        ``checks=True`` for a ``rt.BuildCheckError``; without checks a bad sphere is never hit.

    Examples:
      >>> import jaxrt as rt
      >>> spheres = rt.SphereGeometry([[0., 0, 0], [3, 0, 0]], 1.0)
      >>> hit = rt.Intersector().intersect(rt.Ray([0., 0, 5], [0., 0, -1]), rt.build_primitive_structure(spheres))
      >>> int(hit.type) == rt.IntersectionType.SPHERE, float(hit.distance)
      (True, 4.0)
    """

    kind = kind.SPHERE.name

    def __init__(self, centers: Any, radii: Any, *, primitive_data: Any = None, opaque: bool = True):
        owner = "SphereGeometry"
        centers = _float(centers, "centers", owner)
        if centers.ndim != 2 or centers.shape[1] != 3:
            raise ValueError(f"{owner}: centers must have shape (N, 3), got {tuple(centers.shape)}")
        if centers.shape[0] == 0:
            raise ValueError(f"{owner}: centers is empty (shape {tuple(centers.shape)}); a geometry needs a sphere")
        _check_finite(centers, "centers", owner)
        radii = _radii(radii, centers.shape[0], owner)
        if primitive_data is not None:
            _check_primitive_data(primitive_data, centers.shape[0], owner)
        self.centers = centers
        self.radii = radii
        self.primitive_data = primitive_data
        self.opaque = bool(opaque)

    @property
    def primitive_count(self) -> int:
        """Number of spheres (static)."""
        return int(self.centers.shape[0])

    def leaf_rows(self) -> jax.Array:
        """``(N, 3, 3)`` the spheres as leaf rows (:mod:`jaxrt._src.kinds.sphere`), differentiable."""
        return kind.rows(self.centers, self.radii)

    def bounds(self) -> tuple[jax.Array, jax.Array]:
        """``(N, 3)`` lower and upper corners of each sphere's box."""
        return kind.bounds(self.leaf_rows())

    def tree_flatten(self):
        return (self.centers, self.radii, self.primitive_data), (self.opaque,)

    @classmethod
    def tree_unflatten(cls, aux, children):
        obj = object.__new__(cls)
        obj.centers, obj.radii, obj.primitive_data = children
        (obj.opaque,) = aux
        return obj

    def __repr__(self) -> str:
        return f"SphereGeometry(spheres={self.primitive_count}, opaque={self.opaque})"


@jax.tree_util.register_pytree_node_class
class MotionSphereGeometry:
    """Spheres whose centres and radii move through ``K >= 2`` keyframes, evenly spaced over the structure's
    :class:`~jaxrt.MotionSpec`; a ray with time ``t`` sees centres and radii blended linearly between its two
    neighbouring keyframes.

    Args:
      centers: ``(K, N, 3)`` float centres per keyframe (or a sequence of ``K`` ``(N, 3)`` arrays).
      radii: ``(K, N)`` radii per keyframe, ``(N,)`` or a scalar (the same at every keyframe).
      primitive_data: optional pytree with leading dimension ``N`` (not keyframed).
      opaque: static; ``False`` sends candidates to the filter.

    Raises:
      ValueError: fewer than 2 keyframes, keyframes of different shapes, or any error of
        :class:`SphereGeometry` on a keyframe.

    Examples:
      >>> import jaxrt as rt
      >>> g = rt.MotionSphereGeometry([[[0., 0, 0]], [[1., 0, 0]]], [[1.0], [2.0]])
      >>> g.keyframe_count, g.primitive_count
      (2, 1)
    """

    kind = kind.SPHERE.name
    motion = True

    def __init__(self, centers: Any, radii: Any, *, primitive_data: Any = None, opaque: bool = True):
        owner = "MotionSphereGeometry"
        try:
            centers = keyframe_stack(centers, "centers", owner, (-1, 3))
        except TypeError as error:
            raise ValueError(str(error)) from None
        keys, count = centers.shape[0], centers.shape[1]
        radii = _float(radii, "radii", owner)
        if radii.ndim < 2:
            radii = jnp.broadcast_to(radii, (keys, count) if radii.ndim == 0 else (keys, *radii.shape))
        if radii.shape != (keys, count):
            raise ValueError(
                f"{owner}: radii must be a scalar or have shape ({count},) or ({keys}, {count}), got "
                f"{tuple(radii.shape)}"
            )
        for k in range(keys):
            try:
                SphereGeometry(centers[k], radii[k], primitive_data=primitive_data if k == 0 else None)
            except ValueError as error:
                raise keyframe_error(owner, k, error) from None
        self.centers = centers
        self.radii = radii
        self.primitive_data = primitive_data
        self.opaque = bool(opaque)

    @property
    def keyframe_count(self) -> int:
        """``K`` (static)."""
        return int(self.centers.shape[0])

    @property
    def primitive_count(self) -> int:
        """Number of spheres (static)."""
        return int(self.centers.shape[1])

    def keyframe(self, k: int) -> SphereGeometry:
        """The static geometry of keyframe ``k`` (differentiable; no validation, so usable inside ``jit``)."""
        return SphereGeometry.tree_unflatten((self.opaque,), (self.centers[k], self.radii[k], self.primitive_data))

    def tree_flatten(self):
        return (self.centers, self.radii, self.primitive_data), (self.opaque,)

    @classmethod
    def tree_unflatten(cls, aux, children):
        obj = object.__new__(cls)
        obj.centers, obj.radii, obj.primitive_data = children
        (obj.opaque,) = aux
        return obj

    def __repr__(self) -> str:
        return f"MotionSphereGeometry(keyframes={self.keyframe_count}, spheres={self.primitive_count}, opaque={self.opaque})"
