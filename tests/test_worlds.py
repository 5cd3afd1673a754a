"""Many worlds per step (``rt.update_worlds``): the worlds a mask selects are updated as a full update would
update them, in one bucket or several, and every other world keeps its previous state bit for bit.

The worlds are those of ``python -m jaxrt.bench.worlds`` (a ground and five deforming spheres, 502 triangles),
rebuilt or refit and traced by a small camera; the full update is checked against the float64 oracle.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from reference import brute_force, check_nearest

import jaxrt as rt
from jaxrt.bench import worlds as bench

WORLDS, SIDE = 6, 6
SELECTED = np.array([False, True, False, True, True, False])


def _update(rebuild: bool):
    intersector = rt.Intersector(rt.tags.triangle_data)

    def update(params, t, structure):
        geometries = bench.world_geometries(params, t)
        structure = rt.build_primitive_structure(geometries) if rebuild else rt.refit(structure, geometries)
        return structure, intersector.intersect(bench.world_camera(params, t, SIDE), structure)

    return update


_FUNCTIONS = {mode: _update(mode == "rebuild") for mode in ("rebuild", "refit")}


@pytest.fixture(scope="module")
def start():
    """The worlds at t = 0 (a full update) and the times of the next step (a different one per world)."""
    params = bench.world_params(WORLDS, seed=3)
    zeros = jnp.zeros(WORLDS, jnp.float32)
    fn = _FUNCTIONS["rebuild"]
    shapes = jax.eval_shape(jax.vmap(fn), params, zeros, None)
    blank = jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), shapes)
    # The same compiled program as the full update of the test (same function, capacity and shapes).
    first = rt.update_worlds(fn, jnp.ones(WORLDS, bool), blank, params, zeros, blank[0], capacity=WORLDS)
    return params, first, jnp.linspace(0.4, 1.4, WORLDS, dtype=jnp.float32)


def _world(tree, i):
    return jax.tree_util.tree_map(lambda a: np.asarray(a[i]), tree)


def _assert_same(got, want, what):
    """Ids exactly; floats to a few ulp: the two come from programs of different batch sizes, which XLA may
    vectorise and contract differently (vertices from ``sin``/``cos``, barycentrics as ratios of signed
    volumes; barycentrics lie in [0, 1], hence the absolute term of 16 float32 ulp of 1)."""
    for (path, g), w in zip(jax.tree_util.tree_leaves_with_path(got), jax.tree_util.tree_leaves(want), strict=True):
        g, w = np.asarray(g), np.asarray(w)
        name = f"{what}{jax.tree_util.keystr(path)}"
        if np.issubdtype(w.dtype, np.floating):
            np.testing.assert_allclose(g, w, rtol=1e-6, atol=16 * np.finfo(np.float32).eps, err_msg=name)
        else:
            np.testing.assert_array_equal(g, w, err_msg=name)


def _assert_bitwise(got, want, what):
    for g, w in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want), strict=True):
        assert np.asarray(g).tobytes() == np.asarray(w).tobytes(), what


def _check_against_oracle(params, t, result, worlds=range(WORLDS)):
    """Each world's camera against every triangle of that world at its time, in float64."""
    for i in worlds:
        p = _world(params, i)
        geometries = bench.world_geometries(p, jnp.float32(t[i]))
        triangles = np.concatenate([np.asarray(g.vertices)[np.asarray(g.indices)] for g in geometries])
        counts = [int(g.indices.shape[0]) for g in geometries]
        rays = bench.world_camera(p, jnp.float32(t[i]), SIDE).reshape(-1)
        ref = brute_force(rays.origin, rays.direction, rays.min_distance, rays.max_distance, triangles)
        hits = jax.tree_util.tree_map(lambda a, i=i: np.asarray(a[i]).reshape(SIDE * SIDE, *a.shape[3:]), result)
        failures = check_nearest(hits, ref, counts)
        assert not failures, f"world {i}: " + "\n".join(failures[:10])
        assert (np.asarray(hits.type) != 0).mean() > 0.3  # the camera sees the scene


@pytest.mark.parametrize("mode", ["rebuild", "refit"])
def test_partial_updates_equal_the_full_update_and_leave_other_worlds_untouched(start, mode):
    params, first, t = start
    fn = _FUNCTIONS[mode]
    everything = jnp.ones(WORLDS, bool)
    full = rt.update_worlds(fn, everything, first, params, t, first[0], capacity=WORLDS)
    _check_against_oracle(params, np.asarray(t), full[1])
    mask = jnp.asarray(SELECTED)
    partials = {"two buckets of 2": rt.update_worlds(fn, mask, first, params, t, first[0], capacity=2)}
    if mode == "rebuild":  # inside the caller's jit, one bucket of 4 (the capacity worlds_capacity gives)
        assert rt.worlds_capacity(SELECTED) == 4
        step = jax.jit(lambda m, s, p, t: rt.update_worlds(fn, m, s, p, t, s[0], capacity=4))
        partials["one bucket of 4, in jit"] = step(mask, first, params, t)
    for name, partial in partials.items():
        _check_against_oracle(params, np.asarray(t), partial[1], np.flatnonzero(SELECTED))
        for i in range(WORLDS):
            if SELECTED[i]:
                _assert_same(_world(partial, i), _world(full, i), f"{name}: world {i}")
            else:
                _assert_bitwise(_world(partial, i), _world(first, i), f"{name}: world {i} changed")
    nothing = rt.update_worlds(fn, jnp.zeros(WORLDS, bool), first, params, t, first[0], capacity=2)
    _assert_bitwise(nothing, first, "an empty mask changed a world")


def test_worlds_capacity_is_the_bucket_of_the_selected_count():
    assert rt.worlds_capacity(np.zeros(10, bool)) == 1
    assert rt.worlds_capacity(np.arange(1000) % 10 == 0) == 128
    assert rt.worlds_capacity(np.ones(5, bool)) == 8
    with pytest.raises(ValueError, match="1-D bool"):
        rt.worlds_capacity(np.ones(5, np.int32))


def test_bad_worlds_arguments_raise_naming_them():
    def double(x):
        return 2 * x

    state = jnp.zeros(4)
    with pytest.raises(ValueError, match="mask must be a 1-D bool"):
        rt.update_worlds(double, jnp.ones(4, jnp.int32), state, jnp.arange(4.0))
    with pytest.raises(ValueError, match=r"args\[0\] has shape \(3,\)"):
        rt.update_worlds(double, jnp.ones(4, bool), state, jnp.arange(3.0))
    with pytest.raises(ValueError, match="fn returns int32"):
        rt.update_worlds(lambda x: x.astype(jnp.int32), jnp.ones(4, bool), state, jnp.arange(4.0))
    with pytest.raises(ValueError, match="capacity must be a positive int"):
        rt.update_worlds(double, jnp.ones(4, bool), state, jnp.arange(4.0), capacity=0)
    with pytest.raises(TypeError, match="mesh must be a jax.sharding.Mesh"):
        rt.update_worlds(double, jnp.ones(4, bool), state, jnp.arange(4.0), mesh="gpu")
