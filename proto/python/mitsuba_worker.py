#!/usr/bin/env python3
"""A splatd render worker that path-traces with Mitsuba 3 and streams every sample.

Each pass is a full-image render with 1 sample per pixel, the `independent` sampler seeded with
the pass number, and a box reconstruction filter, so every pixel of a pass is exactly one Monte
Carlo sample of that pixel: the records splatd needs (a wider filter would blend neighbouring
samples into one value). Passes are posted as sample batches with the `splatd_client` package
(`pip install ./proto/python`); the pass
number is the batch sequence number, so a worker restarted with the same `--worker` and
`--first-pass` resends nothing twice.

    pip install mitsuba numpy
    python3 proto/python/mitsuba_worker.py --url http://127.0.0.1:7878 --frame box --passes 64

The built-in scene is Mitsuba's Cornell box with a glass sphere added: light that reaches the
floor through the sphere (a caustic) can only be found by chance, so it arrives as fireflies.
Use `--scene file.xml` for your own scene (rendered as the file says: give its film a box
filter and its sampler one sample per pixel).

Several workers can render one frame together: give each its own `--worker` and a disjoint set
of passes (`--first-pass`, `--passes`), e.g. worker k renders passes k*64 .. k*64+63.

Need-guided (`--guided`, built-in scene): the worker spends a budget of samples (`--samples`,
by default `--passes` times the pixels: the cost of that many passes) where the server says
they help most. It renders a share of the budget as uniform passes first (`--warmup`, 0.25),
then in `--rounds` rounds (6) asks for the need map (`GET /v1/frames/{id}/need?tile=`,
`--tile` 8), spreads the round's samples over the tiles with `splatd_client.plan_samples` and
renders each tile's extra samples as Mitsuba crop windows (the film's crop offset and size; a
row of neighbouring tiles that all want another sample is one window), 1 sample per pixel and a
seed of its own each, posted as batches of records. `--base-doubt` (0.5) adds that much doubt
per sample to every tile's need before planning: the map sees fireflies and thin brightness
bands, not plain noise, and without it the light's tile takes nearly every sample.
`--uniform-share` (0.25) renders that share of every round as uniform passes first. The budget is
spent exactly; the worker prints one line per round. It draws the random numbers of passes
`--first-pass` onwards, at most about twice its budget's passes plus one per batch (it prints
the range): give other workers of the frame disjoint ranges. See `run_guided`.

    python3 proto/python/mitsuba_worker.py --url http://127.0.0.1:7878 --frame box --res 64 \
        --guided --passes 64
"""

import argparse
import os
import random
import sys
import time

import numpy as np

try:
    import splatd_client as sc
except ImportError:  # pragma: no cover - depends on the environment
    sys.exit("mitsuba_worker.py needs the splatd client: pip install ./proto/python")


def image_to_records(image, x0=0, y0=0):
    """(H, W, 3) float image -> (xs, ys, rgb) arrays of one record per pixel, row-major; the
    image's top left pixel is frame pixel (x0, y0) (a crop window's offset)."""
    image = np.asarray(image, dtype=np.float32)
    if image.ndim != 3 or image.shape[2] < 3:
        raise ValueError(f"expected an (H, W, 3) image, got shape {image.shape}")
    h, w = image.shape[:2]
    ys, xs = np.divmod(np.arange(w * h, dtype=np.uint32), np.uint32(w))
    xs += np.uint32(x0)
    ys += np.uint32(y0)
    rgb = np.ascontiguousarray(image[:, :, :3].reshape(-1, 3))
    # Renderers produce the odd NaN or negative value (numerical noise); splatd refuses whole
    # batches holding one, so such samples are sent as black and counted here.
    bad = ~np.isfinite(rgb).all(axis=1) | (rgb < 0).any(axis=1)
    rgb[bad] = 0.0
    return xs, ys, rgb, int(bad.sum())


def post_image(outbox, seq, image):
    """Posts one 1-spp pass as one batch through `outbox` (a `splatd_client.Outbox`, which keeps
    it until it is on disk); returns (BatchAck, number of samples zeroed)."""
    xs, ys, rgb, zeroed = image_to_records(image)
    return outbox.post_batch(seq, xs, ys, rgb), zeroed


