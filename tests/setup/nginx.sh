#!/usr/bin/env bash
# Installs nginx (Debian's nginx-light, else nginx) if no nginx binary is on PATH.
# Idempotent and non-interactive; uses sudo only when not already root.
# Prints the path of the nginx binary on success.
set -euo pipefail

find_nginx() {
    command -v nginx 2>/dev/null || { [ -x /usr/sbin/nginx ] && echo /usr/sbin/nginx; } || true
}

found="$(find_nginx)"
if [ -n "$found" ]; then
    echo "$found"
    exit 0
fi

. "$(dirname "$0")/apt.sh"
need_apt nginx

# Don't let the package start a system nginx on port 80: the tests run their own.
policy_added=""
if [ ! -e /usr/sbin/policy-rc.d ] && [ -z "$SUDO" ]; then
    printf '#!/bin/sh\nexit 101\n' > /usr/sbin/policy-rc.d
    chmod +x /usr/sbin/policy-rc.d
    policy_added=1
fi
cleanup() { if [ -n "$policy_added" ]; then rm -f /usr/sbin/policy-rc.d; fi; }
trap cleanup EXIT

apt_install() {
    apt_get install -y -q --no-install-recommends \
        -o Dpkg::Options::=--force-confdef -o Dpkg::Options::=--force-confold "$@" >&2
}

# Try with the package lists as they are first; refresh them only if that fails.
if ! apt_install nginx-light && ! apt_install nginx; then
    apt_get update -q >&2
    apt_install nginx-light || apt_install nginx
fi

found="$(find_nginx)"
if [ -z "$found" ]; then
    echo "nginx was installed but no nginx binary was found" >&2
    exit 1
fi
echo "$found"
