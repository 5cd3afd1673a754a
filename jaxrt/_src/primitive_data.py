"""Per-primitive user data: one layout per structure, stored in leaf order (Metal's primitive data).

A structure keeps the ``primitive_data`` pytrees of its geometries as one pytree whose leaves have a leading
axis of the structure's capacity, permuted into leaf order, so that the gather after a hit reads the row of
the leaf the traversal found (neighbouring leaves are neighbouring rows). All geometries that carry data must
share one layout (pytree structure, trailing shapes and dtypes of the leaves); rows of geometries without
data, and of padding, are zeros.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["primitive_data_layout", "gather_leaf_data", "data_at"]


def _layout(data: Any) -> tuple:
    leaves, treedef = jax.tree_util.tree_flatten(data)
    return treedef, tuple((tuple(np.shape(x)[1:]), _dtype(x)) for x in leaves)


def _dtype(x: Any) -> np.dtype:
    return x.dtype if isinstance(x, jax.Array) else jnp.asarray(x).dtype


def primitive_data_layout(geometries: tuple[Any, ...]) -> tuple | None:
    """The shared layout of the geometries' primitive data (``None`` when none has data).

    Raises:
      ValueError: two geometries whose data differ in pytree structure, leaf shape or dtype.
    """
    layout, first = None, None
    for index, geometry in enumerate(geometries):
        data = getattr(geometry, "primitive_data", None)
        if data is None:
            continue
        this = _layout(data)
        if layout is None:
            layout, first = this, index
        elif this != layout:
            raise ValueError(
                f"build_primitive_structure: primitive_data of geometries[{index}] has layout {_describe(this)} "
                f"but geometries[{first}] has {_describe(layout)}; the geometries of one structure share one "
                "layout (give every geometry the same fields, zero-filled where unused)"
            )
    return layout


def _describe(layout: tuple) -> str:
    treedef, leaves = layout
    return f"{treedef} with leaves " + ", ".join(f"{dtype}{list(shape)}" for shape, dtype in leaves)


def gather_leaf_data(geometries: tuple[Any, ...], capacity: int, slot: jax.Array) -> Any:
    """The geometries' primitive data concatenated, padded to ``capacity`` rows and gathered at ``slot``.

    ``slot[k]`` is the unsorted primitive slot of leaf ``k`` (``-1`` or past the count: a zero row).
    Returns ``None`` when no geometry has data. Differentiable in the data.
    """
    layout = primitive_data_layout(geometries)
    if layout is None:
        return None
    treedef, leaves = layout
    columns = []
    for position, (shape, dtype) in enumerate(leaves):
        parts = []
        for geometry in geometries:
            if geometry.primitive_data is None:
                parts.append(jnp.zeros((geometry.primitive_count, *shape), dtype))
            else:
                parts.append(jnp.asarray(jax.tree_util.tree_leaves(geometry.primitive_data)[position], dtype))
        column = jnp.concatenate(parts, axis=0)
        count = column.shape[0]
        column = jnp.concatenate([column, jnp.zeros((capacity - count + 1, *shape), dtype)], axis=0)
        columns.append(column[jnp.where((slot < 0) | (slot >= count), capacity, slot)])
    return jax.tree_util.tree_unflatten(treedef, columns)


def data_at(leaf_data: Any, leaf: jax.Array, valid: jax.Array | None = None) -> Any:
    """Rows ``leaf`` of leaf-ordered data (zeros where ``valid`` is False); ``None`` stays ``None``."""
    if leaf_data is None:
        return None

    def take(column):
        row = column[jnp.maximum(leaf, 0)]
        if valid is None:
            return row
        keep = valid.reshape(valid.shape + (1,) * (row.ndim - valid.ndim))
        return jnp.where(keep, row, jnp.zeros_like(row))

    return jax.tree_util.tree_map(take, leaf_data)
