"""Reads an EXR with the OpenEXR project's own Python bindings and prints its channels as JSON.

Used by the Rust integration tests as an independent reader: splatd writes EXRs with the `exr`
crate, and this checks them with the reference implementation.

Output: {"width": W, "height": H, "channels": {"R": [floats, row-major], ...}}
"""

import json
import sys

import numpy as np
import OpenEXR


def main(path: str) -> None:
    with OpenEXR.File(path, separate_channels=True) as f:
        header = f.header()
        (x0, y0), (x1, y1) = header["dataWindow"]
        channels = {}
        for name, channel in f.channels().items():
            pixels = np.asarray(channel.pixels, dtype=np.float64)
            channels[name] = pixels.reshape(-1).tolist()
    json.dump({"width": int(x1 - x0 + 1), "height": int(y1 - y0 + 1), "channels": channels},
              sys.stdout)


if __name__ == "__main__":
    main(sys.argv[1])
