#!/usr/bin/env python3
"""Need-guided against uniform sampling with real Mitsuba renders, at the same total samples.

For each scene of render_streams.py asked for, each budget (in samples per pixel) and each
realization, the benchmark renders two frames on a real `splatd serve` that it starts on
127.0.0.1:

  uniform   `spp` whole 1-spp passes (the Mitsuba worker's plain mode);
  guided    the same number of samples spent by the Mitsuba worker's guided mode
            (`mitsuba_worker.run_guided`: a uniform warm-up, then rounds that ask the server
            for the need map and render crop windows of the tiles it ranks neediest), once per
            policy of --policies;

then reads each frame's reweighted image back (`image.exr`, OpenEXR's Python package) and
scores it against the scene's high-spp ground truth (gt.f32 of render_streams.py) with the
quality benchmark's relMSE: the mean over pixels and channels of (x - ref)^2 / (ref^2 + 0.01).
It prints one table: the relMSE of uniform's plain mean (no reweighting) for scale, of uniform's
reweighted image, of each guided policy's, and guided / uniform (below 1: guided wins), all
averaged over the realizations, plus how many realizations guided won.

Every render draws random numbers of its own, disjoint from every other render's and from the
ground truth's (checked against its meta.json), so all samples are independent.

Run from the repository root (the ground truths are rendered first when missing; at 64x64 and
8192 spp that takes a few minutes per scene):

    cargo build --bin splatd     # debug or release: the relMSE does not depend on it
    python3 benches/quality/guided.py --scenes caustic,slit,smalllight --res 64 --spp 16,64 \
        --realizations 8

Requirements: benches/quality/requirements.txt and tests/requirements.txt (OpenEXR).
"""

import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.abspath(os.path.join(HERE, "..", ".."))
sys.path.insert(0, os.path.join(REPO, "proto", "python"))
sys.path.insert(0, HERE)

import OpenEXR  # noqa: E402
import splatd_client as sc  # noqa: E402
import mitsuba_worker as mw  # noqa: E402

# Run k (a frame) of this benchmark draws the random numbers of passes FIRST_PASS + k * stride
# onwards (see mitsuba_worker.Poster), where stride is four times the largest budget's passes:
# a guided run of P passes' samples uses at most that (each render rounds its start up to a
# multiple of its size, each batch to a whole pass).
FIRST_PASS = 1000


def start_server(binary):
    """`splatd serve` on 127.0.0.1:0; returns (process, url) once it printed its address."""
    proc = subprocess.Popen(
        [binary, "serve", "--addr", "127.0.0.1:0"],
        stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
        env=dict(os.environ, RUST_LOG="warn"),
    )
    line = proc.stdout.readline().strip()
    prefix = "splatd listening on "
    if not line.startswith(prefix):
        proc.kill()
        sys.exit(f"{binary} did not report its address; its first line was {line!r}")
    return proc, line[len(prefix):]


def reweighted(client, frame, width, height):
    """The frame's reweighted RGB (the EXR's unprefixed R, G, B) as (H, W, 3) float64."""
    data = client.image(frame)
    path = f"/tmp/splatd-guided-{os.getpid()}.exr"
    with open(path, "wb") as f:
        f.write(data)
    try:
        with OpenEXR.File(path, separate_channels=True) as exr:
            channels = exr.channels()
            planes = [np.asarray(channels[c].pixels, dtype=np.float64) for c in ("R", "G", "B")]
            means = [np.asarray(channels[f"mean.{c}"].pixels, dtype=np.float64) for c in "RGB"]
    finally:
        os.remove(path)
    rgb = np.stack(planes, axis=-1).reshape(height, width, 3)
    return rgb, np.stack(means, axis=-1).reshape(height, width, 3)


def rel_mse(x, ref):
    return float(np.mean((x - ref) ** 2 / (ref ** 2 + 1e-2)))


