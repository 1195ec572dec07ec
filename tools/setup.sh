#!/usr/bin/env bash
# One-time (idempotent) set-up on a fresh machine: .venv with bpy, moderngl, numpy, OpenEXR,
# pytest, and the extension's wheels. Needs Python 3.11 and network access to PyPI.
set -euo pipefail
cd "$(dirname "$0")/.."
PY="${PYTHON:-$(command -v python3.11 || command -v python3)}"
if ! "$PY" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then
    echo "error: Python 3.11 is required (bpy 5.0.1); found $("$PY" --version 2>&1)" >&2
    exit 2
fi
if [ ! -x .venv/bin/python ]; then
    echo "creating .venv with $PY" >&2
    "$PY" -m venv .venv
fi
if ! .venv/bin/python -m pip install -q --disable-pip-version-check -r requirements.txt; then
    echo "error: pip could not install requirements.txt" >&2
    exit 1
fi
.venv/bin/python tools/fetch_wheels.py >&2
