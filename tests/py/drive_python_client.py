"""Drives the splatd_client package (and the Mitsuba worker's posting helper) against a real
splatd server, for tests/python_client_server.rs.

    python3 tests/py/drive_python_client.py URL OUT_DIR

Creates frame `py` (23x17), posts 6 passes of seeded random samples with fireflies (the
Mitsuba worker's `post_image`, as a renderer would), retries one (a duplicate), checks a bad
batch is refused with its error code, syncs, reads the need map and its neediest crop windows,
and writes the samples it sent to OUT_DIR/samples.f32
(float32, (passes, H, W, 3)) and the served EXR to OUT_DIR/served.exr, for the Rust side to
compare with the core's resolve of the same samples.
"""

import json
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
WORKERS = os.path.join(HERE, "..", "..", "proto", "python")
if os.environ.get("SPLATD_CLIENT_INSTALLED") == "1":
    # The installed package first; the workers' directory only after it, so that the Mitsuba
    # worker's `import splatd_client` gets the installed package too, not the checkout's.
    import splatd_client as sc

    sys.path.append(WORKERS)
    assert not os.path.abspath(sc.__file__).startswith(os.path.abspath(WORKERS)), sc.__file__
else:
    sys.path.insert(0, WORKERS)
    import splatd_client as sc  # noqa: E402
import mitsuba_worker  # noqa: E402  (only its helpers; Mitsuba itself is not imported)

assert mitsuba_worker.sc is sc

W, H, PASSES = 23, 17, 6


def main(url, out):
    client = sc.Client(url, max_attempts=3)
    info = client.create_frame("py", W, H)
    assert info["samples"] == 0, info
    again = client.create_or_get("py", W, H)
    assert again == info, (again, info)
    try:
        client.create_or_get("py", W + 1, H)
        raise AssertionError("a create-or-get with another size was accepted")
    except sc.SplatdError as e:
        assert e.status == 409 and e.error == "frame_exists", (e.status, e.error)
        assert f"size {W}x{H} here, {W + 1}x{H} requested" in e.message, e.message
    rng = np.random.default_rng(5)
    outbox = client.outbox("py", 3)
    passes = []
    for seq in range(PASSES):
        image = rng.lognormal(-1.0, 1.0, size=(H, W, 3)).astype(np.float32)
        image[rng.random((H, W)) < 0.02] *= 500.0
        passes.append(image)
        ack, zeroed = mitsuba_worker.post_image(outbox, seq, image)
        assert ack["accepted"] == W * H and not ack["duplicate"] and zeroed == 0, ack
    again, _ = mitsuba_worker.post_image(outbox, 0, passes[0])
    assert again["duplicate"] and again["accepted"] == 0, again
    # NaN and negative renderer output is zeroed (and counted) by the worker helper...
    dirty = passes[1].copy()
    dirty[0, 0, 0] = np.nan
    dirty[1, 1, 2] = -1.0
    xs, ys, rgb, zeroed = mitsuba_worker.image_to_records(dirty)
    assert zeroed == 2 and rgb[0, 0] == 0.0, zeroed
    # ...while the raw client sends it as is, and the server refuses the batch by name.
    xs, ys = np.array([0, 1], dtype=np.uint32), np.array([0, 1], dtype=np.uint32)
    bad = np.array([[1.0, 1.0, 1.0], [1.0, np.nan, 1.0]], dtype=np.float32)
    try:
        client.post_batch("py", 4, 0, xs, ys, bad)
        raise AssertionError("a NaN sample was accepted")
    except sc.SplatdError as e:
        assert e.status == 422 and e.error == "non_finite_sample", (e.status, e.error)
        assert "record 1" in e.message, e.message
    try:
        client.frame_info("missing")
        raise AssertionError("an unknown frame was found")
    except sc.SplatdError as e:
        assert e.status == 404 and e.error == "unknown_frame", (e.status, e.error)
    sync = client.sync("py")
    assert sync["frame"] == "py" and sync["durable"] is False, sync
    info = client.frame_info("py")
    assert info["samples"] == PASSES * W * H and info["spp_min"] == PASSES, info
    # The need map, and the crop windows a worker would render next: 23x17 in 8 px tiles.
    need = client.need("py", tile=8)
    assert (need["tiles_x"], need["tiles_y"], need["samples"]) == (3, 3, PASSES * W * H), need
    windows = sc.neediest_tiles(need, 3)
    scores = sorted(need["need"], reverse=True)
    assert [need["need"][(y // 8) * 3 + x // 8] for x, y, _, _ in windows] == scores[:3], windows
    assert all(x + w <= W and y + h <= H for x, y, w, h in windows), windows
    every = sc.neediest_tiles(need, 20)
    assert len(every) == 9 and sum(w * h for _, _, w, h in every) == W * H, every
    assert info["convergence"]["spp_min"] == PASSES, info
    counts = client.frame_info("py", convergence="none")
    assert "convergence" not in counts, counts
    assert (counts["samples"], counts["spp_min"], counts["spp_max"]) == (PASSES * W * H, PASSES, PASSES), counts
    np.stack(passes).astype("<f4").tofile(os.path.join(out, "samples.f32"))
    with open(os.path.join(out, "served.exr"), "wb") as f:
        f.write(client.image("py"))
    print(json.dumps({"ok": True, "samples": info["samples"]}))


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
