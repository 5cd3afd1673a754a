"""The kernel cache: a second process's lowering is answered from disk, with the same code, and every input of
the key changes it. jax-triton's stages are stood in for by a small module with the same names, so the test runs
without a GPU; the GPU bench (``python -m jaxrt.bench.first_calls``) measures the real thing."""

from __future__ import annotations

import dataclasses
import types

import pytest

from jaxrt._src.traversal import kernel_cache


@dataclasses.dataclass
class _Result:
    binary: str
    name: str
    shared_mem_bytes: int
    ttgir: str | None
    llir: str | None


class _Kernel:
    """A stand-in for Triton's ``JITFunction``: only its ``cache_key`` is read."""

    def __init__(self, source: str) -> None:
        self.cache_key = f"source:{source}"


def _stand_in() -> types.SimpleNamespace:
    """A module with jax-triton's lowering stages: counts how often the compiler really runs."""
    module = types.SimpleNamespace(compiled=0, CompilationResult=_Result)
    module.triton_kernel_call_lib = types.SimpleNamespace(get_compute_capability=lambda device: 90)

    def ast_to_ttir(fn, *args, **kwargs):
        module.compiled += 1
        return f"ttir of {fn.cache_key}"

    def compile_ttir_inplace(ttir, *args, **kwargs):
        return _Result(binary=f"ptx of {ttir}", name="trace_kernel", shared_mem_bytes=64, ttgir=None, llir=None)

    def get_or_create_triton_kernel(backend_init_func, platform, fn, arg_dtypes, scalar_args, **options):
        ttir_module = module.code_gen.ast_to_ttir(fn)
        ttir = str(ttir_module)
        result = module.compile_ttir_inplace(ttir_module)
        return (result.name, result.binary, result.shared_mem_bytes, ttir), {"attrs": 1}

    module.code_gen = types.SimpleNamespace(ast_to_ttir=ast_to_ttir)
    module.compile_ttir_inplace = compile_ttir_inplace
    module.get_or_create_triton_kernel = get_or_create_triton_kernel
    return module


def _lower(module, source="a", dtypes=("*fp32",), **options):
    options = {"num_warps": 1, "num_stages": 1, "num_ctas": 1, "compute_capability": None,
               "enable_fp_fusion": False, "metaparams": {"LANES": 32}, "dump": False, **options}  # fmt: skip
    return module.get_or_create_triton_kernel(None, "cuda", _Kernel(source), list(dtypes), [], **options)


def test_second_process_reads_the_code_from_disk(tmp_path, monkeypatch):
    monkeypatch.setenv("JAXRT_KERNEL_CACHE", str(tmp_path))
    first = _stand_in()
    kernel_cache.wrap(first)
    compiled = _lower(first)
    assert first.compiled == 1 and len(kernel_cache.entries()) == 1
    second = _stand_in()  # a new process: nothing in memory
    kernel_cache.wrap(second)
    assert _lower(second) == compiled
    assert second.compiled == 0


@pytest.mark.parametrize(
    "change",
    [{"source": "b"}, {"dtypes": ("*i32",)}, {"num_warps": 4}, {"metaparams": {"LANES": 64}},
     {"compute_capability": 80}, {"enable_fp_fusion": True}],  # fmt: skip
)
def test_every_input_of_the_key_changes_it(tmp_path, monkeypatch, change):
    monkeypatch.setenv("JAXRT_KERNEL_CACHE", str(tmp_path))
    module = _stand_in()
    kernel_cache.wrap(module)
    _lower(module)
    _lower(module, **change)
    assert module.compiled == 2 and len(kernel_cache.entries()) == 2


def test_off_unreadable_and_cleared(tmp_path, monkeypatch):
    monkeypatch.setenv("JAXRT_KERNEL_CACHE", "off")
    module = _stand_in()
    kernel_cache.wrap(module)
    _lower(module), _lower(module)
    assert module.compiled == 2 and kernel_cache.cache_dir() is None and kernel_cache.entries() == []
    monkeypatch.setenv("JAXRT_KERNEL_CACHE", str(tmp_path))
    _lower(module)
    (entry,) = kernel_cache.entries()
    entry.write_text("{not json")  # a damaged entry is compiled again and rewritten
    assert _lower(module)[0][1] == "ptx of ttir of source:a" and module.compiled == 4
    assert kernel_cache.clear() == 1 and kernel_cache.entries() == []
