"""The GPU kernel's rows that a primitive structure carries (``kernel_layout``), packed on the GPU side.

The public :class:`~jaxrt.PrimitiveAccelerationStructure` keeps the kernel's node and triangle rows
(:class:`~jaxrt._src.traversal.packed.KernelLayout`, 112 bytes per leaf slot), so that a trace on the GPU does
not repack them per call. The build module (:mod:`jaxrt._src.structures`) knows nothing of the kernel: the
field is an opaque pytree there, and its build and refit take the packer as a static argument. This module,
above both the build and the traversal, decides where a structure carries the rows and passes the kernel's
packer (:func:`jaxrt._src.traversal.packed.kernel_layout`): it is the home of the public
``rt.build_primitive_structure`` and ``rt.refit``, and compaction and loading call :func:`with_kernel_layout`.
"""

from __future__ import annotations

import dataclasses
import importlib.util
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp

from jaxrt._src.instances import InstanceAccelerationStructure, refit_instances
from jaxrt._src.kinds.registry import TRIANGLE
from jaxrt._src.structures import (
    QUALITIES,
    GeometryInfo,
    PrimitiveAccelerationStructure,
    as_geometry_tuple,
    build_structure,
    geometries_dtype,
    geometry_info,
    refit_primitives,
)
from jaxrt._src.traversal import packed

__all__ = ["build_primitive_structure", "kernel_layout_wanted", "refit", "with_kernel_layout"]


def kernel_layout_wanted(geometry_info: tuple[GeometryInfo, ...], dtype: Any) -> bool:
    """Whether a structure of these geometries gets a packed ``KernelLayout`` by default: the GPU kernel
    can trace it here (a GPU backend with Triton and jax-triton installed; float32 triangles, no motion)."""
    if jax.default_backend() != "gpu" or jnp.dtype(dtype) != jnp.float32:
        return False
    if any(not TRIANGLE.holds(g) or g.motion for g in geometry_info):
        return False
    return all(importlib.util.find_spec(name) is not None for name in ("triton", "jax_triton"))


def with_kernel_layout(
    structure: PrimitiveAccelerationStructure, wanted: bool | None = None
) -> PrimitiveAccelerationStructure:
    """``structure`` with its ``KernelLayout`` packed from its arrays (``wanted`` true, or ``None`` and
    :func:`kernel_layout_wanted`), or without one."""
    if wanted is None:
        wanted = kernel_layout_wanted(structure.geometry_info, structure.node_lower.dtype)
    layout = None
    if wanted:
        layout = packed.kernel_layout(
            structure.node_lower, structure.node_upper, structure.node_children, structure.leaf_triangle
        )
    return dataclasses.replace(structure, kernel_layout=layout)


def build_primitive_structure(
    geometries: Any | Sequence[Any],
    *,
    motion: Any = None,
    capacity: int | None = None,
    quality: str = "fast",
    checks: bool = False,
    kernel_layout: bool | None = None,
) -> PrimitiveAccelerationStructure:
    """Build an LBVH over one or more geometries (jitted; also callable on traced arrays inside ``jax.jit``).

    Morton codes of the primitive box centroids (30 bits), a stable radix sort, the Karras 2012 radix tree
    with the index tie-break for equal codes, and node boxes from a sparse-table range reduction.

    Args:
      geometries: a geometry or a sequence of them; hits report the position in this sequence as
        ``geometry_id``.
      motion: the time range and border modes (a :class:`~jaxrt.MotionSpec`) of the ``Motion*Geometry``
        keyframes among ``geometries`` (required with them, refused without them). Every motion geometry of
        the structure has the same keyframe count; static geometries stay put at every time. Node boxes bound
        each primitive over all keyframes (the union of its keyframe boxes); rays read ``rt.Ray.time``.
      capacity: optional minimum number of primitive slots. The capacity is rounded up to a power of two
        (at least 2) so that scenes of similar size share compiled code.
      quality: ``"fast"`` (the LBVH) or ``"high"`` (the LBVH restructured by agglomerative clustering, PLOC,
        :mod:`jaxrt._src.bvh.ploc`): a lower SAH cost at 3 to 10 times the build time; faster to trace where
        triangle sizes vary a lot (building interiors), about as fast on evenly tessellated meshes
        (docs/performance.md); or ``"sah"``: a top-down SAH tree that sweeps every split position on each
        axis (:mod:`jaxrt._src.bvh.sweep_sah`; one pass of three sorts per tree level, so it builds slower
        still, for static scenes traced many times). Same node layout in every case.
      checks: also check traced inputs (non-finite coordinates, negative radii, inverted boxes, indices out
        of range), which constructors check only when concrete: a :class:`~jaxrt._src.checks.BuildCheckError`
        (inside ``jit``, a ``jax.errors.JaxRuntimeError`` carrying its message, which
        :func:`~jaxrt.build_check_errors` raises as the former) instead of silent misses.
        Costs a host synchronisation per build (:mod:`jaxrt._src.checks`).
      kernel_layout: also store the GPU kernel's packed node and triangle rows (112 bytes per leaf slot), so
        that traces on the GPU do not repack them per call. ``None`` (the default): where the GPU kernel can
        trace the structure (a GPU backend with Triton and jax-triton; float32 triangles without motion).

    Returns:
      A :class:`~jaxrt.PrimitiveAccelerationStructure`. Leaf vertices keep their gradient connection to the
      geometry, so hit distances and barycentrics differentiate through the build.

    Examples:
      >>> import jaxrt as rt
      >>> s = rt.build_primitive_structure(rt.TriangleGeometry([[0., 0, 0], [1, 0, 0], [0, 1, 0]]))
      >>> s.capacity
      2
    """
    if quality not in QUALITIES:
        raise ValueError(f"build_primitive_structure: quality must be one of {QUALITIES}, got {quality!r}")
    if kernel_layout is None:
        items = as_geometry_tuple(geometries)  # named errors first
        kernel_layout = kernel_layout_wanted(tuple(map(geometry_info, items)), geometries_dtype(items))
    packer = packed.kernel_layout if kernel_layout else None
    return build_structure(geometries, motion=motion, capacity=capacity, quality=quality, checks=checks, packer=packer)


def refit(structure: Any, geometries_or_instances: Any) -> Any:
    """Recompute the boxes of ``structure`` for moved geometry, keeping its topology (Metal's refit).

    A primitive structure is refit with geometries of the same kinds and primitive counts as those it was
    built from; tree quality degrades as primitives move far from where they were built (rebuild then). An
    instance structure is refit with new :class:`~jaxrt.Instances` (same slot count; its children are kept).
    A primitive structure that carries the GPU kernel's rows gets them repacked.
    """
    if isinstance(structure, InstanceAccelerationStructure):
        return refit_instances(structure, geometries_or_instances)
    packer = None if structure.kernel_layout is None else packed.kernel_layout
    return refit_primitives(structure, geometries_or_instances, packer)
