"""Many worlds per step: a per-world function run only on the worlds a mask selects, in a fixed-size bucket.

Robotics and reinforcement-learning loops keep ``N`` copies of a scene (worlds) whose meshes move every step,
and render a depth and segmentation camera in each. :func:`update_worlds` runs a one-world function (rebuild
or refit the world's structure, trace its cameras) over the worlds of a boolean mask: the indices of the
selected worlds are gathered into a bucket of ``capacity`` slots (``jnp.nonzero(mask, size=capacity)``),
the function is ``jax.vmap``-ed over the bucket, and the outputs are scattered back. Worlds outside the mask
keep their previous values bit for bit, and the work is that of ``capacity`` worlds, not ``N``. Should more
worlds be selected than the bucket holds, further buckets follow in a ``lax.while_loop`` (never a silent
skip); a bucket as large as the worlds is a plain ``vmap`` and a select.

With a mesh the worlds are split over its devices (``jax.shard_map`` over the leading axis of every array);
each device gathers its own selected worlds into its own bucket.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from jaxrt._src import pipeline
from jaxrt._src.sharding import _check_mesh, _explicit, _is_traced

__all__ = ["update_worlds", "worlds_capacity"]


def worlds_capacity(mask: Any, mesh: Mesh | None = None) -> int:
    """The bucket :func:`update_worlds` needs for a concrete ``mask``: the power of two at or above the number
    of selected worlds (per device of ``mesh``: the most any device holds), at least 1.

    Pass it as a static argument of a jitted step so that masks of similar counts share one compiled program.

    Examples:
      >>> import numpy as np, jaxrt as rt
      >>> rt.worlds_capacity(np.arange(1000) % 10 == 0)  # 100 of 1000 worlds
      128
    """
    mask = np.asarray(mask)
    if mask.ndim != 1 or mask.dtype != np.bool_:
        raise ValueError(f"worlds_capacity: mask must be a 1-D bool array, got {mask.dtype} {mask.shape}")
    devices = 1 if mesh is None else _check_mesh(mesh, "worlds_capacity").size
    local = -(-mask.shape[0] // devices)
    padded = np.pad(mask, (0, devices * local - mask.shape[0]))
    return pipeline.power_of_two_bucket(int(padded.reshape(devices, local).sum(axis=1).max(initial=0)))


def _check(mask: Any, previous: Any, args: tuple, owner: str) -> int:
    """The world count; ``ValueError`` naming the argument whose leading axis is not the worlds."""
    if getattr(mask, "ndim", None) != 1 or jnp.dtype(mask.dtype) != jnp.bool_:
        raise ValueError(
            f"{owner}: mask must be a 1-D bool array, one entry per world, got "
            f"{getattr(mask, 'dtype', type(mask).__name__)} {getattr(mask, 'shape', '')}"
        )
    n = mask.shape[0]
    for name, tree in [("previous", previous)] + [(f"args[{i}]", a) for i, a in enumerate(args)]:
        for path, leaf in jax.tree_util.tree_leaves_with_path(tree):
            if getattr(leaf, "ndim", 0) < 1 or leaf.shape[0] != n:
                raise ValueError(
                    f"{owner}: every array of {name} must have the {n} worlds on its first axis; "
                    f"{name}{jax.tree_util.keystr(path)} has shape {getattr(leaf, 'shape', ())}"
                )
    return n


def _check_outputs(fn: Callable, previous: Any, args: tuple, owner: str) -> None:
    """``fn`` of one world returns one world of ``previous``: same tree, shapes and dtypes."""
    first = lambda tree: jax.tree_util.tree_map(lambda a: a[0], tree)  # noqa: E731 - one world, traced abstractly
    out = jax.eval_shape(lambda a: fn(*first(a)), args)
    want = jax.eval_shape(first, previous)
    got_tree, want_tree = jax.tree_util.tree_structure(out), jax.tree_util.tree_structure(want)
    if got_tree != want_tree:
        raise ValueError(f"{owner}: fn returns {got_tree}, but previous holds {want_tree} per world")
    for (path, g), w in zip(jax.tree_util.tree_leaves_with_path(out), jax.tree_util.tree_leaves(want), strict=True):
        if g.shape != w.shape or g.dtype != w.dtype:
            raise ValueError(
                f"{owner}: fn returns {g.dtype}{list(g.shape)} at {jax.tree_util.keystr(path)}, but previous "
                f"holds {w.dtype}{list(w.shape)} per world there"
            )


def _local(fn: Callable, capacity: int, mask: jax.Array, previous: Any, args: tuple) -> Any:
    """The masked update of the worlds on one device (every array's first axis is its worlds)."""
    n = mask.shape[0]
    if capacity >= n:  # everything fits one bucket: no gather, a select keeps the others
        new = jax.vmap(fn)(*args)
        return jax.tree_util.tree_map(
            lambda a, b: jnp.where(mask.reshape(n, *([1] * (a.ndim - 1))), a, b), new, previous
        )

    def bucket(carry):
        remaining, state = carry
        index = jnp.nonzero(remaining, size=capacity, fill_value=n)[0]  # n marks an empty slot
        take = jnp.minimum(index, n - 1)  # empty slots compute a copy of the last world, then are dropped
        out = jax.vmap(fn)(*jax.tree_util.tree_map(lambda a: a[take], args))
        state = jax.tree_util.tree_map(lambda s, o: s.at[index].set(o, mode="drop"), state, out)
        return remaining.at[index].set(False, mode="drop"), state

    return lax.while_loop(lambda carry: jnp.any(carry[0]), bucket, (mask, previous))[1]


def _pad_worlds(tree: Any, n: int, total: int) -> Any:
    """Every leaf padded from ``n`` to ``total`` worlds with copies of the last world."""
    return jax.tree_util.tree_map(lambda a: jnp.concatenate([a, jnp.repeat(a[-1:], total - n, axis=0)]), tree)


def _update(fn: Callable, capacity: int, mesh: Mesh | None, mask: jax.Array, previous: Any, args: tuple) -> Any:
    if mesh is None:
        return _local(fn, capacity, mask, previous, args)
    n, devices = mask.shape[0], mesh.size
    total = -(-n // devices) * devices
    if total != n:  # padding worlds: never selected, cut again below
        mask = jnp.concatenate([mask, jnp.zeros(total - n, bool)])
        previous, args = _pad_worlds(previous, n, total), _pad_worlds(args, n, total)
    spec = P(mesh.axis_names)
    if _explicit(mesh):  # explicit axes (jax.make_mesh's default): the worlds laid out over them first
        mask, previous, args = jax.sharding.reshard((mask, previous, args), NamedSharding(mesh, spec))
    mapped = jax.shard_map(
        functools.partial(_local, fn, capacity), mesh=mesh, in_specs=spec, out_specs=spec, check_vma=False
    )
    out = mapped(mask, previous, args)
    if total == n:
        return out
    if _explicit(mesh):  # a sharded axis cannot be cut to a length the devices do not divide
        out = jax.sharding.reshard(out, NamedSharding(mesh, P()))
    return jax.tree_util.tree_map(lambda a: a[:n], out)


_update_jit = jax.jit(_update, static_argnums=(0, 1, 2))


def update_worlds(
    fn: Callable[..., Any],
    mask: Any,
    previous: Any,
    *args: Any,
    capacity: int | None = None,
    mesh: Mesh | None = None,
) -> Any:
    """``fn`` run on the worlds selected by ``mask``; the other worlds keep ``previous``.

    Work follows the bucket: the selected worlds, rounded up to ``capacity``. Inside ``jax.jit`` pass
    ``capacity`` as a static value. Called on concrete arrays it compiles one program per ``fn``, capacity,
    mesh and shapes. Gradients flow through a single bucket that holds every world (``capacity >= N``), not
    through the loop of buckets.

    Args:
      fn: the update of one world, ``fn(*world_args) -> world_output``, an ordinary JAX function (e.g. build
        or refit the world's structure and trace its cameras). It must return one world of ``previous``:
        the same pytree (including a structure's static data, such as its capacity), shapes and dtypes.
      mask: ``(N,)`` bool: the worlds to update.
      previous: the outputs of the last step, every array with the ``N`` worlds on its first axis; returned
        unchanged, bit for bit, where ``mask`` is false.
      *args: the inputs of ``fn``, every array with the worlds on its first axis (world ``i`` gets
        ``arg[i]``); close over what all worlds share.
      capacity: static bucket size (per device with a ``mesh``): ``fn`` runs ``vmap``-ed over ``capacity``
        worlds at a time, as many times as the selected worlds need (one when ``capacity`` is at least their
        count, e.g. :func:`worlds_capacity`). ``None``: :func:`worlds_capacity` of a concrete ``mask``, or
        every world for a traced one.
      mesh: split the worlds over this mesh's devices (``jax.shard_map``; world counts that do not divide are
        padded and cut); ``None``: the default device.

    Returns:
      ``previous`` with the selected worlds replaced by ``fn``'s outputs.

    Examples:
      >>> import jax.numpy as jnp, jaxrt as rt
      >>> mask = jnp.array([True, False, True, False])
      >>> rt.update_worlds(lambda x: 2 * x, mask, jnp.zeros(4), jnp.arange(4.0)).tolist()
      [0.0, 0.0, 4.0, 0.0]
    """
    owner = "update_worlds"
    if not callable(fn):
        raise TypeError(f"{owner}: fn must be callable, got {fn!r}")
    if mesh is not None:
        _check_mesh(mesh, owner)
    if not isinstance(mask, jax.Array | np.ndarray):
        mask = np.asarray(mask)
    n = _check(mask, previous, args, owner)
    if capacity is not None and (isinstance(capacity, bool) or not isinstance(capacity, int) or capacity < 1):
        raise ValueError(f"{owner}: capacity must be a positive int, got {capacity!r}")
    _check_outputs(fn, previous, args, owner)
    devices = 1 if mesh is None else mesh.size
    local = -(-n // devices)
    traced = _is_traced((mask, previous, args))
    if capacity is None:
        capacity = local if isinstance(mask, jax.core.Tracer) else worlds_capacity(np.asarray(mask), mesh)
    capacity = min(capacity, local)
    if traced:
        return _update(fn, capacity, mesh, jnp.asarray(mask), previous, args)
    return _update_jit(fn, capacity, mesh, jnp.asarray(mask), previous, args)
