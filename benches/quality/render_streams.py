#!/usr/bin/env python3
"""Render real path-traced per-sample streams (with fireflies) plus a ground truth.

Input data for splatd's estimator quality benchmark. Four small scenes are
defined inline (Python dicts, no external files) and rendered with Mitsuba 3's
unidirectional `path` integrator:

  caustic     Cornell-box-like room (diffuse walls) lit by a SMALL, bright area
              light on the ceiling; a glass (dielectric) sphere on the floor
              focuses a caustic. Caustic paths (diffuse -> specular -> light)
              can only be found by BSDF sampling, so they arrive as fireflies.
  smalllight  Diffuse room lit only by a tiny, very bright sphere emitter that a
              diffuse shade hides from the camera and from most of the room,
              plus rough-conductor (glossy) objects: glossy bounces of the tiny
              light seen from diffuse surfaces produce fireflies.
  slit        Not a Cornell box: a closed grey room lit only through a narrow
              slit in its ceiling by a small sun; glossy floor, chrome ball.
              Diffuse bounces that find the thin sunlit stripe are fireflies.
  pool        Not a room: glass on a terrace under a small sun and a dim sky;
              caustics through a glass ball and a slab (BSDF sampling only)
              and the sun seen in a near-mirror ball.

Every "pass" is one full-image render with spp=1, the `independent` sampler,
seed = pass index, and a box reconstruction filter, so each pixel of a pass is
exactly ONE Monte Carlo sample f(X)/p(X) of that pixel (RGB radiance).
The ground truth is the mean of --gt-spp further samples per pixel drawn with
seeds that do not overlap the passes (rendered in chunks of <= 256 spp, each
chunk its own seed; box filter => per-pixel mean of the samples).

Run (from the repository root):

    python3 benches/quality/render_streams.py [--out DIR] [--passes P] [--gt-spp G] [--res N]
        [--scenes caustic,smalllight,slit,pool] [--variant auto|llvm_ad_rgb|scalar_rgb]
        [--check-spp C] [--no-aovs]

The table in docs/ALGORITHM.md was measured on 64x64 streams of 1024 passes
(4 independent realizations of 256 spp for the benchmark):

    S=benches/quality/render_streams.py; O="--res 64 --passes 1024 --check-spp 1024"
    python3 $S $O --scenes pool --gt-spp 32768
    python3 $S $O --scenes slit,caustic,smalllight --gt-spp 8192
    cargo run --release --bin quality

The raw and denoised tables of issue 22 (docs/ALGORITHM.md, "The denoiser's input") were
measured on 128x128 streams with AOVs (about 600 MB per scene):

    S=benches/quality/render_streams.py; O="--res 128 --passes 1024 --check-spp 2048"
    python3 $S $O --scenes caustic,smalllight,slit --gt-spp 16384
    python3 $S $O --scenes pool --gt-spp 32768
    SPLATD_OIDN_LIB=$(bash tests/setup/oidn.sh) cargo run --release --bin quality

Requirements: see benches/quality/requirements.txt (pip install -r ...).
The fast `llvm_ad_rgb` variant needs a libLLVM that Dr.Jit can use: on Debian 12
`apt-get install -y libllvm19` works (LLVM 14, the default `llvm` package, aborts
with "Cannot select ... fminimum"). With --variant auto (default) the script
probes every libLLVM it finds (newest first, in a subprocess) and falls back to
`scalar_rgb` (about 2x slower) if none works. DRJIT_LIBLLVM_PATH, if set, is
tried first.

Output, per scene, in <out>/<scene>/ (default <out> = <repo>/bench-data, git-ignored):

  passes.f32  raw little-endian float32, shape (P, H, W, 3), C order (row-major):
              index [p, y, x, c]; y = 0 is the TOP image row; c = linear RGB
              (Rec.709 primaries, scene-referred radiance, not tone mapped).
              Pass p was rendered with seed p (p = 0..P-1), 1 sample per pixel.
  gt.f32      raw little-endian float32, shape (H, W, 3), same layout: the
              per-pixel mean of G = gt_spp independent samples.
  albedo.f32  (unless --no-aovs) raw little-endian float32, shape (P, H, W, 3), the
              layout of passes.f32: pass p's albedo at the same sample's primary hit
              (Mitsuba 3's `aov` integrator, `albedo`, wrapping the path integrator,
              which then draws exactly the samples it draws alone).
  normal.f32  (unless --no-aovs) the same for the shading normal (`sh_normal`, world
              space, components in [-1, 1]; 0 where the ray leaves the scene).
              These are the guides a denoiser (OIDN) takes; their per-pixel means
              over a run's passes are what a frame with AOVs holds. Streams
              rendered before the AOVs existed lack both files and stay readable.
  meta.json   {"scene", "width", "height", "passes", "gt_spp", "variant",
               "aovs" ({"albedo": "albedo.f32", "normal": "normal.f32"} or {}),
               "seconds" (total render time of the scene), "mean_luminance"
               (image mean of GT Rec.709 luminance), "max_sample_luminance"
               (max luminance over all pass samples), plus extra diagnostics:
               seeds, timings, firefly fractions, noise checks}.

Luminance is Rec.709: Y = 0.2126 R + 0.7152 G + 0.0722 B.

Sanity summary printed per scene: mean of all passes vs GT mean luminance (with
a standard error and z-score), the fraction of samples whose luminance exceeds
10x / 100x the pixel's GT luminance, render time, and noise checks: relMSE of
the GT against an independent check GT with --check-spp samples (default G/4;
0 disables), the GT's own relMSE estimated from its chunk-to-chunk spread, and
the mean relMSE of 16-spp images (16 consecutive passes) vs the GT.
relMSE = mean over pixels and channels of (x - ref)^2 / (ref^2 + 0.01).
"""

