"""Geometry descriptors and their validation.

A geometry is an immutable pytree: its arrays (vertices, indices, primitive data) are leaves, its
configuration (opacity) is static. Validation runs on the host in the constructor wherever the arrays are
concrete; inside ``jax.jit`` (traced arrays) only shapes and dtypes can be checked.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxrt._src.kinds.bounding_box import BOUNDING_BOX
from jaxrt._src.kinds.triangle import TRIANGLE

__all__ = [
    "BoundingBoxGeometry",
    "MotionBoundingBoxGeometry",
    "MotionTriangleGeometry",
    "TriangleGeometry",
    "float_dtype",
    "keyframe_error",
    "keyframe_stack",
]


def float_dtype() -> jnp.dtype:
    """The float dtype geometry is stored in: float64 under ``jax_enable_x64``, else float32."""
    return jnp.dtype(jnp.float64) if jax.config.jax_enable_x64 else jnp.dtype(jnp.float32)


def _is_concrete(x: Any) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _as_float_array(value: Any, name: str, owner: str) -> jax.Array:
    dtype = getattr(value, "dtype", None)
    if dtype is None:
        value = np.asarray(value)
        dtype = value.dtype
    dtype = np.dtype(dtype)
    if dtype not in (np.float32, np.float64):
        raise TypeError(f"{owner}: {name} must be float32 or float64, got dtype {dtype}")
    return jnp.asarray(value, float_dtype())


def _check_finite(array: jax.Array, name: str, owner: str) -> None:
    if not _is_concrete(array):
        return
    host = np.asarray(array)
    bad = ~np.isfinite(host)
    if bad.any():
        index = tuple(int(i) for i in np.argwhere(bad)[0])
        raise ValueError(f"{owner}: {name} has a non-finite value {host[index]} at index {index}")


def _check_primitive_data(data: Any, count: int, owner: str) -> None:
    for path, leaf in jax.tree_util.tree_leaves_with_path(data):
        shape = np.shape(leaf)
        if len(shape) == 0 or shape[0] != count:
            where = jax.tree_util.keystr(path) or "(root)"
            raise ValueError(
                f"{owner}: primitive_data leaf {where} has shape {shape}; its leading dimension must equal "
                f"the primitive count {count}"
            )


def _gather_rows(values: jax.Array, indices: jax.Array) -> jax.Array:
    """``values[indices]`` for ``(T, n)`` indices, with every row of a primitive that has an index outside
    ``[0, len(values))`` set to zero (a gather alone clamps or wraps such an index to a real row)."""
    count = values.shape[0]
    in_range = jnp.all((indices >= 0) & (indices < count), axis=-1)
    rows = values[jnp.where(in_range[:, None], indices, 0)]
    return jnp.where(in_range.reshape(in_range.shape + (1,) * (rows.ndim - 1)), rows, jnp.zeros((), rows.dtype))


@jax.tree_util.register_pytree_node_class
class TriangleGeometry:
    """Triangles from a vertex buffer and an optional index buffer (Metal's triangle geometry descriptor).

    Args:
      vertices: ``(V, 3)`` float32 (or float64 under x64) vertex positions.
      indices: ``(T, 3)`` integer vertex indices per triangle; ``None`` takes consecutive vertex triples.
      primitive_data: optional pytree whose leaves have leading dimension ``T`` (per-triangle user data).
      opaque: static; ``False`` marks the geometry as alpha-tested (candidates go to the filter).

    Raises:
      TypeError: a non-float ``vertices`` or non-integer ``indices`` dtype.
      ValueError: wrong shapes, empty geometry, non-finite vertices, indices out of range, or primitive data
        whose leading dimension is not ``T``. The message names the argument and the offending value.

    Examples:
      >>> import jaxrt as rt
      >>> tri = rt.TriangleGeometry([[0., 0, 0], [1, 0, 0], [0, 1, 0]])
      >>> tri.primitive_count
      1
    """

    kind = TRIANGLE.name

    def __init__(self, vertices: Any, indices: Any = None, *, primitive_data: Any = None, opaque: bool = True):
        owner = "TriangleGeometry"
        vertices = _as_float_array(vertices, "vertices", owner)
        if vertices.ndim != 2 or vertices.shape[1] != 3:
            raise ValueError(f"{owner}: vertices must have shape (V, 3), got {tuple(vertices.shape)}")
        if vertices.shape[0] == 0:
            raise ValueError(f"{owner}: vertices is empty (shape {tuple(vertices.shape)}); a geometry needs a triangle")
        _check_finite(vertices, "vertices", owner)
        if indices is None:
            if vertices.shape[0] % 3:
                raise ValueError(
                    f"{owner}: without indices the vertex count must be a multiple of 3, got {vertices.shape[0]}"
                )
            indices = jnp.arange(vertices.shape[0], dtype=jnp.int32).reshape(-1, 3)
        else:
            dtype = np.dtype(getattr(indices, "dtype", None) or np.asarray(indices).dtype)
            if not np.issubdtype(dtype, np.integer):
                raise TypeError(f"{owner}: indices must have an integer dtype, got {dtype}")
            if _is_concrete(indices):
                host = np.asarray(indices)
                if host.ndim != 2 or host.shape[1] != 3:
                    raise ValueError(f"{owner}: indices must have shape (T, 3), got {host.shape}")
                if host.shape[0] == 0:
                    raise ValueError(f"{owner}: indices is empty (shape {host.shape}); a geometry needs a triangle")
                bad = (host < 0) | (host >= vertices.shape[0])
                if bad.any():
                    t, c = (int(i) for i in np.argwhere(bad)[0])
                    raise ValueError(
                        f"{owner}: indices[{t}, {c}] = {int(host[t, c])} is out of range for "
                        f"{vertices.shape[0]} vertices"
                    )
                if host.max() > np.iinfo(np.int32).max:
                    raise ValueError(f"{owner}: indices exceed the int32 range")
            elif indices.ndim != 2 or indices.shape[1] != 3 or indices.shape[0] == 0:
                raise ValueError(f"{owner}: indices must have shape (T, 3) with T > 0, got {tuple(indices.shape)}")
            indices = jnp.asarray(indices, jnp.int32)
        if primitive_data is not None:
            _check_primitive_data(primitive_data, indices.shape[0], owner)
        self.vertices = vertices
        self.indices = indices
        self.primitive_data = primitive_data
        self.opaque = bool(opaque)

    @property
    def primitive_count(self) -> int:
        """Number of triangles (static)."""
        return int(self.indices.shape[0])

    def triangle_vertices(self) -> jax.Array:
        """``(T, 3, 3)`` vertex positions per triangle (differentiable gather).

        A triangle with an index out of range (possible only for traced indices, which the constructor cannot
        check) gets three vertices at the origin: it has no area, so the build gives it an empty box and no ray
        hits it. (A plain gather would clamp or wrap the index to some other vertex and make a triangle that
        rays hit.)
        """
        return _gather_rows(self.vertices, self.indices)

    def tree_flatten(self):
        return (self.vertices, self.indices, self.primitive_data), (self.opaque,)

    @classmethod
    def tree_unflatten(cls, aux, children):
        obj = object.__new__(cls)
        obj.vertices, obj.indices, obj.primitive_data = children
        (obj.opaque,) = aux
        return obj

    def __repr__(self) -> str:
        return f"TriangleGeometry(vertices={tuple(self.vertices.shape)}, triangles={self.primitive_count}, opaque={self.opaque})"


@jax.tree_util.register_pytree_node_class
class BoundingBoxGeometry:
    """Axis-aligned boxes whose hits come from an intersection function (Metal's bounding-box geometry).

    The traversal finds the boxes a ray enters and calls the intersector's intersection function for this
    geometry on each, nearest box first; the function decides whether and where the ray hits the primitive
    inside the box (see ``rt.intersection_functions`` for analytic spheres, disks and capped cylinders).

    Args:
      lower, upper: ``(N, 3)`` float box corners, ``lower <= upper`` componentwise.
      primitive_data: optional pytree whose leaves have leading dimension ``N`` (given to the function).
      opaque: static; kept for Metal parity (every box hit is decided by its function).

    Raises:
      TypeError: a non-float dtype. ValueError: wrong shapes, empty geometry, non-finite corners, an
        inverted box (``lower > upper``), or primitive data whose leading dimension is not ``N``.

    Examples:
      >>> import jaxrt as rt
      >>> rt.BoundingBoxGeometry([[-1., -1, -1]], [[1., 1, 1]]).primitive_count
      1
    """

    kind = BOUNDING_BOX.name

    def __init__(self, lower: Any, upper: Any, *, primitive_data: Any = None, opaque: bool = True):
        owner = "BoundingBoxGeometry"
        lower = _as_float_array(lower, "lower", owner)
        upper = _as_float_array(upper, "upper", owner)
        for name, value in (("lower", lower), ("upper", upper)):
            if value.ndim != 2 or value.shape[1] != 3:
                raise ValueError(f"{owner}: {name} must have shape (N, 3), got {tuple(value.shape)}")
        if lower.shape != upper.shape:
            raise ValueError(f"{owner}: lower {tuple(lower.shape)} and upper {tuple(upper.shape)} differ in shape")
        if lower.shape[0] == 0:
            raise ValueError(f"{owner}: lower is empty (shape {tuple(lower.shape)}); a geometry needs a box")
        _check_finite(lower, "lower", owner)
        _check_finite(upper, "upper", owner)
        if _is_concrete(lower) and _is_concrete(upper):
            inverted = np.asarray(lower) > np.asarray(upper)
            if inverted.any():
                box, axis = (int(i) for i in np.argwhere(inverted)[0])
                raise ValueError(
                    f"{owner}: box {box} is inverted on axis {axis}: lower {float(lower[box, axis])} > "
                    f"upper {float(upper[box, axis])}"
                )
        if primitive_data is not None:
            _check_primitive_data(primitive_data, lower.shape[0], owner)
        self.lower = lower
        self.upper = upper
        self.primitive_data = primitive_data
        self.opaque = bool(opaque)

    @property
    def primitive_count(self) -> int:
        """Number of boxes (static)."""
        return int(self.lower.shape[0])

    def bounds(self) -> tuple[jax.Array, jax.Array]:
        """``(N, 3)`` lower and upper corners of each primitive's box."""
        return self.lower, self.upper

    def tree_flatten(self):
        return (self.lower, self.upper, self.primitive_data), (self.opaque,)

    @classmethod
    def tree_unflatten(cls, aux, children):
        obj = object.__new__(cls)
        obj.lower, obj.upper, obj.primitive_data = children
        (obj.opaque,) = aux
        return obj

    def __repr__(self) -> str:
        return f"BoundingBoxGeometry(boxes={self.primitive_count}, opaque={self.opaque})"


# --- keyframe motion ---------------------------------------------------------------------------------------------


def keyframe_stack(value: Any, name: str, owner: str, trailing: tuple[int, ...] | None = None) -> jax.Array:
    """A float ``(K, ...)`` keyframe array from an array or a sequence of per-keyframe arrays, validated.

    Raises a ``ValueError`` naming ``owner`` and ``name`` for fewer than two keyframes, keyframes of different
    shapes, a wrong trailing shape (``trailing``; ``-1`` matches any size) or non-finite values.
    """
    if isinstance(value, list | tuple) and value and not np.isscalar(value[0]):
        frames = [_as_float_array(v, f"{name}[{k}]", owner) for k, v in enumerate(value)]
        for k, frame in enumerate(frames[1:], 1):
            if frame.shape != frames[0].shape:
                raise ValueError(
                    f"{owner}: keyframe {k} of {name} has shape {tuple(frame.shape)}, keyframe 0 has "
                    f"{tuple(frames[0].shape)}; every keyframe needs the same shape"
                )
        value = jnp.stack(frames)
    else:
        value = _as_float_array(value, name, owner)
    if value.ndim < 1 or value.shape[0] < 2:
        raise ValueError(
            f"{owner}: {name} needs at least 2 keyframes on its leading axis, got shape {tuple(value.shape)}"
        )
    if trailing is not None and (
        value.ndim != 1 + len(trailing) or any(t not in (-1, s) for t, s in zip(trailing, value.shape[1:], strict=True))
    ):
        want = ", ".join("n" if t == -1 else str(t) for t in trailing)
        raise ValueError(f"{owner}: {name} must have shape (K, {want}), got {tuple(value.shape)}")
    _check_finite(value, name, owner)
    return value


def keyframe_error(owner: str, k: int, error: Exception) -> Exception:
    """``error`` from validating keyframe ``k`` as a static geometry, reworded for ``owner``."""
    message = str(error).split(": ", 1)[-1]
    return type(error)(f"{owner}: keyframe {k}: {message}")


@jax.tree_util.register_pytree_node_class
class MotionTriangleGeometry:
    """Triangles whose vertices move through ``K >= 2`` keyframes (Metal's motion triangle geometry).

    The keyframes are evenly spaced over the structure's :class:`~jaxrt.MotionSpec` time range; a ray with
    time ``t`` sees the vertices blended linearly between its two neighbouring keyframes.

    Args:
      vertices: ``(K, V, 3)`` float vertex positions per keyframe (or a sequence of ``K`` ``(V, 3)`` arrays).
      indices: ``(T, 3)`` integer vertex indices, shared by every keyframe; ``None``: consecutive triples.
      primitive_data: optional pytree with leading dimension ``T`` (per-triangle data; not keyframed).
      opaque: static; ``False`` sends candidates to the filter.

    Raises:
      TypeError: non-float vertices or non-integer indices. ValueError: fewer than 2 keyframes, keyframes of
        different shapes, non-finite vertices, or any error of :class:`TriangleGeometry` on a keyframe.

    Examples:
      >>> import jaxrt as rt
      >>> tri = [[0., 0, 0], [1, 0, 0], [0, 1, 0]]
      >>> g = rt.MotionTriangleGeometry([tri, [[0., 0, 1], [1, 0, 1], [0, 1, 1]]])
      >>> g.keyframe_count, g.primitive_count
      (2, 1)
    """

    kind = TRIANGLE.name
    motion = True

    def __init__(self, vertices: Any, indices: Any = None, *, primitive_data: Any = None, opaque: bool = True):
        owner = "MotionTriangleGeometry"
        vertices = keyframe_stack(vertices, "vertices", owner, (-1, 3))
        try:
            first = TriangleGeometry(vertices[0], indices, primitive_data=primitive_data, opaque=opaque)
        except (TypeError, ValueError) as error:
            raise keyframe_error(owner, 0, error) from None
        self.vertices = vertices
        self.indices = first.indices
        self.primitive_data = primitive_data
        self.opaque = bool(opaque)

    @property
    def keyframe_count(self) -> int:
        """``K`` (static)."""
        return int(self.vertices.shape[0])

    @property
    def primitive_count(self) -> int:
        """Number of triangles (static)."""
        return int(self.indices.shape[0])

    def keyframe(self, k: int) -> TriangleGeometry:
        """The static geometry of keyframe ``k`` (differentiable; no validation, so usable inside ``jit``)."""
        return TriangleGeometry.tree_unflatten((self.opaque,), (self.vertices[k], self.indices, self.primitive_data))

    def tree_flatten(self):
        return (self.vertices, self.indices, self.primitive_data), (self.opaque,)

    @classmethod
    def tree_unflatten(cls, aux, children):
        obj = object.__new__(cls)
        obj.vertices, obj.indices, obj.primitive_data = children
        (obj.opaque,) = aux
        return obj

    def __repr__(self) -> str:
        return (
            f"MotionTriangleGeometry(keyframes={self.keyframe_count}, vertices={tuple(self.vertices.shape[1:])}, "
            f"triangles={self.primitive_count}, opaque={self.opaque})"
        )


@jax.tree_util.register_pytree_node_class
class MotionBoundingBoxGeometry:
    """Boxes that move through ``K >= 2`` keyframes (Metal's motion bounding-box geometry).

    The intersection function receives the box blended at the ray's time in its candidate.

    Args:
      lower, upper: ``(K, N, 3)`` float box corners per keyframe (or sequences of ``K`` ``(N, 3)`` arrays).
      primitive_data: optional pytree with leading dimension ``N``.
      opaque: static; kept for Metal parity.

    Raises:
      TypeError: non-float corners. ValueError: fewer than 2 keyframes, keyframe shapes that differ (between
        keyframes or between ``lower`` and ``upper``), non-finite corners, or an inverted box in a keyframe.

    Examples:
      >>> import jaxrt as rt
      >>> g = rt.MotionBoundingBoxGeometry([[[0., 0, 0]], [[1., 0, 0]]], [[[1., 1, 1]], [[2., 1, 1]]])
      >>> g.keyframe_count, g.primitive_count
      (2, 1)
    """

    kind = BOUNDING_BOX.name
    motion = True

    def __init__(self, lower: Any, upper: Any, *, primitive_data: Any = None, opaque: bool = True):
        owner = "MotionBoundingBoxGeometry"
        lower = keyframe_stack(lower, "lower", owner, (-1, 3))
        upper = keyframe_stack(upper, "upper", owner, (-1, 3))
        if lower.shape != upper.shape:
            raise ValueError(
                f"{owner}: lower {tuple(lower.shape)} and upper {tuple(upper.shape)} keyframes differ in shape"
            )
        for k in range(lower.shape[0]):
            try:
                BoundingBoxGeometry(lower[k], upper[k], primitive_data=primitive_data if k == 0 else None)
            except (TypeError, ValueError) as error:
                raise keyframe_error(owner, k, error) from None
        self.lower = lower
        self.upper = upper
        self.primitive_data = primitive_data
        self.opaque = bool(opaque)

    @property
    def keyframe_count(self) -> int:
        """``K`` (static)."""
        return int(self.lower.shape[0])

    @property
    def primitive_count(self) -> int:
        """Number of boxes (static)."""
        return int(self.lower.shape[1])

    def keyframe(self, k: int) -> BoundingBoxGeometry:
        """The static geometry of keyframe ``k`` (no validation, so usable inside ``jit``)."""
        return BoundingBoxGeometry.tree_unflatten((self.opaque,), (self.lower[k], self.upper[k], self.primitive_data))

    def tree_flatten(self):
        return (self.lower, self.upper, self.primitive_data), (self.opaque,)

    @classmethod
    def tree_unflatten(cls, aux, children):
        obj = object.__new__(cls)
        obj.lower, obj.upper, obj.primitive_data = children
        (obj.opaque,) = aux
        return obj

    def __repr__(self) -> str:
        return f"MotionBoundingBoxGeometry(keyframes={self.keyframe_count}, boxes={self.primitive_count}, opaque={self.opaque})"
