"""A Triton kernel that runs the GPU traversal kernel's curve leaf test alone, one (ray, curve row) pair per lane,
for ``tests/test_gpu_curves.py`` (imported only where Triton is installed)."""

from __future__ import annotations

import triton
import triton.language as tl

from jaxrt._src.traversal.triton_curves import curve_leaf, curve_ray


@triton.jit
def leaf_pairs(
    rows_ptr, rays_ptr, n, hit_out, distance_out,
    LANES: tl.constexpr, PIECES: tl.constexpr, ITERATIONS: tl.constexpr, APPROACH: tl.constexpr,
    TOLERANCE: tl.constexpr, DISK: tl.constexpr, SPHERE: tl.constexpr, FLAT: tl.constexpr,
):  # fmt: skip
    """Lane ``i`` tests leaf row ``i`` against ray ``i`` with the kernel's ``curve_leaf``. The ray block ``(34, n)``: origin (rows 0-2), the interval (3-4), whether
    the lane tests its leaf (5), the hit and distance the leaf test starts from (6-7; a triangle test's answer),
    the curve frame (24-33, as :func:`~jaxrt._src.traversal.triton_curves.curve_ray` reads it)."""
    lane = tl.program_id(0) * LANES + tl.arange(0, LANES)
    ox = tl.load(rays_ptr + lane)
    oy = tl.load(rays_ptr + n + lane)
    oz = tl.load(rays_ptr + 2 * n + lane)
    t_min = tl.load(rays_ptr + 3 * n + lane)
    t_max = tl.load(rays_ptr + 4 * n + lane)
    test = tl.load(rays_ptr + 5 * n + lane) != 0
    hit = tl.load(rays_ptr + 6 * n + lane) != 0
    distance = tl.load(rays_ptr + 7 * n + lane)
    ray = curve_ray(rays_ptr, n, lane, ox, oy, oz)
    hit, distance = curve_leaf(rows_ptr, lane, test, hit, distance, ray, t_min, t_max, LANES, PIECES, ITERATIONS, APPROACH, TOLERANCE, DISK, SPHERE, FLAT)  # fmt: skip
    tl.store(hit_out + lane, hit.to(tl.int32))
    tl.store(distance_out + lane, distance)
