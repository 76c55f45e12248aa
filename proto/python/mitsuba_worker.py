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
Use `--scene file.xml` for your own scene (its film and sampler are overridden as above).

Several workers can render one frame together: give each its own `--worker` and a disjoint set
of passes (`--first-pass`, `--passes`), e.g. worker k renders passes k*64 .. k*64+63.
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


def image_to_records(image):
    """(H, W, 3) float image -> (xs, ys, rgb) arrays of one record per pixel, row-major."""
    image = np.asarray(image, dtype=np.float32)
    if image.ndim != 3 or image.shape[2] < 3:
        raise ValueError(f"expected an (H, W, 3) image, got shape {image.shape}")
    h, w = image.shape[:2]
    ys, xs = np.divmod(np.arange(w * h, dtype=np.uint32), np.uint32(w))
    rgb = np.ascontiguousarray(image[:, :, :3].reshape(-1, 3))
    # Renderers produce the odd NaN or negative value (numerical noise); splatd refuses whole
    # batches holding one, so such samples are sent as black and counted here.
    bad = ~np.isfinite(rgb).all(axis=1) | (rgb < 0).any(axis=1)
    rgb[bad] = 0.0
    return xs, ys, rgb, int(bad.sum())


def post_image(client, frame, worker, seq, image):
    """Posts one 1-spp pass as one batch; returns (BatchAck, number of samples zeroed)."""
    xs, ys, rgb, zeroed = image_to_records(image)
    return client.post_batch(frame, worker, seq, xs, ys, rgb), zeroed


def builtin_scene(mi, res):
    scene = mi.cornell_box()
    scene["sensor"]["film"]["width"] = res
    scene["sensor"]["film"]["height"] = res
    scene["sensor"]["film"]["rfilter"] = {"type": "box"}
    scene["sensor"]["sampler"] = {"type": "independent", "sample_count": 1}
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
    return mi.load_dict(scene)


def main(argv):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--url", default="http://127.0.0.1:7878")
    p.add_argument("--frame", default="mitsuba")
    p.add_argument("--res", type=int, default=256, help="image width and height (built-in scene)")
    p.add_argument("--passes", type=int, default=64)
    p.add_argument("--first-pass", type=int, default=0)
    p.add_argument("--worker", type=int, default=None, help="worker id (default: random)")
    p.add_argument("--token", default=os.environ.get("SPLATD_TOKEN"))
    p.add_argument("--scene", default=None, help="a Mitsuba XML scene instead of the built-in one")
    p.add_argument("--variant", default="scalar_rgb", help="Mitsuba variant, e.g. llvm_ad_rgb")
    args = p.parse_args(argv)

    import mitsuba as mi  # imported here so the helpers above work without Mitsuba

    mi.set_variant(args.variant)
    if args.scene:
        scene = mi.load_file(args.scene)
    else:
        scene = builtin_scene(mi, args.res)
    film = scene.sensors()[0].film()
    width, height = (int(v) for v in film.crop_size())
    worker = args.worker if args.worker is not None else random.getrandbits(53)
    client = sc.Client(args.url, token=args.token)
    try:
        client.create_frame(args.frame, width, height)
    except sc.SplatdError as e:
        if e.error != "frame_exists":
            raise
    zeroed_total = 0
    start = time.time()
    for i in range(args.passes):
        seq = args.first_pass + i
        image = np.array(mi.render(scene, spp=1, seed=seq))
        ack, zeroed = post_image(client, args.frame, worker, seq, image)
        zeroed_total += zeroed
        info = client.frame_info(args.frame)
        print(
            f"pass {seq}: {ack['accepted']} samples{' (duplicate)' if ack['duplicate'] else ''}, "
            f"frame at {info['spp_mean']:.1f} spp, {time.time() - start:.1f} s",
            flush=True,
        )
    client.sync(args.frame)
    if zeroed_total:
        print(f"{zeroed_total} NaN or negative samples were sent as black", file=sys.stderr)
    print(f"done: {args.passes} passes as worker {worker}; image at {args.url}/v1/frames/{args.frame}/image.exr")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
