"""The any-hit child order: a box that holds the ray's start is entered after one the ray enters ahead.

Four triangles, two around the origin (``A``: a wall at ``z = 1`` and a small one at ``z = -1``, so their box
holds the origin) and two ahead (``B``: walls at ``z = 5`` and ``z = 6``). A ray from the origin along ``+z``
hits ``A``'s wall first, so the nearest hit is there; the any-hit query enters ``B``'s box first and stops at
``z = 5``. A ray from ``z = -10`` starts in neither box and keeps the nearest-first order (any hit at
``z = -1``). Every backend makes the same decision: the portable traversal, the compiled CPU loop (lean and
general: instanced) and the GPU kernel (on a GPU, or in Triton's interpreter in a fresh process).
"""

from __future__ import annotations

import numpy as np
import pytest
from test_gpu_instanced import ON_GPU, kernel_launches_here, kernel_test, run_kernel_tests_in_interpreter

import jaxrt as rt
from jaxrt._src.traversal import cpu, gpu

kernel_here = pytest.fixture(kernel_launches_here, name="kernel_here")

#: Triangle ``k`` lies in the plane ``z = DEPTHS[k]``; 0 and 1 form the box around the origin.
DEPTHS = (1.0, -1.0, 5.0, 6.0)
SIZES = (2.0, 0.5, 2.0, 2.0)


def _structures():
    tri = np.array([[[-s, -s, z], [s, -s, z], [0.0, s, z]] for z, s in zip(DEPTHS, SIZES, strict=True)], np.float32)
    blas = rt.build_primitive_structure(rt.TriangleGeometry(tri.reshape(-1, 3)))
    instanced = rt.build_instance_structure([blas], rt.Instances([0], np.eye(3, 4, dtype=np.float32)[None]))
    return blas, instanced


def _rays() -> rt.Ray:
    origin = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -10.0]], np.float32)
    direction = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]], np.float32)
    return rt.Ray(origin, direction, np.zeros(2, np.float32), np.full(2, np.inf, np.float32))


def _check(backend: str) -> None:
    blas, instanced = _structures()
    for structure, tags in ((blas, ()), (instanced, (rt.tags.instancing, rt.tags.max_levels(1)))):
        rays = _rays()
        nearest = rt.Intersector(*tags, backend=backend).intersect(rays, structure)
        first = rt.Intersector(*tags, backend=backend, accept_any_intersection=True).intersect(rays, structure)
        np.testing.assert_array_equal(np.asarray(nearest.primitive_id), [0, 1])
        np.testing.assert_array_equal(np.asarray(nearest.distance), [1.0, 9.0])
        # From inside box A the any-hit query enters box B first; from outside both, the nearer box first.
        np.testing.assert_array_equal(np.asarray(first.primitive_id), [2, 1])
        np.testing.assert_array_equal(np.asarray(first.distance), [5.0, 9.0])


def test_tree_separates_the_boxes():
    """The premise: the root's children are the box around the origin and the box ahead."""
    blas, _ = _structures()
    lower, upper = np.asarray(blas.node_lower)[0], np.asarray(blas.node_upper)[0]
    holds_origin = np.all((lower <= 0.0) & (upper >= 0.0), axis=1)
    assert sorted(holds_origin.tolist()) == [False, True]
    assert lower[~holds_origin][0, 2] == 5.0


@pytest.mark.parametrize("backend", ["portable", "cpu"])
def test_any_hit_enters_the_box_ahead_first(backend):
    if backend == "cpu" and cpu.unavailable_reason() is not None:
        pytest.skip(cpu.unavailable_reason())
    _check(backend)


def test_kernel_in_interpreter():
    """Runs this module's kernel test in Triton's interpreter, in a fresh process."""
    run_kernel_tests_in_interpreter(__file__, "kernel_makes")


@kernel_test
def test_kernel_makes_the_same_decisions(kernel_here, monkeypatch):
    calls = []
    kernel_call = gpu.kernel_call
    monkeypatch.setattr(gpu, "kernel_call", lambda *args, **kwargs: calls.append(1) or kernel_call(*args, **kwargs))
    if not ON_GPU:  # the interpreter stands in for the GPU
        monkeypatch.setattr(gpu, "unavailable_reason", lambda intersector: None)
    _check("gpu")
    assert len(calls) == 4  # each query on each structure ran the kernel
