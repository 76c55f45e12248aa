#!/usr/bin/env bash
# The whole test suite, from a fresh clone with only the Rust toolchain present: installs what
# the tests need beyond cargo's own crates, then runs every test.
#
#   Python 3 + numpy + OpenEXR   independent EXR reader/writer, the Python client's tests (pip)
#   python3-venv                 the Python client package installed into a fresh venv
#   nginx                        the load balancer in front of several nodes (Debian package)
#   chromium + chromedriver      the live page, driven headless (Debian packages)
#   Mitsuba 3 + Dr.Jit           the Mitsuba worker's guided-mode test (pip, pinned in
#                                benches/quality/requirements.txt)
#   Open Image Denoise 2.5.1     the denoiser that `?denoise=oidn` loads at run time (pip's
#                                pyoidn wheel); its path is exported as SPLATD_OIDN_LIB
#   blender                      the Blender worker's test on Debian's Blender 3.4 (Debian package)
#   bpy                          the same test on Blender 5.0 as a Python module (pip, pinned in
#                                tests/requirements-bpy.txt, into a venv of its own under
#                                ~/.cache/splatd; needs CPython 3.11)
#   openimageio-tools            oiiotool's view of EXR headers (optional)
#
# A Blender that cannot be installed makes its test skip with a loud SKIP line, except on CI
# (CI=true), where this script and the test fail: CI must run it.
#
# The Debian packages are installed as root (or with sudo) when missing; each script is
# idempotent and does nothing when its tools are already there.
set -euo pipefail
cd "$(dirname "$0")/.."

# Set-up runs one run at a time on the machine: two runs side by side on a fresh machine would
# otherwise install the same packages at once (apt-get fails at once on dpkg's lock, and two pip
# installs of one package can race). The lock is let go of before the tests start.
if command -v flock >/dev/null 2>&1; then
    exec 9>"${TMPDIR:-/tmp}/splatd-setup.lock"
    flock 9
fi
if ! command -v python3 >/dev/null 2>&1 || ! python3 -m pip --version >/dev/null 2>&1; then
    . tests/setup/apt.sh
    need_apt python3
    apt_get update -qq
    apt_get install -y -qq --no-install-recommends python3 python3-pip python3-venv >/dev/null
fi
python3 -m pip install --quiet --disable-pip-version-check --root-user-action=ignore \
    -r tests/requirements.txt 2>/dev/null \
    || python3 -m pip install --quiet --disable-pip-version-check --break-system-packages \
        -r tests/requirements.txt

# Installed up front, once: the tests call the same scripts, which then find the tools present
# (two tests running apt-get at the same time would fight over its lock).
bash tests/setup/nginx.sh >/dev/null
bash tests/setup/python_venv.sh >/dev/null
bash tests/setup/mitsuba.sh >/dev/null
# OIDN: the denoise crate's and the server's denoise tests load the library this names. In CI a
# failed install fails the run; elsewhere those tests say loudly that they checked nothing.
if oidn_lib="$(bash tests/setup/oidn.sh)"; then
    export SPLATD_OIDN_LIB="$oidn_lib"
elif [ "${CI:-}" = true ]; then
    echo "tests/setup/oidn.sh failed: Open Image Denoise is needed in CI" >&2
    exit 1
else
    echo "WARNING: Open Image Denoise could not be installed; the denoise tests will check nothing" >&2
fi
# Without a Blender the worker's test on it skips, saying so loudly; in CI a failed install fails
# the run here, before the test would fail on it. Without oiiotool the provenance test checks the
# EXR header with OpenEXR's Python package only.
for blender in blender bpy; do
    if ! bash "tests/setup/$blender.sh" >/dev/null; then
        if [ "${CI:-}" = true ]; then
            echo "tests/setup/$blender.sh failed: the Blender worker's test needs it in CI" >&2
            exit 1
        fi
        echo "WARNING: $blender could not be installed; the Blender worker's test on it will SKIP" >&2
    fi
done
bash tests/setup/oiio.sh >/dev/null || echo "oiiotool could not be installed; not used"
bash tests/setup/chromium.sh >/dev/null
exec 9>&-

cargo test --workspace
python3 proto/python/test_splatd_client.py
