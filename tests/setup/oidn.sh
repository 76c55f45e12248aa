#!/usr/bin/env bash
# Installs Intel Open Image Denoise 2.5.1 from PyPI's `pyoidn` wheel for python3, unless that
# version is installed already, and prints the absolute path of its libOpenImageDenoise.so.2
# (what `splatd serve --oidn-lib` and SPLATD_OIDN_LIB take). The wheel also ships OIDN's own
# `oidnDenoise` beside it (../bin/), which the denoise crate's tests compare against.
# Idempotent and non-interactive (pip only; pip's --break-system-packages fallback as in
# tests/run.sh). Debian has no OIDN package, and splatd loads the library at run time, so
# nothing else needs it.
set -euo pipefail

want=2.5.1
where() {
    # find_spec locates the package without importing it (importing would load the library).
    python3 - "$want" <<'PY'
import importlib.metadata, importlib.util, os, sys
have = importlib.metadata.version("pyoidn")  # the wheel says 2.5.1.0
if have != sys.argv[1] and not have.startswith(sys.argv[1] + "."):
    sys.exit(1)
spec = importlib.util.find_spec("pyoidn")
lib = os.path.join(list(spec.submodule_search_locations)[0], "oidn", "lib", "libOpenImageDenoise.so.2")
if not os.path.isfile(lib):
    sys.exit(1)
print(os.path.realpath(os.path.dirname(lib)) + "/libOpenImageDenoise.so.2")
PY
}

if ! where >/dev/null 2>&1; then
    python3 -m pip install --quiet --disable-pip-version-check --root-user-action=ignore \
        "pyoidn==$want" >&2 \
        || python3 -m pip install --quiet --disable-pip-version-check --break-system-packages \
            "pyoidn==$want" >&2
    if ! where >/dev/null 2>&1; then
        echo "pip installed pyoidn==$want but python3 finds no pyoidn/oidn/lib/libOpenImageDenoise.so.2 in it" >&2
        exit 1
    fi
fi
where
