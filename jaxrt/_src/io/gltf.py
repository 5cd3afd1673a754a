"""glTF 2.0 scenes as instance structures over shared meshes (node hierarchy and EXT_mesh_gpu_instancing).

The file is parsed with pygltflib (``pip install 'jaxrt[gltf]'``); accessors are decoded here with numpy.
Each glTF mesh becomes one :class:`~jaxrt.PrimitiveAccelerationStructure` (one geometry per triangle
primitive: ``geometry_id`` is the primitive's index in the mesh), built once however many nodes use it.

With ``hierarchy=True`` the node tree becomes nested instance structures: a node that places several things
(its mesh, once or once per EXT_mesh_gpu_instancing transform, and what its children place, each by the
child's local transform) becomes an instance structure over them; a node that places one thing passes it up
to its parent with the transforms composed, so chains of single children add no level. The scene's root
nodes are placed by the top structure. The structure is about as deep as the tree (``GltfScene.levels``). With ``hierarchy=False`` every mesh placement is one instance of a single-level
structure, with the node's world transform. Both trace the same triangles.

Nothing is special-cased per file: node ``matrix`` or TRS, triangle lists, strips and fans (other modes
are skipped), indexed or not, buffers in a GLB chunk, a ``.bin`` file or a ``data:`` URI, and the
EXT_mesh_gpu_instancing TRANSLATION / ROTATION / SCALE attributes (float or normalised integers).
Instances whose transform is singular (a zero scale hides a node in glTF) are left out and counted.
"""

from __future__ import annotations

import base64
import dataclasses
import os
from pathlib import Path
from typing import Any

import numpy as np

from jaxrt._src.geometry import TriangleGeometry
from jaxrt._src.instances import Instances, build_instance_structure
from jaxrt._src.prepacked import build_primitive_structure
from jaxrt._src.transforms import SINGULAR_TOLERANCE

__all__ = ["GltfScene", "load_gltf"]

_COMPONENT = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_TRIANGLES, _STRIP, _FAN = 4, 5, 6


@dataclasses.dataclass(frozen=True)
class GltfScene:
    """A loaded glTF scene.

    Attributes:
      structure: the top :class:`~jaxrt.InstanceAccelerationStructure`; trace it with
        ``rt.Intersector(rt.tags.instancing, rt.tags.max_levels(scene.levels))``.
      levels: instance levels of ``structure``.
      meshes: per glTF mesh, its primitive structure (``None`` for a mesh without triangles or unused).
      mesh_triangles: per glTF mesh, its ``(T, 3, 3)`` float32 triangles in mesh space (``None`` likewise).
      placements: ``(mesh index, (4, 4) float64 world transform)`` of every mesh instance in the scene.
      skipped_instances: mesh or node instances left out for a singular transform.
    """

    structure: Any
    levels: int
    meshes: tuple[Any, ...]
    mesh_triangles: tuple[np.ndarray | None, ...]
    placements: tuple[tuple[int, np.ndarray], ...]
    skipped_instances: int

    @property
    def triangle_count(self) -> int:
        """Distinct triangles stored (each mesh once)."""
        used = {m for m, _ in self.placements}
        return sum(self.mesh_triangles[m].shape[0] for m in used)

    @property
    def instanced_triangle_count(self) -> int:
        """Triangles in the flattened scene."""
        return sum(self.mesh_triangles[m].shape[0] for m, _ in self.placements)

    def world_triangles(self) -> np.ndarray:
        """``(F, 3, 3)`` float64 world-space triangles of the flattened scene, in placement order."""
        parts = []
        for mesh, matrix in self.placements:
            tri = self.mesh_triangles[mesh].astype(np.float64)
            parts.append(tri @ matrix[:3, :3].T + matrix[:3, 3])
        return np.concatenate(parts) if parts else np.zeros((0, 3, 3))


def _read_buffers(gltf, path: Path) -> list[bytes]:
    buffers = []
    for index, buffer in enumerate(gltf.buffers):
        uri = buffer.uri
        if uri is None:
            blob = gltf.binary_blob()
            if blob is None:
                raise ValueError(f"load_gltf: {str(path)!r}: buffer {index} has no URI and the file has no GLB chunk")
            buffers.append(bytes(blob))
        elif uri.startswith("data:"):
            buffers.append(base64.b64decode(uri.split(",", 1)[1]))
        else:
            file = path.parent / uri
            if not file.is_file():
                raise FileNotFoundError(f"load_gltf: {str(path)!r}: buffer {index} file {str(file)!r} is missing")
            buffers.append(file.read_bytes())
    return buffers