import argparse
import glob
import json
import os
import re
import subprocess
import sys
import time

import numpy as np

REC709 = np.array([0.2126, 0.7152, 0.0722], dtype=np.float64)
CHUNK_SPP = 256          # GT is rendered in chunks of at most this many spp
EPS_REL = 1e-2           # relMSE denominator guard

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))


# --------------------------------------------------------------------------
# Variant selection (done before importing mitsuba in this process)
# --------------------------------------------------------------------------

_PROBE = r"""
import mitsuba as mi
mi.set_variant('llvm_ad_rgb')
d = mi.cornell_box()
d['sensor']['film']['width'] = 16
d['sensor']['film']['height'] = 16
import numpy as np
a = np.array(mi.render(mi.load_dict(d), spp=2))
assert np.isfinite(a).all() and a.mean() > 0
print('OK')
"""


def _llvm_candidates():
    cands = []
    env = os.environ.get("DRJIT_LIBLLVM_PATH")
    if env:
        cands.append(env)
    found = set()
    for pat in ("/usr/lib/x86_64-linux-gnu/libLLVM*.so*", "/usr/lib/llvm-*/lib/libLLVM*.so*",
                "/usr/lib/aarch64-linux-gnu/libLLVM*.so*", "/usr/local/lib/libLLVM*.so*"):
        for p in glob.glob(pat):
            if os.path.isfile(p):
                found.add(os.path.realpath(p))

    def ver(p):
        m = re.search(r"libLLVM[-.]?(?:so\.)?(\d+)", os.path.basename(p))
        return int(m.group(1)) if m else 0

    cands += sorted(found, key=ver, reverse=True)
    out = []
    for c in cands:
        if c not in out:
            out.append(c)
    return out


