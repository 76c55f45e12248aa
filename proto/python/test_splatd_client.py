"""Tests of the splatd_client package: `python3 -m pytest` or `python3 test_splatd_client.py`.

Imports the package beside this file, unless SPLATD_CLIENT_INSTALLED=1 asks for the installed one
(tests/python_package.rs runs these tests in a fresh virtual environment with the package
installed by pip).

Plain asserts only; the retry tests run a tiny HTTP server on 127.0.0.1 that
answers a bounded, scripted list of responses.
"""

import http.server
import json
import os
import struct
import sys
import threading
import urllib.request

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
if os.environ.get("SPLATD_CLIENT_INSTALLED") == "1":
    # Python put this file's directory first on the path, where the checkout's package is.
    sys.path = [p for p in sys.path if os.path.abspath(p or os.curdir) != HERE]
else:
    sys.path.insert(0, HERE)
import splatd_client as sc  # noqa: E402

if os.environ.get("SPLATD_CLIENT_INSTALLED") == "1":
    assert not os.path.abspath(sc.__file__).startswith(HERE), sc.__file__


def _random_batch(rng, n):
    xs = rng.integers(0, 2**32, size=n, dtype=np.uint64).astype(np.uint32)
    ys = rng.integers(0, 2**32, size=n, dtype=np.uint64).astype(np.uint32)
    rgb = rng.standard_normal((n, 3)).astype(np.float32) * 100
    return xs, ys, rgb


def _expect_wire_error(code, data, **limits):
    try:
        sc.decode_batch(data, **limits)
    except sc.WireError as e:
        assert e.code == code, (e.code, str(e))
        return str(e)
    raise AssertionError(f"expected WireError {code}")


def test_round_trip_random():
    rng = np.random.default_rng(1)
    for n in (0, 1, 2, 17, 1000):
        xs, ys, rgb = _random_batch(rng, n)
        data = sc.encode_batch("frame.a_b-1", 2**64 - 1, n, xs, ys, rgb)
        assert len(data) == 4 + 2 + 8 + 11 + 8 + 8 + 8 + 20 * n
        b = sc.decode_batch(data)
        assert b.frame == "frame.a_b-1" and b.worker == 2**64 - 1 and b.seq == n
        assert b.xs.dtype == np.uint32 and np.array_equal(b.xs, xs)
        assert np.array_equal(b.ys, ys)
        assert b.rgb.dtype == np.float32 and b.rgb.shape == (n, 3)
        assert b.rgb.tobytes() == rgb.tobytes()
        assert sc.encode_batch(*b) == data


def test_layout():
    data = sc.encode_batch("f1", 7, 3, [1, 4294967295], [2, 0], [[0.5, 1.0, 2.0], [0.0, -0.0, 65504.0]])
    assert data[0:4] == b"SPLB"
    assert data[4:6] == struct.pack("<H", 1)
    assert data[6:14] == struct.pack("<Q", 2)
    assert data[14:16] == b"f1"
    assert data[16:40] == struct.pack("<QQQ", 7, 3, 2)
    assert data[40:60] == struct.pack("<IIfff", 1, 2, 0.5, 1.0, 2.0)
    assert data[60:80] == struct.pack("<IIfff", 4294967295, 0, 0.0, -0.0, 65504.0)
    assert len(data) == 80


def test_decode_errors():
    good = sc.encode_batch("f", 1, 1, [1, 2], [3, 4], np.ones((2, 3)))
    assert "XPLB" in _expect_wire_error("bad_magic", b"X" + good[1:])
    _expect_wire_error("unsupported_version", good[:4] + struct.pack("<H", 2) + good[6:])
    for cut in range(len(good)):
        _expect_wire_error("truncated_batch", good[:cut])
    _expect_wire_error("trailing_bytes", good + b"\0")
    _expect_wire_error("too_many_records", good, max_records=1)
    huge = good[: len(good) - 40 - 8] + struct.pack("<Q", 1 << 60)
    _expect_wire_error("truncated_batch", huge)
    _expect_wire_error("invalid_frame_id", good[:6] + struct.pack("<Q", 2**64 - 1) + good[14:])
    _expect_wire_error("malformed_batch", good[:14] + b"\xff" + good[15:])
    bad_id = good[:14] + b"/" + good[15:]
    _expect_wire_error("invalid_frame_id", bad_id)


