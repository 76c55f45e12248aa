# Sourced by the setup scripts: `need_apt WHAT` checks that apt-get can install WHAT and sets
# SUDO to what runs it as root (empty when already root), or exits saying why it cannot;
# `apt_get ARGS` runs apt-get with them, one at a time on the machine.
need_apt() {
    if ! command -v apt-get >/dev/null 2>&1; then
        echo "$1 is not installed and apt-get is not available; install it by hand" >&2
        exit 1
    fi
    SUDO=""
    if [ "$(id -u)" -ne 0 ]; then
        if command -v sudo >/dev/null 2>&1; then
            SUDO="sudo -n"
        else
            echo "$1 is not installed, and installing it needs root (no sudo found)" >&2
            exit 1
        fi
    fi
}

# apt-get takes dpkg's lock and fails at once when another apt-get holds it: two test runs side
# by side on a fresh machine (each installing what it needs) made one of them fail. So every
# apt-get these scripts run waits its turn on one lock file (flock, from util-linux), and also
# waits for dpkg's own lock if something else on the machine holds it.
APT_LOCK="${TMPDIR:-/tmp}/splatd-apt.lock"
apt_get() {
    local apt=(env DEBIAN_FRONTEND=noninteractive apt-get -o DPkg::Lock::Timeout=600 "$@")
    if command -v flock >/dev/null 2>&1; then
        # shellcheck disable=SC2086 # SUDO is a command and its flags, or nothing
        flock -w 1200 "$APT_LOCK" $SUDO "${apt[@]}"
    else
        # shellcheck disable=SC2086
        $SUDO "${apt[@]}"
    fi
}
