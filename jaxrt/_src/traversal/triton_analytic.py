"""The built-in analytic intersection functions in Triton: sphere, disk and capped cylinder leaves of the kernel.

:func:`analytic_hit` is the leaf test of :mod:`jaxrt._src.traversal.triton_kernel` for bounding-box leaves whose
geometry uses one of :mod:`jaxrt._src.primitives.analytic`'s functions. The shapes are the formulas of
:mod:`jaxrt._src.formulas.analytic`, which the portable functions also call, instantiated for Triton: correctly
rounded divisions and square roots (``div_rn``, ``sqrt_rn``), no contraction (a dot product is
``(x0 y0 + x1 y1) + x2 y2``), the first smallest root in ``[t_min, t_max]`` kept in the function's order of
candidates. ``t_max`` is the ray's current nearest distance, as the portable traversal passes it to the
function.

Parameters come from the leaf's row (:func:`jaxrt._src.traversal.packed.pack_analytic`): ``p`` (the sphere's
or disk's centre, the cylinder's ``p0``), ``q`` (the disk's normal, the cylinder's ``p1``), ``radius`` and the
shape code (1 sphere, 2 disk, 3 capped cylinder, 5 built-in sphere: :mod:`jaxrt._src.formulas.sphere`).
"""

from __future__ import annotations

import triton
import triton.language as tl

from jaxrt._src import formulas

_shapes = formulas.instance("analytic", "triton")
_sphere = _shapes.sphere
_disk = _shapes.disk
_capped_cylinder = _shapes.capped_cylinder
_ray_sphere = formulas.instance("sphere", "triton").ray_sphere


@triton.jit
def _any(flags):
    """Whether some lane of the warp has ``flags`` set (a warp-uniform value)."""
    return tl.max(flags.to(tl.int32), axis=0) > 0


@triton.jit
def _merge(hit, distance, shape_hit, shape_t):
    return hit | shape_hit, tl.where(shape_hit, shape_t, distance)


@triton.jit
def analytic_hit(
    code, mask, px, py, pz, qx, qy, qz, radius, ox, oy, oz, dx, dy, dz, t_min, t_max, SHAPES: tl.constexpr
):  # fmt: skip
    """``(hit, distance)`` of analytic leaves where ``mask`` (``inf`` where not hit): each lane's shape by its
    ``code``. ``SHAPES`` (compile-time) has bit ``code - 1`` set for each shape the scene holds: only those
    are compiled, and with several each is computed only where some lane of the warp needs it."""
    hit = tl.zeros(mask.shape, tl.int1)
    distance = tl.full(mask.shape, float("inf"), tl.float32)
    if (SHAPES & 1) != 0:
        lanes = mask & (code == 1.0)
        if (SHAPES & (SHAPES - 1)) != 0:
            if _any(lanes):
                h, t = _sphere(px, py, pz, radius, ox, oy, oz, dx, dy, dz, t_min, t_max)
                hit, distance = _merge(hit, distance, lanes & h, t)
        else:
            h, t = _sphere(px, py, pz, radius, ox, oy, oz, dx, dy, dz, t_min, t_max)
            hit, distance = _merge(hit, distance, lanes & h, t)
    if (SHAPES & 2) != 0:
        lanes = mask & (code == 2.0)
        if (SHAPES & (SHAPES - 1)) != 0:
            if _any(lanes):
                h, t = _disk(px, py, pz, qx, qy, qz, radius, ox, oy, oz, dx, dy, dz, t_min, t_max)
                hit, distance = _merge(hit, distance, lanes & h, t)
        else:
            h, t = _disk(px, py, pz, qx, qy, qz, radius, ox, oy, oz, dx, dy, dz, t_min, t_max)
            hit, distance = _merge(hit, distance, lanes & h, t)
    if (SHAPES & 4) != 0:
        lanes = mask & (code == 3.0)
        if (SHAPES & (SHAPES - 1)) != 0:
            if _any(lanes):
                h, t = _capped_cylinder(px, py, pz, qx, qy, qz, radius, ox, oy, oz, dx, dy, dz, t_min, t_max)
                hit, distance = _merge(hit, distance, lanes & h, t)
        else:
            h, t = _capped_cylinder(px, py, pz, qx, qy, qz, radius, ox, oy, oz, dx, dy, dz, t_min, t_max)
            hit, distance = _merge(hit, distance, lanes & h, t)
    if (SHAPES & 32) != 0:  # built-in spheres (rt.SphereGeometry), code 5
        lanes = mask & (code == 5.0)
        if (SHAPES & (SHAPES - 1)) != 0:
            if _any(lanes):
                h, t, _ = _ray_sphere(px, py, pz, radius, ox, oy, oz, dx, dy, dz, t_min, t_max)
                hit, distance = _merge(hit, distance, lanes & h, t)
        else:
            h, t, _ = _ray_sphere(px, py, pz, radius, ox, oy, oz, dx, dy, dz, t_min, t_max)
            hit, distance = _merge(hit, distance, lanes & h, t)
    return hit, tl.where(hit, distance, float("inf"))
