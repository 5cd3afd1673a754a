#!/usr/bin/env bash
# Lint and run the test suite on the CPU. Creates .venv on first use.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PYTHON" -m venv .venv
.venv/bin/python -m pip install -q --disable-pip-version-check -e ".[test]"
.venv/bin/python -m ruff check jaxrt tests examples
exec .venv/bin/python -m pytest jaxrt tests -q -p no:cacheprovider "$@"