def choose_variant(requested):
    """Return (variant, libllvm_path or None). Sets DRJIT_LIBLLVM_PATH if needed."""
    if requested == "scalar_rgb":
        return "scalar_rgb", None
    for lib in _llvm_candidates() + [None]:
        env = dict(os.environ)
        if lib:
            env["DRJIT_LIBLLVM_PATH"] = lib
        try:
            r = subprocess.run([sys.executable, "-c", _PROBE], env=env, capture_output=True,
                               text=True, timeout=300)
            ok = r.returncode == 0 and "OK" in r.stdout
        except subprocess.TimeoutExpired:
            ok = False
        print(f"[variant] probe llvm_ad_rgb with libLLVM={lib or '(drjit default)'}: "
              f"{'ok' if ok else 'FAILED'}", flush=True)
        if ok:
            if lib:
                os.environ["DRJIT_LIBLLVM_PATH"] = lib
            return "llvm_ad_rgb", lib
    if requested == "llvm_ad_rgb":
        sys.exit("llvm_ad_rgb requested but no working libLLVM found "
                 "(try: apt-get install -y libllvm19)")
    print("[variant] falling back to scalar_rgb", flush=True)
    return "scalar_rgb", None


# --------------------------------------------------------------------------
# Scenes
# --------------------------------------------------------------------------

def _room(mi, T, res, max_depth, white, red, green):
    """Cornell-box-like room: x,y in [-1,1], back wall z=-1, open towards camera."""
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": max_depth},
        "sensor": {
            "type": "perspective",
            "fov": 37.5, "fov_axis": "smaller",
            "near_clip": 0.001, "far_clip": 100.0,
            "to_world": T().look_at(origin=[0, 0, 3.9], target=[0, 0, 0], up=[0, 1, 0]),
            "sampler": {"type": "independent", "sample_count": 1, "seed": 0},
            "film": {"type": "hdrfilm", "width": res, "height": res,
                     "pixel_format": "rgb", "component_format": "float32",
                     "rfilter": {"type": "box"}},
        },
        "white": {"type": "diffuse", "reflectance": {"type": "rgb", "value": white}},
        "red": {"type": "diffuse", "reflectance": {"type": "rgb", "value": red}},
        "green": {"type": "diffuse", "reflectance": {"type": "rgb", "value": green}},
        "floor": {"type": "rectangle", "bsdf": {"type": "ref", "id": "white"},
                  "to_world": T().translate([0, -1, 0]).rotate([1, 0, 0], -90)},
        "ceiling": {"type": "rectangle", "bsdf": {"type": "ref", "id": "white"},
                    "to_world": T().translate([0, 1, 0]).rotate([1, 0, 0], 90)},
        "back": {"type": "rectangle", "bsdf": {"type": "ref", "id": "white"},
                 "to_world": T().translate([0, 0, -1])},
        "red-wall": {"type": "rectangle", "bsdf": {"type": "ref", "id": "red"},
                     "to_world": T().translate([-1, 0, 0]).rotate([0, 1, 0], 90)},
        "green-wall": {"type": "rectangle", "bsdf": {"type": "ref", "id": "green"},
                       "to_world": T().translate([1, 0, 0]).rotate([0, 1, 0], -90)},
    }


def scene_caustic(mi, res):
    T = mi.ScalarTransform4f
    d = _room(mi, T, res, 8,
              white=[0.80, 0.66, 0.62], red=[0.57, 0.043, 0.044], green=[0.105, 0.378, 0.076])
    # Small (0.09 x 0.09) bright ceiling light towards the back, so the caustic
    # of the sphere lands on the floor in front of it (visible to the camera).
    d["light"] = {
        "type": "rectangle",
        "to_world": T().translate([0.0, 0.99, -0.45]).rotate([1, 0, 0], 90).scale([0.045, 0.045, 1]),
        "bsdf": {"type": "ref", "id": "white"},
        "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [390.0, 300.0, 150.0]}},
    }
    d["glass-sphere"] = {
        "type": "sphere", "center": [0.1, -0.62, 0.15], "radius": 0.38,
        "bsdf": {"type": "dielectric", "int_ior": 1.5, "ext_ior": 1.0},
    }
    d["tall-box"] = {
        "type": "cube", "bsdf": {"type": "ref", "id": "white"},
        "to_world": T().translate([-0.55, -0.45, -0.55]).rotate([0, 1, 0], 18).scale([0.22, 0.55, 0.22]),
    }
    return d


