"""Posts pass files through the Python client's Outbox, then syncs, for tests/service_faults.rs:
the server is killed and restarted while this runs, and the frame must end with every pass once.

    python3 tests/py/post_through_restart.py URL FRAME WORKER PASS.exr...

Creates the frame (create-or-get, the size read from the first pass with OpenEXR's package),
posts pass k as (WORKER, k) with `Outbox.post_pass`, calls `Outbox.sync`, and prints one JSON
line: the passes acknowledged, how many were resent, and the SyncAck.
"""

import json
import os
import sys

import OpenEXR

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "..", "proto", "python"))
import splatd_client as sc  # noqa: E402


def main(url, frame, worker, paths):
    with OpenEXR.File(paths[0]) as f:
        (x0, y0), (x1, y1) = f.header()["dataWindow"]
    client = sc.Client(url, timeout=30)
    client.create_or_get(frame, int(x1 - x0 + 1), int(y1 - y0 + 1))
    outbox = client.outbox(frame, worker)
    acked = 0
    for k, path in enumerate(paths):
        with open(path, "rb") as f:
            outbox.post_pass(k, f.read())
        acked += 1
    synced = outbox.sync()
    print(json.dumps({"acknowledged": acked, "resent": outbox.resent, "sync": synced}))


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4:])
