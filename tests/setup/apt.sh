# Sourced by the setup scripts: `need_apt WHAT` checks that apt-get can install WHAT and sets
# SUDO to what runs it as root (empty when already root), or exits saying why it cannot.
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
