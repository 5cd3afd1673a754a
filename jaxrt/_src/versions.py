"""The jax versions jaxrt is tested with, and the import-time checks that keep other versions from failing silently.

CI runs the suite on two lanes: the oldest supported Python with the jax pip resolves for it, and the newest
Python with the newest jax inside the range below. ``pyproject.toml`` states the same range; a jax outside
it gets a :class:`JaxVersionWarning` at ``import jaxrt`` instead of untested (possibly wrong) answers.

Known XLA defects inside the range are worked around here:

* jaxlib 0.11.x on the CPU: the YNNPACK reduce fusion (``__ynn_fusion``) computes ``1 / sqrt(sum(x * x))``
  as ``inf`` when the quotient is also broadcast into another fusion, on batches of 4096 rows or more (a
  ray frame's ``1 / |direction|``: every curve missed). jaxlib 0.10 and 0.12 compute it correctly. On
  0.11.x, ``import jaxrt`` turns that fusion off (``--xla_cpu_experimental_ynn_fusion_type=``) unless
  ``XLA_FLAGS`` already sets it or a backend is already running (then it warns).
"""

from __future__ import annotations

import os
import re
import warnings

#: The jax versions CI tests: ``MIN_JAX <= jax < BELOW_JAX`` (the range in ``pyproject.toml``).
#: This release of jaxrt (``jaxrt.__version__``; pyproject.toml states the same).
VERSION = "0.1.0"
MIN_JAX = (0, 10, 2)
BELOW_JAX = (0, 12, 1)
#: jaxlib minor versions whose CPU YNNPACK reduce fusion gives wrong results (see the module docstring).
_YNN_DEFECT = ((0, 11),)
_YNN_FLAG = "--xla_cpu_experimental_ynn_fusion_type="


class JaxVersionWarning(UserWarning):
    """jax is outside the tested range, or a known defect of this jax could not be worked around."""


def parse(version: str) -> tuple[int, ...]:
    """The leading numeric components of a version string (``"0.12.0.1"`` -> ``(0, 12, 0, 1)``)."""
    parts = []
    for piece in version.split("."):
        digits = re.match(r"\d+", piece)
        if digits is None:
            break
        parts.append(int(digits.group()))
        if digits.group() != piece:
            break
    return tuple(parts)


def tested_range() -> str:
    """The tested range as a requirement string (``jax>=0.10.2,<0.12.1``)."""
    return f"jax>={'.'.join(map(str, MIN_JAX))},<{'.'.join(map(str, BELOW_JAX))}"


def check_jax_version(version: str) -> str | None:
    """A message when ``version`` is outside the tested range, else ``None``."""
    parsed = parse(version)
    if MIN_JAX <= parsed < BELOW_JAX:
        return None
    return (
        f"jaxrt is tested with {tested_range()}; jax {version} is outside that range and untested: results "
        f"may be wrong. Install a tested version: pip install '{tested_range()}'"
    )


def work_around_ynn_defect(jaxlib_version: str, environ: dict | None = None, initialized: bool = False) -> str | None:
    """Turn off XLA's CPU YNNPACK fusion on jaxlib versions where it is wrong.

    Returns a warning message when the workaround cannot apply (a backend is already running), else ``None``.
    """
    environ = os.environ if environ is None else environ
    if parse(jaxlib_version)[:2] not in _YNN_DEFECT:
        return None
    flags = environ.get("XLA_FLAGS", "")
    if "xla_cpu_experimental_ynn_fusion_type" in flags:
        return None  # the user chose
    if initialized:
        return (
            f"jaxlib {jaxlib_version}'s CPU YNNPACK fusion computes some reductions wrongly (1 / sqrt(sum(x * x)) "
            f"as inf on 4096 rows or more) and jax was already running when jaxrt was imported, too late to turn "
            f"it off: import jaxrt first, or set XLA_FLAGS={_YNN_FLAG} yourself, or use jax 0.10 or 0.12"
        )
    environ["XLA_FLAGS"] = f"{flags} {_YNN_FLAG}".strip()
    return None


def check_at_import() -> None:
    """Warn about an untested jax and apply the workarounds of known defects (run when ``jaxrt`` is imported)."""
    import jax
    import jaxlib

    message = check_jax_version(jax.__version__)
    if message is not None:
        warnings.warn(message, JaxVersionWarning, stacklevel=2)
    try:
        from jax._src import xla_bridge

        initialized = bool(xla_bridge.backends_are_initialized())
    except (ImportError, AttributeError):  # a jax without this private query: assume the worst
        initialized = True
    message = work_around_ynn_defect(jaxlib.__version__, initialized=initialized)
    if message is not None:
        warnings.warn(message, JaxVersionWarning, stacklevel=2)


check_at_import()
