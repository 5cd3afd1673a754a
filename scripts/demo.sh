#!/usr/bin/env bash
# Render the demo scene (out/demo.png) and print its speed/accuracy summary. Creates .venv on first use.
# The editable install is skipped on a re-run while pyproject.toml is unchanged (a stamp in .venv keyed on
# its SHA-256); delete .venv/.jaxrt-demo-stamp to force it.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PYTHON" -m venv .venv
STAMP=.venv/.jaxrt-demo-stamp
KEY=$(.venv/bin/python -c 'import hashlib; print(hashlib.sha256(open("pyproject.toml", "rb").read()).hexdigest(), "demo")')
if [ "$(cat "$STAMP" 2>/dev/null)" != "$KEY" ]; then
  .venv/bin/python -m pip install -q --disable-pip-version-check --config-settings editable_mode=compat -e ".[demo]"
  echo "$KEY" >"$STAMP"
fi
exec .venv/bin/python examples/demo.py "$@"
