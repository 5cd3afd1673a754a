"""A disk cache of the GPU kernels' compiled code, so that a new process does not compile them again.

jax-triton lowers a kernel by running Triton's whole compiler in Python (source to Triton IR, then TTGIR, LLVM IR
and PTX) in every process: it keeps the result only in memory, and JAX's persistent compilation cache cannot
help, because the PTX is part of the program that cache is keyed by. For the curve kernel that step took 18-28 s
on an H200 in every process. This module keeps each kernel's Triton IR and PTX on disk, keyed by everything that
can change them, and hands them back to jax-triton on the next process's first call.

The key is a SHA-256 of: the kernel's source and the source of every function it calls (Triton's own
``JITFunction.cache_key``), the argument types and specialisations, the compile-time constants, the launch
options, the device's compute capability, and the versions of Triton, jax-triton and jaxlib. An entry is one
JSON file; an unreadable one is ignored and rewritten.

Where: ``$JAXRT_KERNEL_CACHE`` when set (``0``, ``off`` or an empty string turn the cache off), else
``$XDG_CACHE_HOME/jaxrt/kernels`` (``~/.cache/jaxrt/kernels``). Clear it with :func:`clear` or by deleting the
folder; ``python -m jaxrt.warmup`` fills it ahead of time.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib.metadata
import json
import os
import tempfile
import types
from collections.abc import Iterator
from pathlib import Path
from typing import Any

#: Bumped when an entry's format changes, so that old entries are not read.
FORMAT = 1

_installed: list[Any] = []  # jax-triton's module, once wrapped


def cache_dir() -> Path | None:
    """The folder that holds the cached kernels, or ``None`` when the cache is turned off."""
    setting = os.environ.get("JAXRT_KERNEL_CACHE")
    if setting is not None:
        return None if setting.strip().lower() in ("", "0", "off", "false", "no") else Path(setting).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "jaxrt" / "kernels"


def clear() -> int:
    """Delete every cached kernel; returns how many entries were removed."""
    folder = cache_dir()
    if folder is None or not folder.is_dir():
        return 0
    removed = 0
    for entry in folder.glob("*.json"):
        entry.unlink(missing_ok=True)
        removed += 1
    return removed


def entries() -> list[Path]:
    """The cached kernels' files (an empty list when the cache is off or empty)."""
    folder = cache_dir()
    return sorted(folder.glob("*.json")) if folder is not None and folder.is_dir() else []


def install() -> None:
    """Route jax-triton's kernel compilation through the disk cache (idempotent; needs jax-triton)."""
    if _installed:
        return
    from jax_triton import triton_lib

    _installed.append(triton_lib)
    wrap(triton_lib)


def wrap(triton_lib: Any) -> None:
    """Replace ``triton_lib.get_or_create_triton_kernel`` (jax-triton's, or a stand-in with the same stages in
    tests) by one that answers from and fills the disk cache."""
    original = triton_lib.get_or_create_triton_kernel

    def get_or_create_triton_kernel(backend_init_func, platform, fn, arg_dtypes, scalar_args, **options):
        folder = cache_dir()
        if folder is None or options.get("dump"):
            return original(backend_init_func, platform, fn, arg_dtypes, scalar_args, **options)
        path = folder / f"{_key(triton_lib, platform, fn, arg_dtypes, scalar_args, options)}.json"
        entry = _read(path)
        if entry is not None:
            with _replayed(triton_lib, entry):
                return original(backend_init_func, platform, fn, arg_dtypes, scalar_args, **options)
        recorded: dict[str, Any] = {}
        with _recorded(triton_lib, recorded):
            result = original(backend_init_func, platform, fn, arg_dtypes, scalar_args, **options)
        if "binary" in recorded and isinstance(recorded["binary"], str):
            _write(path, recorded)
        return result

    triton_lib.get_or_create_triton_kernel = get_or_create_triton_kernel


def _version(package: str) -> str:
    try:
        return importlib.metadata.version(package)
    except importlib.metadata.PackageNotFoundError:
        return "absent"


def _key(triton_lib: Any, platform: str, fn: Any, arg_dtypes: Any, scalar_args: Any, options: dict) -> str:
    capability = options.get("compute_capability")
    if capability is None:
        capability = triton_lib.triton_kernel_call_lib.get_compute_capability(0)
    parts = (
        FORMAT,
        _version("triton"),
        _version("jax-triton"),
        _version("jaxlib"),
        platform,
        capability,
        fn.cache_key,
        tuple(arg_dtypes),
        tuple(tuple(s) for s in scalar_args),
        tuple(sorted((k, repr(v)) for k, v in options.items() if k not in ("dump", "compute_capability"))),
    )
    return hashlib.sha256(repr(parts).encode()).hexdigest()


class _Text:
    """Stands for the Triton IR module that jax-triton only prints once the code is cached."""

    def __init__(self, text: str) -> None:
        self.text = text

    def __str__(self) -> str:
        return self.text


@contextlib.contextmanager
def _replayed(triton_lib: Any, entry: dict[str, Any]) -> Iterator[None]:
    """jax-triton's compiler stages answered from ``entry`` for the duration of one lowering."""
    result = triton_lib.CompilationResult(
        binary=entry["binary"], name=entry["name"], shared_mem_bytes=entry["shared_mem_bytes"], ttgir=None, llir=None
    )
    front = types.SimpleNamespace(ast_to_ttir=lambda *args, **kwargs: _Text(entry["ttir"]))
    with _swapped(triton_lib, code_gen=front, compile_ttir_inplace=lambda *args, **kwargs: result):
        yield


@contextlib.contextmanager
def _recorded(triton_lib: Any, into: dict[str, Any]) -> Iterator[None]:
    """jax-triton's compiler stages run as usual; their Triton IR and PTX are copied into ``into``."""
    front, back = triton_lib.code_gen, triton_lib.compile_ttir_inplace

    def ast_to_ttir(*args, **kwargs):
        module = front.ast_to_ttir(*args, **kwargs)
        into["ttir"] = str(module)
        return module

    def compile_ttir_inplace(*args, **kwargs):
        result = back(*args, **kwargs)
        into.update(binary=result.binary, name=result.name, shared_mem_bytes=int(result.shared_mem_bytes))
        return result

    with _swapped(triton_lib, code_gen=types.SimpleNamespace(ast_to_ttir=ast_to_ttir),
                  compile_ttir_inplace=compile_ttir_inplace):  # fmt: skip
        yield


@contextlib.contextmanager
def _swapped(module: Any, **values: Any) -> Iterator[None]:
    saved = {name: getattr(module, name) for name in values}
    for name, value in values.items():
        setattr(module, name, value)
    try:
        yield
    finally:
        for name, value in saved.items():
            setattr(module, name, value)


def _read(path: Path) -> dict[str, Any] | None:
    try:
        entry = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    wanted = {"ttir": str, "binary": str, "name": str, "shared_mem_bytes": int}
    if not isinstance(entry, dict) or any(not isinstance(entry.get(k), t) for k, t in wanted.items()):
        return None
    return entry


def _write(path: Path, entry: dict[str, Any]) -> None:
    """Write ``entry`` atomically (a new file renamed into place), so that concurrent processes never read half
    of one; a folder that cannot be written leaves the cache unused, not the call failed."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile("w", dir=path.parent, suffix=".tmp", delete=False) as handle:
            json.dump(entry, handle)
        os.replace(handle.name, path)
    except OSError:
        return
