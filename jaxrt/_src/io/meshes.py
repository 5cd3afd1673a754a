"""Triangle meshes from files (PLY, OBJ, STL, OFF, glTF, ... and their ``.gz`` versions) through trimesh.

The loader returns plain arrays, ready for :class:`jaxrt.TriangleGeometry`: the mesh is read as stored
(``process=False``: no vertex merging, no reordering), polygons are triangulated by trimesh, and every
object of a multi-object file is concatenated into one mesh.

glTF files that flattening would misread are refused or flagged: a file using ``EXT_mesh_gpu_instancing``
raises (trimesh would keep one copy of each instanced mesh), and a file with several scenes warns (only the
default scene is read); :func:`jaxrt.io.load_gltf` reads both.
"""

from __future__ import annotations

import gzip
import io
import json
import os
import struct
import warnings
from pathlib import Path

import numpy as np

__all__ = ["load_mesh"]


def _file_type(path: Path) -> tuple[str, bool]:
    """``(trimesh file type, gzipped)`` from the file name, e.g. ``("obj", True)`` for ``x.obj.gz``."""
    suffixes = [s.lower() for s in path.suffixes]
    gzipped = bool(suffixes) and suffixes[-1] == ".gz"
    if gzipped:
        suffixes = suffixes[:-1]
    if not suffixes:
        raise ValueError(f"load_mesh: cannot tell the format of {str(path)!r}: the file name has no extension")
    return suffixes[-1].lstrip("."), gzipped


#: trimesh's loaders that are archives or point clouds, not mesh formats.
_NOT_MESHES = frozenset(["zip", "tar.gz", "tar.bz2", "bz2", "xyz", "stl_ascii"])


def _mesh_formats(trimesh) -> list[str]:
    """The mesh file extensions the installed trimesh reads (its optional loaders add some)."""
    return sorted(f for f in trimesh.available_formats() if f not in _NOT_MESHES)


def _unsupported(path: Path, file_type: str, formats: list[str], detail: str = "") -> ValueError:
    listed = ", ".join(f".{f}" for f in formats)
    return ValueError(
        f"load_mesh: cannot read {str(path)!r}: the .{file_type} format is not supported{detail}; "
        f"supported: {listed} (each also gzipped, e.g. .obj.gz)"
    )


def _gltf_json(data: bytes, file_type: str) -> dict | None:
    """The JSON document of a ``.gltf`` or ``.glb`` file's bytes (``None`` where it cannot be parsed: the
    loader then reports the problem)."""
    try:
        if file_type == "glb":
            if len(data) < 20 or data[:4] != b"glTF":
                return None
            length, kind = struct.unpack_from("<II", data, 12)
            if kind != 0x4E4F534A:  # "JSON"
                return None
            return json.loads(data[20 : 20 + length])
        return json.loads(data)
    except (ValueError, UnicodeDecodeError, struct.error):
        return None


def _check_gltf(document: dict | None, name: str) -> None:
    """Raise for GPU instancing and warn for several scenes, which flattening to one mesh would misread."""
    if not isinstance(document, dict):
        return
    nodes = document.get("nodes") or []
    instanced = "EXT_mesh_gpu_instancing" in (document.get("extensionsUsed") or []) or any(
        "EXT_mesh_gpu_instancing" in (node.get("extensions") or {}) for node in nodes if isinstance(node, dict)
    )
    if instanced:
        raise ValueError(
            f"load_mesh: {name!r} uses EXT_mesh_gpu_instancing (GPU instancing), whose copies a single mesh would "
            "drop; load it with rt.io.load_gltf (an instance structure; GltfScene.world_triangles() gives the "
            "flattened triangles)"
        )
    scenes = document.get("scenes") or []
    if len(scenes) > 1:
        default = document.get("scene", 0)
        warnings.warn(
            f"load_mesh: {name!r} holds {len(scenes)} scenes; only the default scene ({default}) is read. "
            "rt.io.load_gltf(path, scene=k) loads any of them",
            UserWarning,
            stacklevel=3,
        )


