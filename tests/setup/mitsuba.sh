#!/usr/bin/env bash
# Installs Mitsuba 3 (and Dr.Jit) from PyPI for python3, at the versions pinned in
# benches/quality/requirements.txt, unless python3 already imports that Mitsuba: the Mitsuba
# worker's test renders with it. Idempotent and non-interactive (pip only, no root needed when
# python3's site-packages are writable; otherwise pip's --break-system-packages fallback, as in
# tests/run.sh). Prints the python3 to run the worker with.
set -euo pipefail
cd "$(dirname "$0")/../.."

want="$(sed -n 's/^mitsuba==//p' benches/quality/requirements.txt)"
have() {
    python3 -c "import mitsuba, sys; sys.exit(mitsuba.__version__ != '$want')" >/dev/null 2>&1
}

if ! have; then
    python3 -m pip install --quiet --disable-pip-version-check --root-user-action=ignore \
        -r benches/quality/requirements.txt >&2 \
        || python3 -m pip install --quiet --disable-pip-version-check --break-system-packages \
            -r benches/quality/requirements.txt >&2
    if ! have; then
        echo "pip installed benches/quality/requirements.txt but python3 cannot import mitsuba $want" >&2
        exit 1
    fi
fi
python3 -c "import sys; print(sys.executable)"