def _accessor(gltf, buffers: list[bytes], index: int, name: str) -> np.ndarray:
    """Accessor ``index`` as an array ``(count,)`` or ``(count, width)``; normalised integers become floats."""
    accessor = gltf.accessors[index]
    if accessor.sparse is not None:
        raise ValueError(f"load_gltf: accessor {index} ({name}) is sparse, which this loader does not read")
    dtype = np.dtype(_COMPONENT[accessor.componentType]).newbyteorder("<")
    width = _WIDTH[accessor.type]
    count = accessor.count
    if accessor.bufferView is None:
        data = np.zeros((count, width), dtype)
    else:
        view = gltf.bufferViews[accessor.bufferView]
        raw = buffers[view.buffer]
        start = (view.byteOffset or 0) + (accessor.byteOffset or 0)
        element = dtype.itemsize * width
        stride = view.byteStride or element
        if count and start + stride * (count - 1) + element > len(raw):
            raise ValueError(f"load_gltf: accessor {index} ({name}) reads past the end of buffer {view.buffer}")
        rows = np.lib.stride_tricks.as_strided(
            np.frombuffer(raw, np.uint8, offset=start, count=max(0, stride * (count - 1) + element)),
            shape=(count, element),
            strides=(stride, 1),
        )
        data = np.ascontiguousarray(rows).view(dtype).reshape(count, width)
    if accessor.normalized and dtype.kind in "iu":
        info = np.iinfo(dtype)
        data = np.maximum(data.astype(np.float64) / info.max, -1.0)
    return data[:, 0] if width == 1 else data


