"""Writes passes with AOVs beside the beauty, with OpenEXR's own Python package, for
tests/aov_passes.rs.

    python3 tests/py/write_aov_passes.py OUT_DIR --width 29 --height 17 --passes 8 --seed 3

Pass k is `pass_K.exr`: even passes in Cycles' single-part multilayer layout (half-float
`ViewLayer.Combined.R/G/B/A`, `ViewLayer.DiffCol.R/G/B`, `ViewLayer.Normal.X/Y/Z`, float
`ViewLayer.Depth.Z`), odd passes as one part per layer (parts named `ViewLayer.Combined`,
`ViewLayer.DiffCol`, ... with unprefixed channels), so both layouts feed the same AOVs. Depth is
1e10 (Cycles' background) in a few pixels and normals are negative in half of them.

Also written:
* `expected.f64`: per AOV channel, in the order DiffCol R, G, B, Normal X, Y, Z, Depth Z, the
  numpy mean over the passes of the values OpenEXR reads back from the files (little-endian
  float64, channels x height x width);
* `plain.exr`: a beauty-only pass (`R`, `G`, `B`), which carries no AOVs;
* `partial.exr`: a beauty and DiffCol only (the other AOVs missing);
* `bad_depth.exr`: a full pass whose depth at pixel (3, 2) is infinite.
"""

import argparse
import os

import numpy as np
import OpenEXR

AOVS = [("ViewLayer.DiffCol", "RGB"), ("ViewLayer.Normal", "XYZ"), ("ViewLayer.Depth", "Z")]


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("out_dir")
    p.add_argument("--width", type=int, default=29)
    p.add_argument("--height", type=int, default=17)
    p.add_argument("--passes", type=int, default=8)
    p.add_argument("--seed", type=int, default=3)
    args = p.parse_args()
    os.makedirs(args.out_dir, exist_ok=True)
    rng = np.random.default_rng(args.seed)
    h, w = args.height, args.width
    hd = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}

    def layers():
        beauty = rng.lognormal(-1.0, 1.5, size=(3, h, w))
        beauty[:, rng.random((h, w)) < 0.02] *= 1000.0
        depth = rng.uniform(0.5, 40.0, size=(h, w)).astype(np.float32)
        depth[rng.random((h, w)) < 0.1] = 1e10
        normal = rng.normal(size=(3, h, w))
        normal /= np.linalg.norm(normal, axis=0)
        return {
            "ViewLayer.Combined": dict(zip("RGB", beauty.astype(np.float16)),
                                       A=np.ones((h, w), np.float16)),
            "ViewLayer.DiffCol": dict(zip("RGB", rng.uniform(0, 1, (3, h, w)).astype(np.float16))),
            "ViewLayer.Normal": dict(zip("XYZ", normal.astype(np.float16))),
            "ViewLayer.Depth": {"Z": depth},
        }

    def single_part(path, ls):
        channels = {f"{name}.{c}": v for name, chans in ls.items() for c, v in chans.items()}
        with OpenEXR.File(hd, channels) as f:
            f.write(path)

    def multi_part(path, ls):
        parts = [OpenEXR.Part(dict(hd), chans, name) for name, chans in ls.items()]
        with OpenEXR.File(parts) as f:
            f.write(path)

    def read_aovs(path):
        """The AOV channels as OpenEXR reads them back, in the declared order."""
        planes = []
        with OpenEXR.File(path, separate_channels=True) as f:
            by_name = {}
            for part in f.parts:
                for name, ch in part.channels.items():
                    full = name if part.name() in ("", None) or name.startswith(part.name()) \
                        else f"{part.name()}.{name}"
                    by_name[full] = np.asarray(ch.pixels, np.float64)
        for layer, chans in AOVS:
            planes.extend(by_name[f"{layer}.{c}"] for c in chans)
        return np.stack(planes)

    total = np.zeros((7, h, w))
    for k in range(args.passes):
        path = os.path.join(args.out_dir, f"pass_{k}.exr")
        (single_part if k % 2 == 0 else multi_part)(path, layers())
        total += read_aovs(path)
    (total / args.passes).astype("<f8").tofile(os.path.join(args.out_dir, "expected.f64"))

    ls = layers()
    with OpenEXR.File(hd, dict(ls["ViewLayer.Combined"])) as f:
        f.write(os.path.join(args.out_dir, "plain.exr"))
    single_part(os.path.join(args.out_dir, "partial.exr"),
                {k: v for k, v in ls.items() if k in ("ViewLayer.Combined", "ViewLayer.DiffCol")})
    ls["ViewLayer.Depth"]["Z"][2, 3] = np.inf
    single_part(os.path.join(args.out_dir, "bad_depth.exr"), ls)


if __name__ == "__main__":
    main()
