"""Writes passes in the layouts renderers use, with OpenEXR's own Python package, for
tests/passes_layouts.rs.

    python3 tests/py/write_layouts.py OUT_DIR --width 37 --height 23 --seed 7

For every file, `manifest.json` says what a reader must make of it:

* `layer`: the layer the beauty must be read from (found automatically, or named by `ask`);
  `raw` then holds the beauty's R, G, B as OpenEXR itself reads them back from the file
  (little-endian float32, height x width x 3), so lossy compressions are compared with the
  reference decoder's output, not with the values before compression;
* `error`: the pass must be refused, with a message containing each of `mentions`.

Every file holds other layers beside the beauty, with other values, so a reader that takes the
wrong layer is caught.
"""

import argparse
import json
import os

import numpy as np
import OpenEXR


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out_dir")
    parser.add_argument("--width", type=int, default=37)
    parser.add_argument("--height", type=int, default=23)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    os.makedirs(args.out_dir, exist_ok=True)
    rng = np.random.default_rng(args.seed)
    h, w = args.height, args.width
    entries = []

    def values(dtype=np.float32, scale=1.0):
        v = rng.lognormal(-1.0, 1.5, size=(h, w)) * scale
        v[rng.random((h, w)) < 0.02] *= 1000.0
        return np.minimum(v, 60000.0).astype(dtype)

    def rgb(prefix, dtype=np.float32):
        if dtype == np.uint32:
            return {f"{prefix}{c}": np.floor(values(np.float64, 100.0)).astype(np.uint32)
                    for c in "RGB"}
        return {f"{prefix}{c}": values(dtype) for c in "RGB"}

    def header(compression=OpenEXR.ZIP_COMPRESSION, tiled=None):
        hd = {"compression": compression, "type": OpenEXR.scanlineimage}
        if tiled:
            tiles = OpenEXR.TileDescription()
            tiles.xSize, tiles.ySize = tiled
            tiles.mode = OpenEXR.ONE_LEVEL
            hd["type"] = OpenEXR.tiledimage
            hd["tiles"] = tiles
        return hd

    def read_back(path, part, prefix):
        """The beauty as OpenEXR reads it: the reference decoder's values."""
        with OpenEXR.File(path, separate_channels=True) as f:
            channels = f.parts[part].channels
            planes = [np.asarray(channels[f"{prefix}{c}"].pixels).astype(np.float32)
                      for c in "RGB"]
        return np.stack(planes, axis=-1)

    def expect(name, path, layer, part, prefix, ask=None):
        raw = os.path.join(args.out_dir, f"{name}.f32")
        read_back(path, part, prefix).astype("<f4").tofile(raw)
        entries.append({"name": name, "exr": path, "layer": layer, "ask": ask, "raw": raw})

    def refuse(name, path, mentions, ask=None):
        entries.append({"name": name, "exr": path, "error": True, "mentions": mentions,
                        "ask": ask})

    def write(name, hd, channels):
        path = os.path.join(args.out_dir, f"{name}.exr")
        with OpenEXR.File(hd, channels) as f:
            f.write(path)
        return path

    def write_parts(name, parts):
        path = os.path.join(args.out_dir, f"{name}.exr")
        with OpenEXR.File([OpenEXR.Part(hd, ch, part) for part, hd, ch in parts]) as f:
            f.write(path)
        return path

    # Single part, prefixed layers: the beauty is the layer named `beauty` (not the first RGB).
    channels = {**rgb("albedo."), **rgb("beauty.", np.float16),
                "depth.Z": values(), "beauty.A": np.ones((h, w), np.float16)}
    path = write("prefixed", header(OpenEXR.PIZ_COMPRESSION), channels)
    expect("prefixed", path, "beauty", 0, "beauty.")
    # ... and any of its RGB layers when named.
    expect("prefixed-asked", path, "albedo", 0, "albedo.", ask="albedo")
    refuse("prefixed-unknown", path, ["no layer \"normal\"", "\"albedo\" (B, G, R)",
                                       "\"beauty\" (A, B, G, R)", "\"depth\" (Z)"],
           ask="normal")
    refuse("prefixed-not-rgb", path, ["layer \"depth\" (Z) cannot be the beauty"], ask="depth")

    # Blender/Cycles OPEN_EXR_MULTILAYER: one part, <view layer>.<pass>.<channel>, half floats.
    cycles = {**rgb("ViewLayer.Combined.", np.float16),
              "ViewLayer.Combined.A": np.ones((h, w), np.float16),
              **rgb("ViewLayer.DiffCol.", np.float16),
              "ViewLayer.Depth.Z": values(),
              **{f"ViewLayer.Normal.{c}": values(np.float16) for c in "XYZ"},
              **rgb("ViewLayer.Noisy Image.", np.float16)}
    path = write("cycles", header(OpenEXR.ZIP_COMPRESSION), cycles)
    expect("cycles", path, "ViewLayer.Combined", 0, "ViewLayer.Combined.")
    expect("cycles-noisy", path, "ViewLayer.Noisy Image", 0, "ViewLayer.Noisy Image.",
           ask="ViewLayer.Noisy Image")
    # Two view layers: both are `<view layer>.Combined`, so the caller has to choose.
    two = {**cycles, **rgb("Background.Combined.", np.float16)}
    path = write("cycles-two-views", header(OpenEXR.ZIPS_COMPRESSION), two)
    refuse("cycles-two-views", path, ["several layers that could be the beauty",
                                      "\"Background.Combined\"", "\"ViewLayer.Combined\""])
    expect("cycles-two-views-asked", path, "Background.Combined", 0, "Background.Combined.",
           ask="Background.Combined")

    # Multi-part: an RGB AOV part first, the beauty in a part named `beauty`, a depth part.
    parts = [("albedo", header(), rgb("")),
             ("beauty", header(OpenEXR.PIZ_COMPRESSION), {**rgb("", np.float16)}),
             ("depth", header(), {"Z": values()})]
    path = write_parts("multipart", parts)
    expect("multipart", path, "beauty", 1, "")
    expect("multipart-asked", path, "albedo", 0, "", ask="albedo")
    # Multi-part with prefixed channels (`rgba` part holding `rgba.R` ...) after an AOV part.
    parts = [("normal", header(), {f"normal.{c}": values() for c in "XYZ"}),
             ("rgba", header(OpenEXR.RLE_COMPRESSION), rgb("rgba.", np.uint32))]
    path = write_parts("multipart-prefixed", parts)
    expect("multipart-prefixed", path, "rgba", 1, "rgba.")

    # Tiled, tiles that do not divide the image, beside an RGB AOV.
    channels = {**rgb(""), **rgb("specular.")}
    path = write("tiled", header(OpenEXR.ZIP_COMPRESSION, tiled=(16, 8)), channels)
    expect("tiled", path, "", 0, "")
    path = write("tiled-piz-half", header(OpenEXR.PIZ_COMPRESSION, tiled=(7, 5)),
                 rgb("", np.float16))
    expect("tiled-piz-half", path, "", 0, "")
    parts = [("diffuse", header(tiled=(8, 8)), rgb("")),
             ("Combined", header(OpenEXR.B44_COMPRESSION, tiled=(32, 4)), rgb("", np.float16))]
    path = write_parts("tiled-multipart", parts)
    expect("tiled-multipart", path, "Combined", 1, "")

    # Only one RGB layer, whatever its name.
    path = write("only-rgb", header(), {**rgb("direct."), "depth.Z": values()})
    expect("only-rgb", path, "direct", 0, "direct.")

    # No beauty: no RGB layer at all, or several AOVs none of which is named like a beauty.
    path = write("no-rgb", header(), {"depth.Z": values(),
                                      **{f"normal.{c}": values() for c in "XYZ"}})
    refuse("no-rgb", path, ["no layer with channels R, G and B",
                            "\"depth\" (Z)", "\"normal\" (X, Y, Z)"])
    path = write("aovs-only", header(), {**rgb("albedo."), **rgb("emission.")})
    refuse("aovs-only", path, ["several layers that could be the beauty", "\"albedo\"",
                               "\"emission\""])

    # Every compression, with a float, a half and a uint channel in one file.
    mixed = {"R": values(np.float32), "G": values(np.float16),
             "B": np.floor(values(np.float64, 100.0)).astype(np.uint32),
             "A": np.ones((h, w), np.float16)}
    for name, compression in [("none", OpenEXR.NO_COMPRESSION),
                              ("rle", OpenEXR.RLE_COMPRESSION),
                              ("zips", OpenEXR.ZIPS_COMPRESSION),
                              ("zip", OpenEXR.ZIP_COMPRESSION),
                              ("piz", OpenEXR.PIZ_COMPRESSION),
                              ("pxr24", OpenEXR.PXR24_COMPRESSION),
                              ("b44", OpenEXR.B44_COMPRESSION),
                              ("b44a", OpenEXR.B44A_COMPRESSION),
                              ("dwaa", OpenEXR.DWAA_COMPRESSION),
                              ("dwab", OpenEXR.DWAB_COMPRESSION)]:
        path = write(f"compression-{name}", header(compression), mixed)
        expect(f"compression-{name}", path, "", 0, "")
    # OpenEXR 3.3's ZSTD is not one the `exr` crate reads: refused, saying so.
    path = write("compression-zstd", header(OpenEXR.ZSTD_COMPRESSION), mixed)
    refuse("compression-zstd", path, ["could not read the OpenEXR pass",
                                      "unknown compression method"])

    manifest = {"width": w, "height": h, "files": entries}
    with open(os.path.join(args.out_dir, "manifest.json"), "w") as f:
        json.dump(manifest, f, indent=1)


if __name__ == "__main__":
    main()
