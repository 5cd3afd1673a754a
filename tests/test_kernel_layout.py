"""The GPU kernel's rows packed once in the structure (``kernel_layout``).

Every way a primitive structure is made (build, batched build, refit, compaction, loading) must leave its
packed rows equal, bit for bit, to packing its arrays; a structure without them is packed per call, with the
same kernel results. The kernel runs on a GPU or in Triton's interpreter (in a fresh process, as in
``tests/test_gpu_instanced.py``).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrt as rt
from jaxrt._src import prepacked
from jaxrt._src.scene_view import traversal_scene
from jaxrt._src.traversal import gpu, packed

INTERPRETED = os.environ.get("TRITON_INTERPRET") == "1"
ON_GPU = jax.default_backend() == "gpu" and gpu._import_error() is None


def _triangles(seed: int, n: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    centre = rng.uniform(-1.0, 1.0, (n, 1, 3))
    return (centre + 0.3 * rng.standard_normal((n, 3, 3))).reshape(-1, 3).astype(np.float32)


def _build(seed: int = 0, n: int = 37, **kwargs) -> rt.PrimitiveAccelerationStructure:
    return rt.build_primitive_structure(rt.TriangleGeometry(_triangles(seed, n)), **kwargs)


def _bits(a) -> np.ndarray:
    return np.asarray(a).view(np.uint32)


def _assert_layout_matches(structure: rt.PrimitiveAccelerationStructure) -> None:
    """The structure's packed rows equal packing its arrays now."""
    layout = structure.kernel_layout
    assert layout is not None
    want = packed.kernel_layout(
        structure.node_lower, structure.node_upper, structure.node_children, structure.leaf_triangle
    )
    assert layout.nodes.shape == (structure.capacity - 1, packed.NODE_WIDTH)
    assert layout.triangles.shape == (structure.capacity, packed.TRIANGLE_WIDTH)
    np.testing.assert_array_equal(_bits(layout.nodes), _bits(want.nodes))
    np.testing.assert_array_equal(_bits(layout.triangles), _bits(want.triangles))


# --- the layout on every path that makes a structure ---------------------------------------------------------


def test_default_build_has_a_layout_only_where_the_kernel_runs():
    structure = _build()
    assert (structure.kernel_layout is not None) == (ON_GPU and not jax.config.jax_enable_x64)
    assert _build(kernel_layout=False).kernel_layout is None
    boxes = rt.BoundingBoxGeometry(np.zeros((3, 3), np.float32), np.ones((3, 3), np.float32))
    assert rt.build_primitive_structure(boxes).kernel_layout is None  # the kernel declines boxes


@pytest.mark.parametrize("quality", ["fast", "high"])
def test_build_layout_equals_packing(quality):
    structure = _build(quality=quality, kernel_layout=True)
    _assert_layout_matches(structure)
    plain = _build(quality=quality, kernel_layout=False)
    np.testing.assert_array_equal(structure.node_children, plain.node_children)
    np.testing.assert_array_equal(_bits(structure.node_lower), _bits(plain.node_lower))


def test_batched_build_layout_equals_packing():
    vertices = jnp.stack([_triangles(s, 20) for s in range(3)])
    batch = jax.vmap(lambda v: rt.build_primitive_structure(rt.TriangleGeometry(v), kernel_layout=True))(vertices)
    assert batch.kernel_layout.nodes.shape[0] == 3
    for s in range(3):
        _assert_layout_matches(jax.tree.map(lambda a, s=s: a[s], batch))


def test_refit_keeps_the_layout_consistent():
    structure = _build(kernel_layout=True)
    moved = _triangles(0, 37) + np.float32(0.25) * _triangles(1, 37)
    refit = rt.refit(structure, rt.TriangleGeometry(moved))
    _assert_layout_matches(refit)
    assert not np.array_equal(_bits(refit.kernel_layout.nodes), _bits(structure.kernel_layout.nodes))
    assert rt.refit(_build(kernel_layout=False), rt.TriangleGeometry(moved)).kernel_layout is None
    refit_jit = jax.jit(rt.refit)(structure, rt.TriangleGeometry(moved))
    _assert_layout_matches(refit_jit)


@pytest.mark.parametrize("quality", ["fast", "high"])
def test_compaction_keeps_the_layout_consistent(quality):
    structure = _build(quality=quality, kernel_layout=True)
    compacted = rt.compact(structure)
    assert compacted.capacity < structure.capacity
    _assert_layout_matches(compacted)
    assert rt.compact(_build(quality=quality, kernel_layout=False)).kernel_layout is None


@pytest.mark.parametrize("wanted", [False, True])
def test_load_packs_where_a_build_would(tmp_path, monkeypatch, wanted):
    structure = _build(kernel_layout=True)
    path = tmp_path / "s.jaxrt"
    rt.save(path, structure)
    monkeypatch.setattr(prepacked, "kernel_layout_wanted", lambda info, dtype: wanted)
    loaded = rt.load(path)
    if wanted:
        _assert_layout_matches(loaded)
        np.testing.assert_array_equal(_bits(loaded.kernel_layout.nodes), _bits(structure.kernel_layout.nodes))
    else:
        assert loaded.kernel_layout is None


