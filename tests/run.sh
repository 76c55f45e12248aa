#!/usr/bin/env bash
# The whole test suite, from a fresh clone with only the Rust toolchain and Python 3 present:
# installs what the tests need beyond cargo's own crates, then runs every test.
set -euo pipefail
cd "$(dirname "$0")/.."

# Independent readers and the Python client's tests need numpy and OpenEXR's Python package.
python3 -m pip install --quiet --disable-pip-version-check --root-user-action=ignore -r tests/requirements.txt

cargo test --workspace
python3 proto/python/test_splatd_client.py
