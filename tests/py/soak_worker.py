"""A soak worker written with the Python client, for src/bin/soak.rs: posts batches of random
records through `splatd_client.Outbox` while the server is killed and restarted, then syncs.

    python3 tests/py/soak_worker.py URL FRAME WORKER SEED BATCH SIZE STOP_FILE OUT

Streams batches (worker WORKER, seq 0, 1, ...) of BATCH records over a SIZE x SIZE frame until
STOP_FILE exists, then syncs. Every record is appended to OUT (the batch wire layout's records:
u32 x, u32 y, f32 r, g, b) before its batch is first sent, so the soak can add exactly what was
sent to its reference. A transient failure (the server is down for longer than the client's
retries) is retried with the same seq and bytes; any refusal ends the worker with an error.
Prints one JSON line: batches, resent, kept.
"""

import json
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "..", "proto", "python"))
import splatd_client as sc  # noqa: E402


def patiently(call):
    for _ in range(200):
        try:
            return call()
        except sc.SplatdError as e:
            if e.status is not None:
                raise
            time.sleep(0.1)
    raise RuntimeError("the server never came back")


def main(url, frame, worker, seed, batch, size, stop, out):
    client = sc.Client(url, max_attempts=60, initial_backoff=0.02, max_backoff=0.5)
    outbox = client.outbox(frame, worker)
    rng = np.random.default_rng(seed)
    seq = 0
    with open(out, "wb") as sent:
        while not os.path.exists(stop):
            records = np.empty(batch, dtype=sc.RECORD_DTYPE)
            records["x"] = rng.integers(0, size, batch)
            records["y"] = rng.integers(0, size, batch)
            v = rng.random(batch).astype(np.float32)
            fireflies = rng.random(batch) < 1 / 64
            v[fireflies] *= 2e4
            records["r"], records["g"], records["b"] = v, 0.5 * v, 0.25 * v
            sent.write(records.tobytes())
            sent.flush()
            rgb = np.column_stack((records["r"], records["g"], records["b"]))
            patiently(lambda: outbox.post_batch(seq, records["x"], records["y"], rgb))
            seq += 1
    patiently(outbox.sync)
    print(json.dumps({"batches": seq, "resent": outbox.resent, "kept": outbox.kept}))


if __name__ == "__main__":
    a = sys.argv[1:]
    main(a[0], a[1], int(a[2]), int(a[3]), int(a[4]), int(a[5]), a[6], a[7])
