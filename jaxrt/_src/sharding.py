"""Rays split over the devices of a mesh, the structure replicated: one host or several (``jax.distributed``).

A ray batch of any size is laid out as ``d`` equal rows (``d`` devices), each holding ``ceil(n / d)`` rays
followed by disabled padding up to the bucket :meth:`~jaxrt.Intersector.intersect` pads a batch to (a power of
two, or a multiple of its chunk). Every device traces its row with the ordinary ``intersect`` inside
``jax.shard_map``; the padding is cut before the result is returned, so it never shows. Spreading the padding
over the rows keeps the devices equally loaded whatever ``n``.

The structure is copied whole to every device (:func:`replicate`): a scene must fit one device's memory
beside its share of the rays. Nothing here splits a scene.

With several processes (``jax.distributed.initialize``), every process passes the same rays and structure
(host or local arrays) and gets back global arrays whose shards live on the devices of their process; read
them with ``jax.experimental.multihost_utils.process_allgather`` or ``addressable_shards``.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from jaxrt._src import pipeline
from jaxrt._src.intersector import Intersector
from jaxrt._src.ray import Ray
from jaxrt._src.result import IntersectionResult

__all__ = ["device_mesh", "intersect_sharded", "replicate", "row_layout"]


def device_mesh(devices: Any = None, axis_name: str = "rays") -> Mesh:
    """A one-axis mesh over ``devices`` (default: every device of every process, ``jax.devices()``).

    Args:
      devices: a sequence of devices, an int (the first that many of ``jax.devices()``), or ``None``.
      axis_name: the mesh axis name.

    Returns:
      A :class:`jax.sharding.Mesh` with one axis of ``len(devices)`` devices.

    Raises:
      ValueError: ``devices`` is an int outside ``[1, jax.device_count()]`` or an empty sequence.

    Examples:
      >>> import jaxrt as rt
      >>> dict(rt.device_mesh(1).shape)
      {'rays': 1}
    """
    everything = jax.devices()
    if devices is None:
        chosen = everything
    elif isinstance(devices, int) and not isinstance(devices, bool):
        if not 1 <= devices <= len(everything):
            raise ValueError(f"device_mesh: devices must be in [1, {len(everything)}], got {devices}")
        chosen = everything[:devices]
    else:
        chosen = list(devices)
        if not chosen:
            raise ValueError("device_mesh: devices is an empty sequence")
    return Mesh(np.asarray(chosen, dtype=object), (axis_name,))


def _check_mesh(mesh: Any, owner: str) -> Mesh:
    if not isinstance(mesh, Mesh):
        raise TypeError(f"{owner}: mesh must be a jax.sharding.Mesh (see rt.device_mesh), got {type(mesh).__name__}")
    return mesh


def replicate(tree: Any, mesh: Mesh) -> Any:
    """``tree`` (a structure, or any pytree of arrays) copied whole to every device of ``mesh``.

    A no-op for arrays already replicated there, so a structure replicated once is traced many times without
    copies. With several processes every process must pass the same values.
    """
    _check_mesh(mesh, "replicate")
    sharding = NamedSharding(mesh, P())

    def put(a):
        if isinstance(a, jax.Array) and a.sharding == sharding:
            return a
        if sharding.is_fully_addressable:
            return jax.device_put(a, sharding)
        host = np.asarray(a)
        return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])

    return jax.tree_util.tree_map(put, tree)


def row_layout(n: int, devices: int) -> tuple[int, int]:
    """``(per, rows)``: ``n`` items over ``devices`` rows of ``per = ceil(n / devices)`` items, each padded to
    ``rows`` (the bucket ``intersect`` pads a batch of ``per`` rays to), so a device traces no more padding
    than a single call would."""
    per = max(1, -(-n // devices))
    chunk = pipeline.INTERSECT_CHUNK
    rows = pipeline.power_of_two_bucket(per) if per <= chunk else -(-per // chunk) * chunk
    return per, rows


def _spread(xp: Any, a: Any, n: int, devices: int, per: int, rows: int) -> Any:
    """``(n, ...)`` -> ``(devices * rows, ...)``: row ``k`` holds items ``k*per .. k*per+per-1``, then zeros."""
    tail = [(0, 0)] * (a.ndim - 1)
    a = xp.pad(a, [(0, devices * per - n), *tail])
    a = a.reshape(devices, per, *a.shape[1:])
    a = xp.pad(a, [(0, 0), (0, rows - per), *tail])
    return a.reshape(devices * rows, *a.shape[2:])


def _gather(a: Any, n: int, devices: int, per: int, rows: int, shape: tuple[int, ...], mesh: Mesh) -> Any:
    """The inverse of :func:`_spread`, reshaped to the batch ``shape`` (trailing axes kept). On a mesh with
    explicit axes (``jax.make_mesh``'s default) the rows are first gathered on every device: slicing a
    sharded axis to a length the devices do not divide is not defined there."""
    if _explicit(mesh) and (per != rows or devices * per != n):
        a = jax.sharding.reshard(a, NamedSharding(mesh, P()))
    a = a.reshape(devices, rows, *a.shape[1:])[:, :per]
    return a.reshape(devices * per, *a.shape[2:])[:n].reshape(*shape, *a.shape[2:])


@functools.lru_cache(maxsize=64)
def _program(intersector: Any, mesh: Mesh) -> Any:
    """The jitted ``shard_map`` of ``intersector.intersect`` over the rows of ``mesh`` (structure replicated)."""
    spec = P(mesh.axis_names)
    return jax.jit(
        jax.shard_map(intersector.intersect, mesh=mesh, in_specs=(spec, P()), out_specs=spec, check_vma=False)
    )


@functools.partial(jax.jit, static_argnums=(1, 2, 3, 4, 5, 6))
def _trim(result: Any, n: int, devices: int, per: int, rows: int, shape: tuple[int, ...], mesh: Mesh) -> Any:
    return jax.tree_util.tree_map(lambda a: _gather(a, n, devices, per, rows, shape, mesh), result)


def _explicit(mesh: Mesh) -> bool:
    return any(t == jax.sharding.AxisType.Explicit for t in mesh.axis_types)


def _constrain(tree: Any, sharding: NamedSharding) -> Any:
    """``tree`` laid out by ``sharding`` inside a trace (``reshard`` where the mesh's axes are explicit)."""
    return (
        jax.sharding.reshard(tree, sharding)
        if _explicit(sharding.mesh)
        else jax.lax.with_sharding_constraint(tree, sharding)
    )


def _is_traced(tree: Any) -> bool:
    return any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(tree))


def intersect_sharded(intersector: Any, rays: Ray, structure: Any, *, mesh: Mesh | None = None) -> IntersectionResult:
    """``intersector.intersect(rays, structure)`` with the rays split over the devices of ``mesh``.

    Any number of rays: the batch is padded and spread in equal rows, one per device (:func:`row_layout`),
    and the padding is cut from the result. The structure is replicated (:func:`replicate`; pass it
    replicated already to avoid a copy per call), so it must fit on one device. Works on concrete arrays
    (one compiled program per padded row size) and inside ``jax.jit`` (the caller's program then holds the
    padding and the ``shard_map``). With several processes (``jax.distributed``) every process passes the
    same rays and structure and gets global arrays (the same values as one process).

    Args:
      intersector: an :class:`~jaxrt.Intersector`.
      rays: a :class:`~jaxrt.Ray` batch of any shape.
      structure: a primitive or instance acceleration structure.
      mesh: the devices (default :func:`device_mesh`: all of them); the rays are split over all its axes.

    Returns:
      The :class:`~jaxrt.IntersectionResult` of a single ``intersect`` call (same fields, shapes and hits),
      as arrays spread over the mesh.

    Examples:
      >>> import jaxrt as rt
      >>> s = rt.build_primitive_structure(rt.TriangleGeometry([[0., 0, 0], [1, 0, 0], [0, 1, 0]]))
      >>> rays = rt.Ray([[.2, .2, -1]] * 5, [0., 0, 1])  # five rays, whatever the device count
      >>> rt.intersect_sharded(rt.Intersector(), rays, s).distance.tolist()
      [1.0, 1.0, 1.0, 1.0, 1.0]
    """
    if not isinstance(intersector, Intersector):
        raise TypeError(f"intersect_sharded: intersector must be an rt.Intersector, got {type(intersector).__name__}")
    if not isinstance(rays, Ray):
        raise TypeError(f"intersect_sharded: rays must be a jaxrt.Ray, got {type(rays).__name__}")
    mesh = device_mesh() if mesh is None else _check_mesh(mesh, "intersect_sharded")
    shape = rays.shape
    n = math.prod(shape)
    if n == 0:
        raise ValueError(f"intersect_sharded: rays has no ray (batch shape {shape})")
    devices = mesh.size
    per, rows = row_layout(n, devices)
    flat = rays.reshape(n)
    spec = P(mesh.axis_names)
    if _is_traced((rays, structure)):
        spread = jax.tree_util.tree_map(lambda a: _spread(jnp, a, n, devices, per, rows), flat)
        spread = _constrain(spread, NamedSharding(mesh, spec))
        mapped = jax.shard_map(intersector.intersect, mesh=mesh, in_specs=(spec, P()), out_specs=spec, check_vma=False)
        return jax.tree_util.tree_map(
            lambda a: _gather(a, n, devices, per, rows, shape, mesh), mapped(spread, structure)
        )
    sharding = NamedSharding(mesh, spec)
    exact = per == rows and devices * per == n  # nothing to pad: the rows are the batch as it is
    if sharding.is_fully_addressable:
        spread = flat if exact else jax.tree_util.tree_map(lambda a: _spread(jnp, a, n, devices, per, rows), flat)
        spread = jax.device_put(spread, sharding)
    else:  # several processes: each fills the rows of its own devices from its (identical) host copy
        leaves, tree = jax.tree_util.tree_flatten(flat)
        host = [_spread(np, np.asarray(a), n, devices, per, rows) for a in leaves]  # numpy: no device copy
        spread = jax.tree_util.tree_unflatten(
            tree, [jax.make_array_from_callback(a.shape, sharding, lambda index, a=a: a[index]) for a in host]
        )
    out = _program(intersector, mesh)(spread, replicate(structure, mesh))
    if exact and len(shape) == 1:
        return out
    return _trim(out, n, devices, per, rows, tuple(shape), mesh)