def load_mesh(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """Read a triangle mesh from a file.

    Args:
      path: a mesh file in a format trimesh reads (``.ply``, ``.obj``, ``.stl``, ``.off``, ``.gltf``, ``.glb``,
        and those of trimesh's optional loaders), optionally gzipped (``.obj.gz``): the format comes from the
        extension before ``.gz``.

    Returns:
      ``(vertices, indices)``: ``(V, 3)`` float32 positions and ``(T, 3)`` int32 vertex indices, checked to be
      finite and in range. Vertices are as trimesh reads them (its OBJ reader drops unreferenced ones).

    Raises:
      ImportError: trimesh is not installed (``pip install 'jaxrt[bench]'``).
      FileNotFoundError: ``path`` does not exist.
      ValueError: the format is not one trimesh reads (the message lists those that work), a glTF file uses
        GPU instancing (read it with :func:`~jaxrt.io.load_gltf`), the file cannot be parsed, holds no
        triangles, a coordinate is not finite in float32, or an index is out of range; the message names the
        file and the offending value.

    Warns:
      UserWarning: a glTF file holds several scenes (only the default one is read; see ``load_gltf``).

    Examples:
      >>> import pathlib, tempfile
      >>> from jaxrt.io import load_mesh
      >>> path = pathlib.Path(tempfile.mkdtemp()) / "tri.obj"
      >>> _ = path.write_text("v 0 0 0\\nv 1 0 0\\nv 0 1 0\\nf 1 2 3\\n")
      >>> vertices, indices = load_mesh(path)
      >>> vertices.dtype, indices.tolist()
      (dtype('float32'), [[0, 1, 2]])
    """
    try:
        import trimesh
    except ImportError as error:
        raise ImportError(
            "load_mesh needs trimesh to read mesh files; install it with `pip install trimesh` "
            "(or `pip install 'jaxrt[bench]'`)"
        ) from error
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"load_mesh: no such file: {str(path)!r}")
    file_type, gzipped = _file_type(path)
    formats = _mesh_formats(trimesh)
    if file_type not in formats:
        raise _unsupported(path, file_type, formats)
    try:
        if gzipped:
            with gzip.open(path, "rb") as stream:
                data = stream.read()
        elif file_type in ("gltf", "glb"):
            data = path.read_bytes()
        if file_type in ("gltf", "glb"):
            _check_gltf(_gltf_json(data, file_type), str(path))
        source = io.BytesIO(data) if gzipped else path
        # A .gltf's buffers are resolved next to it: give trimesh the path itself unless it was gzipped.
        mesh = trimesh.load(source, file_type=file_type, force="mesh", process=False, skip_materials=True)
    except NotImplementedError as error:
        raise _unsupported(path, file_type, formats, f" by this trimesh ({error})") from error
    except (OSError, EOFError, gzip.BadGzipFile) as error:
        raise ValueError(f"load_mesh: cannot read {str(path)!r}: {error}") from error
    vertices = np.asarray(getattr(mesh, "vertices", np.zeros((0, 3))), dtype=np.float64)
    faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))))
    return _validated(vertices, faces, str(path))


def _validated(vertices: np.ndarray, faces: np.ndarray, name: str) -> tuple[np.ndarray, np.ndarray]:
    """Cast to float32/int32 and check shapes, finiteness and index range."""
    if faces.size == 0 or faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"load_mesh: {name!r} holds no triangles (faces of shape {faces.shape})")
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"load_mesh: {name!r} has vertices of shape {vertices.shape}, expected (V, 3)")
    with np.errstate(over="ignore"):
        vertices32 = vertices.astype(np.float32)
    bad = ~np.isfinite(vertices32)
    if bad.any():
        row, col = (int(i) for i in np.argwhere(bad)[0])
        raise ValueError(
            f"load_mesh: {name!r}: vertex {row} coordinate {col} = {vertices[row, col]} is not finite in float32"
        )
    out_of_range = (faces < 0) | (faces >= len(vertices))
    if out_of_range.any():
        row, col = (int(i) for i in np.argwhere(out_of_range)[0])
        raise ValueError(
            f"load_mesh: {name!r}: face {row} index {col} = {int(faces[row, col])} is out of range for "
            f"{len(vertices)} vertices"
        )
    return np.ascontiguousarray(vertices32), np.ascontiguousarray(faces.astype(np.int32))