def scene_smalllight(mi, res):
    T = mi.ScalarTransform4f
    d = _room(mi, T, res, 8,
              white=[0.75, 0.75, 0.72], red=[0.60, 0.12, 0.10], green=[0.15, 0.45, 0.20])
    # Tiny very bright sphere light, hidden under a diffuse shade (a thin slab
    # below it): it lights the ceiling/upper walls; the room is lit indirectly.
    d["tiny-light"] = {
        "type": "sphere", "center": [0.45, 0.50, -0.45], "radius": 0.015,
        "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [3600.0, 3200.0, 2600.0]}},
    }
    d["shade"] = {
        "type": "cube", "bsdf": {"type": "ref", "id": "white"},
        "to_world": T().translate([0.45, 0.42, -0.25]).scale([0.45, 0.012, 0.6]),
    }
    d["gold-sphere"] = {
        "type": "sphere", "center": [-0.45, -0.68, 0.05], "radius": 0.32,
        "bsdf": {"type": "roughconductor", "material": "Au", "distribution": "ggx", "alpha": 0.06},
    }
    d["alu-plate"] = {  # glossy plate leaning against the back wall
        "type": "rectangle",
        "to_world": T().translate([0.35, -0.55, -0.80]).rotate([1, 0, 0], -25).scale([0.45, 0.45, 1]),
        "bsdf": {"type": "roughconductor", "material": "Al", "distribution": "beckmann", "alpha": 0.12},
    }
    d["copper-box"] = {
        "type": "cube",
        "to_world": T().translate([0.45, -0.85, 0.3]).rotate([0, 1, 0], -20).scale([0.18, 0.15, 0.18]),
        "bsdf": {"type": "roughconductor", "material": "Cu", "distribution": "ggx", "alpha": 0.2},
    }
    return d


def scene_slit(mi, res):
    """A closed room lit only through a narrow slit in its ceiling by a small sun outside.

    Not a Cornell box: the camera is inside a closed grey room with a glossy floor. The sun's
    light enters through a slit 0.06 wide and paints a thin bright stripe on the floor; the rest
    of the room is lit by that stripe (diffuse bounces that find it by chance are fireflies) and
    by glossy floor reflections of the slit and the sun (found by BSDF sampling only when the
    floor's lobe is narrow).
    """
    T = mi.ScalarTransform4f
    grey = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.7, 0.68, 0.64]}}
    d = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 8},
        "sensor": {
            "type": "perspective", "fov": 70.0, "fov_axis": "smaller",
            "near_clip": 0.001, "far_clip": 100.0,
            "to_world": T().look_at(origin=[0.6, 0.2, 0.95], target=[-0.1, -0.45, -1.0],
                                    up=[0, 1, 0]),
            "sampler": {"type": "independent", "sample_count": 1, "seed": 0},
            "film": {"type": "hdrfilm", "width": res, "height": res,
                     "pixel_format": "rgb", "component_format": "float32",
                     "rfilter": {"type": "box"}},
        },
        "grey": grey,
        "floor": {"type": "rectangle",
                  "bsdf": {"type": "roughplastic", "distribution": "ggx", "alpha": 0.03,
                           "diffuse_reflectance": {"type": "rgb", "value": [0.35, 0.22, 0.12]}},
                  "to_world": T().translate([0, -1, 0]).rotate([1, 0, 0], -90)},
        # The ceiling leaves a slit x in [0, 0.06], the whole depth of the room.
        "ceiling-left": {"type": "rectangle", "bsdf": {"type": "ref", "id": "grey"},
                         "to_world": T().translate([-0.5, 1, 0]).rotate([1, 0, 0], 90)
                         .scale([0.5, 1, 1])},
        "ceiling-right": {"type": "rectangle", "bsdf": {"type": "ref", "id": "grey"},
                          "to_world": T().translate([0.53, 1, 0]).rotate([1, 0, 0], 90)
                          .scale([0.47, 1, 1])},
        "back": {"type": "rectangle", "bsdf": {"type": "ref", "id": "grey"},
                 "to_world": T().translate([0, 0, -1])},
        "front": {"type": "rectangle", "bsdf": {"type": "ref", "id": "grey"},
                  "to_world": T().translate([0, 0, 1]).rotate([0, 1, 0], 180)},
        "left": {"type": "rectangle", "bsdf": {"type": "ref", "id": "grey"},
                 "to_world": T().translate([-1, 0, 0]).rotate([0, 1, 0], 90)},
        "right": {"type": "rectangle", "bsdf": {"type": "ref", "id": "grey"},
                  "to_world": T().translate([1, 0, 0]).rotate([0, 1, 0], -90)},
        "sun": {"type": "sphere", "center": [-1.0, 5.0, 0.3], "radius": 0.2,
                "emitter": {"type": "area",
                            "radiance": {"type": "rgb", "value": [4000.0, 3600.0, 3000.0]}}},
        "chrome-ball": {"type": "sphere", "center": [-0.5, -0.75, -0.4], "radius": 0.25,
                        "bsdf": {"type": "roughconductor", "material": "Cr",
                                 "distribution": "ggx", "alpha": 0.02}},
        "block": {"type": "cube", "bsdf": {"type": "ref", "id": "grey"},
                  "to_world": T().translate([0.45, -0.7, -0.5]).rotate([0, 1, 0], 25)
                  .scale([0.25, 0.3, 0.25])},
    }
    return d


