"""Triangle meshes from files (PLY, OBJ, STL, OFF, glTF, ... and their ``.gz`` versions) through trimesh.

The loader returns plain arrays, ready for :class:`jaxrt.TriangleGeometry`: the mesh is read as stored
(``process=False``: no vertex merging, no reordering), polygons are triangulated by trimesh, and every
object of a multi-object file is concatenated into one mesh.
"""

from __future__ import annotations

import gzip
import io
import os
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


def load_mesh(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """Read a triangle mesh from a file.

    Args:
      path: a mesh file in any format trimesh reads (``.ply``, ``.obj``, ``.stl``, ``.off``, ``.glb``, ...),
        optionally gzipped (``.obj.gz``): the format comes from the extension before ``.gz``.

    Returns:
      ``(vertices, indices)``: ``(V, 3)`` float32 positions and ``(T, 3)`` int32 vertex indices, checked to be
      finite and in range. Vertices are as trimesh reads them (its OBJ reader drops unreferenced ones).

    Raises:
      ImportError: trimesh is not installed (``pip install 'jaxrt[bench]'``).
      FileNotFoundError: ``path`` does not exist.
      ValueError: the file holds no triangles, a coordinate is not finite in float32, or an index is out of
        range; the message names the file and the offending value.

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
    try:
        if gzipped:
            with gzip.open(path, "rb") as stream:
                buffer = io.BytesIO(stream.read())
            mesh = trimesh.load(buffer, file_type=file_type, force="mesh", process=False, skip_materials=True)
        else:
            mesh = trimesh.load(path, file_type=file_type, force="mesh", process=False, skip_materials=True)
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
