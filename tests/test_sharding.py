"""Many rays, many devices: chunked batches and rays sharded over devices give the hits of one plain call.

The sharded test runs in a subprocess with ``XLA_FLAGS=--xla_force_host_platform_device_count=4`` (the flag
must be set before JAX starts), tracing rays split over four CPU devices with ``jax.shard_map`` around
``Intersector.intersect``, the structure replicated: by hand, as docs/performance.md gives, and through
``rt.intersect_sharded`` for ray counts that do not divide by the devices (eagerly and inside ``jit``). The
worlds of tests/test_worlds.py are then updated split over the four devices (six worlds: two padding worlds
are added and cut) and checked against the float64 oracle. tests/test_multihost.py runs two processes.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import jax
import numpy as np
import pytest

import jaxrt as rt
from jaxrt._src import pipeline as pipeline


def _scene_and_rays(n_rays: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    triangles = (rng.uniform(-1, 1, (60, 1, 3)) + 0.3 * rng.normal(size=(60, 3, 3))).astype(np.float32)
    structure = rt.build_primitive_structure(rt.TriangleGeometry(triangles.reshape(-1, 3)))
    origin = rng.uniform(-2, 2, (n_rays, 3)).astype(np.float32)
    direction = (rng.uniform(-0.5, 0.5, (n_rays, 3)) - origin).astype(np.float32)
    t_max = np.where(rng.random(n_rays) < 0.1, 0.5, np.inf).astype(np.float32)
    return structure, rt.Ray(origin, direction, 0.0, t_max)


def _assert_same(result, reference):
    """Same hits; hit distances and barycentrics to rounding (XLA may fuse, and contract, differently per
    program)."""
    for name in reference:
        got, want = np.asarray(result[name]), np.asarray(reference[name])
        if np.issubdtype(want.dtype, np.floating):
            np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6, err_msg=name)
        else:
            np.testing.assert_array_equal(got, want, err_msg=name)


def test_batches_over_the_chunk_size_are_traced_in_chunks(monkeypatch):
    structure, rays = _scene_and_rays(300)
    intersector = rt.Intersector(rt.tags.triangle_data)
    whole = intersector.intersect(rays, structure)
    calls = []
    chunked = pipeline._intersect_chunks
    monkeypatch.setattr(pipeline, "_intersect_chunks", lambda *a: calls.append(a[3]) or chunked(*a))
    monkeypatch.setattr(pipeline, "INTERSECT_CHUNK", 64)
    parts = intersector.intersect(rays, structure)  # 300 rays: padded to 320, five chunks of 64
    assert calls == [64]
    assert parts.distance.shape == (300,)
    _assert_same(parts, whole)


_SHARDED = textwrap.dedent(
    """
    import jax
    import numpy as np
    from jax.sharding import NamedSharding, PartitionSpec as P

    import jaxrt as rt
    from test_sharding import _assert_same, _scene_and_rays

    assert jax.device_count() == 4, jax.devices()
    structure, rays = _scene_and_rays(1000)  # 250 rays per device: each pads its own shard
    intersector = rt.Intersector(rt.tags.triangle_data)
    reference = intersector.intersect(rays, structure)
    mesh = jax.make_mesh((4,), ("rays",))
    rays = jax.device_put(rays, NamedSharding(mesh, P("rays")))
    sharded = jax.jit(
        jax.shard_map(intersector.intersect, mesh=mesh, in_specs=(P("rays"), P()), out_specs=P("rays"), check_vma=False)
    )
    out = sharded(rays, structure)
    assert out.distance.sharding.spec == P("rays"), out.distance.sharding
    assert len({s.device for s in out.distance.addressable_shards}) == 4
    assert int((reference.primitive_id >= 0).sum()) > 100
    _assert_same(out, reference)

    # Any ray count, any batch shape: padded in equal rows (250.25 rays per device here), cut again.
    structure, rays = _scene_and_rays(1001, seed=1)
    reference = intersector.intersect(rays, structure)
    out = rt.intersect_sharded(intersector, rays, structure)
    assert out.distance.shape == (1001,)
    assert len({s.device for s in out.distance.addressable_shards}) == 4
    _assert_same(out, reference)
    grid = jax.tree.map(lambda a: a[:91], rays).reshape(7, 13)  # 23 rays per device, padded to 32
    inside = jax.jit(lambda r, s: rt.intersect_sharded(intersector, r, s, mesh=mesh))(grid, structure)
    assert inside.triangle_barycentric_coord.shape == (7, 13, 2)
    _assert_same(inside, jax.tree.map(lambda a: a[:91].reshape(7, 13, *a.shape[1:]), reference))
    two = rt.intersect_sharded(intersector, jax.tree.map(lambda a: a[:3], rays), structure, mesh=rt.device_mesh(2))  # fewer rays than rows
    _assert_same(two, jax.tree.map(lambda a: a[:3], reference))

    # Worlds split over the devices (six worlds: two padding worlds added and cut): the selected ones match the
    # float64 oracle (tests/test_worlds.py compares partial and full updates on one device), the others are as
    # they were.
    import jax.numpy as jnp
    from test_worlds import SELECTED, WORLDS, _FUNCTIONS, _assert_bitwise, _check_against_oracle, _world, inputs

    fn = _FUNCTIONS["rebuild"]
    step = inputs(np.linspace(0.4, 1.4, WORLDS))
    shapes = jax.eval_shape(jax.vmap(fn), *step, None)
    blank = jax.tree.map(lambda a: jnp.full(a.shape, 7, a.dtype), shapes)
    mesh = rt.device_mesh(4, "worlds")
    spread = rt.update_worlds(fn, jnp.asarray(SELECTED), blank, *step, blank[0], mesh=mesh)
    assert len({s.device for s in spread[1].distance.addressable_shards}) == 4
    _check_against_oracle(step, spread[1], np.flatnonzero(SELECTED))
    for i in np.flatnonzero(~SELECTED):
        _assert_bitwise(_world(spread, i), _world(blank, i), f"world {i} changed")

    # Seven worlds on a mesh with explicit axes (jax.make_mesh's default), eagerly and in jit, one world per
    # bucket (several buckets on a device).
    mask = np.array([True, False, True, False, True, True, False])
    x, want = np.arange(7, dtype=np.float32), np.where(mask, 2 * np.arange(7), -1)
    explicit = jax.make_mesh((4,), ("w",))
    double = lambda v: 2 * v
    eager = rt.update_worlds(double, mask, np.full(7, -1.0, np.float32), x, mesh=explicit)
    np.testing.assert_array_equal(eager, want)
    jitted = jax.jit(lambda m, p, x: rt.update_worlds(double, m, p, x, mesh=explicit, capacity=1))
    np.testing.assert_array_equal(jitted(jnp.asarray(mask), jnp.full(7, -1.0), jnp.asarray(x)), want)
    print("sharded ok")
    """
)


def test_bad_sharding_arguments_raise_naming_them():
    structure, rays = _scene_and_rays(4)
    intersector = rt.Intersector()
    with pytest.raises(TypeError, match="mesh must be a jax.sharding.Mesh"):
        rt.intersect_sharded(intersector, rays, structure, mesh="gpu")
    with pytest.raises(TypeError, match="rays must be a jaxrt.Ray"):
        rt.intersect_sharded(intersector, rays.origin, structure)
    with pytest.raises(TypeError, match="intersector must be an rt.Intersector"):
        rt.intersect_sharded(None, rays, structure)
    with pytest.raises(ValueError, match="has no ray"):
        rt.intersect_sharded(intersector, _empty(rays), structure)
    with pytest.raises(ValueError, match=r"devices must be in \[1, \d+\], got 0"):
        rt.device_mesh(0)
    with pytest.raises(ValueError, match="empty sequence"):
        rt.device_mesh([])


def _empty(rays):
    return jax.tree_util.tree_map(lambda a: a[:0], rays)


def test_rays_sharded_over_four_devices_equal_one_call():
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4", JAX_PLATFORMS="cpu")
    env["PYTHONPATH"] = os.pathsep.join([os.path.dirname(__file__), env.get("PYTHONPATH", "")])
    run = subprocess.run([sys.executable, "-c", _SHARDED], env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0 and "sharded ok" in run.stdout, run.stdout + run.stderr