def scene_pool(mi, res):
    """Glass on a terrace under a small sun and a dim sky.

    Not a Cornell box: an open ground plane seen from above at an angle, a glass sphere and a
    glass slab throwing caustics on it (diffuse -> glass -> sun: only BSDF sampling finds the
    sun through glass, so every caustic sample is a firefly), and the caustics also seen
    through the glass; a near-mirror metal sphere shows the tiny sun.
    """
    T = mi.ScalarTransform4f
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 10},
        "sensor": {
            "type": "perspective", "fov": 40.0, "fov_axis": "smaller",
            "near_clip": 0.001, "far_clip": 100.0,
            "to_world": T().look_at(origin=[0.0, 2.6, 4.2], target=[0.0, 0.0, 0.2],
                                    up=[0, 1, 0]),
            "sampler": {"type": "independent", "sample_count": 1, "seed": 0},
            "film": {"type": "hdrfilm", "width": res, "height": res,
                     "pixel_format": "rgb", "component_format": "float32",
                     "rfilter": {"type": "box"}},
        },
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [0.05, 0.07, 0.1]}},
        "sun": {"type": "sphere", "center": [-3.0, 14.0, -7.0], "radius": 1.0,
                "emitter": {"type": "area",
                            "radiance": {"type": "rgb", "value": [1100.0, 1000.0, 850.0]}}},
        "ground": {"type": "rectangle",
                   "bsdf": {"type": "diffuse",
                            "reflectance": {"type": "checkerboard",
                                            "color0": {"type": "rgb", "value": [0.55, 0.5, 0.45]},
                                            "color1": {"type": "rgb", "value": [0.3, 0.3, 0.32]},
                                            "to_uv": T().scale([6, 6, 1])}},
                   "to_world": T().rotate([1, 0, 0], -90).scale([4, 4, 1])},
        "glass-ball": {"type": "sphere", "center": [-0.6, 0.5, -0.2], "radius": 0.5,
                       "bsdf": {"type": "dielectric", "int_ior": 1.5, "ext_ior": 1.0}},
        "glass-slab": {"type": "cube",
                       "bsdf": {"type": "dielectric", "int_ior": 1.33, "ext_ior": 1.0},
                       "to_world": T().translate([0.7, 0.35, 0.1]).rotate([0, 1, 0], 30)
                       .rotate([1, 0, 0], 20).scale([0.35, 0.35, 0.08])},
        "steel-ball": {"type": "sphere", "center": [0.3, 0.25, 1.0], "radius": 0.25,
                       "bsdf": {"type": "roughconductor", "material": "Cr",
                                "distribution": "ggx", "alpha": 0.05}},
    }


