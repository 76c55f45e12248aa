#!/usr/bin/env bash
# Installs Debian's chromium and chromium-driver if either binary is missing, for
# tests/live_page.rs. Idempotent and non-interactive; uses sudo only when not already root.
# Refreshes the package lists only if installing from the present ones fails.
# Prints the paths of the chromium and chromedriver binaries (one per line) on success.
set -euo pipefail

find_bin() {
    for name in "$@"; do
        command -v "$name" 2>/dev/null && return 0
        for dir in /usr/bin /usr/lib/chromium; do
            if [ -x "$dir/$name" ]; then
                echo "$dir/$name"
                return 0
            fi
        done
    done
    return 0
}

found() {
    chromium="$(find_bin chromium chromium-browser)"
    driver="$(find_bin chromedriver)"
    [ -n "$chromium" ] && [ -n "$driver" ]
}

if found; then
    echo "$chromium"
    echo "$driver"
    exit 0
fi

. "$(dirname "$0")/apt.sh"
need_apt chromium/chromedriver

apt_install() {
    apt_get install -y -q --no-install-recommends \
        -o Dpkg::Options::=--force-confdef -o Dpkg::Options::=--force-confold \
        chromium chromium-driver >&2
}

# Try with the package lists as they are first; refresh them only if that fails.
if ! apt_install; then
    apt_get update -q >&2
    apt_install
fi

if ! found; then
    echo "chromium and chromium-driver were installed, but chromium='$chromium' chromedriver='$driver'" >&2
    exit 1
fi
echo "$chromium"
echo "$driver"