def test_frame_id_rules():
    for ok in ("a", "shot_010.v2-final", "x" * 128, "..."):
        sc.validate_frame_id(ok)
    for bad in ("", ".", "..", "a/b", "a b", "\u00e9", "x" * 129):
        try:
            sc.validate_frame_id(bad)
        except sc.WireError as e:
            assert e.code == "invalid_frame_id"
        else:
            raise AssertionError(f"{bad!r} accepted")


def test_encode_argument_checks():
    for args in (
        ("f", 0, 0, [1, 2], [1], np.zeros((2, 3))),
        ("f", 0, 0, [1], [1], np.zeros((1, 2))),
        ("f", 0, 0, [-1], [1], np.zeros((1, 3))),
        ("f", 0, 0, [1.5], [1], np.zeros((1, 3))),
        ("f", -1, 0, [1], [1], np.zeros((1, 3))),
        ("f", 0, 2**64, [1], [1], np.zeros((1, 3))),
    ):
        try:
            sc.encode_batch(*args)
        except ValueError:
            pass
        else:
            raise AssertionError(f"accepted {args!r}")


def test_version_is_tied_to_the_wire_format():
    major, minor, patch = sc.__version__.split(".")
    assert int(major) == sc.VERSION, (sc.__version__, sc.VERSION)
    assert minor.isdigit() and patch.isdigit(), sc.__version__
    # The version byte the encoder writes is that VERSION.
    data = sc.encode_batch("f", 1, 2, [0], [0], [[1.0, 1.0, 1.0]])
    assert struct.unpack_from("<4sH", data) == (sc.MAGIC, sc.VERSION)


def test_selftest_batch_round_trips():
    data = sc.encode_batch(*sc.selftest_batch())
    b = sc.decode_batch(data)
    assert b.frame == "selftest.frame-01" and b.seq == (1 << 63) + 5


class _Scripted(http.server.BaseHTTPRequestHandler):
    responses = []  # (status, body) popped in order
    seen = []  # (method, path, headers, body)

    def _serve(self):
        n = int(self.headers.get("Content-Length") or 0)
        body = self.rfile.read(n)
        self.seen.append((self.command, self.path, dict(self.headers), body))
        status, payload = self.responses.pop(0)
        raw = json.dumps(payload).encode()
        self.send_response(status)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(raw)))
        self.end_headers()
        self.wfile.write(raw)

    do_GET = do_POST = do_PUT = _serve

    def log_message(self, *args):
        pass


def _serve(responses):
    _Scripted.responses = list(responses)
    _Scripted.seen = []
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _Scripted)
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
    thread.start()
    return server, f"http://127.0.0.1:{server.server_address[1]}"


def _client(base, **kw):
    # No proxies: the test server is on loopback.
    opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))
    return sc.Client(base, opener=opener, timeout=5, initial_backoff=0.005, max_backoff=0.02, **kw)


def test_post_batch_retries_with_same_bytes():
    ack = {"frame": "f", "worker": 5, "seq": 9, "accepted": 2, "duplicate": False}
    unavailable = {"error": "unavailable", "message": "restarting"}
    server, base = _serve([(503, unavailable), (503, unavailable), (200, ack)])
    try:
        xs, ys, rgb = [1, 2], [3, 4], np.ones((2, 3), dtype=np.float32)
        got = _client(base, token="tok").post_batch("f", 5, 9, xs, ys, rgb)
        assert got == ack
        expected = sc.encode_batch("f", 5, 9, xs, ys, rgb)
        assert len(_Scripted.seen) == 3
        for method, path, headers, body in _Scripted.seen:
            assert (method, path) == ("POST", "/v1/frames/f/samples")
            assert headers["Content-Type"] == sc.BATCH_CONTENT_TYPE
            assert headers["Authorization"] == "Bearer tok"
            assert body == expected
    finally:
        server.shutdown()
        server.server_close()