def builtin_scene_dict(mi, res):
    """The built-in scene as a Mitsuba scene dict (see the module docs)."""
    scene = mi.cornell_box()
    scene["sensor"]["film"]["width"] = res
    scene["sensor"]["film"]["height"] = res
    scene["integrator"] = {"type": "path", "max_depth": 8}
    scene["glass"] = {
        "type": "sphere",
        "center": [0.35, -0.6, 0.2],
        "radius": 0.35,
        "bsdf": {"type": "dielectric", "int_ior": 1.5},
    }
    # A smaller, brighter light: the same power from a tenth of the area makes fireflies.
    light = scene["light"]
    light["emitter"]["radiance"]["value"] = [180.0, 130.0, 90.0]
    light["to_world"] = mi.ScalarTransform4f.translate([0.0, 0.99, 0.01]) @ (
        mi.ScalarTransform4f.rotate([1, 0, 0], 90) @ mi.ScalarTransform4f.scale([0.07, 0.07, 1.0])
    )
    return scene


class Renderer:
    """Renders one-sample-per-pixel images of a Mitsuba scene given as a dict, whole or crop
    windows of it, each render with a seed of its own.

    The scene's sensor gets a box reconstruction filter and the `independent` sampler with one
    sample per pixel, so each pixel of a render is exactly one Monte Carlo sample. A crop window
    is rendered by a copy of the sensor whose film has Mitsuba's `crop_offset_x/y` and
    `crop_width/height`: pixel (i, j) of the crop is pixel (x + i, y + j) of the frame, sampled
    exactly as a whole render samples it.
    """

    def __init__(self, mi, scene_dict):
        self.mi = mi
        self.scalar = mi.variant().startswith("scalar")
        sensor = dict(scene_dict["sensor"])
        sensor["film"] = dict(sensor["film"])
        sensor["film"]["rfilter"] = {"type": "box"}
        sensor["sampler"] = {"type": "independent", "sample_count": 1}
        self.sensor_dict = sensor
        self.scene = mi.load_dict({**scene_dict, "sensor": sensor})
        film = self.scene.sensors()[0].film()
        self.width, self.height = (int(v) for v in film.crop_size())
        self._crops = {}

    def _seed(self, seed, pixels):
        # Mitsuba seeds a render of N pixels at seed * N (mod 2**32): measured with Mitsuba
        # 3.9.1, a 64x64 render with seed s + 2**20 repeats the one with seed s.
        if not 0 <= seed or (seed + 1) * pixels > 2**32:
            raise ValueError(f"render seed {seed} of {pixels} pixels is outside Mitsuba's 32-bit seeds")
        if self.scalar:
            return seed
        import drjit as dr  # the JIT variants: an opaque seed does not recompile the kernel

        return dr.opaque(self.mi.UInt32, seed)

    def render(self, seed, window=None):
        """One sample per pixel of the whole frame, or of `window` = (x, y, width, height):
        an (height, width, 3) float32 array."""
        if window is None or tuple(window) == (0, 0, self.width, self.height):
            seed = self._seed(seed, self.width * self.height)
            return np.array(self.mi.render(self.scene, spp=1, seed=seed), dtype=np.float32)
        x, y, w, h = (int(v) for v in window)
        if w < 1 or h < 1 or x < 0 or y < 0 or x + w > self.width or y + h > self.height:
            raise ValueError(f"crop window {window} is not inside the {self.width}x{self.height} frame")
        sensor = self._crops.get((x, y, w, h))
        if sensor is None:
            d = dict(self.sensor_dict)
            d["film"] = dict(d["film"], crop_offset_x=x, crop_offset_y=y, crop_width=w, crop_height=h)
            sensor = self._crops[(x, y, w, h)] = self.mi.load_dict(d)
        seed = self._seed(seed, w * h)
        image = np.array(self.mi.render(self.scene, sensor=sensor, spp=1, seed=seed), dtype=np.float32)
        if image.shape[:2] != (h, w):
            raise RuntimeError(f"Mitsuba rendered crop {window} as an image of shape {image.shape}")
        return image


