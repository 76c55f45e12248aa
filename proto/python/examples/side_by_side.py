"""Puts the plain mean and splatd's reweighted estimate of a served frame side by side as a PNG.

    python side_by_side.py image.exr out.png [--scale N]

Reads `GET /v1/frames/{id}/image.exr` (channels R, G, B: reweighted; mean.R/G/B: the plain
mean) with OpenEXR's Python package, picks one exposure for both (the median luminance of the
reweighted image mapped to 0.3, as splatd's previews do), tone-maps with the same filmic curve
and sRGB transfer function as splatd's preview.png, and writes mean | reweighted with a dark
grey gap, each pixel enlarged N times (default 2) so fireflies stay visible. numpy and the
standard library only (the PNG is written with zlib).
"""

import argparse
import struct
import zlib

import numpy as np
import OpenEXR


def read(path):
    with OpenEXR.File(path, separate_channels=True) as f:
        ch = f.channels()
        layer = lambda p: np.stack([np.asarray(ch[p + c].pixels, np.float32) for c in "RGB"], -1)
        return layer("mean."), layer("")


def exposure(rgb, key=0.3):
    lum = rgb @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    lum = lum[np.isfinite(lum) & (lum > 0)]
    return key / float(np.median(lum)) if lum.size else 1.0


def tonemap(rgb, exp):
    x = np.clip(np.nan_to_num(rgb * exp, nan=0.0, posinf=1e4), 0.0, 1e4)
    filmic = np.clip((x * (2.51 * x + 0.03)) / (x * (2.43 * x + 0.59) + 0.14), 0.0, 1.0)
    srgb = np.where(filmic <= 0.0031308, 12.92 * filmic, 1.055 * filmic ** (1 / 2.4) - 0.055)
    return np.round(srgb * 255).astype(np.uint8)


def png(pixels):
    h, w, _ = pixels.shape
    raw = b"".join(b"\x00" + pixels[y].tobytes() for y in range(h))

    def chunk(kind, data):
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(raw, 9)) + chunk(b"IEND", b""))


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("exr")
    p.add_argument("png")
    p.add_argument("--scale", type=int, default=2)
    args = p.parse_args()
    mean, reweighted = read(args.exr)
    exp = exposure(reweighted)
    panels = [tonemap(img, exp).repeat(args.scale, 0).repeat(args.scale, 1)
              for img in (mean, reweighted)]
    gap = np.full((panels[0].shape[0], 4, 3), 40, np.uint8)
    with open(args.png, "wb") as f:
        f.write(png(np.concatenate([panels[0], gap, panels[1]], axis=1)))
    print(f"{args.png}: mean | reweighted, exposure {exp:.4g}")


if __name__ == "__main__":
    main()
