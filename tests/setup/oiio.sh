#!/usr/bin/env bash
# Installs OpenImageIO's command-line tools (Debian's openimageio-tools: oiiotool) if oiiotool
# is not on PATH; the provenance test then also checks the resolved EXR's header with
# `oiiotool --info -v`. Idempotent and non-interactive; uses sudo only when not already root.
# Prints the path of oiiotool on success.
set -euo pipefail

found="$(command -v oiiotool 2>/dev/null || true)"
if [ -n "$found" ]; then
    echo "$found"
    exit 0
fi

. "$(dirname "$0")/apt.sh"
need_apt openimageio-tools

apt_install() { apt_get install -y -q --no-install-recommends "$@" >&2; }
if ! apt_install openimageio-tools; then
    apt_get update -q >&2
    apt_install openimageio-tools
fi

found="$(command -v oiiotool 2>/dev/null || true)"
if [ -z "$found" ]; then
    echo "openimageio-tools was installed but no oiiotool was found" >&2
    exit 1
fi
echo "$found"