def test_4xx_is_final_and_carries_error_body():
    err = {"error": "pixel_out_of_range", "message": "x 9 >= width 4"}
    server, base = _serve([(422, err)])
    try:
        try:
            _client(base).post_batch("f", 1, 1, [9], [0], [[1, 1, 1]])
        except sc.SplatdError as e:
            assert (e.status, e.error, e.message) == (422, "pixel_out_of_range", "x 9 >= width 4")
        else:
            raise AssertionError("422 not raised")
        assert len(_Scripted.seen) == 1
    finally:
        server.shutdown()
        server.server_close()


def test_create_frame_and_gave_up():
    info = {"id": "f", "width": 4, "height": 2}
    server, base = _serve([(201, info), (500, {}), (500, {})])
    try:
        c = _client(base, max_attempts=2)
        assert c.create_frame("f", 4, 2, resolve={"variant": "off"}) == info
        assert json.loads(_Scripted.seen[0][3]) == {"id": "f", "width": 4, "height": 2, "resolve": {"variant": "off"}}
        try:
            c.frame_info("f")
        except sc.SplatdError as e:
            assert e.error == "gave_up" and "2 attempts" in e.message, e
        else:
            raise AssertionError("expected gave_up")
    finally:
        server.shutdown()
        server.server_close()


def test_create_or_get_puts_the_parameters_and_pass_layers_are_encoded():
    info = {"id": "f", "width": 4, "height": 2}
    ack = {"frame": "f", "worker": 3, "seq": 4, "accepted": 8, "duplicate": False}
    conflict = {"error": "frame_exists", "message": "frame \"f\" exists with different parameters"}
    server, base = _serve([(500, {}), (200, info), (409, conflict), (200, ack)])
    try:
        c = _client(base, token="w")
        # Idempotent, so retried like any request: the 500 is followed by the same PUT.
        assert c.create_or_get("f", 4, 2, cascades={"base": 4.0}) == info
        for method, path, headers, body in _Scripted.seen:
            assert (method, path) == ("PUT", "/v1/frames/f")
            assert headers["Content-Type"] == "application/json"
            assert json.loads(body) == {"width": 4, "height": 2, "cascades": {"base": 4.0}}
        assert len(_Scripted.seen) == 2
        try:
            c.create_or_get("f", 8, 2)
        except sc.SplatdError as e:
            assert (e.status, e.error) == (409, "frame_exists"), e
        else:
            raise AssertionError("409 not raised")
        assert c.post_pass("f", 3, 4, b"exr bytes", layer="View Layer.Combined&x") == ack
        method, path, headers, body = _Scripted.seen[-1]
        assert (method, body) == ("POST", b"exr bytes")
        assert path == "/v1/frames/f/passes?worker=3&seq=4&layer=View%20Layer.Combined%26x", path
        assert headers["Content-Type"] == "image/x-exr"
    finally:
        server.shutdown()
        server.server_close()


def _ack(seq, boot, floor, duplicate=False):
    return {"frame": "f", "worker": 7, "seq": seq, "accepted": 0 if duplicate else 1,
            "duplicate": duplicate, "boot": boot, "durable_floor": floor}


