#!/usr/bin/env bash
# Makes docs/cycles.png, the README's Cycles before/after picture: Blender's Cycles renders a
# small scene full of fireflies (proto/python/examples/firefly_scene.py) as PASSES passes of SPP
# samples each through the Blender worker into a real `splatd serve`; then the served frame's
# plain mean and splatd's reweighted estimate are put side by side, tone-mapped with the same
# exposure (proto/python/examples/side_by_side.py).
#
#   scripts/cycles_picture.sh [PASSES [SPP [OUT]]]      (defaults: 48 2 docs/cycles.png)
#
# Needs blender (tests/setup/blender.sh installs Debian's) and python3 with venv (tests/setup/
# python_venv.sh); installs the Python client, numpy and OpenEXR into a temporary venv. Not a
# test: a few minutes of rendering.
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
passes="${1:-48}"
spp="${2:-2}"
out="${3:-$root/docs/cycles.png}"

blender="$(bash "$root/tests/setup/blender.sh")"
python3="$(bash "$root/tests/setup/python_venv.sh")"
work="$(mktemp -d)"
server_pid=""
cleanup() {
    if [ -n "$server_pid" ]; then kill "$server_pid" 2>/dev/null || true; fi
    rm -rf "$work"
}
trap cleanup EXIT

"$python3" -m venv "$work/venv"
"$work/venv/bin/python" -m pip install --quiet --disable-pip-version-check \
    -r "$root/tests/requirements.txt" "$root/proto/python"
site="$("$work/venv/bin/python" -c "import sysconfig; print(sysconfig.get_paths()['purelib'])")"

(cd "$root" && cargo build --quiet --bin splatd)
"$root/target/debug/splatd" serve --addr 127.0.0.1:0 --log-level warn >"$work/serve.out" 2>"$work/serve.err" &
server_pid=$!
addr=""
for _ in $(seq 100); do
    addr="$(grep -o '127\.0\.0\.1:[0-9]*' "$work/serve.out" | head -1 || true)"
    [ -n "$addr" ] && break
    kill -0 "$server_pid" || { cat "$work/serve.err" >&2; exit 1; }
    sleep 0.1
done
[ -n "$addr" ] || { echo "splatd serve printed no address" >&2; exit 1; }

PYTHONPATH="$site" "$blender" -b --factory-startup --python-use-system-env --python-exit-code 1 \
    --python "$root/proto/python/blender_worker.py" -- \
    --scene-script "$root/proto/python/examples/firefly_scene.py" \
    --url "http://$addr" --frame cycles --passes "$passes" --spp "$spp" --seed 1 \
    --keep-dir "$work/passes" | grep '^pass '

curl --fail --silent --show-error "http://$addr/v1/frames/cycles/image.exr" -o "$work/image.exr"
"$work/venv/bin/python" "$root/proto/python/examples/side_by_side.py" "$work/image.exr" "$out"
