"""Reads an EXR with the OpenEXR project's own Python bindings and prints its channels as JSON.

Used by the Rust integration tests as an independent reader: splatd writes EXRs with the `exr`
crate, and this checks them with the reference implementation.

Output: {"width": W, "height": H, "channels": {"R": [floats, row-major], ...},
"attributes": {"software": "...", "splatd:kappa": 4.0, ...}} (the `software` attribute and every
`splatd:` one, numbers as numbers, vectors as lists).
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
        attributes = {}
        for name, value in header.items():
            if name == "software" or name.startswith("splatd:"):
                if isinstance(value, np.ndarray):
                    # The binding gives a `double` attribute as a one-element float64 array.
                    value = value.item() if value.shape == (1,) else value.tolist()
                elif isinstance(value, (np.floating, np.integer)):
                    value = value.item()
                attributes[name] = value
    json.dump({"width": int(x1 - x0 + 1), "height": int(y1 - y0 + 1), "channels": channels,
               "attributes": attributes},
              sys.stdout)


if __name__ == "__main__":
    main(sys.argv[1])