def parse_policy(text):
    """`warmup:rounds:uniform_share:base_doubt`, e.g. `0.25:6:0.25:0.5` (see run_guided)."""
    try:
        warmup, rounds, share, doubt = text.split(":")
        return {"warmup": float(warmup), "rounds": int(rounds), "uniform_share": float(share),
                "base_doubt": float(doubt)}
    except ValueError:
        raise argparse.ArgumentTypeError(f"policy {text!r} is not WARMUP:ROUNDS:UNIFORM_SHARE")


def ground_truth(args, name):
    """gt.f32 and meta.json of render_streams.py for `name`, rendered first when missing."""
    folder = os.path.join(args.ref, name)
    meta_path = os.path.join(folder, "meta.json")
    if not os.path.exists(meta_path):
        print(f"rendering the {name} ground truth ({args.gt_spp} spp) with render_streams.py",
              flush=True)
        subprocess.run(
            [sys.executable, os.path.join(HERE, "render_streams.py"), "--out", args.ref,
             "--res", str(args.res), "--passes", "1", "--check-spp", "0", "--gt-spp",
             str(args.gt_spp), "--scenes", name, "--variant", args.variant],
            check=True,
        )
    with open(meta_path) as f:
        meta = json.load(f)
    if (meta["width"], meta["height"]) != (args.res, args.res):
        sys.exit(f"{meta_path} is {meta['width']}x{meta['height']}, not {args.res}x{args.res}: "
                 f"use another --ref")
    # render_streams.py renders whole frames (its seeds are pass numbers here).
    last = max(meta["gt_seeds"][1], meta["pass_seeds"][1], (meta.get("check_seeds") or [0, 0])[1])
    if last >= FIRST_PASS:
        sys.exit(f"{meta_path}: the ground truth used seeds up to {last}; this benchmark starts at {FIRST_PASS}")
    gt = np.fromfile(os.path.join(folder, "gt.f32"), dtype="<f4").reshape(args.res, args.res, 3)
    return gt.astype(np.float64), meta


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", default="caustic,slit")
    ap.add_argument("--res", type=int, default=64)
    ap.add_argument("--spp", default="16,64", help="budgets, in samples per pixel")
    ap.add_argument("--realizations", type=int, default=4)
    ap.add_argument("--policies", type=parse_policy, nargs="+",
                    default=[parse_policy("0.25:6:0:0"), parse_policy("0.25:6:0.25:0.5")],
                    help="guided policies WARMUP:ROUNDS:UNIFORM_SHARE:BASE_DOUBT (see "
                    "mitsuba_worker.run_guided; the worker's defaults are 0.25:6:0.25:0.5)")
    ap.add_argument("--tile", type=int, default=8, help="need map tile edge")
    ap.add_argument("--gt-spp", type=int, default=8192)
    ap.add_argument("--ref", default=os.path.join(REPO, "bench-data", "guided-ref"),
                    help="render_streams.py output holding the ground truths")
    ap.add_argument("--splatd", default=None,
                    help="splatd binary (default target/release/splatd, else target/debug/splatd)")
    ap.add_argument("--variant", default="scalar_rgb")
    args = ap.parse_args()
    budgets = [int(s) for s in args.spp.split(",") if s]
    names = [s for s in args.scenes.split(",") if s]
    binary = args.splatd or next(
        (p for p in (os.path.join(REPO, "target", m, "splatd") for m in ("release", "debug"))
         if os.path.exists(p)), None)
    if not binary:
        sys.exit("no splatd binary: cargo build --release --bin splatd (or pass --splatd)")
    stride = 4 * max(budgets) + 16
    runs = len(names) * len(budgets) * args.realizations * (1 + len(args.policies))
    if FIRST_PASS + runs * stride > 2**32 // (args.res * args.res):
        sys.exit("these runs need more random numbers than Mitsuba's 32-bit seeds hold")

    gts = {name: ground_truth(args, name) for name in names}
    import mitsuba as mi
    import render_streams

    mi.set_variant(args.variant)
    proc, url = start_server(binary)
    client = sc.Client(url)
    started = time.time()
    rows = []
    run = 0
    try:
        for name in names:
            gt, meta = gts[name]
            renderer = mw.Renderer(mi, render_streams.SCENES[name](mi, args.res))
            pixels = renderer.width * renderer.height
            for spp in budgets:
                errors = {"mean": [], "uniform": [], **{i: [] for i in range(len(args.policies))}}
                for r in range(args.realizations):
                    def fresh(label):
                        nonlocal run
                        frame = f"{name}-{spp}-{r}-{label}"
                        client.create_frame(frame, renderer.width, renderer.height)
                        first = FIRST_PASS + run * stride
                        run += 1
                        return frame, first

                    frame, first = fresh("uniform")
                    poster = mw.Poster(client.outbox(frame, 1), renderer, first)
                    for _ in range(spp):
                        poster.render()
                        poster.flush()
                    image, mean = reweighted(client, frame, renderer.width, renderer.height)
                    errors["uniform"].append(rel_mse(image, gt))
                    errors["mean"].append(rel_mse(mean, gt))
                    client.delete_frame(frame)
                    for i, policy in enumerate(args.policies):
                        frame, first = fresh(f"guided{i}")
                        summary = mw.run_guided(client.outbox(frame, 1), renderer, spp * pixels,
                                                first_pass=first, tile=args.tile,
                                                log=lambda line: None, **policy)
                        assert client.frame_info(frame)["samples"] == summary["samples"] == spp * pixels
                        assert summary["passes_used"] <= first + stride, summary["passes_used"]
                        image, _ = reweighted(client, frame, renderer.width, renderer.height)
                        errors[i].append(rel_mse(image, gt))
                        client.delete_frame(frame)
                    print(f"  {name} {spp} spp realization {r}: uniform {errors['uniform'][-1]:.4f}, "
                          + ", ".join(f"guided{i} {errors[i][-1]:.4f}" for i in range(len(args.policies)))
                          + f" ({time.time() - started:.0f} s)", flush=True)
                rows.append((name, spp, errors))
    finally:
        proc.terminate()
        proc.wait()

    print()
    print(f"{args.res}x{args.res}, need map tiles {args.tile}x{args.tile}, {args.realizations} "
          f"realizations, ground truth {args.gt_spp} spp, Mitsuba {mi.__version__} {args.variant}")
    for i, p in enumerate(args.policies):
        print(f"guided{i}: {p['warmup']:g} of the budget in uniform passes, then {p['rounds']} rounds, "
              f"each {p['uniform_share']:g} in uniform passes and the rest where the need map "
              f"points, base doubt {p['base_doubt']:g}")
    head = "| scene | spp | plain mean | uniform |"
    for i in range(len(args.policies)):
        head += f" guided{i} | ratio | median ratio | wins |"
    print(head)
    print("|" + " --- |" * (4 + 4 * len(args.policies)))
    for name, spp, errors in rows:
        u = np.mean(errors["uniform"])
        line = f"| {name} | {spp} | {np.mean(errors['mean']):.4f} | {u:.4f} |"
        for i in range(len(args.policies)):
            g = np.mean(errors[i])
            median = np.median(np.array(errors[i]) / np.array(errors["uniform"]))
            wins = sum(a < b for a, b in zip(errors[i], errors["uniform"]))
            line += f" {g:.4f} | {g / u:.3f} | {median:.3f} | {wins}/{len(errors[i])} |"
        print(line)
    print("(relMSE against the ground truth, mean over realizations; plain mean: uniform's image "
          "without reweighting; ratio: guided's mean / uniform's, below 1 is better at the same "
          "samples; median ratio: of the realizations' own ratios (realization r of both uses "
          "the same budget, not the same samples); wins: realizations where guided was better)")


if __name__ == "__main__":
    main()
