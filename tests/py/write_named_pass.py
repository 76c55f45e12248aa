"""Writes one pass with OpenEXR's own Python package: a beauty (`R`, `G`, `B` = 1, 2, 0.5) and
one constant float channel per name given, for tests/aov_names.rs.

    echo '{"ViewLayer.Depth.Z": 0.25}' | python3 tests/py/write_named_pass.py OUT.exr WIDTH HEIGHT

The channel names come as JSON on stdin, so names with spaces, quotes or 255 bytes pass
through no shell.
"""

import json
import sys

import numpy as np
import OpenEXR


def main(path: str, width: int, height: int) -> None:
    extra = json.load(sys.stdin)
    channels = {}
    for name, value in [("R", 1.0), ("G", 2.0), ("B", 0.5)] + sorted(extra.items()):
        channels[name] = np.full((height, width), value, dtype=np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, channels) as f:
        f.write(path)
    # OpenEXR cuts names longer than 255 bytes; the test must know it wrote what it asked.
    with OpenEXR.File(path, separate_channels=True) as f:
        written = set(f.channels().keys())
    missing = set(channels) - written
    if missing:
        sys.exit(f"OpenEXR did not write the channels {sorted(missing)}")


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]), int(sys.argv[3]))
