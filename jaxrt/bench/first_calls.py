"""First calls per specialisation, cold and warm: ``python -m jaxrt.bench.first_calls``.

Runs ``python -m jaxrt.warmup`` in two fresh processes that share new, empty caches: the first process compiles
everything (cold), the second finds the kernels in the kernel cache and XLA's programs in JAX's persistent
compilation cache (warm). Prints one row per specialisation with both first-call times.

    python -m jaxrt.bench.first_calls [--only triangles curves] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path


def _run(folder: Path, name: str, only: list[str] | None) -> dict[str, float]:
    env = dict(
        os.environ,
        JAXRT_KERNEL_CACHE=str(folder / "kernels"),
        JAX_COMPILATION_CACHE_DIR=str(folder / "xla"),
        JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
        JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES="0",
        NUMBA_CACHE_DIR=str(folder / "numba"),
    )
    out = folder / f"{name}.json"
    command = [sys.executable, "-m", "jaxrt.warmup", "--json", str(out)] + (["--only", *only] if only else [])
    subprocess.run(command, env=env, check=True)
    return json.loads(out.read_text())


def main(argv: list[str] | None = None) -> dict:
    """Run the cold and warm processes; returns ``{"cold": {...}, "warm": {...}}`` in seconds."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", nargs="*", help="specialisations (python -m jaxrt.warmup --list)")
    parser.add_argument("--json", help="write the table to this file")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="jaxrt-first-calls-") as folder:
        cold = _run(Path(folder), "cold", args.only)
        warm = _run(Path(folder), "warm", args.only)
    print(f"{'specialisation':16s} {'cold s':>8s} {'warm s':>8s}")
    for name in cold:
        print(f"{name:16s} {cold[name]:8.2f} {warm[name]:8.2f}")
    result = {"cold": cold, "warm": warm}
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
