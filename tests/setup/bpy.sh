#!/usr/bin/env bash
# Installs Blender as a Python module (PyPI's `bpy` wheel, at the version pinned in
# tests/requirements-bpy.txt) into a virtual environment of its own, for the Blender worker's
# test on a current Blender. Idempotent and non-interactive: when the environment already imports
# that bpy nothing is downloaded. Prints the environment's python on success; exits non-zero
# saying why otherwise.
#
# The environment lives outside the checkout, so a fresh clone or `cargo clean` does not
# download the wheel (about 370 MB) again: $SPLATD_BPY_VENV, else
# ${XDG_CACHE_HOME:-~/.cache}/splatd/bpy-<version>. bpy's wheels are built for one CPython
# (3.11 for Blender 4.x and 5.0): python3.11 is used, or python3 when it is 3.11.
set -euo pipefail
cd "$(dirname "$0")/../.."

want="$(sed -n 's/^bpy==//p' tests/requirements-bpy.txt)"
venv="${SPLATD_BPY_VENV:-${XDG_CACHE_HOME:-$HOME/.cache}/splatd/bpy-$want}"
python="$venv/bin/python"

have() {
    [ -x "$python" ] && "$python" -c "import bpy, sys; sys.exit(bpy.app.version_string != '$want')" >/dev/null 2>&1
}

if ! have; then
    base=""
    for candidate in python3.11 python3; do
        if command -v "$candidate" >/dev/null 2>&1 \
            && "$candidate" -c "import sys; sys.exit(sys.version_info[:2] != (3, 11))" 2>/dev/null; then
            base="$(command -v "$candidate")"
            break
        fi
    done
    if [ -z "$base" ]; then
        echo "bpy $want needs CPython 3.11 (its wheels are built for it); found no python3.11" \
            "(python3 is $(python3 --version 2>&1 || echo missing))" >&2
        exit 1
    fi
    bash tests/setup/python_venv.sh >/dev/null
    # Replaced only when it is a venv (a broken or older one): never whatever else is there.
    if [ -e "$venv" ]; then
        if [ ! -f "$venv/pyvenv.cfg" ]; then
            echo "$venv exists and is not a Python venv; not touching it (set SPLATD_BPY_VENV)" >&2
            exit 1
        fi
        rm -rf "$venv"
    fi
    mkdir -p "$(dirname "$venv")"
    "$base" -m venv "$venv"
    # No wheel cache: the installed module is what is kept, not a second copy of the download.
    if ! "$python" -m pip install --quiet --disable-pip-version-check --no-cache-dir \
        -r tests/requirements-bpy.txt >&2; then
        echo "pip could not install tests/requirements-bpy.txt into $venv" >&2
        exit 1
    fi
    if ! have; then
        "$python" -c "import bpy" >&2 || true
        echo "pip installed bpy $want into $venv, but its python cannot import it (above)" >&2
        exit 1
    fi
fi
echo "$python"