def test_outbox_resends_what_a_restart_lost_and_forgets_what_is_durable():
    xs, ys, rgb = [0], [0], [[1.0, 2.0, 3.0]]
    bodies = [sc.encode_batch("f", 7, k, xs, ys, np.array(rgb) * (k + 1)) for k in range(4)]
    server, base = _serve([
        (200, _ack(0, 1, 0)), (200, _ack(1, 1, 0)),
        # Restarted (boot 2) from a snapshot older than batches 0 and 1: both are resent.
        (200, _ack(2, 2, 0)), (200, _ack(0, 2, 0)), (200, _ack(1, 2, 3)),
        # The floor passed 0..2: only 3 is kept, and the sync of the same process covers it.
        (200, _ack(3, 2, 3)), (200, {"frame": "f", "boot": 2, "durable": True}),
    ])
    try:
        outbox = _client(base).outbox("f", 7)
        for k in range(4):
            outbox.post_batch(k, xs, ys, np.array(rgb) * (k + 1))
        assert (outbox.kept, outbox.resent) == (1, 2), (outbox.kept, outbox.resent)
        assert outbox.sync()["durable"] and outbox.kept == 0
        sent = [body for _, _, _, body in _Scripted.seen[:-1]]
        assert sent == [bodies[0], bodies[1], bodies[2], bodies[0], bodies[1], bodies[3]]
    finally:
        server.shutdown()
        server.server_close()


def test_outbox_resends_only_what_the_new_floor_does_not_cover():
    xs, ys = [0], [0]
    server, base = _serve([
        (200, _ack(0, 1, 0)), (200, _ack(1, 1, 0)),
        # Restarted from a snapshot that held batch 0 (floor 1 in the new process): 1 is resent.
        (200, _ack(2, 2, 1)), (200, _ack(1, 2, 3)),
    ])
    try:
        outbox = _client(base).outbox("f", 7)
        for k in range(3):
            outbox.post_batch(k, xs, ys, [[float(k), 0.0, 0.0]])
        assert (outbox.kept, outbox.resent) == (0, 1), (outbox.kept, outbox.resent)
        assert sc.decode_batch(_Scripted.seen[-1][3]).seq == 1
    finally:
        server.shutdown()
        server.server_close()


def test_outbox_sync_resends_passes_acknowledged_by_a_process_that_died():
    server, base = _serve([
        (200, _ack(11, 1, 0)), (200, _ack(12, 1, 0)),
        # The server restarted between the last pass and the sync: both passes are resent and
        # the sync asked again, of the process that now has them.
        (200, {"frame": "f", "boot": 2, "durable": True}),
        (200, _ack(11, 2, 0)), (200, _ack(12, 2, 0, duplicate=True)),
        (200, {"frame": "f", "boot": 2, "durable": True}),
    ])
    try:
        outbox = _client(base).outbox("f", 7)
        outbox.post_pass(11, b"pass 11", layer="ViewLayer.Combined")
        outbox.post_pass(12, b"pass 12")
        assert outbox.sync()["boot"] == 2
        assert (outbox.kept, outbox.resent) == (0, 2)
        paths = [(path, body) for _, path, _, body in _Scripted.seen]
        assert paths[3] == ("/v1/frames/f/passes?worker=7&seq=11&layer=ViewLayer.Combined", b"pass 11"), paths
        assert paths[4] == ("/v1/frames/f/passes?worker=7&seq=12", b"pass 12"), paths
        assert [p for p, _ in paths].count("/v1/frames/f/sync") == 2, paths
    finally:
        server.shutdown()
        server.server_close()


def test_outbox_keeps_nothing_for_a_server_without_durability():
    ack = {"frame": "f", "worker": 7, "seq": 0, "accepted": 1, "duplicate": False, "boot": 1}
    server, base = _serve([(200, ack), (200, {"frame": "f", "boot": 1, "durable": False})])
    try:
        outbox = _client(base).outbox("f", 7)
        outbox.post_pass(0, b"pass")
        assert outbox.kept == 0
        assert outbox.sync()["durable"] is False
        assert len(_Scripted.seen) == 2
    finally:
        server.shutdown()
        server.server_close()


