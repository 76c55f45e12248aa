"""Writes sample passes as OpenEXR with OpenEXR's own Python package, for tests/passes_exr.rs.

An independent writer: splatd reads the files with the Rust `exr` crate; these are written by
the reference C++ library. Every EXR comes with the exact values it was meant to hold, as raw
little-endian float32 (height x width x 3, row-major, RGB interleaved) in a `.f32` file beside
it. For half-float files the raw values are the float32 values *before* rounding to half; the
reader compares after rounding them the same way (round to nearest even).

    python3 tests/py/write_passes.py OUT_DIR --width 37 --height 23 --passes 3 --seed 7

writes into OUT_DIR, for every pass i:

* pass{i}.float.exr  float32 R, G, B plus A and Z (to be ignored), ZIP, including a few
                     negative, NaN and infinite samples (passes do not filter values);
* pass{i}.half.exr   float16 R, G, B, PIZ;
* pass{i}.uint.exr   uint32 R, G, B (integer values), no compression;

plus `luminance.exr` (only a Y channel), `cropped.exr` (a border render: data window (2, 3)
size (w-3)x(h-4) inside a display window of w x h), `multipart.exr` (a Y-only part, then an RGB part whose
values are in `multipart.f32`), and `manifest.json` listing every file with its size and type.
"""

import argparse
import json
import os

import numpy as np
import OpenEXR


def write(path, channels, compression):
    header = {"compression": compression, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, channels) as f:
        f.write(path)


def firefly_values(rng, height, width):
    """Mostly dim samples, a few very bright ones, some exact zeros: a 1-spp render."""
    v = rng.lognormal(mean=-1.5, sigma=1.5, size=(height, width, 3))
    fireflies = rng.random((height, width)) < 0.02
    v[fireflies] *= 1000.0
    v[rng.random((height, width, 3)) < 0.05] = 0.0
    # Within half's range, so the same values serve every variant.
    return np.minimum(v, 60000.0).astype(np.float32)


def rgb_channels(values):
    return {name: np.ascontiguousarray(values[:, :, c]) for c, name in enumerate("RGB")}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out_dir")
    parser.add_argument("--width", type=int, default=37)
    parser.add_argument("--height", type=int, default=23)
    parser.add_argument("--passes", type=int, default=3)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    os.makedirs(args.out_dir, exist_ok=True)
    rng = np.random.default_rng(args.seed)
    h, w = args.height, args.width
    files = []

    def emit(stem, variant, values, channels, compression):
        exr = os.path.join(args.out_dir, f"{stem}.exr")
        raw = os.path.join(args.out_dir, f"{stem}.f32")
        write(exr, channels, compression)
        values.astype("<f4").tofile(raw)
        files.append({"exr": exr, "raw": raw, "variant": variant, "width": w, "height": h})

    for i in range(args.passes):
        values = firefly_values(rng, h, w)

        special = values.copy()
        special[0, 0] = [-1.0, np.nan, np.inf]
        special[h - 1, w - 1] = [-np.inf, -0.5, 3.0e38]
        channels = rgb_channels(special)
        channels["A"] = np.full((h, w), 0.25, dtype=np.float32)
        channels["Z"] = rng.random((h, w)).astype(np.float32)
        emit(f"pass{i}.float", "float", special, channels, OpenEXR.ZIP_COMPRESSION)

        channels = {k: v.astype(np.float16) for k, v in rgb_channels(values).items()}
        emit(f"pass{i}.half", "half", values, channels, OpenEXR.PIZ_COMPRESSION)

        integers = np.floor(values * 100.0).astype(np.uint32)
        channels = rgb_channels(integers)
        emit(f"pass{i}.uint", "uint", integers.astype(np.float32), channels,
             OpenEXR.NO_COMPRESSION)

    lum = os.path.join(args.out_dir, "luminance.exr")
    write(lum, {"Y": rng.random((h, w)).astype(np.float32)}, OpenEXR.ZIP_COMPRESSION)

    values = firefly_values(rng, h, w)

    def header():
        # One dict per part: the binding stores the part's name in it.
        return {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}

    parts = [
        OpenEXR.Part(header(), {"Y": rng.random((h, w)).astype(np.float32)}, "depth"),
        OpenEXR.Part(header(), rgb_channels(values), "beauty"),
    ]
    multi = os.path.join(args.out_dir, "multipart.exr")
    with OpenEXR.File(parts) as f:
        f.write(multi)
    multi_raw = os.path.join(args.out_dir, "multipart.f32")
    values.astype("<f4").tofile(multi_raw)

    # A border render: pixels for only part of the frame (data window inside display window).
    cropped = os.path.join(args.out_dir, "cropped.exr")
    header = {
        "compression": OpenEXR.ZIP_COMPRESSION,
        "type": OpenEXR.scanlineimage,
        "displayWindow": (np.array([0, 0], dtype=np.int32), np.array([w - 1, h - 1], dtype=np.int32)),
        "dataWindow": (np.array([2, 3], dtype=np.int32), np.array([w - 2, h - 2], dtype=np.int32)),
    }
    crop = firefly_values(rng, h - 4, w - 3)
    with OpenEXR.File(header, rgb_channels(crop)) as f:
        f.write(cropped)

    manifest = {
        "cropped": cropped,
        "passes": files,
        "luminance": lum,
        "multipart": {"exr": multi, "raw": multi_raw, "width": w, "height": h},
    }
    with open(os.path.join(args.out_dir, "manifest.json"), "w") as f:
        json.dump(manifest, f, indent=1)


if __name__ == "__main__":
    main()
