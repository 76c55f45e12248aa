"""Writes noisy 1-spp passes with albedo and normal AOVs, with OpenEXR's own Python package, for
tests/denoise_oidn.rs.

    python3 tests/py/write_denoise_passes.py OUT_DIR --width 64 --height 48 --passes 8 --seed 5

Pass k is `pass_K.exr`, single part in Cycles' multilayer layout (float
`ViewLayer.Combined.R/G/B`, `ViewLayer.DiffCol.R/G/B`, `ViewLayer.Normal.X/Y/Z`). The scene: a
flat wall of one albedo and one normal on the left half (the test's "flat region", columns
0..W/2), a checker of two albedos under a tilted normal on the right; the light falls off
smoothly from left to right. Each pass's beauty is albedo x light x exponential noise (mean 1,
no extreme fireflies: the test compares the denoised energy with the mean's, and what the
resolve removes from fireflies at 8 spp is the estimator's business); the guides are the same in
every pass, so their means are clean.
"""

import argparse
import os

import numpy as np
import OpenEXR


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("out_dir")
    p.add_argument("--width", type=int, default=64)
    p.add_argument("--height", type=int, default=48)
    p.add_argument("--passes", type=int, default=8)
    p.add_argument("--seed", type=int, default=5)
    args = p.parse_args()
    os.makedirs(args.out_dir, exist_ok=True)
    rng = np.random.default_rng(args.seed)
    h, w = args.height, args.width
    hd = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}

    ys, xs = np.mgrid[0:h, 0:w]
    left = xs < w // 2
    checker = ((xs // 8 + ys // 8) % 2 == 0)
    albedo = np.empty((3, h, w))
    albedo[:, left] = np.array([0.6, 0.5, 0.4])[:, None]
    albedo[:, ~left & checker] = np.array([0.8, 0.8, 0.8])[:, None]
    albedo[:, ~left & ~checker] = np.array([0.2, 0.3, 0.6])[:, None]
    normal = np.empty((3, h, w))
    normal[:, left] = np.array([0.0, 0.0, 1.0])[:, None]
    normal[:, ~left] = (np.array([0.6, 0.0, 0.8]))[:, None]
    light = 2.0 - 1.0 * xs / w

    for k in range(args.passes):
        noise = rng.exponential(1.0, size=(h, w))
        beauty = albedo * light * noise
        channels = {}
        channels.update({f"ViewLayer.Combined.{c}": beauty[i].astype(np.float32)
                         for i, c in enumerate("RGB")})
        channels.update({f"ViewLayer.DiffCol.{c}": albedo[i].astype(np.float32)
                         for i, c in enumerate("RGB")})
        channels.update({f"ViewLayer.Normal.{c}": normal[i].astype(np.float32)
                         for i, c in enumerate("XYZ")})
        with OpenEXR.File(hd, channels) as f:
            f.write(os.path.join(args.out_dir, f"pass_{k}.exr"))


if __name__ == "__main__":
    main()