def primitive_faces(gltf, buffers, primitive, count: int, where: str, owner: str = "load_gltf") -> np.ndarray:
    """Vertex indices ``(T, 3)`` of a triangle, strip or fan primitive with ``count`` vertices, checked in range
    (a ``ValueError`` that names ``owner`` and ``where`` otherwise)."""
    mode = _TRIANGLES if primitive.mode is None else primitive.mode
    if primitive.indices is None:
        indices = np.arange(count)
    else:
        indices = _accessor(gltf, buffers, primitive.indices, f"{where} indices").astype(np.int64)
    if mode == _TRIANGLES:
        faces = indices[: len(indices) // 3 * 3].reshape(-1, 3)
    elif mode == _STRIP:
        i = np.arange(max(0, len(indices) - 2))
        faces = np.stack([indices[i], indices[i + 1 + i % 2], indices[i + 2 - i % 2]], axis=-1)
    else:
        i = np.arange(1, max(1, len(indices) - 1))
        faces = np.stack([np.full_like(i, indices[0]), indices[i], indices[i + 1]], axis=-1)
    if faces.size and ((faces < 0) | (faces >= count)).any():
        raise ValueError(f"{owner}: {where}: an index is out of range for {count} vertices")
    return faces


def _triangles(gltf, buffers, mesh_index: int) -> list[np.ndarray]:
    """Triangles ``(T, 3, 3)`` of each triangle primitive of a mesh (other modes are skipped)."""
    out = []
    for k, primitive in enumerate(gltf.meshes[mesh_index].primitives):
        mode = _TRIANGLES if primitive.mode is None else primitive.mode
        if mode not in (_TRIANGLES, _STRIP, _FAN) or primitive.attributes.POSITION is None:
            continue
        where = f"mesh {mesh_index} primitive {k}"
        positions = _accessor(gltf, buffers, primitive.attributes.POSITION, f"{where} POSITION").astype(np.float64)
        faces = primitive_faces(gltf, buffers, primitive, positions.shape[0], where)
        tri = positions[faces].astype(np.float32)
        if not np.isfinite(tri).all():
            raise ValueError(f"load_gltf: {where}: a vertex position is not finite")
        if tri.shape[0]:
            out.append(tri)
    return out


def _quaternion_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` of unit quaternions ``(..., 4)`` stored ``(x, y, z, w)`` (glTF order)."""
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def _trs(translation, rotation, scale) -> np.ndarray:
    """``(..., 4, 4)`` matrices ``T R S``."""
    translation, rotation, scale = (np.asarray(a, np.float64) for a in (translation, rotation, scale))
    shape = np.broadcast_shapes(translation.shape[:-1], rotation.shape[:-1], scale.shape[:-1])
    m = np.zeros((*shape, 4, 4))
    m[..., :3, :3] = _quaternion_matrix(rotation) * scale[..., None, :]
    m[..., :3, 3] = translation
    m[..., 3, 3] = 1.0
    return m


def _local_matrix(node) -> np.ndarray:
    if node.matrix is not None:
        return np.asarray(node.matrix, np.float64).reshape(4, 4).T  # column-major in the file
    return _trs(
        node.translation if node.translation is not None else [0.0, 0.0, 0.0],
        node.rotation if node.rotation is not None else [0.0, 0.0, 0.0, 1.0],
        node.scale if node.scale is not None else [1.0, 1.0, 1.0],
    )


def _gpu_instances(gltf, buffers, node, index: int) -> np.ndarray | None:
    """EXT_mesh_gpu_instancing transforms ``(K, 4, 4)`` of a node, or ``None``."""
    extension = (node.extensions or {}).get("EXT_mesh_gpu_instancing")
    if not extension:
        return None
    attributes = extension.get("attributes", {})
    columns = {}
    for name, default in (("TRANSLATION", [0.0, 0.0, 0.0]), ("ROTATION", [0.0, 0.0, 0.0, 1.0]), ("SCALE", [1.0] * 3)):
        if name in attributes:
            columns[name] = _accessor(gltf, buffers, attributes[name], f"node {index} {name}").astype(np.float64)
        else:
            columns[name] = np.asarray([default])
    counts = {len(v) for k, v in columns.items() if k in attributes}
    if len(counts) > 1:
        raise ValueError(
            f"load_gltf: node {index}: EXT_mesh_gpu_instancing attributes differ in count {sorted(counts)}"
        )
    return _trs(columns["TRANSLATION"], columns["ROTATION"], columns["SCALE"])


def _node_name(gltf, index: int) -> str:
    name = gltf.nodes[index].name
    return f"node {index}" + (f" ({name!r})" if name else "")


def _check_acyclic(gltf, roots: list[int]) -> None:
    """Node references must form a forest (or a DAG): a node that is its own ancestor is an error."""
    state: dict[int, int] = {}  # 1 on the current path, 2 done

    def visit(i: int, path: list[int]) -> None:
        if not 0 <= i < len(gltf.nodes):
            raise ValueError(f"load_gltf: node {path[-1] if path else '?'} has child {i}, which does not exist")
        if state.get(i) == 2:
            return
        if state.get(i) == 1:
            cycle = " -> ".join(str(n) for n in path[path.index(i) :] + [i])
            raise ValueError(
                f"load_gltf: the node hierarchy has a cycle ({cycle}): {_node_name(gltf, i)} is its own ancestor"
            )
        state[i] = 1
        for child in gltf.nodes[i].children or []:
            visit(child, path + [i])
        state[i] = 2

    for root in roots:
        visit(root, [])


def _is_invertible(matrix: np.ndarray) -> bool:
    linear = matrix[:3, :3]
    scale = np.prod(np.linalg.norm(linear, axis=1))
    return bool(np.isfinite(matrix).all() and scale > 0 and abs(np.linalg.det(linear)) / scale >= SINGULAR_TOLERANCE)


def _bucket(n: int) -> int:
    return max(1, 1 << (n - 1).bit_length())


def _instance_structure(entries: list[tuple[Any, np.ndarray]]):
    """An instance structure over ``(structure, 4x4 transform)`` entries; slots padded to a power of two.

    The padding instances lie past the build's ``count``, so they do not exist; padding lets structures of
    similar size share one compiled build.
    """
    structures: list[Any] = []
    index = []
    for structure, _ in entries:
        position = next((k for k, s in enumerate(structures) if s is structure), None)
        if position is None:
            position = len(structures)
            structures.append(structure)
        index.append(position)
    n = len(entries)
    slots = _bucket(n)
    transform = np.tile(np.eye(3, 4, dtype=np.float32), (slots, 1, 1))
    transform[:n] = np.stack([m[:3] for _, m in entries]).astype(np.float32)
    index = np.asarray(index + [0] * (slots - n), np.int32)
    return build_instance_structure(structures, Instances(index, transform), count=n)


def load_gltf(path: str | os.PathLike[str], *, scene: int | None = None, hierarchy: bool = True) -> GltfScene:
    """Load a glTF 2.0 scene (``.gltf`` or ``.glb``) as instance structures over shared meshes.

    Args:
      path: the file.
      scene: index of the scene to load; ``None`` takes the file's default scene (or the first).
      hierarchy: ``True`` mirrors the node tree with nested instance structures; ``False`` gives one level
        of instances placed by world transforms.

    Returns:
      A :class:`GltfScene`.

    Raises:
      ImportError: pygltflib is missing (``pip install 'jaxrt[gltf]'``).
      FileNotFoundError: the file or one of its buffers is missing.
      ValueError: a node cycle (naming the nodes), an index or accessor out of range, a sparse accessor,
        non-finite positions, or a scene without triangles.

    Examples:
      >>> import jaxrt as rt  # doctest: +SKIP
      >>> scene = rt.io.load_gltf("SimpleInstancing.gltf")  # doctest: +SKIP
      >>> scene.instanced_triangle_count  # doctest: +SKIP
      1500
    """
    try:
        import pygltflib
    except ImportError as error:
        raise ImportError("load_gltf needs pygltflib; install it with `pip install 'jaxrt[gltf]'`") from error

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"load_gltf: no such file: {str(path)!r}")
    gltf = pygltflib.GLTF2().load(str(path))
    buffers = _read_buffers(gltf, path)
    if not gltf.scenes:
        roots = [i for i in range(len(gltf.nodes)) if not any(i in (n.children or []) for n in gltf.nodes)]
    else:
        chosen = scene if scene is not None else (gltf.scene or 0)
        if not 0 <= chosen < len(gltf.scenes):
            raise ValueError(f"load_gltf: scene {chosen} does not exist; the file has {len(gltf.scenes)} scenes")
        roots = list(gltf.scenes[chosen].nodes or [])
    _check_acyclic(gltf, roots)

    mesh_triangles: list[np.ndarray | None] = [None] * len(gltf.meshes)
    meshes: list[Any] = [None] * len(gltf.meshes)

    def mesh_structure(m: int):
        if meshes[m] is None:
            parts = _triangles(gltf, buffers, m)
            if not parts:
                return None
            mesh_triangles[m] = np.concatenate(parts)
            meshes[m] = build_primitive_structure([TriangleGeometry(p.reshape(-1, 3)) for p in parts])
        return meshes[m]

    placements: list[tuple[int, np.ndarray]] = []
    skipped = 0

    def mesh_entries(i: int) -> list[tuple[Any, np.ndarray]]:
        """The node's own mesh, once or per GPU instance, in the node's space."""
        node = gltf.nodes[i]
        if node.mesh is None:
            return []
        structure = mesh_structure(node.mesh)
        if structure is None:
            return []
        gpu = _gpu_instances(gltf, buffers, node, i)
        matrices = [np.eye(4)] if gpu is None else list(gpu)
        return [(structure, m) for m in matrices if _is_invertible(m)]

    def collect(i: int, world: np.ndarray) -> None:
        """Placements of every mesh instance below node ``i`` (for counts and ``world_triangles``)."""
        nonlocal skipped
        node = gltf.nodes[i]
        world = world @ _local_matrix(node)
        if node.mesh is not None and mesh_structure(node.mesh) is not None:
            gpu = _gpu_instances(gltf, buffers, node, i)
            for m in [np.eye(4)] if gpu is None else list(gpu):
                if _is_invertible(m) and _is_invertible(world):
                    placements.append((node.mesh, world @ m))
                else:
                    skipped += 1
        for child in node.children or []:
            collect(child, world)

    for root in roots:
        collect(root, np.eye(4))

    if hierarchy:
        built: dict[int, list[tuple[Any, np.ndarray]]] = {}

        def node_entries(i: int) -> list[tuple[Any, np.ndarray]]:
            """What node ``i`` places, in its own space: one entry passes up to the parent (its transform
            composed there), several become an instance structure (so chains of single children add no level)."""
            if i in built:
                return built[i]
            entries = mesh_entries(i)
            for child in gltf.nodes[i].children or []:
                local = _local_matrix(gltf.nodes[child])
                if _is_invertible(local):
                    entries += [(structure, local @ m) for structure, m in node_entries(child)]
            if len(entries) > 1:
                entries = [(_instance_structure(entries), np.eye(4))]
            built[i] = entries
            return entries

        top = []
        for root in roots:
            local = _local_matrix(gltf.nodes[root])
            if _is_invertible(local):
                top += [(structure, local @ m) for structure, m in node_entries(root)]
    else:
        top = [(meshes[m], world) for m, world in placements]
    if not top:
        raise ValueError(
            f"load_gltf: {str(path)!r} has no triangles in scene {scene if scene is not None else 'default'}"
        )
    structure = _instance_structure(top)
    return GltfScene(
        structure=structure,
        levels=structure.levels,
        meshes=tuple(meshes),
        mesh_triangles=tuple(mesh_triangles),
        placements=tuple(placements),
        skipped_instances=skipped,
    )
