#!/usr/bin/env bash
# One-time (idempotent) set-up on a fresh machine. Needs network access to PyPI.
#   .venv        Python 3.13: bpy 5.3.0 (the current Blender) and requirements.txt
#   .venv-bpy42  Python 3.11: bpy 4.2 LTS and numpy only (requirements-bpy42.txt), for the
#                compatibility smoke test (tests/test_compat_smoke.py)
#   wheels/      the extension's bundled wheels (blender_manifest.toml), cp311 and cp313
# Interpreters: $PYTHON (3.13) and $PYTHON311 if set, else python3.13 / python3.11 on PATH, else
# pyenv's ~/.pyenv/versions/3.13*/ and 3.11*/. A venv of the wrong Python version is recreated.
set -euo pipefail
cd "$(dirname "$0")/.."

# find_python X.Y [candidate...]: print the first candidate that really runs as Python X.Y
# (a pyenv shim on PATH may exist and still fail for a version that is not selected).
find_python() {
    local want="$1" c
    shift
    for c in "$@"; do
        [ -n "$c" ] || continue
        if "$c" -c "import sys; sys.exit(sys.version_info[:2] != tuple(map(int, '$want'.split('.'))))" \
            >/dev/null 2>&1; then
            echo "$c"
            return 0
        fi
    done
    return 1
}

pyenv_candidates() {  # newest patch release first
    local root="${PYENV_ROOT:-$HOME/.pyenv}"
    ls -d "$root"/versions/"$1"*/bin/python"$1" 2>/dev/null | sort -rV || true
}

# make_venv DIR PYTHON REQUIREMENTS: (re)create DIR with PYTHON's version, install REQUIREMENTS
# unless the same file was already installed there with the same interpreter (stamp file).
make_venv() {
    local dir="$1" py="$2" req="$3" want have stamp
    want="$("$py" -c 'import sys; print("%d.%d" % sys.version_info[:2])')"
    if [ -x "$dir/bin/python" ]; then
        have="$("$dir/bin/python" -c 'import sys; print("%d.%d" % sys.version_info[:2])' 2>/dev/null || echo none)"
        if [ "$have" != "$want" ]; then
            echo "recreating $dir: it has Python $have, needs $want" >&2
            rm -rf "$dir"
        fi
    fi
    if [ ! -x "$dir/bin/python" ]; then
        echo "creating $dir with $py (Python $want)" >&2
        "$py" -m venv "$dir"
    fi
    stamp="$want $(sha256sum "$req" | cut -d' ' -f1)"
    if [ "$(cat "$dir/.lpv-installed" 2>/dev/null || true)" != "$stamp" ]; then
        echo "installing $req into $dir" >&2
        if ! "$dir/bin/python" -m pip install -q --disable-pip-version-check -r "$req"; then
            echo "error: pip could not install $req into $dir" >&2
            exit 1
        fi
        echo "$stamp" > "$dir/.lpv-installed"
    fi
}

PY313="$(find_python 3.13 "${PYTHON:-}" "$(command -v python3.13 || true)" \
    $(pyenv_candidates 3.13) || true)"
if [ -z "$PY313" ]; then
    echo "error: Python 3.13 is required (bpy 5.3.0 is built for it) and none was found:" \
        "set PYTHON=/path/to/python3.13, put python3.13 on PATH, or install it with" \
        "'pyenv install 3.13'" >&2
    exit 2
fi
PY311="$(find_python 3.11 "${PYTHON311:-}" "$(command -v python3.11 || true)" \
    $(pyenv_candidates 3.11) "$(command -v python3 || true)" || true)"
if [ -z "$PY311" ]; then
    echo "error: Python 3.11 is required for .venv-bpy42 (bpy 4.2 LTS, the compatibility" \
        "smoke test) and none was found: set PYTHON311=/path/to/python3.11 or put python3.11" \
        "on PATH" >&2
    exit 2
fi

make_venv .venv "$PY313" requirements.txt
make_venv .venv-bpy42 "$PY311" requirements-bpy42.txt
.venv/bin/python tools/fetch_wheels.py -q >&2
