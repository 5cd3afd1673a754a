"""glTF animation as keyframe motion: node TRS animation becomes instance motion, morph-target weights become
moving vertices.

The animation is sampled at ``K`` evenly spaced times over its time range (the span of the selected
animations' keyframe times), with the glTF interpolation of each channel (``STEP``, ``LINEAR`` with slerp
for rotations, ``CUBICSPLINE`` Hermite splines), and the scene is flattened to one level of instances whose
``(N, K, 3, 4)`` transforms are each mesh node's world transform at those times. A mesh node whose morph
weights are animated gets its own :class:`~jaxrt.MotionTriangleGeometry` with the morphed positions at the
same times. Between samples the traversal blends linearly (and transforms component-wise), so ``K`` decides
how closely rotations and splines are followed. Skinning (joints and weights) is not read.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any

import numpy as np

from jaxrt._src.geometry import MotionTriangleGeometry, TriangleGeometry
from jaxrt._src.instances import Instances, build_instance_structure
from jaxrt._src.io.gltf import (
    _FAN,
    _STRIP,
    _TRIANGLES,
    _accessor,
    _is_invertible,
    _read_buffers,
    _trs,
    primitive_faces,
)
from jaxrt._src.motion import MotionSpec
from jaxrt._src.prepacked import build_primitive_structure

__all__ = ["GltfMotion", "load_gltf_motion", "sample_channel"]


@dataclasses.dataclass(frozen=True)
class GltfMotion:
    """An animated glTF scene as keyframe motion.

    Attributes:
      structure: an :class:`~jaxrt.InstanceAccelerationStructure` with instance motion (and primitive motion
        for morphing meshes); trace it with ``rt.Intersector(rt.tags.instancing, rt.tags.instance_motion,
        rt.tags.primitive_motion)``.
      motion: the :class:`~jaxrt.MotionSpec` (the animation's time range, clamped at both ends).
      times: ``(K,)`` the keyframe times.
      placements: ``(mesh index, (K, 4, 4) world transforms)`` of every mesh instance, in instance order.
      nodes: the glTF node of every instance.
      triangles: per instance, ``(K, T, 3, 3)`` float32 mesh-space triangles at each keyframe.
    """

    structure: Any
    motion: Any
    times: np.ndarray
    placements: tuple[tuple[int, np.ndarray], ...]
    triangles: tuple[np.ndarray, ...]
    nodes: tuple[int, ...] = ()

    def world_triangles(self, k: int) -> np.ndarray:
        """``(F, 3, 3)`` float64 world-space triangles of keyframe ``k`` (every instance, in order)."""
        parts = []
        for (_, matrices), tri in zip(self.placements, self.triangles, strict=True):
            m = matrices[k]
            parts.append(tri[k].astype(np.float64) @ m[:3, :3].T + m[:3, 3])
        return np.concatenate(parts)


def _slerp(a: np.ndarray, b: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Spherical interpolation of unit quaternions ``(..., 4)`` along the shorter arc."""
    dot = np.sum(a * b, axis=-1, keepdims=True)
    b = np.where(dot < 0, -b, b)
    dot = np.abs(dot)
    angle = np.arccos(np.clip(dot, -1.0, 1.0))
    small = angle < 1e-6
    sin = np.where(small, 1.0, np.sin(angle))
    wa = np.where(small, 1.0 - s, np.sin((1.0 - s) * angle) / sin)
    wb = np.where(small, s, np.sin(s * angle) / sin)
    out = wa * a + wb * b
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


def sample_channel(inputs: np.ndarray, outputs: np.ndarray, interpolation: str, times: np.ndarray, path: str):
    """A glTF sampler's values ``(len(times), width)`` at ``times`` (clamped to its first/last key).

    ``outputs`` is ``(N, width)`` (``(3 N, width)`` for ``CUBICSPLINE``: in-tangent, value, out-tangent per
    key); rotations (``path == "rotation"``) are slerped (``LINEAR``) or renormalised (``CUBICSPLINE``).
    """
    n = inputs.shape[0]
    if interpolation == "CUBICSPLINE":
        outputs = outputs.reshape(n, 3, -1)
        in_tangent, values, out_tangent = outputs[:, 0], outputs[:, 1], outputs[:, 2]
    else:
        values = outputs.reshape(n, -1)
    t = np.clip(times, inputs[0], inputs[-1])
    k = np.clip(np.searchsorted(inputs, t, side="right") - 1, 0, max(n - 2, 0))
    if n == 1:
        return np.repeat(values[:1], len(times), axis=0)
    dt = inputs[k + 1] - inputs[k]
    s = ((t - inputs[k]) / np.where(dt > 0, dt, 1.0))[:, None]
    if interpolation == "STEP":
        return np.where(s >= 1.0, values[k + 1], values[k])
    if interpolation == "CUBICSPLINE":  # glTF 2.0 spec, appendix C: Hermite with tangents scaled by dt
        s2, s3 = s * s, s * s * s
        d = dt[:, None]
        out = (
            (2 * s3 - 3 * s2 + 1) * values[k]
            + (s3 - 2 * s2 + s) * d * out_tangent[k]
            + (-2 * s3 + 3 * s2) * values[k + 1]
            + (s3 - s2) * d * in_tangent[k + 1]
        )
        return out / np.linalg.norm(out, axis=-1, keepdims=True) if path == "rotation" else out
    if path == "rotation":
        return _slerp(values[k], values[k + 1], s)
    return (1.0 - s) * values[k] + s * values[k + 1]


def _morphed_triangles(gltf, buffers, mesh_index: int, weights: np.ndarray) -> np.ndarray | None:
    """``(K, T, 3, 3)`` triangles of a mesh with morph ``weights`` ``(K, targets)`` applied to its positions."""
    parts = []
    for p, primitive in enumerate(gltf.meshes[mesh_index].primitives):
        mode = _TRIANGLES if primitive.mode is None else primitive.mode
        if mode not in (_TRIANGLES, _STRIP, _FAN) or primitive.attributes.POSITION is None:
            continue
        where = f"mesh {mesh_index} primitive {p}"
        base = _accessor(gltf, buffers, primitive.attributes.POSITION, f"{where} POSITION").astype(np.float64)
        positions = np.repeat(base[None], weights.shape[0], axis=0)
        for i, target in enumerate(primitive.targets or []):
            index = target.get("POSITION") if isinstance(target, dict) else getattr(target, "POSITION", None)
            if index is not None and i < weights.shape[1]:
                delta = _accessor(gltf, buffers, index, f"{where} target {i}").astype(np.float64)
                positions += weights[:, i, None, None] * delta[None]
        faces = primitive_faces(gltf, buffers, primitive, base.shape[0], where, owner="load_gltf_motion")
        if faces.size:
            parts.append(positions[:, faces])
    if not parts:
        return None
    out = np.concatenate(parts, axis=1).astype(np.float32)
    if not np.isfinite(out).all():
        raise ValueError(f"load_gltf_motion: mesh {mesh_index}: a morphed vertex position is not finite")
    return out


def load_gltf_motion(
    path: str | os.PathLike[str], *, keyframes: int = 16, animations: Any = None, scene: int | None = None
) -> GltfMotion:
    """Load an animated glTF 2.0 scene as keyframe motion (node TRS animation and morph-target weights).

    Args:
      path: the ``.gltf`` or ``.glb`` file.
      keyframes: ``K >= 2`` samples over the animation's time range.
      animations: indices of the animations to play together (``None``: all of them).
      scene: the scene to load (``None``: the default scene).

    Returns:
      A :class:`GltfMotion`.

    Raises:
      ImportError: pygltflib is missing.
      FileNotFoundError: a missing file or buffer.
      ValueError: fewer than 2 keyframes, no animation (or an index out of range), an animation of zero
        duration, or no triangles.
    """
    try:
        import pygltflib
    except ImportError as error:
        raise ImportError("load_gltf_motion needs pygltflib; install it with `pip install 'jaxrt[gltf]'`") from error

    owner = "load_gltf_motion"
    if isinstance(keyframes, bool) or not isinstance(keyframes, int) or keyframes < 2:
        raise ValueError(f"{owner}: keyframes must be an int >= 2, got {keyframes!r}")
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{owner}: no such file: {str(path)!r}")
    gltf = pygltflib.GLTF2().load(str(path))
    buffers = _read_buffers(gltf, path)
    if not gltf.animations:
        raise ValueError(f"{owner}: {str(path)!r} has no animations; load it with rt.io.load_gltf")
    chosen = range(len(gltf.animations)) if animations is None else list(animations)
    for a in chosen:
        if not 0 <= a < len(gltf.animations):
            raise ValueError(f"{owner}: animation {a} does not exist; the file has {len(gltf.animations)}")
    channels = []
    for a in chosen:
        animation = gltf.animations[a]
        for c, channel in enumerate(animation.channels):
            if channel.target.node is None:
                continue
            sampler = animation.samplers[channel.sampler]
            where = f"animation {a} channel {c}"
            inputs = _accessor(gltf, buffers, sampler.input, f"{where} input").astype(np.float64).reshape(-1)
            outputs = _accessor(gltf, buffers, sampler.output, f"{where} output").astype(np.float64)
            outputs = outputs.reshape(inputs.shape[0] * (3 if sampler.interpolation == "CUBICSPLINE" else 1), -1)
            channels.append(
                (channel.target.node, channel.target.path, inputs, outputs, sampler.interpolation or "LINEAR")
            )
    if not channels:
        raise ValueError(f"{owner}: the chosen animations have no node channels")
    start = min(c[2][0] for c in channels)
    end = max(c[2][-1] for c in channels)
    if not end > start:
        raise ValueError(f"{owner}: the animation has zero duration (every key at time {start})")
    times = np.linspace(start, end, keyframes)
    sampled: dict[tuple[int, str], np.ndarray] = {}
    for node, target, inputs, outputs, interpolation in channels:
        values = sample_channel(inputs, outputs, interpolation, times, target)
        if target == "weights":
            values = values.reshape(keyframes, -1)
        sampled[(node, target)] = values

    def local(i: int) -> np.ndarray:
        node = gltf.nodes[i]
        if node.matrix is not None:
            return np.broadcast_to(np.asarray(node.matrix, np.float64).reshape(4, 4).T, (keyframes, 4, 4))
        trs = {
            "translation": node.translation if node.translation is not None else [0.0, 0.0, 0.0],
            "rotation": node.rotation if node.rotation is not None else [0.0, 0.0, 0.0, 1.0],
            "scale": node.scale if node.scale is not None else [1.0, 1.0, 1.0],
        }
        parts = [
            sampled.get((i, k), np.broadcast_to(np.asarray(v, np.float64), (keyframes, len(v)))) for k, v in trs.items()
        ]
        return _trs(*parts)

    roots = list(gltf.scenes[scene if scene is not None else (gltf.scene or 0)].nodes or []) if gltf.scenes else []
    placements: list[tuple[int, np.ndarray]] = []
    nodes: list[int] = []
    triangles: list[np.ndarray] = []
    structures: list[Any] = []
    cache: dict[Any, tuple[Any, np.ndarray]] = {}
    spec = MotionSpec(float(start), float(end))

    def mesh_of(i: int):
        node = gltf.nodes[i]
        mesh = gltf.meshes[node.mesh]
        morphing = (i, "weights") in sampled
        if morphing:
            key = ("node", i)
            weights = sampled[(i, "weights")]
        else:
            key = ("mesh", node.mesh)
            default = getattr(node, "weights", None) or mesh.weights or []
            weights = np.broadcast_to(np.asarray(default, np.float64), (keyframes, len(default)))
        if key not in cache:
            tri = _morphed_triangles(gltf, buffers, node.mesh, np.asarray(weights).reshape(keyframes, -1))
            if tri is None:
                cache[key] = (None, None)
            elif morphing:
                geometry = MotionTriangleGeometry(tri.reshape(keyframes, -1, 3))
                cache[key] = (build_primitive_structure(geometry, motion=spec), tri)
            else:
                cache[key] = (build_primitive_structure(TriangleGeometry(tri[0].reshape(-1, 3))), tri)
        return cache[key]

    def visit(i: int, world: np.ndarray) -> None:
        world = world @ local(i)
        node = gltf.nodes[i]
        if node.mesh is not None and all(_is_invertible(m) for m in world):
            structure, tri = mesh_of(i)
            if structure is not None:
                placements.append((node.mesh, world))
                nodes.append(i)
                triangles.append(tri)
                structures.append(structure)
        for child in node.children or []:
            visit(child, world)

    for root in roots:
        visit(root, np.broadcast_to(np.eye(4), (keyframes, 4, 4)))
    if not placements:
        raise ValueError(f"{owner}: {str(path)!r} has no triangles in the chosen scene")
    distinct: list[Any] = []
    index = []
    for s in structures:
        position = next((k for k, d in enumerate(distinct) if d is s), None)
        if position is None:
            position = len(distinct)
            distinct.append(s)
        index.append(position)
    transforms = np.stack([m[:, :3] for _, m in placements]).astype(np.float32)  # (N, K, 3, 4)
    structure = build_instance_structure(distinct, Instances(index, transforms), motion=spec)
    return GltfMotion(structure, spec, times, tuple(placements), tuple(triangles), tuple(nodes))