def test_outbox_refuses_a_kept_number_with_other_content():
    server, base = _serve([(200, _ack(5, 1, 0))])
    try:
        outbox = _client(base).outbox("f", 7)
        outbox.post_pass(5, b"a")
        try:
            outbox.post_pass(5, b"b")
        except ValueError as e:
            assert "seq 5" in str(e), e
        else:
            raise AssertionError("a seq reused with other content was sent")
        assert len(_Scripted.seen) == 1
    finally:
        server.shutdown()
        server.server_close()


def _need_map(need, width=10, height=4, tile=4):
    tx, ty = -(-width // tile), -(-height // tile)
    return {"frame": "f", "width": width, "height": height, "tile": tile, "tiles_x": tx,
            "tiles_y": ty, "samples": 0, "need": need}


def test_tile_windows_and_neediest_tiles():
    m = _need_map([0.5, 2.0, 1.0, 0.0, 2.0, 0.1], width=10, height=6)
    assert sc.tile_windows(m) == [(0, 0, 4, 4), (4, 0, 4, 4), (8, 0, 2, 4),
                                  (0, 4, 4, 2), (4, 4, 4, 2), (8, 4, 2, 2)]
    # Neediest first; the tie between tiles 1 and 4 goes to the lower index.
    assert sc.neediest_tiles(m, 3) == [(4, 0, 4, 4), (4, 4, 4, 2), (8, 0, 2, 4)]
    try:
        sc.tile_windows(dict(m, need=[1.0]))
    except ValueError as e:
        assert "1 scores for 3x2 tiles" in str(e), e
    else:
        raise AssertionError("a map with too few scores was accepted")


def test_plan_samples_by_hand():
    # Tiles of 16, 16 and 8 pixels; square roots of the needs 2, 1, 0 (sum 3).
    m = _need_map([4.0, 1.0, 0.0])
    # Shares 100*2/3/16 = 4.17 and 100/3/16 = 2.08 passes: 4 and 2 (96 samples); the 4 left fit
    # no tile.
    assert sc.plan_samples(m, 100) == [4, 2, 0]
    # Shares 1.67, 0.83, 0: 1 pass (16), then by largest fraction: tile 1 (16 more), tile 0 does
    # not fit in the 8 left, tile 2 does.
    assert sc.plan_samples(m, 40) == [1, 1, 1]
    # No need anywhere: in proportion to the pixels, here one pass of every tile.
    assert sc.plan_samples(_need_map([0.0, 0.0, 0.0]), 40) == [1, 1, 1]
    assert sc.plan_samples(m, 0) == [0, 0, 0]
    try:
        sc.plan_samples(m, -1)
    except ValueError as e:
        assert "negative" in str(e)
    else:
        raise AssertionError("a negative budget was accepted")


def test_aovs_are_declared_as_the_server_expects():
    info = {"id": "f", "width": 4, "height": 2}
    server, base = _serve([(201, info), (200, info)])
    try:
        c = _client(base)
        aovs = [("ViewLayer.DiffCol", ["R", "G", "B"]), ("ViewLayer.Depth", ("Z",))]
        expected = [{"name": "ViewLayer.DiffCol", "channels": ["R", "G", "B"]},
                    {"name": "ViewLayer.Depth", "channels": ["Z"]}]
        assert c.create_frame("f", 4, 2, aovs=aovs) == info
        assert json.loads(_Scripted.seen[0][3])["aovs"] == expected
        assert c.create_or_get("f", 4, 2, aovs=aovs) == info
        assert json.loads(_Scripted.seen[1][3]) == {"width": 4, "height": 2, "aovs": expected}
    finally:
        server.shutdown()
        server.server_close()


if __name__ == "__main__":
    tests = [(name, fn) for name, fn in sorted(globals().items()) if name.startswith("test_") and callable(fn)]
    failed = 0
    for name, fn in tests:
        try:
            fn()
            print(f"{name} ... ok")
        except Exception as e:  # noqa: BLE001 - report every failure
            failed += 1
            print(f"{name} ... FAILED: {type(e).__name__}: {e}")
    print(f"{len(tests) - failed} passed, {failed} failed")
    sys.exit(1 if failed else 0)
