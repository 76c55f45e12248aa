#!/usr/bin/env bash
# Profiles the `splatd serve` a benchmark starts: runs the benchmark, waits for its server child,
# waits until the benchmark's output (stdout and stderr) shows a line matching START (an
# extended regex; empty: at once), then records that process with `perf record -F 999 -g` for
# SECONDS (0: until the server exits) and prints the server's top symbols, overall and per
# thread name (renders run on `splatd-render` threads, requests and ingest on `tokio-rt-worker`).
# It records the whole machine (`perf record -a`) and reports only the server's samples, with
# percentages of the server's own: `perf record -p` misses the threads a server starts while
# perf attaches to it.
#
#   benches/perf_server.sh OUT.data SECONDS START -- target/release/watchbench --rounds 1
#
# perf: `apt-get install -y linux-perf` if missing. The benchmark's output goes to OUT.log.
set -euo pipefail
out="$1" secs="$2" start="$3"
shift 3
[ "${1:-}" = "--" ] && shift
log="${out%.data}.log"
"$@" >"$log" 2>&1 &
bench=$!
server=""
for _ in $(seq 600); do
    server="$(pgrep -P "$bench" -f "splatd serve " | head -1 || true)"
    [ -n "$server" ] && break
    sleep 0.1
done
[ -n "$server" ] || { echo "no splatd child of $bench" >&2; wait "$bench"; exit 1; }
if [ -n "$start" ]; then
    for _ in $(seq 6000); do
        grep -Eq "$start" "$log" && break
        kill -0 "$bench" 2>/dev/null || break
        sleep 0.1
    done
fi
echo "recording splatd $server ($(cut -d' ' -f1-3 /proc/loadavg))" >&2
if [ "$secs" = 0 ]; then
    perf record -F 999 -g -a -o "$out" -- tail --pid="$server" -f /dev/null 2>/dev/null || true
else
    perf record -F 999 -g -a -o "$out" -- sleep "$secs" 2>/dev/null || true
fi
wait "$bench" || echo "benchmark exited with $?" >&2
echo "== top symbols (self) =="
perf report -i "$out" --pid "$server" --percentage relative --stdio --no-children --sort symbol 2>/dev/null \
    | grep -E '^ +[0-9.]+%' | sed 's/ *- *- *$//; s/  */ /g' | head -25 || true
echo "== by thread name and symbol (self) =="
perf report -i "$out" --pid "$server" --percentage relative --stdio --no-children --sort comm,symbol 2>/dev/null \
    | grep -E '^ +[0-9.]+%' | sed 's/ *- *- *$//; s/  */ /g' | head -25 || true
echo "== by thread name =="
perf report -i "$out" --pid "$server" --percentage relative --stdio --no-children --sort comm 2>/dev/null \
    | grep -E '^ +[0-9.]+%' | sed 's/ *- *- *$//; s/  */ /g' | head -10 || true
