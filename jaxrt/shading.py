"""Differentiable shading helpers for experiments: camera rays, normals, Lambert shading, ambient occlusion."""

from jaxrt._src.shading import (
    ambient_occlusion,
    cosine_hemisphere,
    hit_points,
    lambert,
    pinhole_rays,
    triangle_normals,
)

__all__ = ["ambient_occlusion", "cosine_hemisphere", "hit_points", "lambert", "pinhole_rays", "triangle_normals"]
