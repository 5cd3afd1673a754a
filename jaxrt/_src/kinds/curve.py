"""Curves (``rt.CurveGeometry``, ``rt.MotionCurveGeometry``): round (swept-sphere tubes) and flat (ray-facing
ribbons) segments of any basis, converted to cubic Bezier segments at build time.

Round and flat curves are one kind: they share the leaf layout, and each segment's flags say which test it
takes (the intersector's static ``curve_type`` may compile one of them only).

Leaf layout (``C`` leaf slots; ``K`` keyframes with keyframe motion):

====================  ================  =========  ==================================================================
array                 per leaf          fill       contents
====================  ================  =========  ==================================================================
``leaf_curve``        (6, 4) float      zeros      the segment packed by :func:`jaxrt._src.curves.pack_segments`:
                                                   cubic Bezier points and radii relative to the first control
                                                   point, that point, and the predecessor's joint derivative
``leaf_curve_flags``  () int32          zeros      links to the neighbours, end caps, type (flat), and the bit
                                                   ``IS_CURVE`` marking curve leaves
``motion_curve``      (K, 6, 4) float   zeros      ``leaf_curve`` at each keyframe (the packing is linear in the
                                                   control points, so blended packed keyframes pack the blend)
====================  ================  =========  ==================================================================

Bounds: the Bezier hull grown by the radius (:func:`jaxrt._src.primitives.curve.segment_bounds`).
Intersection: :func:`jaxrt._src.primitives.curve.intersect` (Newton on the segment's pieces, caps and joints);
re-intersection: :func:`~jaxrt._src.primitives.curve.smooth_hit`. The compiled traversals' test: the formula
:mod:`jaxrt._src.formulas.curve` (the CPU traversal's, and the GPU kernel's through
:mod:`jaxrt._src.traversal.triton_curves`). Point queries do not take curves yet. No
decision needs JAX.
"""

from __future__ import annotations

from jaxrt._src.kinds.kind import Coverage, Kind, LeafArray
from jaxrt._src.primitives import curve as formulas

__all__ = ["CURVE"]

CURVE = Kind(
    name="curve",
    plural="curves",
    be="are",
    intersection_type=3,
    leaf_arrays=(
        LeafArray("leaf_curve", (6, 4), "float", "zeros", "motion_curve", "the packed cubic Bezier segment"),
        LeafArray("leaf_curve_flags", (), "int32", "zeros", None, "links, end caps, type and IS_CURVE"),
    ),
    bounds=formulas.segment_bounds,
    intersect=formulas.intersect,
    reintersect=formulas.smooth_hit,
    closest_point=None,  # point queries do not take curves yet
    tags=("curve_data", "normal"),
    fields={"curve_parameter": "curve_data"},
    coverage={
        "gpu": Coverage(instanced=False, motion=False, alone=True, waves=False),
        "cpu": Coverage(instanced=False, motion=False, alone=True, waves=False),
    },
    doc="A curve segment.",
    tag_docs={
        "curve_data": "Adds ``curve_parameter`` (curve geometry).",
    },
    geometry="CurveGeometry",
    float_array="control_points",
)
