#!/usr/bin/env bash
# Render the demo scene (out/demo.png) and print its speed/accuracy summary. Creates .venv on first use.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PYTHON" -m venv .venv
.venv/bin/python -m pip install -q --disable-pip-version-check --config-settings editable_mode=compat -e ".[demo]"
exec .venv/bin/python examples/demo.py "$@"
