#!/usr/bin/env bash
# Lint and run the test suite on the CPU. Creates the lane's virtual environment on first use.
#
#   bash scripts/test.sh [pytest args]                  # .venv: Python 3.11 (or $PYTHON), the jax pip resolves
#   JAXRT_LANE=next bash scripts/test.sh [pytest args]  # .venv-next: the newest Python 3.13/3.12 found
#                                                       # ($PYTHON_NEXT), upgraded to the newest jax in range
#
# The package is installed in setuptools' "compat" editable mode (a path entry, not an import hook), so that
# a clone in a folder named jaxrt still imports the package, not the clone, from the folder above it.
# Exit status: pytest's, except that "no tests collected" (5) is a failure (1).
set -euo pipefail
cd "$(dirname "$0")/.."
LANE=${JAXRT_LANE:-main}
PIP=(-m pip install -q --disable-pip-version-check --config-settings editable_mode=compat)

find_next_python() {
  if [ -n "${PYTHON_NEXT:-}" ]; then echo "$PYTHON_NEXT"; return; fi
  local root candidate
  root=$(pyenv root 2>/dev/null || echo "$HOME/.pyenv")
  for candidate in python3.13 python3.12 "$root"/versions/3.13*/bin/python3 "$root"/versions/3.12*/bin/python3; do
    # A pyenv shim exists for versions that are not selected: take a candidate only if it runs.
    if "$candidate" -c 'import sys; assert sys.version_info >= (3, 12)' >/dev/null 2>&1; then
      command -v "$candidate"
      return
    fi
  done
  return 1
}

case "$LANE" in
  main)
    VENV=.venv
    [ -x "$VENV/bin/python" ] || "${PYTHON:-python3}" -m venv "$VENV"
    "$VENV/bin/python" "${PIP[@]}" -e ".[test]"
    ;;
  next)
    VENV=.venv-next
    if [ ! -x "$VENV/bin/python" ]; then
      NEXT=$(find_next_python) || { echo "scripts/test.sh: JAXRT_LANE=next needs Python 3.13 or 3.12 (set PYTHON_NEXT)" >&2; exit 2; }
      "$NEXT" -m venv "$VENV"
      echo '*' >"$VENV/.gitignore"
    fi
    # The newest jax and jaxlib inside pyproject.toml's range, even when an older one is installed.
    "$VENV/bin/python" "${PIP[@]}" --upgrade -e ".[test]" jax jaxlib
    ;;
  *)
    echo "scripts/test.sh: JAXRT_LANE must be main or next, got '$LANE'" >&2
    exit 2
    ;;
esac

"$VENV/bin/python" -c 'import sys, jax, jaxlib; print(f"lane {sys.argv[1]}: Python {sys.version.split()[0]}, jax {jax.__version__}, jaxlib {jaxlib.__version__}")' "$LANE"
"$VENV/bin/python" -m ruff check jaxrt tests examples
# JAX's persistent compilation cache, one per lane inside its environment: a program that two workers or two
# test files compile alike is compiled once, and a second run finds the programs of the first. Deleting the
# folder (or the environment) clears it; a JAX_COMPILATION_CACHE_DIR already set is used instead.
export JAX_COMPILATION_CACHE_DIR=${JAX_COMPILATION_CACHE_DIR:-$PWD/$VENV/jax-cache}
export JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=${JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS:-0}
export JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES=${JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES:--1}
status=0
# One pytest worker per core (pytest-xdist), each test file kept on one worker so that its module-scoped
# fixtures and compiled shapes are shared; JAXRT_TEST_WORKERS=0 runs in this process alone.
WORKERS=${JAXRT_TEST_WORKERS:-auto}
PARALLEL=()
[ "$WORKERS" = 0 ] || PARALLEL=(-n "$WORKERS" --dist loadfile)
"$VENV/bin/python" -m pytest jaxrt tests -q -p no:cacheprovider "${PARALLEL[@]}" "$@" || status=$?
if [ "$status" -eq 5 ]; then
  echo "scripts/test.sh: lane $LANE collected no tests (pytest exit 5): failing" >&2
  status=1
fi
exit "$status"
