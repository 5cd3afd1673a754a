"""Lane refill in the GPU kernel (``KernelOptions.refill``): a lane whose ray is finished takes the program's next
ray at once. Only which lane traces a ray, and when, changes: every ray makes the same decisions, so every result
field and counter is bit for bit the block-by-block kernel's.

As in ``test_gpu_curves.py``: the kernel runs in Triton's interpreter on the CPU (in a fresh process; at most two
programs, so that each walks several blocks) or on a CUDA GPU.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest
from test_curves_primitive import aimed_rays
from test_curves_structure import hair
from test_gpu_curves import _bits, _flat_kinked
from test_gpu_instanced import kernel_launches_here, kernel_test, run_kernel_tests_in_interpreter

import jaxrt as rt
from jaxrt._src import leaves as leaf_tests
from jaxrt._src.scene_view import scene_view
from jaxrt._src.traversal import gpu

kernel_here = pytest.fixture(kernel_launches_here, name="kernel_here")
ALL_RAYS = np.uint32(0xFFFFFFFF)
QUERIES = (
    dict(any_hit=False),
    dict(any_hit=True),
    dict(any_hit=False, max_hits=3),
    dict(any_hit=False, count_all=True),
)


def test_kernel_in_interpreter():
    """Runs this module's kernel tests in Triton's interpreter, in a fresh process."""
    run_kernel_tests_in_interpreter(__file__)


def _call(config: gpu._Config) -> gpu.KernelCall:
    return gpu.kernel_call(jnp.zeros((1, 16)), jnp.zeros((1, 12)), jnp.zeros((1, 16)), jnp.zeros((20, 4096)), config)


def test_refill_is_declined_where_not_covered():
    """Refill covers binary nodes of a primitive structure without keyframe motion or analytic leaves (with
    curves and hit lists); instance levels, motion and analytic leaves trace block by block. With refill at
    most ``refill_programs`` programs run; off, the launch is unchanged."""
    on = dataclasses.replace(gpu.DEFAULT_OPTIONS, refill=True, refill_programs=16)
    base = gpu._Config(False, 0, 24, 0, 8, on, False)
    assert _call(base).params["REFILL"] and _call(base).programs == 16
    for change in (dict(max_hits=4), dict(count=True), dict(curves=(8, 3, 2, 1e-3, False, True, 0))):
        assert _call(dataclasses.replace(base, **change)).params["REFILL"]
    for change in (dict(levels=1, roots=True), dict(node_keys=2, leaf_keys=2), dict(analytic=1)):
        call = _call(dataclasses.replace(base, **change))
        assert not call.params["REFILL"] and call.programs == 128
    off = _call(dataclasses.replace(base, options=gpu.DEFAULT_OPTIONS))
    assert gpu.DEFAULT_OPTIONS.refill or (not off.params["REFILL"] and off.programs == 128)


def _runs(view, args, curves, settings) -> None:
    """Every query traced with each of ``settings`` (``KernelOptions``), compared bit for bit with the first."""
    for query in QUERIES:
        runs = [
            gpu.trace_scene(view.traversal, view.layout, *args, cull=0, curves=curves, options=options, **query)
            for options in settings
        ]
        for options, got in zip(settings, runs, strict=True):
            assert _bits(got) == _bits(runs[0]), (query, options)
        hits = (np.asarray(runs[0].leaf) >= 0).sum()
        assert hits > len(args[0]) // 4 or query.get("count_all"), (query, hits)


@kernel_test
def test_refill_changes_no_decision_with_curves(kernel_here):
    """Triangles, round and flat segments in one structure (deferred curve tests on and off), nearest, any hit,
    the 3 nearest hits and counting: with refill every result field and counter is the block-by-block kernel's
    bit for bit (three blocks, the last partly padding, in two programs or one; some rays disabled)."""
    linear, bezier = _flat_kinked("sphere")
    round_ = hair(seed=30, strands=3, end_caps="disk")
    rng = np.random.default_rng(41)
    triangles = rt.TriangleGeometry(rng.uniform(-1, 2.5, (12, 3)).astype(np.float32))
    view = scene_view(rt.build_primitive_structure([triangles, bezier, linear, round_]))
    n = 90
    origin, direction = aimed_rays(rng, round_, n // 2)
    joints = np.array([[1, 0, 1], [1, 0, 0], [1.1, 1, 0]], np.float64)[rng.integers(0, 3, n - n // 2)]
    aimed = rng.normal(size=(n - n // 2, 3))
    aimed /= np.linalg.norm(aimed, axis=1, keepdims=True)
    origin = np.concatenate([origin, joints + rng.normal(scale=0.1, size=(n - n // 2, 3)) - 8.0 * aimed])
    direction = np.concatenate([direction, aimed])
    t_max = np.where(rng.random(n) < 0.2, rng.uniform(6.0, 9.0, n), np.inf)
    args = (jnp.asarray(origin, jnp.float32), jnp.asarray(direction, jnp.float32), jnp.zeros(n, jnp.float32),
            jnp.asarray(t_max, jnp.float32), jnp.asarray(rng.random(n) > 0.1), jnp.full(n, ALL_RAYS, jnp.uint32))  # fmt: skip
    curves = gpu.curve_leaves(view, leaf_tests.curve_configuration(rt.Intersector(), view))
    settings = [
        gpu.KernelOptions(curve_batch=16, refill=False),
        gpu.KernelOptions(curve_batch=16, refill=True),
        gpu.KernelOptions(curve_batch=0, refill=True),
        gpu.KernelOptions(curve_batch=5, refill=True, refill_programs=1),
    ]
    _runs(view, args, curves, settings)


@kernel_test
def test_refill_changes_no_decision_on_triangles(kernel_here):
    """A triangle soup and rays of very uneven length (from inside the soup, grazing it, missing it; a fifth
    disabled, a run of disabled rays, some bounded): more rays than a block per program, the last block partly
    padding. Refill with two programs and with one gives the block-by-block result bit for bit."""
    rng = np.random.default_rng(42)
    centre = rng.uniform(-1.0, 1.0, (60, 1, 3))
    soup = centre + 0.25 * rng.standard_normal((60, 3, 3))
    view = scene_view(rt.build_primitive_structure(rt.TriangleGeometry(soup.reshape(-1, 3).astype(np.float32))))
    n = 130
    inside = rng.uniform(-0.8, 0.8, (n, 3))
    outside = 3.0 * rng.normal(size=(n, 3))
    origin = np.where((np.arange(n) % 3 == 0)[:, None], inside, outside)
    target = rng.uniform(-1.5, 1.5, (n, 3))
    direction = np.where((np.arange(n) % 3 == 0)[:, None], rng.normal(size=(n, 3)), target - origin)
    t_max = np.where(rng.random(n) < 0.15, rng.uniform(0.1, 2.0, n), np.inf)
    enabled = rng.random(n) > 0.2
    enabled[30:66] = False  # a whole block disabled, and a run beyond it
    args = (jnp.asarray(origin, jnp.float32), jnp.asarray(direction, jnp.float32), jnp.zeros(n, jnp.float32),
            jnp.asarray(t_max, jnp.float32), jnp.asarray(enabled), jnp.full(n, ALL_RAYS, jnp.uint32))  # fmt: skip
    settings = [
        gpu.KernelOptions(refill=False),
        gpu.KernelOptions(refill=True),
        gpu.KernelOptions(refill=True, refill_programs=1),
    ]
    _runs(view, args, None, settings)
    visited = np.asarray(gpu.trace_scene(view.traversal, view.layout, *args, any_hit=False, cull=0).nodes_visited)
    assert visited[enabled].min() < visited[enabled].max() // 4  # uneven lengths
