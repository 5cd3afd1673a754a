"""Conservative ray/box slab test (Ize 2013).

Reference: Ize, "Robust BVH Ray Traversal", JCGT 2(2), 2013: with the reciprocal direction rounded once, the
far slab distance scaled by ``1 + 2 * gamma(3)`` bounds the rounding of the subtraction, the product and the
reciprocal, so no box the exact ray passes through is missed. Direction components are clamped away from
zero before the reciprocal (:func:`jaxrt._src.numerics.safe_reciprocal`), so axis-parallel rays and rays
starting on a slab plane produce no NaN.
"""

from __future__ import annotations

import jax

from jaxrt._src import formulas
from jaxrt._src.numerics import RECIPROCAL_CLAMP, gamma

_box = formulas.instance("box", "jax")

FAR_SCALE = 1.0 + 2.0 * gamma(3)
#: Reciprocals at least this large come from clamped (zero) direction components (see ``safe_reciprocal``).
PARALLEL_RECIPROCAL = 0.5 / RECIPROCAL_CLAMP


def ray_box(
    origin: jax.Array, inv_direction: jax.Array, t_min: jax.Array, t_max: jax.Array, lower: jax.Array, upper: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """Whether a ray overlaps boxes within ``[t_min, t_max]``, and the entry distance.

    The formulas of :mod:`jaxrt._src.formulas.box` (shared with the compiled traversals), elementwise over the
    boxes.

    Args:
      origin, inv_direction: ``(3,)`` ray origin and safe reciprocal direction.
      t_min, t_max: scalars, the ray's distance interval.
      lower, upper: ``(..., 3)`` boxes; an empty box (+inf, -inf) never overlaps.

    Returns:
      ``hit`` (bool) and ``t_near`` (entry distance, clamped to ``t_min``), both of shape ``(...)``.
    """
    slabs = []
    for axis in range(3):
        slabs += _box.slab_axis(
            lower[..., axis], upper[..., axis], origin[..., axis], inv_direction[..., axis], PARALLEL_RECIPROCAL
        )
    hit, t_near, _ = _box.box_hit(*slabs, lower[..., 0], upper[..., 0], t_min, t_max, FAR_SCALE)
    return hit, t_near