class Poster:
    """Renders windows, each with a seed of its own, and posts them in batches of at most
    `max_records` samples.

    Mitsuba seeds a render of N pixels at seed * N, and draws that render's random numbers from
    there on, so renders of different sizes with nearby seeds would reuse each other's random
    numbers. The poster hands out these starting points in order instead: a render of N pixels
    gets the first multiple of N at or after the previous render's end, and ends N further on.
    It starts at `first_pass` * (pixels of the frame), where whole-frame pass `first_pass` starts,
    so a worker whose renders went up to `passes_used()` used the same random numbers as passes
    `first_pass` .. `passes_used() - 1` of the plain mode: give workers disjoint ranges. Every
    batch starts at a whole pass, whose number is the batch's sequence number (as in the plain
    mode)."""

    def __init__(self, outbox, renderer, first_pass, max_records=1 << 20):
        self.outbox, self.renderer = outbox, renderer
        self.frame_pixels = renderer.width * renderer.height
        self.first_pass = int(first_pass)
        self.stream = self.first_pass * self.frame_pixels  # where the next render may start
        self.max_records = max_records
        self.posted = 0  # samples the server acknowledged
        self.zeroed = 0
        self.batches = 0
        self._parts = []
        self._pending = 0
        self._seq = None

    def passes_used(self):
        """One past the last whole-frame pass whose random numbers this poster's renders used."""
        return -(-self.stream // self.frame_pixels)

    def render(self, window=None):
        """Renders `window` (the whole frame when None) once with the next seed and queues it;
        returns its number of samples."""
        x0, y0, w, h = (0, 0, self.renderer.width, self.renderer.height) if window is None else window
        seed = -(-self.stream // (w * h))
        if self._seq is None:
            self._seq = self.stream // self.frame_pixels
        image = self.renderer.render(seed, window)
        self.stream = (seed + 1) * w * h
        xs, ys, rgb, zeroed = image_to_records(image, x0, y0)
        self.zeroed += zeroed
        self._parts.append((xs, ys, rgb))
        self._pending += len(xs)
        if self._pending >= self.max_records:
            self.flush()
        return len(xs)

    def flush(self):
        """Posts what is queued as one batch."""
        if not self._parts:
            return
        xs, ys, rgb = (np.concatenate(c) for c in zip(*self._parts))
        ack = self.outbox.post_batch(self._seq, xs, ys, rgb)
        if ack["accepted"] != len(xs) or ack["duplicate"]:
            raise RuntimeError(
                f"batch {self._seq} of worker {self.outbox.worker}: the server acknowledged {ack['accepted']} "
                f"of {len(xs)} samples{' as a duplicate' if ack['duplicate'] else ''}"
            )
        self.posted += len(xs)
        self.batches += 1
        self._parts, self._pending, self._seq = [], 0, None
        self.stream = self.passes_used() * self.frame_pixels  # the next batch starts a pass


def pass_windows(need_map, plan):
    """The crop windows that render `plan` (more samples per pixel for each tile of a need map,
    see `splatd_client.plan_samples`): for pass k = 1, 2, ..., each run of neighbouring tiles of
    a tile row that still want a k-th sample is one window. Returns [(window, pixels)]."""
    windows = sc.tile_windows(need_map)
    tx = int(need_map["tiles_x"])
    out = []
    for k in range(1, max(plan, default=0) + 1):
        for row in range(int(need_map["tiles_y"])):
            i = row * tx
            while i < (row + 1) * tx:
                if plan[i] < k:
                    i += 1
                    continue
                j = i
                while j + 1 < (row + 1) * tx and plan[j + 1] >= k:
                    j += 1
                x, y, _, h = windows[i]
                w = windows[j][0] + windows[j][2] - x
                out.append(((x, y, w, h), w * h))
                i = j + 1
    return out


def leftover_windows(need_map, samples):
    """Windows of exactly `samples` pixels, whole rows of the neediest tiles first (then part of
    one row), for the rest of a budget that no whole pass of a tile fits."""
    out = []
    for x, y, w, h in sc.neediest_tiles(need_map, len(need_map["need"])):
        if samples <= 0:
            break
        rows = min(samples // w, h)
        if rows:
            out.append((x, y, w, rows))
            samples -= rows * w
        if 0 < samples < w and rows < h:
            out.append((x, y + rows, samples, 1))
            samples = 0
    if samples:
        raise ValueError(f"{samples} samples left over do not fit in the frame")
    return out


def run_guided(outbox, renderer, budget, first_pass=0, warmup=0.25, rounds=6,
               uniform_share=0.0, base_doubt=0.0, tile=8, log=print):
    """Spends exactly `budget` samples on `frame`, steered by the server's need map.

    First `floor(warmup * budget / pixels)` uniform passes (one sample of every pixel each); then
    `rounds` rounds share the rest equally. A round first renders `floor(uniform_share * its
    budget / pixels)` more uniform passes, so no pixel starves, then asks the server for the
    need map (`GET /v1/frames/{id}/need?tile=`) and spreads the rest of its budget over the
    tiles with `splatd_client.plan_samples` (in proportion to the square root of their need),
    rendering each tile's extra passes as crop windows. Before planning, every tile's need gets
    `base_doubt / (spp + 1)` added: the map's score counts the energy in doubt (removed as
    fireflies, or in thinly supported bands), not plain Monte Carlo noise, which every tile has;
    without it a tile such as the light's, whose doubt stays high, takes nearly every sample. What a plan cannot spend (less than a
    tile) moves on to the next round; the last round spends its remainder on whole and partial
    rows of the neediest tiles. Returns a summary dict; `log` gets one line per round.
    """
    pixels = renderer.width * renderer.height
    budget = int(budget)
    if budget < 0 or rounds < 1 or not 0 <= warmup <= 1 or not 0 <= uniform_share <= 1:
        raise ValueError("need budget >= 0, rounds >= 1, warmup and uniform_share in [0, 1]")
    client, frame = outbox.client, outbox.frame
    poster = Poster(outbox, renderer, first_pass)
    warm = int(warmup * budget) // pixels
    for _ in range(warm):
        poster.render()
        poster.flush()
    left = budget - warm * pixels
    per_round = left // rounds
    carry = 0
    summary = {"warmup_passes": warm, "rounds": []}
    for r in range(rounds):
        round_budget = (left if r + 1 == rounds else per_round) + carry
        left -= round_budget - carry
        uniform = int(uniform_share * round_budget) // pixels
        for _ in range(uniform):
            poster.render()
        poster.flush()
        guided = round_budget - uniform * pixels
        need_map = client.need(frame, tile)
        if need_map["width"] != renderer.width or need_map["height"] != renderer.height:
            raise RuntimeError(
                f"frame {frame} is {need_map['width']}x{need_map['height']}, the scene renders "
                f"{renderer.width}x{renderer.height}"
            )
        if need_map["samples"] < poster.posted:
            raise RuntimeError(
                f"the need map of {frame} counts {need_map['samples']} samples, but this worker "
                f"alone has had {poster.posted} acknowledged"
            )
        if base_doubt:
            # Every tile has some doubt the map cannot see (plain Monte Carlo noise): `base_doubt`
            # of its energy, per sample it would have after one more pass, like the map's score.
            need_map = dict(need_map, need=[
                n + base_doubt / (spp + 1) for n, spp in zip(need_map["need"], need_map["spp_mean"])
            ])
        plan = sc.plan_samples(need_map, guided)
        spent = 0
        for window, n in pass_windows(need_map, plan):
            spent += poster.render(window)
        carry = guided - spent
        if r + 1 == rounds:
            for window in leftover_windows(need_map, carry):
                spent += poster.render(window)
            carry = 0
        poster.flush()
        tiles = sum(1 for p in plan if p)
        summary["rounds"].append(
            {"map_samples": need_map["samples"], "uniform_passes": uniform, "plan": plan,
             "guided_samples": spent}
        )
        log(
            f"round {r}: need map at {need_map['samples']} samples; {uniform} uniform passes, "
            f"{spent} samples on {tiles} of {len(plan)} tiles (up to {max(plan, default=0)} passes "
            f"each), {poster.posted} posted in all"
        )
    if poster.posted != budget:
        raise RuntimeError(f"guided rendering posted {poster.posted} samples, its budget was {budget}")
    summary.update(samples=poster.posted, batches=poster.batches, zeroed=poster.zeroed,
                   passes_used=poster.passes_used())
    return summary


def main(argv):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--url", default="http://127.0.0.1:7878")
    p.add_argument("--frame", default="mitsuba")
    p.add_argument("--res", type=int, default=256, help="image width and height (built-in scene)")
    p.add_argument("--passes", type=int, default=64, help="passes; with --guided, the budget in passes")
    p.add_argument("--first-pass", type=int, default=0, help="first pass (seed and sequence number)")
    p.add_argument("--worker", type=int, default=None, help="worker id (default: random)")
    p.add_argument("--token", default=os.environ.get("SPLATD_TOKEN"))
    p.add_argument("--scene", default=None, help="a Mitsuba XML scene instead of the built-in one")
    p.add_argument("--variant", default="scalar_rgb", help="Mitsuba variant, e.g. llvm_ad_rgb")
    g = p.add_argument_group("need-guided rendering (built-in scene)")
    g.add_argument("--guided", action="store_true", help="render crop windows where the need map points")
    g.add_argument("--samples", type=int, default=None, help="total samples (default: passes x pixels)")
    g.add_argument("--warmup", type=float, default=0.25, help="share of the budget rendered uniformly first")
    g.add_argument("--rounds", type=int, default=6, help="need map requests for the rest")
    # The defaults are the estimator's DEFAULT_UNIFORM_SHARE and DEFAULT_BASE_DOUBT
    # (splatd_estimator::NeedMap::with_base_doubt).
    g.add_argument("--uniform-share", type=float, default=0.25,
                   help="share of each round rendered as uniform passes before the guided part")
    g.add_argument("--base-doubt", type=float, default=0.5,
                   help="doubt every tile is given beyond the map's (plain noise), see run_guided")
    g.add_argument("--tile", type=int, default=8, help="need map tile edge, in pixels")
    args = p.parse_args(argv)
    if args.guided and args.scene:
        p.error("--guided renders crop windows of the built-in scene; --scene is not supported with it")

    import mitsuba as mi  # imported here so the helpers above work without Mitsuba

    mi.set_variant(args.variant)
    renderer = None
    if args.scene:
        scene = mi.load_file(args.scene)
        film = scene.sensors()[0].film()
        width, height = (int(v) for v in film.crop_size())
    else:
        renderer = Renderer(mi, builtin_scene_dict(mi, args.res))
        width, height = renderer.width, renderer.height
    worker = args.worker if args.worker is not None else random.getrandbits(53)
    client = sc.Client(args.url, token=args.token)
    # Everything posted goes through the outbox, which keeps it until the server has it on disk
    # and resends it if the server restarts meanwhile.
    outbox = client.outbox(args.frame, worker)
    try:
        client.create_frame(args.frame, width, height)
    except sc.SplatdError as e:
        if e.error != "frame_exists":
            raise
    start = time.time()
    if args.guided:
        budget = args.samples if args.samples is not None else args.passes * width * height
        summary = run_guided(
            outbox, renderer, budget, first_pass=args.first_pass,
            warmup=args.warmup, rounds=args.rounds, uniform_share=args.uniform_share,
            base_doubt=args.base_doubt, tile=args.tile, log=lambda line: print(f"{line}, {time.time() - start:.1f} s", flush=True),
        )
        outbox.sync()
        if summary["zeroed"]:
            print(f"{summary['zeroed']} NaN or negative samples were sent as black", file=sys.stderr)
        print(
            f"done: {summary['samples']} samples in {summary['batches']} batches as worker {worker}, "
            f"random numbers of passes {args.first_pass} to {summary['passes_used'] - 1}; "
            f"image at {args.url}/v1/frames/{args.frame}/image.exr"
        )
        return 0
    zeroed_total = 0
    for i in range(args.passes):
        seq = args.first_pass + i
        if renderer is not None:
            image = renderer.render(seq)
        else:
            image = np.array(mi.render(scene, spp=1, seed=seq))
        ack, zeroed = post_image(outbox, seq, image)
        zeroed_total += zeroed
        info = client.frame_info(args.frame, convergence="none")
        print(
            f"pass {seq}: {ack['accepted']} samples{' (duplicate)' if ack['duplicate'] else ''}, "
            f"frame at {info['spp_mean']:.1f} spp, {time.time() - start:.1f} s",
            flush=True,
        )
    outbox.sync()
    if zeroed_total:
        print(f"{zeroed_total} NaN or negative samples were sent as black", file=sys.stderr)
    print(f"done: {args.passes} passes as worker {worker}; image at {args.url}/v1/frames/{args.frame}/image.exr")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
