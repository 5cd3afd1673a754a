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
shape code (1 sphere, 2 disk, 3 capped cylinder; from 5 on the kinds that declare an analytic row, such as the
built-in spheres' :mod:`jaxrt._src.formulas.sphere`). :func:`analytic_hit` is generated at import from the kind
registry (:mod:`jaxrt._src.traversal.analytic_rows`): one warp-uniform branch per shape.
"""

from __future__ import annotations

import triton
import triton.language as tl

from jaxrt._src import formulas
from jaxrt._src.traversal import analytic_rows


@triton.jit
def _any(flags):
    """Whether some lane of the warp has ``flags`` set (a warp-uniform value)."""
    return tl.max(flags.to(tl.int32), axis=0) > 0


@triton.jit
def _merge(hit, distance, shape_hit, shape_t):
    return hit | shape_hit, tl.where(shape_hit, shape_t, distance)


_generated = analytic_rows.compile_source(
    "triton",
    analytic_rows.triton_source(),
    dict(
        triton=triton,
        tl=tl,
        _any=_any,
        _merge=_merge,
        tests=lambda module, name: getattr(formulas.instance(module, "triton"), name),
    ),
)
analytic_hit = _generated.analytic_hit
