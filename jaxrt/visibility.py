"""Visibility-aware gradients: edge sampling of silhouettes and shadow edges for pixel integrals.

:func:`jaxrt.pixel_integral` is the usual entry point; the pieces below let a custom integrator add the
boundary term itself. See ``docs/differentiable.md``.
"""

from jaxrt._src.visibility import (
    DirectionalLight,
    EdgeSamples,
    PinholeCamera,
    PointLight,
    SilhouetteMesh,
    boundary_term,
    edge_differences,
    primary_edge_samples,
    shadow_edge_samples,
)

__all__ = [
    "DirectionalLight",
    "EdgeSamples",
    "PinholeCamera",
    "PointLight",
    "SilhouetteMesh",
    "boundary_term",
    "edge_differences",
    "primary_edge_samples",
    "shadow_edge_samples",
]
