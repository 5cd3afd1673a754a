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


_INDICES = [bench._GROUND_INDICES] + [bench._SPHERE_INDICES] * bench.OBJECTS


def _update(rebuild: bool):
    intersector = rt.Intersector(rt.tags.triangle_data)

    def update(vertices, rays, structure):
        geometries = [rt.TriangleGeometry(v, i) for v, i in zip(vertices, _INDICES, strict=True)]
        structure = rt.build_primitive_structure(geometries) if rebuild else rt.refit(structure, geometries)
        return structure, intersector.intersect(rays, structure)

    return update


_FUNCTIONS = {mode: _update(mode == "rebuild") for mode in ("rebuild", "refit")}


@jax.jit
@jax.vmap
def _world_inputs(params, t):
    return [g.vertices for g in bench.world_geometries(params, t)], bench.world_camera(params, t, SIDE)


def inputs(t, seed: int = 3):
    """Every world's vertices (one array per geometry) and camera rays at its time ``t``: computed once, so that
    the updates compared below read the same bits (``sin`` and ``cos`` in programs of other batch sizes may
    round differently)."""
    return _world_inputs(bench.world_params(WORLDS, seed), jnp.asarray(t, jnp.float32))


@pytest.fixture(scope="module")
def start():
    """The worlds at t = 0 (a full update) and the inputs of the next step (a different time per world)."""
    vertices, rays = inputs(np.zeros(WORLDS))
    fn = _FUNCTIONS["rebuild"]
    shapes = jax.eval_shape(jax.vmap(fn), vertices, rays, None)
    blank = jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), shapes)
    # The same compiled program as the full update of the test (same function, capacity and shapes).
    first = rt.update_worlds(fn, jnp.ones(WORLDS, bool), blank, vertices, rays, blank[0], capacity=WORLDS)
    return first, inputs(np.linspace(0.4, 1.4, WORLDS))


def _world(tree, i):
    return jax.tree_util.tree_map(lambda a: np.asarray(a[i]), tree)


def _assert_same(got, want, what):
    """Ids exactly; floats to rounding (XLA may vectorise programs of other batch sizes differently)."""
    for (path, g), w in zip(jax.tree_util.tree_leaves_with_path(got), jax.tree_util.tree_leaves(want), strict=True):
        g, w = np.asarray(g), np.asarray(w)
        name = f"{what}{jax.tree_util.keystr(path)}"
        if np.issubdtype(w.dtype, np.floating):
            np.testing.assert_allclose(g, w, rtol=1e-6, atol=1e-6, err_msg=name)
        else:
            np.testing.assert_array_equal(g, w, err_msg=name)


def _assert_bitwise(got, want, what):
    for g, w in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want), strict=True):
        assert np.asarray(g).tobytes() == np.asarray(w).tobytes(), what


def _check_against_oracle(step, result, worlds=range(WORLDS)):
    """Each world's camera against every triangle of that world, in float64."""
    vertices, rays = step
    for i in worlds:
        triangles = np.concatenate([np.asarray(v[i])[ix] for v, ix in zip(vertices, _INDICES, strict=True)])
        counts = [len(ix) for ix in _INDICES]
        r = jax.tree_util.tree_map(lambda a, i=i: np.asarray(a[i]).reshape(SIDE * SIDE, *a.shape[3:]), rays)
        ref = brute_force(r.origin, r.direction, r.min_distance, r.max_distance, triangles)
        hits = jax.tree_util.tree_map(lambda a, i=i: np.asarray(a[i]).reshape(SIDE * SIDE, *a.shape[3:]), result)
        failures = check_nearest(hits, ref, counts)
        assert not failures, f"world {i}: " + "\n".join(failures[:10])
        assert (np.asarray(hits.type) != 0).mean() > 0.3  # the camera sees the scene


@pytest.mark.parametrize("mode", ["rebuild", "refit"])
def test_partial_updates_equal_the_full_update_and_leave_other_worlds_untouched(start, mode):
    first, step = start
    vertices, rays = step
    fn = _FUNCTIONS[mode]
    mask = jnp.asarray(SELECTED)
    partials = {"two buckets of 2": rt.update_worlds(fn, mask, first, vertices, rays, first[0], capacity=2)}
    full = None
    if mode == "rebuild":  # the full update (refit: the oracle alone, to spare a compilation)
        full = rt.update_worlds(fn, jnp.ones(WORLDS, bool), first, vertices, rays, first[0], capacity=WORLDS)
        _check_against_oracle(step, full[1])
        # Inside the caller's jit, one bucket of 4 (the capacity worlds_capacity gives).
        assert rt.worlds_capacity(SELECTED) == 4
        jitted = jax.jit(lambda m, s, v, r: rt.update_worlds(fn, m, s, v, r, s[0], capacity=4))
        partials["one bucket of 4, in jit"] = jitted(mask, first, vertices, rays)
    for name, partial in partials.items():
        _check_against_oracle(step, partial[1], np.flatnonzero(SELECTED))
        for i in range(WORLDS):
            if not SELECTED[i]:
                _assert_bitwise(_world(partial, i), _world(first, i), f"{name}: world {i} changed")
            elif full is not None:
                _assert_same(_world(partial, i), _world(full, i), f"{name}: world {i}")
    nothing = rt.update_worlds(fn, jnp.zeros(WORLDS, bool), first, vertices, rays, first[0], capacity=2)
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


def test_gradients_flow_through_a_bucket_of_every_world():
    mask = jnp.array([True, False, True, True])
    x = jnp.array([1.0, 2.0, 3.0, 4.0])

    def loss(x):
        return jnp.sum(rt.update_worlds(jnp.square, mask, jnp.zeros(4), x, capacity=4))

    np.testing.assert_array_equal(jax.grad(loss)(x), np.where(mask, 2 * x, 0.0))
