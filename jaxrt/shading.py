"""Differentiable shading helpers for experiments.

Camera rays, hit points, normals, interpolated vertex attributes and textures, Lambert, Phong and
Blinn-Phong shading, ambient occlusion and a one-bounce diffuse estimator. See ``docs/differentiable.md``.
"""

from jaxrt._src.shading import (
    ambient_occlusion,
    blinn_phong,
    cosine_hemisphere,
    face_forward,
    hit_points,
    interpolate,
    interpolate_normals,
    lambert,
    one_bounce_diffuse,
    phong,
    pinhole_rays,
    texture_lookup,
    triangle_normals,
    vertex_normals,
)

__all__ = [
    "ambient_occlusion",
    "blinn_phong",
    "cosine_hemisphere",
    "face_forward",
    "hit_points",
    "interpolate",
    "interpolate_normals",
    "lambert",
    "one_bounce_diffuse",
    "phong",
    "pinhole_rays",
    "texture_lookup",
    "triangle_normals",
    "vertex_normals",
]
