"""Compares the Blender worker's passes, splatd's served image and a high-spp reference, for
tests/blender_worker.rs. Every file is read with OpenEXR's own Python package.

    python3 tests/py/blender_stats.py DIR PASSES

reads DIR/passes/pass_{0..PASSES-1}.exr (as Blender wrote them: RGB, or multilayer with the
beauty in `ViewLayer.Combined` and AOV layers beside it, in one part (Blender 3.x) or one part per
layer (Blender 4.x, 5.x)), DIR/served.exr (splatd's image.exr) and DIR/reference.exr (one render
with a 1-pixel box filter at many spp), and prints JSON:

* `served_vs_passes`: the largest |served mean - mean of the passes| over pixels and channels,
  and the largest such difference relative to the value;
* `layers`: the passes' layers other than the beauty, with their channels, as OpenEXR reads
  them from the first pass (what the frame should have declared);
* `aovs`: the passes' AOV channels (every channel outside the beauty), and `aovs_worst`, the
  largest |served - mean of the passes| over pixels and channels in units of
  `1e-6 * (1 + |mean|)` (the fixed point's step 2^-20, and float32's rounding of large depths):
  at most 1 when the server keeps exact means;
* `spp_min`, `spp_max`: of the served `spp.Y`;
* `global`, `lamp`, `edges`: for all pixels, the lamp's pixels (the reference's six brightest,
  where a fixed sub-pixel position is most biased) and the edges (the tenth of the other pixels
  where the reference changes most from a neighbour), the sum over the region of
  luminance(mean of passes - reference) and its standard deviation from the passes' own spread
  (plus the reference's, taken as the same per-sample spread over its spp). Sums over many
  pixels are compared, not single pixels: one pixel's 1-spp values are too skewed for a
  48-sample standard deviation to bound it.
"""

import json
import os
import sys

import numpy as np
import OpenEXR

LUMA = np.array([0.2126, 0.7152, 0.0722])


# The beauty's layer in a multilayer pass.
COMBINED = "ViewLayer.Combined."


def channels(path):
    """Every channel of every part, named as splatd names them: in a multi-part file the part's
    name comes first unless the channel's name already starts with it."""
    out = {}
    with OpenEXR.File(path, separate_channels=True) as f:
        multipart = len(f.parts) > 1
        for part in f.parts:
            prefix = part.name() if multipart else ""
            for name, c in part.channels.items():
                if prefix and not name.startswith(prefix + "."):
                    name = f"{prefix}.{name}"
                out[name] = np.asarray(c.pixels, dtype=np.float64)
    return out


def rgb(ch, prefix=""):
    return np.stack([ch[f"{prefix}{c}"] for c in "RGB"], axis=-1)


def main(d, passes, reference_spp):
    files = [channels(os.path.join(d, "passes", f"pass_{k}.exr")) for k in range(passes)]
    beauty = COMBINED if f"{COMBINED}R" in files[0] else ""
    stack = np.stack([rgb(ch, beauty) for ch in files])
    mean = stack.mean(axis=0)
    served_ch = channels(os.path.join(d, "served.exr"))
    served = rgb(served_ch, "mean.")
    spp = served_ch["spp.Y"]
    diff = np.abs(served - mean)
    rel = diff / np.maximum(np.abs(mean), 1e-30)
    aovs = sorted(n for n in files[0] if beauty and not n.startswith(beauty))
    layers = {}
    for name in aovs:
        layer, _, channel = name.rpartition(".")
        layers.setdefault(layer, []).append(channel)
    aovs_worst = 0.0
    for name in aovs:
        aov_mean = np.mean([ch[name] for ch in files], axis=0)
        off = np.abs(served_ch[name] - aov_mean) / (1e-6 * (1.0 + np.abs(aov_mean)))
        aovs_worst = max(aovs_worst, float(off.max()))

    reference = rgb(channels(os.path.join(d, "reference.exr")))
    luma_passes = stack @ LUMA  # (passes, H, W)
    per_pass_var = luma_passes.var(axis=0, ddof=1)
    var = per_pass_var / passes + per_pass_var / reference_spp
    delta = (mean - reference) @ LUMA

    def region(mask):
        return {"sum": float(delta[mask].sum()), "sigma": float(np.sqrt(var[mask].sum())),
                "pixels": int(mask.sum()), "reference": float((reference @ LUMA)[mask].sum())}

    ref_luma = reference @ LUMA
    lamp = ref_luma >= np.sort(ref_luma, axis=None)[-6]
    # Edges: the tenth of the pixels where the reference changes most to a neighbour.
    padded = np.pad(ref_luma, 1, mode="edge")
    h, w = ref_luma.shape
    step = np.zeros_like(ref_luma)
    for dy, dx in ((0, 1), (2, 1), (1, 0), (1, 2)):
        step = np.maximum(step, np.abs(padded[dy:dy + h, dx:dx + w] - ref_luma))
    edges = (step >= np.quantile(step, 0.9)) & ~lamp
    json.dump({
        "served_vs_passes": {"max_abs": float(diff.max()), "max_rel": float(rel.max())},
        "layers": layers, "aovs": aovs, "aovs_worst": aovs_worst,
        "spp_min": float(spp.min()), "spp_max": float(spp.max()),
        "global": region(np.ones_like(lamp)),
        "lamp": region(lamp),
        "edges": region(edges),
    }, sys.stdout)


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]), int(sys.argv[3]))