SCENES = {"caustic": scene_caustic, "smalllight": scene_smalllight, "slit": scene_slit,
          "pool": scene_pool}


# --------------------------------------------------------------------------
# Rendering + checks
# --------------------------------------------------------------------------

def luminance(rgb):
    return np.tensordot(np.asarray(rgb, dtype=np.float64), REC709, axes=([-1], [0]))


def rel_mse(x, ref):
    x = np.asarray(x, np.float64)
    ref = np.asarray(ref, np.float64)
    return float(np.mean((x - ref) ** 2 / (ref ** 2 + EPS_REL)))


AOV_SPEC = "albedo:albedo,nn:sh_normal"   # Mitsuba's aov integrator: RGB, albedo, normal


def render_scene(mi, dr, name, args, variant):
    res = args.res
    d = SCENES[name](mi, res)
    scene = mi.load_dict(d)
    aovs = not args.no_aovs
    # Passes with AOVs: the aov integrator wraps the scene's own integrator; its first three
    # channels are that integrator's radiance from the same random numbers (checked: identical
    # means), then albedo and the shading normal.
    pass_scene = scene
    if aovs:
        pass_scene = mi.load_dict({**d, "integrator": {"type": "aov", "aovs": AOV_SPEC,
                                                       "integrator": d["integrator"]}})
    H = W = res
    P, G = args.passes, args.gt_spp
    outdir = os.path.join(args.out, name)
    os.makedirs(outdir, exist_ok=True)

    def render(spp, seed, which=scene, channels=3):
        s = dr.opaque(mi.UInt32, seed) if variant != "scalar_rgb" else seed
        img = np.array(mi.render(which, spp=spp, seed=s), dtype=np.float32)
        assert img.shape == (H, W, channels), img.shape
        return img

    # seeds: passes 0..P-1, GT chunks P.., check chunks after those (disjoint).
    gt_chunks = [CHUNK_SPP] * (G // CHUNK_SPP) + ([G % CHUNK_SPP] if G % CHUNK_SPP else [])
    C = args.check_spp if args.check_spp >= 0 else G // 4
    ck_chunks = [CHUNK_SPP] * (C // CHUNK_SPP) + ([C % CHUNK_SPP] if C % CHUNK_SPP else [])
    gt_seed0 = P
    ck_seed0 = P + len(gt_chunks)

    render(1, 0)  # warm-up: JIT compilation is not counted as render time
    if aovs:
        render(1, 0, pass_scene, 9)
    t_start = time.time()

    # ---- passes: one sample per pixel each (with its albedo and normal)
    passes = np.empty((P, H, W, 3), dtype=np.float32)
    albedo = np.empty((P, H, W, 3), dtype=np.float32) if aovs else None
    normal = np.empty((P, H, W, 3), dtype=np.float32) if aovs else None
    t0 = time.time()
    for p in range(P):
        if aovs:
            img = render(1, p, pass_scene, 9)
            passes[p], albedo[p], normal[p] = img[..., 0:3], img[..., 3:6], img[..., 6:9]
        else:
            passes[p] = render(1, p)
    t_passes = time.time() - t0
    passes.astype("<f4", copy=False).tofile(os.path.join(outdir, "passes.f32"))
    aov_files = {}
    if aovs:
        for key, arr in (("albedo", albedo), ("normal", normal)):
            aov_files[key] = f"{key}.f32"
            arr.astype("<f4", copy=False).tofile(os.path.join(outdir, aov_files[key]))
        del albedo, normal

    # ---- ground truth: weighted mean of chunk means
    t0 = time.time()
    chunk_means = []
    gt_sum = np.zeros((H, W, 3), np.float64)
    for k, spp in enumerate(gt_chunks):
        img = render(spp, gt_seed0 + k)
        chunk_means.append((spp, img))
        gt_sum += img.astype(np.float64) * spp
    gt = gt_sum / G
    t_gt = time.time() - t0
    gt.astype("<f4").tofile(os.path.join(outdir, "gt.f32"))

    # ---- independent check GT (noise of the GT)
    t0 = time.time()
    check = None
    if C > 0:
        ck_sum = np.zeros((H, W, 3), np.float64)
        for k, spp in enumerate(ck_chunks):
            ck_sum += render(spp, ck_seed0 + k).astype(np.float64) * spp
        check = ck_sum / C
    t_check = time.time() - t0
    seconds = time.time() - t_start

    # ---- statistics
    lum_s = luminance(passes)                       # (P,H,W)
    lum_gt = luminance(gt)                          # (H,W)
    pass_img_means = lum_s.mean(axis=(1, 2))        # (P,)
    mean_passes = float(pass_img_means.mean())
    se_passes = float(pass_img_means.std(ddof=1) / np.sqrt(P)) if P > 1 else float("nan")
    mean_gt = float(lum_gt.mean())
    z = (mean_passes - mean_gt) / se_passes if se_passes > 0 else float("nan")
    valid = lum_gt > 1e-4
    n_valid = int(valid.sum())
    ff = {}
    for k in (10, 100):
        over = lum_s > k * lum_gt[None]
        ff[f"frac_over_{k}x_gt"] = float(over[:, valid].mean()) if n_valid else float("nan")
    max_lum = float(lum_s.max())
    nonfinite = int((~np.isfinite(passes)).sum())
    # share of image energy carried by the >10x samples
    over10 = (lum_s > 10 * lum_gt[None]) & valid[None]
    energy_share_10x = float(lum_s[over10].sum() / max(lum_s[:, valid].sum(), 1e-30))

    relmse_16 = None
    if P >= 16:
        groups = P // 16
        relmse_16 = float(np.mean([rel_mse(passes[g * 16:(g + 1) * 16].mean(axis=0), gt)
                                   for g in range(groups)]))
    relmse_gt_chunks = None
    if len(chunk_means) >= 2 and all(s == chunk_means[0][0] for s, _ in chunk_means):
        stack = np.stack([img for _, img in chunk_means]).astype(np.float64)
        var_gt = stack.var(axis=0, ddof=1) / len(chunk_means)
        relmse_gt_chunks = float(np.mean(var_gt / (gt ** 2 + EPS_REL)))
    relmse_check = rel_mse(check, gt) if check is not None else None
    # E[relMSE(check, gt)] ~ relvar(gt) * (1 + G/C)  => GT's own relMSE estimate
    relmse_gt_from_check = relmse_check / (1 + G / C) if check is not None else None

    meta = {
        "scene": name, "width": W, "height": H, "passes": P, "gt_spp": G,
        "variant": variant, "seconds": round(seconds, 3), "aovs": aov_files,
        "mean_luminance": mean_gt, "max_sample_luminance": max_lum,
        "dtype": "float32 little-endian", "passes_shape": [P, H, W, 3], "gt_shape": [H, W, 3],
        "layout": "row-major [p][y][x][rgb], y=0 is the top row, linear Rec.709 RGB radiance",
        "pass_seeds": [0, P - 1], "spp_per_pass": 1, "rfilter": "box", "sampler": "independent",
        "integrator": d["integrator"],
        "gt_chunk_spp": gt_chunks, "gt_seeds": [gt_seed0, gt_seed0 + len(gt_chunks) - 1],
        "check_spp": C,
        "check_seeds": [ck_seed0, ck_seed0 + len(ck_chunks) - 1] if C > 0 else None,
        "seconds_passes": round(t_passes, 3), "seconds_gt": round(t_gt, 3),
        "seconds_check": round(t_check, 3),
        "mean_luminance_passes": mean_passes, "mean_luminance_passes_stderr": se_passes,
        "nonfinite_values": nonfinite, "pixels_with_gt_lum_gt_1e-4": n_valid,
        **ff, "energy_share_of_over_10x_samples": energy_share_10x,
        "relmse_16spp_vs_gt": relmse_16,
        "relmse_gt_est_from_chunks": relmse_gt_chunks,
        "relmse_check_vs_gt": relmse_check, "relmse_gt_est_from_check": relmse_gt_from_check,
        "relmse_eps": EPS_REL,
        "mitsuba_version": mi.__version__, "libllvm": os.environ.get("DRJIT_LIBLLVM_PATH"),
    }
    with open(os.path.join(outdir, "meta.json"), "w") as f:
        json.dump(meta, f, indent=2)

    def fmt(x):
        return "n/a" if x is None else f"{x:.3g}"

    print(f"\n== {name}: {W}x{H}, {P} passes, GT {G} spp, check {C} spp ({variant})")
    print(f"   render time: {seconds:.1f}s (passes {t_passes:.1f}s, GT {t_gt:.1f}s, "
          f"check {t_check:.1f}s)")
    print(f"   mean luminance: passes {mean_passes:.5f} +- {se_passes:.5f}, GT {mean_gt:.5f} "
          f"(z = {z:+.2f})")
    print(f"   GT luminance percentiles 5/50/95%: "
          f"{np.percentile(lum_gt, 5):.4f} / {np.percentile(lum_gt, 50):.4f} / "
          f"{np.percentile(lum_gt, 95):.4f}")
    print(f"   fireflies: {ff['frac_over_10x_gt']:.3e} of samples > 10x pixel GT, "
          f"{ff['frac_over_100x_gt']:.3e} > 100x; they carry {energy_share_10x:.1%} of the energy; "
          f"max sample luminance {max_lum:.4g}; non-finite values {nonfinite}")
    print(f"   relMSE: 16-spp vs GT {fmt(relmse_16)}; GT itself ~{fmt(relmse_gt_chunks)} (chunks), "
          f"~{fmt(relmse_gt_from_check)} (check); check({C})-vs-GT {fmt(relmse_check)}")
    warn = []
    if abs(z) > 4:
        warn.append("passes mean and GT mean disagree by more than 4 sigma")
    if ff["frac_over_10x_gt"] < 1e-4:
        warn.append("hardly any fireflies")
    if relmse_16 is not None and relmse_gt_chunks is not None and relmse_gt_chunks > 0.1 * relmse_16:
        warn.append("GT noise is not << 16-spp noise")
    if not (0.02 <= mean_gt <= 2.0):
        warn.append("unusual mean brightness")
    if nonfinite:
        warn.append("non-finite sample values")
    for w in warn:
        print(f"   WARNING: {w}")
    for fn in ("passes.f32", "gt.f32", "meta.json", *aov_files.values()):
        print(f"   {os.path.join(outdir, fn)}: {os.path.getsize(os.path.join(outdir, fn))} bytes")
    return meta


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default=os.path.join(REPO, "bench-data"))
    ap.add_argument("--passes", type=int, default=256)
    ap.add_argument("--gt-spp", type=int, default=4096)
    ap.add_argument("--check-spp", type=int, default=-1,
                    help="spp of the independent check GT (default gt_spp/4; 0 = skip)")
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--variant", default="auto", choices=["auto", "llvm_ad_rgb", "scalar_rgb"])
    ap.add_argument("--no-aovs", action="store_true",
                    help="skip albedo.f32 and normal.f32 (the denoiser's guides)")
    args = ap.parse_args()
    names = [s for s in args.scenes.split(",") if s]
    for s in names:
        if s not in SCENES:
            ap.error(f"unknown scene {s!r}; known: {', '.join(SCENES)}")
    if args.passes < 1 or args.gt_spp < 1 or args.res < 1:
        ap.error("--passes, --gt-spp and --res must be >= 1")

    variant, lib = choose_variant(args.variant)
    import drjit as dr
    import mitsuba as mi
    mi.set_variant(variant)
    print(f"[variant] using {variant}" + (f" (libLLVM {lib})" if lib else "")
          + f", mitsuba {mi.__version__}, drjit {dr.__version__}", flush=True)

    t0 = time.time()
    for name in names:
        render_scene(mi, dr, name, args, variant)
    print(f"\ntotal wall time {time.time() - t0:.1f}s; data in {args.out}")


if __name__ == "__main__":
    main()
