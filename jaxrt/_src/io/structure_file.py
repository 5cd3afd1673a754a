"""Saving and loading acceleration structures: a versioned ``.npz`` file with a JSON header, no pickle.

File format (``FORMAT_VERSION`` 1): a zip archive written by :func:`numpy.savez` whose entries are ``.npy``
arrays, read back with ``allow_pickle=False``:

- ``header``: a ``uint8`` array holding UTF-8 JSON ``{"header": {...}, "sha256": ...}``, the checksum being
  that of the header serialised with sorted keys and no spaces. The header holds ``format``
  (``"jaxrt.structure"``), ``format_version``, ``jaxrt_version``, ``kind`` (``"primitive"`` or
  ``"instance"``), the static metadata of every component (``geometry_info`` with curve infos, the layout of
  the primitive data pytree, the instance graph ``children``), and for every array its entry name, dtype,
  shape and SHA-256.
- one entry per array: ``p{i}.{field}`` for primitive structure ``i``, ``p{i}.leaf_primitive_data.{k}`` for
  leaf ``k`` of its primitive data pytree, ``t{j}.{field}`` for instance table ``j``.

Loading checks everything before building a structure: the archive, the header's checksum, format and version,
the set of entries, each array's dtype, shape and checksum, the shapes the layout requires of each component
(:mod:`jaxrt._src.structures`, :mod:`jaxrt._src.instances`), and the index ranges (node children, geometry and
instance ids, the instance graph), so that a damaged or edited file raises a ``ValueError`` that says what is
wrong rather than loading a structure that traces garbage. Nothing in a file is executed: pytree structure is
described by JSON (dicts with string keys, lists, tuples, ``None`` and arrays).
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import os
import tempfile
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxrt._src.curves import CurveBasis, CurveEndCaps, CurveInfo, CurveType
from jaxrt._src.instances import InstanceAccelerationStructure, InstanceTable
from jaxrt._src.kinds.registry import CURVE, KINDS
from jaxrt._src.prepacked import with_kernel_layout
from jaxrt._src.structures import GeometryInfo, PrimitiveAccelerationStructure
from jaxrt._src.versions import VERSION

__all__ = ["FORMAT", "FORMAT_VERSION", "save", "load"]

FORMAT = "jaxrt.structure"
#: The version this module writes and the only one it reads.
FORMAT_VERSION = 1
_HEADER = "header"
_KINDS = tuple(k.name for k in KINDS)
#: The leaf arrays a structure has only with geometry of their kind, with that kind.
_KIND_FIELDS = tuple((a.name, k.name) for k in KINDS for a in k.leaf_arrays if not a.shared)
_PRIMITIVE_FIELDS = (
    "node_lower",
    "node_upper",
    "node_children",
    "node_range",
    "leaf_geometry",
    "leaf_primitive",
    "leaf_triangle",
    "geometry_primitive_count",
    "leaf_curve",
    "leaf_curve_flags",
    "leaf_box",
)
_OPTIONAL_FIELDS = ("leaf_curve", "leaf_curve_flags", "leaf_box")
# Keyframe motion is not part of format version 1 (``save`` refuses moving structures).
_TABLE_FIELDS = tuple(f.name for f in dataclasses.fields(InstanceTable) if not f.name.startswith("motion"))
#: Dtype kinds allowed in primitive data (booleans, integers, floats, complex); structure fields are fixed.
_DATA_KINDS = "biufc"


def _canonical(value: Any) -> bytes:
    return json.dumps(value, sort_keys=True, separators=(",", ":")).encode()


def _sha256(array: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(array).tobytes()).hexdigest()


# --- saving -----------------------------------------------------------------------------------------------------


def _host_array(x: Any, name: str) -> np.ndarray:
    if isinstance(x, jax.core.Tracer):
        raise ValueError(f"save: {name} is traced; save a concrete structure, outside jax.jit")
    return np.asarray(x)


def _describe_tree(tree: Any, prefix: str, arrays: dict[str, np.ndarray]) -> Any:
    """A JSON description of a pytree of arrays; the arrays go to ``arrays`` under ``prefix.{k}``."""
    if tree is None:
        return {"type": "none"}
    if isinstance(tree, dict):
        if not all(isinstance(k, str) for k in tree):
            raise ValueError(f"save: primitive data dict keys must be strings to be stored, got {list(tree)!r}")
        keys = sorted(tree)  # the order jax flattens a dict in
        return {"type": "dict", "keys": keys, "items": [_describe_tree(tree[k], prefix, arrays) for k in keys]}
    if type(tree) in (list, tuple):
        return {"type": type(tree).__name__, "items": [_describe_tree(x, prefix, arrays) for x in tree]}
    if isinstance(tree, jax.Array | np.ndarray):
        name = f"{prefix}.{len([k for k in arrays if k.startswith(prefix + '.')])}"
        arrays[name] = _host_array(tree, name)
        return {"type": "array", "name": name}
    raise ValueError(
        f"save: primitive data node of type {type(tree).__name__} cannot be described without pickle; "
        "use dicts with string keys, lists, tuples and arrays"
    )


def _geometry_info_json(info: GeometryInfo) -> dict:
    curve = None
    if info.curve is not None:
        c = info.curve
        curve = {
            "basis": c.basis.value,
            "control_point_count": int(c.control_point_count),
            "curve_type": c.curve_type.value,
            "end_caps": c.end_caps.value,
        }
    return {"kind": info.kind, "opaque": bool(info.opaque), "curve": curve}


def _unbatched(component: Any, first: str, name: str) -> None:
    shape = np.shape(getattr(component, first))
    if len(shape) != 1:
        raise ValueError(f"save: {name} is batched ({first} has shape {shape}); save one structure at a time")


def save(
    path: str | os.PathLike[str], structure: PrimitiveAccelerationStructure | InstanceAccelerationStructure
) -> None:
    """Write a structure to ``path`` (a versioned ``.npz`` archive with a JSON header; no pickle).

    Primitive structures (triangles, curves, boxes, primitive data) and instance structures of any depth
    (every distinct component once, with the instance graph) round-trip bit for bit through :func:`load`. The
    file is written to a temporary name first and then renamed, so a crash leaves no half-written file.

    Args:
      path: the file to write (the name is used as given; ``.npz`` is not appended).
      structure: a concrete :class:`~jaxrt.PrimitiveAccelerationStructure` or
        :class:`~jaxrt.InstanceAccelerationStructure`.

    Raises:
      TypeError: ``structure`` is not an acceleration structure.
      ValueError: a traced or batched structure, or primitive data that JSON cannot describe (a node other
        than a dict with string keys, a list, a tuple, ``None`` or an array).
      NotImplementedError: a structure with keyframe motion (not part of this file format version).

    Examples:
      >>> import os, tempfile, numpy as np, jaxrt as rt
      >>> s = rt.build_primitive_structure(rt.TriangleGeometry([[0., 0, 0], [1, 0, 0], [0, 1, 0]]))
      >>> path = os.path.join(tempfile.mkdtemp(), "triangle.npz")
      >>> rt.save(path, s)
      >>> np.array_equal(rt.load(path).node_lower, s.node_lower)
      True
    """
    if isinstance(structure, PrimitiveAccelerationStructure):
        kind, prims, tables, children = "primitive", (structure,), (), ()
    elif isinstance(structure, InstanceAccelerationStructure):
        kind = "instance"
        prims, tables, children = structure.primitive_structures, structure.instance_tables, structure.children
    else:
        raise TypeError(
            f"save: structure must be a PrimitiveAccelerationStructure or an InstanceAccelerationStructure, "
            f"got {type(structure).__name__}"
        )
    moving = any(s.motion is not None for s in prims) or any(t.motion is not None for t in tables)
    if moving:
        raise NotImplementedError(
            "save: structures with keyframe motion (primitive or instance motion) are not stored by file format "
            f"version {FORMAT_VERSION}; save the keyframed geometry and instances and rebuild"
        )
    arrays: dict[str, np.ndarray] = {}
    prim_headers = []
    for i, s in enumerate(prims):
        _unbatched(s, "leaf_geometry", f"primitive structure {i}")
        fields = {}
        for field in _PRIMITIVE_FIELDS:
            value = getattr(s, field)
            if value is not None:
                fields[field] = f"p{i}.{field}"
                arrays[fields[field]] = _host_array(value, f"p{i}.{field}")
        data = _describe_tree(s.leaf_primitive_data, f"p{i}.leaf_primitive_data", arrays)
        prim_headers.append(
            {
                "geometry_info": [_geometry_info_json(g) for g in s.geometry_info],
                "arrays": fields,
                "primitive_data": data,
            }
        )
    table_headers = []
    for j, t in enumerate(tables):
        _unbatched(t, "leaf_instance", f"instance table {j}")
        fields = {}
        for field in _TABLE_FIELDS:
            fields[field] = f"t{j}.{field}"
            arrays[fields[field]] = _host_array(getattr(t, field), fields[field])
        table_headers.append({"arrays": fields})
    header = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "jaxrt_version": VERSION,
        "kind": kind,
        "primitive_structures": prim_headers,
        "instance_tables": table_headers,
        "children": [list(map(int, refs)) for refs in children],
        "arrays": {
            name: {"dtype": a.dtype.str, "shape": list(a.shape), "sha256": _sha256(a)} for name, a in arrays.items()
        },
    }
    for name, a in arrays.items():
        if a.dtype.kind not in _DATA_KINDS:
            raise ValueError(f"save: array {name} has dtype {a.dtype}, which this format does not store")
    document = {"header": header, "sha256": hashlib.sha256(_canonical(header)).hexdigest()}
    entries = {_HEADER: np.frombuffer(json.dumps(document, indent=1).encode(), np.uint8), **arrays}
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    fd, temporary = tempfile.mkstemp(prefix=".jaxrt-", suffix=".npz.tmp", dir=folder)
    try:
        with os.fdopen(fd, "wb") as file:
            np.savez(file, **entries)
        os.replace(temporary, path)
    except BaseException:
        if os.path.exists(temporary):
            os.unlink(temporary)
        raise


# --- loading ----------------------------------------------------------------------------------------------------


#: The first bytes of a zip archive (local file header, or the end record of an empty archive) and of a .npy file.
_ARCHIVE_MAGIC = (b"PK\x03\x04", b"PK\x05\x06", b"\x93NUMPY")


def _reason(error: Exception) -> str:
    """NumPy's error, without its advice to load pickled data unsafely: a jaxrt file never holds pickles."""
    text = str(error)
    if "allow_pickle" in text or "pickle" in text.lower():
        return "it holds pickled (object) data, which no jaxrt structure file holds; it was not loaded"
    return f"{type(error).__name__}: {text}"


