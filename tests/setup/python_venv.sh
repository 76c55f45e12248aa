#!/usr/bin/env bash
# Makes sure `python3 -m venv` can create a virtual environment with pip in it (Debian splits
# that into python3-venv). Idempotent and non-interactive; uses sudo only when not already root.
# Prints the python3 used on success.
set -euo pipefail

can_venv() {
    local probe
    probe="$(mktemp -d)"
    local ok=1
    if python3 -m venv "$probe/venv" >/dev/null 2>&1 && "$probe/venv/bin/python" -m pip --version >/dev/null 2>&1; then
        ok=0
    fi
    rm -rf "$probe"
    return $ok
}

if ! command -v python3 >/dev/null 2>&1 || ! can_venv; then
    . "$(dirname "$0")/apt.sh"
    need_apt "python3 with venv and pip"
    apt_install() { apt_get install -y -q --no-install-recommends "$@" >&2; }
    if ! apt_install python3 python3-venv python3-pip; then
        apt_get update -q >&2
        apt_install python3 python3-venv python3-pip
    fi
    if ! can_venv; then
        echo "python3 -m venv still cannot make an environment with pip after installing python3-venv" >&2
        exit 1
    fi
fi
command -v python3
