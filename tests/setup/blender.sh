#!/usr/bin/env bash
# Installs Blender (Debian's blender package) if no blender binary is on PATH, for the Blender
# worker's test. Idempotent and non-interactive; uses sudo only when not already root.
# Prints the path of the blender binary on success; exits non-zero saying why otherwise (the
# test then skips with that message, or fails on CI). On Debian 12 that is Blender 3.4; the
# current Blender is tested as the bpy module (tests/setup/bpy.sh).
set -euo pipefail

found="$(command -v blender 2>/dev/null || true)"
if [ -n "$found" ]; then
    echo "$found"
    exit 0
fi

. "$(dirname "$0")/apt.sh"
need_apt blender

apt_install() { apt_get install -y -q --no-install-recommends "$@" >&2; }
# Try with the package lists as they are first; refresh them only if that fails.
if ! apt_install blender; then
    apt_get update -q >&2
    apt_install blender
fi

found="$(command -v blender 2>/dev/null || true)"
if [ -z "$found" ]; then
    echo "blender was installed but no blender binary was found" >&2
    exit 1
fi
echo "$found"