class _Reader:
    """Reads and checks the entries of one file; every failure is a ``ValueError`` naming the file."""

    def __init__(self, path: str):
        self.path = path
        with open(path, "rb") as file:
            raw = file.read()
        if not raw.startswith(_ARCHIVE_MAGIC):
            raise self.error(
                f"is not a readable .npz archive: it starts with {raw[:16]!r}, not with a zip archive's b'PK' "
                "(jaxrt structure files are written by rt.save)"
            )
        try:
            self.archive = np.load(io.BytesIO(raw), allow_pickle=False)
        except Exception as error:  # noqa: BLE001 - numpy and zipfile raise many types for damaged files
            raise self.error(f"is not a readable .npz archive ({_reason(error)})") from None
        if not isinstance(self.archive, np.lib.npyio.NpzFile):
            raise self.error("is a bare .npy array, not a jaxrt structure archive")
        self.files = set(self.archive.files)

    def error(self, message: str) -> ValueError:
        return ValueError(f"load: {self.path} {message}")

    def entry(self, name: str) -> np.ndarray:
        try:
            return self.archive[name]
        except KeyError:
            raise self.error(f"has no array {name!r} (missing entry)") from None
        except Exception as error:  # noqa: BLE001 - CRC errors, truncated entries, object arrays
            raise self.error(f"has a damaged array {name!r} ({_reason(error)})") from None

    def header(self) -> dict:
        if _HEADER not in self.files:
            raise self.error(f"has no {_HEADER!r} entry; it is not a jaxrt structure file")
        raw = self.entry(_HEADER)
        if raw.dtype != np.uint8 or raw.ndim != 1:
            raise self.error(f"has a {_HEADER!r} entry of dtype {raw.dtype} and shape {raw.shape}, not uint8 text")
        try:
            document = json.loads(raw.tobytes().decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as error:
            raise self.error(f"has a header that is not valid JSON ({error})") from None
        if not isinstance(document, dict) or not isinstance(document.get("header"), dict):
            raise self.error("has a header without the 'header' object")
        header = document["header"]
        if header.get("format") != FORMAT:
            raise self.error(f"has format {header.get('format')!r}, not {FORMAT!r}")
        version = header.get("format_version")
        if version != FORMAT_VERSION:
            raise self.error(
                f"has format version {version!r}; this jaxrt reads version {FORMAT_VERSION} "
                f"(the file was written by jaxrt {header.get('jaxrt_version')!r})"
            )
        if document.get("sha256") != hashlib.sha256(_canonical(header)).hexdigest():
            raise self.error("has a header whose SHA-256 does not match its content (edited or corrupted)")
        return header

    def arrays(self, header: dict) -> dict[str, np.ndarray]:
        table = header.get("arrays")
        if not isinstance(table, dict):
            raise self.error("has a header without its 'arrays' table")
        missing = sorted(set(table) - self.files)
        if missing:
            raise self.error(f"is missing the arrays {missing} listed in its header (truncated or edited)")
        extra = sorted(self.files - set(table) - {_HEADER})
        if extra:
            raise self.error(f"has entries {extra} that its header does not list")
        out = {}
        for name, spec in table.items():
            array = self.entry(name)
            try:
                dtype, shape, digest = np.dtype(spec["dtype"]), tuple(spec["shape"]), spec["sha256"]
            except (KeyError, TypeError) as error:
                raise self.error(f"has a malformed header entry for array {name!r} ({error})") from None
            if array.dtype.kind not in _DATA_KINDS:
                raise self.error(f"has array {name!r} of dtype {array.dtype}, which this format does not store")
            if array.dtype != dtype or array.shape != shape:
                raise self.error(
                    f"has array {name!r} of dtype {array.dtype} and shape {array.shape}; its header says "
                    f"{dtype} {shape}"
                )
            if _sha256(array) != digest:
                raise self.error(f"has array {name!r} whose SHA-256 does not match its header (corrupted)")
            out[name] = array
        return out


def _curve_info(spec: Any, where: str, reader: _Reader) -> CurveInfo:
    try:
        return CurveInfo(
            CurveBasis(spec["basis"]),
            int(spec["control_point_count"]),
            CurveType(spec["curve_type"]),
            CurveEndCaps(spec["end_caps"]),
        )
    except (KeyError, TypeError, ValueError) as error:
        raise reader.error(f"has an invalid curve description {spec!r} in {where} ({error})") from None


def _geometry_info(spec: Any, where: str, reader: _Reader) -> GeometryInfo:
    if not isinstance(spec, dict) or spec.get("kind") not in _KINDS or not isinstance(spec.get("opaque"), bool):
        raise reader.error(f"has an invalid geometry description {spec!r} in {where}")
    curve = spec.get("curve")
    if (spec["kind"] == CURVE.name) != (curve is not None):
        raise reader.error(f"has a geometry description {spec!r} in {where} whose curve does not match its kind")
    return GeometryInfo(spec["kind"], spec["opaque"], None if curve is None else _curve_info(curve, where, reader))


def _rebuild_tree(spec: Any, arrays: dict[str, np.ndarray], used: set, where: str, reader: _Reader) -> Any:
    if not isinstance(spec, dict):
        raise reader.error(f"has an invalid pytree description {spec!r} in {where}")
    kind = spec.get("type")
    if kind == "none":
        return None
    if kind == "array":
        name = spec.get("name")
        if name not in arrays or name in used:
            raise reader.error(f"has a pytree in {where} naming array {name!r}, unknown or used twice")
        used.add(name)
        return arrays[name]
    items = spec.get("items")
    if not isinstance(items, list):
        raise reader.error(f"has an invalid pytree description {spec!r} in {where}")
    children = [_rebuild_tree(x, arrays, used, where, reader) for x in items]
    if kind == "list":
        return children
    if kind == "tuple":
        return tuple(children)
    if kind == "dict":
        keys = spec.get("keys")
        if not isinstance(keys, list) or len(keys) != len(children) or not all(isinstance(k, str) for k in keys):
            raise reader.error(f"has an invalid dict description in {where}")
        return dict(zip(keys, children, strict=True))
    raise reader.error(f"has an unknown pytree node type {kind!r} in {where}")


def _field_arrays(spec: Any, allowed: tuple[str, ...], required: tuple[str, ...], arrays: dict, where: str, reader):
    names = spec.get("arrays") if isinstance(spec, dict) else None
    if not isinstance(names, dict) or not set(names) <= set(allowed) or not set(required) <= set(names):
        raise reader.error(f"has an invalid array list for {where}: {names!r}")
    out = {}
    for field, name in names.items():
        if name not in arrays:
            raise reader.error(f"names an unknown array {name!r} for {where}.{field}")
        out[field] = arrays[name]
    return out


def _expect(reader, where: str, field: str, array: np.ndarray, shape: tuple, dtypes: tuple[str, ...]) -> None:
    if array.shape != shape or array.dtype.name not in dtypes:
        raise reader.error(
            f"has {where}.{field} of shape {array.shape} and dtype {array.dtype}; the layout requires "
            f"shape {shape} and dtype {' or '.join(dtypes)}"
        )


def _within(reader, where: str, field: str, array: np.ndarray, low: int, high: int) -> None:
    """Values in ``[low, high]``, naming the first offending one."""
    bad = (array < low) | (array > high)
    if bad.any():
        index = tuple(int(i) for i in np.argwhere(bad)[0])
        raise reader.error(f"has {where}.{field}{list(index)} = {array[index]} outside [{low}, {high}]")


_FLOATS = ("float32", "float64")


def _check_nodes(reader, where: str, a: dict, capacity: int, float_dtype: str) -> None:
    nodes = capacity - 1
    for field in ("node_lower", "node_upper"):
        _expect(reader, where, field, a[field], (nodes, 2, 3), (float_dtype,))
    for field in ("node_children", "node_range"):
        _expect(reader, where, field, a[field], (nodes, 2), ("int32",))
    _within(reader, where, "node_children", a["node_children"], -capacity, nodes - 1)
    _within(reader, where, "node_range", a["node_range"], 0, capacity - 1)


def _primitive(spec: Any, i: int, arrays: dict, used: set, reader: _Reader) -> PrimitiveAccelerationStructure:
    where = f"primitive structure {i}"
    a = _field_arrays(
        spec, _PRIMITIVE_FIELDS, tuple(f for f in _PRIMITIVE_FIELDS if f not in _OPTIONAL_FIELDS), arrays, where, reader
    )
    used.update(spec["arrays"].values())
    infos = spec.get("geometry_info")
    if not isinstance(infos, list) or not infos:
        raise reader.error(f"has no geometry_info for {where}")
    info = tuple(_geometry_info(g, f"{where}.geometry_info[{k}]", reader) for k, g in enumerate(infos))
    kinds = {g.kind for g in info}
    if a["leaf_geometry"].ndim != 1 or a["leaf_geometry"].shape[0] < 2:
        raise reader.error(f"has {where}.leaf_geometry of shape {a['leaf_geometry'].shape}; it must be (C,), C >= 2")
    capacity = int(a["leaf_geometry"].shape[0])
    float_dtype = a["node_lower"].dtype.name
    if float_dtype not in _FLOATS:
        raise reader.error(f"has {where}.node_lower of dtype {float_dtype}; the layout requires float32 or float64")
    _check_nodes(reader, where, a, capacity, float_dtype)
    _expect(reader, where, "leaf_geometry", a["leaf_geometry"], (capacity,), ("int32",))
    _expect(reader, where, "leaf_primitive", a["leaf_primitive"], (capacity,), ("int32",))
    _expect(reader, where, "leaf_triangle", a["leaf_triangle"], (capacity, 3, 3), (float_dtype,))
    _expect(reader, where, "geometry_primitive_count", a["geometry_primitive_count"], (len(info),), ("int32",))
    for field, kind in _KIND_FIELDS:
        if (field in a) != (kind in kinds):
            raise reader.error(
                f"has {where}.{field} {'present' if field in a else 'missing'}, but its geometries are {sorted(kinds)}"
            )
    if "leaf_curve" in a:
        _expect(reader, where, "leaf_curve", a["leaf_curve"], (capacity, 6, 4), (a["leaf_curve"].dtype.name,))
        if a["leaf_curve"].dtype.name not in _FLOATS:
            raise reader.error(f"has {where}.leaf_curve of dtype {a['leaf_curve'].dtype}, not a float")
        _expect(reader, where, "leaf_curve_flags", a["leaf_curve_flags"], (capacity,), ("int32",))
    if "leaf_box" in a:
        _expect(reader, where, "leaf_box", a["leaf_box"], (capacity, 2, 3), (float_dtype,))
    counts = a["geometry_primitive_count"]
    _within(reader, where, "geometry_primitive_count", counts, 0, capacity)
    if int(counts.sum()) > capacity or int(counts.sum()) != int(np.sum(a["leaf_geometry"] >= 0)):
        raise reader.error(
            f"has {where}.geometry_primitive_count {counts.tolist()} that does not match its "
            f"{int(np.sum(a['leaf_geometry'] >= 0))} real leaves (capacity {capacity})"
        )
    _within(reader, where, "leaf_geometry", a["leaf_geometry"], -1, len(info) - 1)
    limit = np.where(a["leaf_geometry"] >= 0, counts[np.maximum(a["leaf_geometry"], 0)] - 1, -1)
    bad = (
        (a["leaf_primitive"] < -1)
        | (a["leaf_primitive"] > limit)
        | ((a["leaf_geometry"] >= 0) & (a["leaf_primitive"] < 0))
    )
    if bad.any():
        k = int(np.argmax(bad))
        raise reader.error(
            f"has {where}.leaf_primitive[{k}] = {a['leaf_primitive'][k]} out of range for geometry "
            f"{a['leaf_geometry'][k]}"
        )
    data = _rebuild_tree(spec.get("primitive_data", {"type": "none"}), arrays, used, f"{where}.primitive_data", reader)
    for leaf in jax.tree_util.tree_leaves(data):
        if leaf.ndim < 1 or leaf.shape[0] != capacity:
            raise reader.error(
                f"has {where} primitive data of shape {leaf.shape}; rows must equal the capacity {capacity}"
            )
    device = {k: jnp.asarray(v) for k, v in a.items()}
    structure = PrimitiveAccelerationStructure(
        **device,
        geometry_info=info,
        leaf_primitive_data=jax.tree_util.tree_map(jnp.asarray, data),
    )
    # The GPU kernel's packed rows are not stored: packed here where a build would pack them.
    return with_kernel_layout(structure)


def _table(spec: Any, j: int, arrays: dict, used: set, reader: _Reader) -> InstanceTable:
    where = f"instance table {j}"
    a = _field_arrays(spec, _TABLE_FIELDS, _TABLE_FIELDS, arrays, where, reader)
    used.update(spec["arrays"].values())
    if a["leaf_instance"].ndim != 1 or a["leaf_instance"].shape[0] < 2:
        raise reader.error(f"has {where}.leaf_instance of shape {a['leaf_instance'].shape}; it must be (C,), C >= 2")
    capacity = int(a["leaf_instance"].shape[0])
    if a["transform"].ndim != 3 or a["transform"].shape[0] < 1:
        raise reader.error(f"has {where}.transform of shape {a['transform'].shape}; it must be (N, 3, 4)")
    n = int(a["transform"].shape[0])
    float_dtype = a["node_lower"].dtype.name
    if float_dtype not in _FLOATS:
        raise reader.error(f"has {where}.node_lower of dtype {float_dtype}; the layout requires float32 or float64")
    _check_nodes(reader, where, a, capacity, float_dtype)
    _expect(reader, where, "leaf_instance", a["leaf_instance"], (capacity,), ("int32",))
    _expect(reader, where, "structure_index", a["structure_index"], (n,), ("int32",))
    for field in ("transform", "world_to_object"):
        _expect(reader, where, field, a[field], (n, 3, 4), _FLOATS)
    for field in ("mask", "user_id", "options"):
        _expect(reader, where, field, a[field], (n,), ("uint32",))
    _expect(reader, where, "count", a["count"], (), ("int32",))
    _within(reader, where, "leaf_instance", a["leaf_instance"], -1, n - 1)
    _within(reader, where, "count", a["count"], 0, n)
    return InstanceTable(**{k: jnp.asarray(v) for k, v in a.items()})


def _check_x64(arrays: dict[str, np.ndarray], reader: _Reader) -> None:
    if jax.config.jax_enable_x64:
        return
    for name, array in arrays.items():
        if array.dtype.itemsize == 8 and array.dtype.kind in "iuf":
            raise reader.error(
                f"has 64-bit array {name!r} ({array.dtype}) but jax_enable_x64 is off; it would not load bit for "
                "bit (enable x64 first)"
            )


def load(path: str | os.PathLike[str]) -> PrimitiveAccelerationStructure | InstanceAccelerationStructure:
    """Read a structure written by :func:`save`, bit for bit, after checking the whole file.

    Args:
      path: the file.

    Returns:
      The :class:`~jaxrt.PrimitiveAccelerationStructure` or :class:`~jaxrt.InstanceAccelerationStructure`.

    Raises:
      FileNotFoundError: no such file.
      ValueError: a file that is not a structure archive, truncated or corrupted (damaged zip, checksum
        mismatch), of another format version, hand-edited (header checksum, entries, shapes, dtypes or index
        ranges that do not match), with missing or extra arrays, object arrays, or 64-bit arrays while
        ``jax_enable_x64`` is off. The message names the file and what is wrong.

    Examples:
      See :func:`save`.
    """
    reader = _Reader(os.fspath(path))
    header = reader.header()
    arrays = reader.arrays(header)
    _check_x64(arrays, reader)
    kind = header.get("kind")
    prims, tables, children = header.get("primitive_structures"), header.get("instance_tables"), header.get("children")
    if not isinstance(prims, list) or not isinstance(tables, list) or not isinstance(children, list):
        raise reader.error("has a header without its component lists")
    if kind == "primitive" and (len(prims) != 1 or tables or children):
        raise reader.error(f"is a primitive structure with {len(prims)} primitive components and {len(tables)} tables")
    if kind == "instance" and not tables:
        raise reader.error("is an instance structure without instance tables")
    if kind not in ("primitive", "instance"):
        raise reader.error(f"has an unknown structure kind {kind!r}")
    used: set = set()
    primitive_structures = tuple(_primitive(spec, i, arrays, used, reader) for i, spec in enumerate(prims))
    instance_tables = tuple(_table(spec, j, arrays, used, reader) for j, spec in enumerate(tables))
    unused = sorted(set(arrays) - used)
    if unused:
        raise reader.error(f"has arrays {unused} that no component uses")
    if kind == "primitive":
        return primitive_structures[0]
    if not all(isinstance(refs, list) and all(type(c) is int for c in refs) and refs for refs in children):
        raise reader.error(f"has an invalid instance graph {children!r}")
    try:
        return InstanceAccelerationStructure(
            primitive_structures=primitive_structures,
            instance_tables=instance_tables,
            children=tuple(tuple(refs) for refs in children),
        )
    except ValueError as error:
        raise reader.error(f"has an invalid instance graph ({error})") from None