def test_instance_structures_hold_primitive_structures_with_layouts():
    inner = _build(kernel_layout=True)
    instances = rt.Instances(np.zeros((1,), np.int32), np.eye(3, 4, dtype=np.float32)[None])
    top = rt.build_instance_structure([inner], instances)
    _assert_layout_matches(top.primitive_structures[0])
    _assert_layout_matches(rt.compact(top).primitive_structures[0])


# --- the kernel with the prepacked rows ----------------------------------------------------------------------


def test_kernel_layout_in_interpreter():
    """Runs this module's kernel tests in Triton's interpreter, in a fresh process."""
    pytest.importorskip("triton")
    if INTERPRETED or ON_GPU:
        pytest.skip("the kernel tests run directly here")
    command = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-x", __file__, "-k", "kernel_runs"]
    env = dict(os.environ, TRITON_INTERPRET="1", JAX_PLATFORMS="cpu")
    done = subprocess.run(command, env=env, cwd=Path(__file__).parents[1], capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stdout[-4000:] + done.stderr[-2000:]
    assert " passed" in done.stdout and " skipped" not in done.stdout.splitlines()[-1], done.stdout[-2000:]


sys.path.insert(0, str(Path(__file__).parent))
from test_gpu_instanced import LAUNCHES  # noqa: E402

kernel_test = pytest.mark.skipif(not (INTERPRETED or ON_GPU), reason="runs in the interpreter process or on a GPU")


@pytest.fixture
def kernel_here(monkeypatch):
    """The kernel on this machine (the GPU, or the interpreter), recording each call's ``prepacked``."""
    from test_gpu_instanced import interpreted_launch

    if not ON_GPU:
        monkeypatch.setattr(gpu, "_launch", interpreted_launch)
        monkeypatch.setattr(gpu, "MAX_PROGRAMS", 2)
        monkeypatch.setattr(gpu, "unavailable_reason", lambda intersector: None)
    calls = []
    kernel = gpu._kernel
    monkeypatch.setattr(gpu, "_kernel", lambda *a, config: calls.append(config.prepacked) or kernel(*a, config=config))
    gpu._traversal.cache_clear()
    yield calls
    gpu._traversal.cache_clear()


def _rays(n: int, seed: int) -> rt.Ray:
    rng = np.random.default_rng(seed)
    origin = rng.uniform(-1.5, 1.5, (n, 3)).astype(np.float32) + np.float32([0, 0, -4])
    target = rng.uniform(-1.2, 1.2, (n, 3)).astype(np.float32)
    return rt.Ray(origin, target - origin)


def _assert_equal_results(a, b) -> None:
    for name in b:
        np.testing.assert_array_equal(np.asarray(a[name]), np.asarray(b[name]), err_msg=name)


@kernel_test
@pytest.mark.parametrize("any_hit", [False, True])
def test_kernel_runs_prepacked_like_packed_per_call(any_hit, kernel_here):
    """The same fields, bit for bit, from the prepacked rows and from rows packed per call, and the same
    leaves as the portable path."""
    tags = (rt.tags.triangle_data, rt.tags.stats)
    with_rows, without = _build(3, 40, kernel_layout=True), _build(3, 40, kernel_layout=False)
    ray = _rays(96, 4)
    intersector = rt.Intersector(*tags, backend="gpu", accept_any_intersection=any_hit)
    got = intersector.intersect(ray, with_rows)
    assert kernel_here == [True]
    want = intersector.intersect(ray, without)
    assert kernel_here == [True, False]
    _assert_equal_results(got, want)
    assert (np.asarray(got.type) != 0).sum() > 10
    portable = rt.Intersector(*tags, backend="portable", accept_any_intersection=any_hit).intersect(ray, without)
    np.testing.assert_array_equal(got.primitive_id, portable.primitive_id)


@kernel_test
def test_kernel_runs_prepacked_under_vmap(kernel_here):
    """vmap over ray batches keeps the prepacked rows (one launch); vmap over structures packs per call."""
    structure = _build(6, 30, kernel_layout=True)
    ray = _rays(64, 7)
    intersector = rt.Intersector(backend="gpu")
    folded = jax.tree.map(lambda a: a.reshape(2, 32, *a.shape[1:]), ray)
    LAUNCHES.clear()
    got = jax.vmap(lambda r: intersector.intersect(r, structure))(folded)
    assert kernel_here and all(kernel_here)
    if not ON_GPU:
        assert [n for _, n in LAUNCHES] == [64], LAUNCHES  # 2 x 32 rays in one launch
    flat = intersector.intersect(ray, structure)
    np.testing.assert_array_equal(np.asarray(got.primitive_id).reshape(-1), flat.primitive_id)
    np.testing.assert_array_equal(np.asarray(got.distance).reshape(-1), flat.distance)

    kernel_here.clear()
    others = [_build(s, 30, kernel_layout=True) for s in (6, 8)]
    pair = jax.tree.map(lambda *a: jnp.stack(a), *others)
    rays = jax.tree.map(lambda a: a.reshape(2, 32, *a.shape[1:]), ray)
    scenes = [traversal_scene(s) for s in others]
    got = jax.vmap(intersector.intersect)(rays, pair)
    assert kernel_here and not any(kernel_here)
    for s, one in enumerate(others):
        r = jax.tree.map(lambda a, s=s: a[s], rays)
        want = rt.Intersector(backend="portable").intersect(r, one)
        np.testing.assert_array_equal(np.asarray(got.primitive_id)[s], want.primitive_id)
    assert scenes[0][1] == scenes[1][1]
