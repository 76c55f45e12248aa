"""Python client of splatd: encode sample batches and send them to a server.

Dependencies: the standard library and numpy. Install with
``pip install ./proto/python`` (package ``splatd-client``); the package's major
version is the batch wire format version it speaks (``VERSION``).

A batch is one worker's bundle of Monte Carlo samples for one frame: every
record is ONE sample (pixel x, pixel y, linear RGB radiance), and the server
counts samples per pixel, so never pre-average several samples into one
record. The byte layout is documented in ``proto/PROTOCOL.md`` and matches the
Rust crate ``splatd-proto`` byte for byte (a Rust test checks this)::

    b"SPLB" | u16 version=1 | u64 len | frame id (len bytes, UTF-8)
    | u64 worker | u64 seq | u64 n | n x (u32 x, u32 y, f32 r, f32 g, f32 b)

all little-endian. The records are built with one numpy structured array, no
Python loop, so encoding millions of samples is cheap.

Durability: a worker posts through an :class:`Outbox` (``client.outbox(frame, worker)``), which
keeps every batch and pass until the server has it on disk and resends it when the server
restarted; ``Client.post_batch`` and ``Client.post_pass`` are single requests.

Retries: ``(worker, seq)`` identifies a batch. ``Client.post_batch`` encodes
once and resends exactly the same bytes on connection errors, timeouts, 5xx,
408 and 429, so that the server can drop a duplicate if an earlier attempt
did arrive. Choose a worker id unique per process and below 2**53 (e.g.
``random.getrandbits(53)``), so that JSON readers that use doubles keep it
exact, and never reuse a (worker, seq) pair for different samples.

Example::

    import numpy as np
    from splatd_client import Client

    c = Client("http://render-head:7878", token="...")  # a `write` token will do
    c.create_or_get("shot010", 1920, 1080)
    xs = np.array([10, 11], dtype=np.uint32)
    ys = np.array([20, 20], dtype=np.uint32)
    rgb = np.array([[0.5, 0.4, 0.3], [9.0, 8.0, 7.0]], dtype=np.float32)
    print(c.post_batch("shot010", worker=1234, seq=0, xs=xs, ys=ys, rgb=rgb))

Command line (``python3 -m splatd_client``): ``--selftest-emit PATH`` writes a
fixed batch (used by the Rust compatibility test), ``--selftest-check PATH``
decodes PATH and checks that it is that batch.
"""

from __future__ import annotations

import http.client
import json
import math
import random
import re
import struct
import sys
import time
import urllib.error
import urllib.parse
import urllib.request
from typing import Any, Dict, List, NamedTuple, Optional, Tuple

try:
    import numpy as np
except ImportError:  # pragma: no cover - depends on the environment
    sys.stderr.write(
        "splatd_client needs numpy: install it with `python3 -m pip install numpy`\n"
    )
    raise

MAGIC = b"SPLB"
#: The batch wire format version this client writes and reads.
VERSION = 1
#: The package version: ``VERSION`` of the wire format, then the client's own ``minor.patch``.
__version__ = "1.2.0"
RECORD_SIZE = 20
MAX_FRAME_ID_LEN = 128
DEFAULT_MAX_RECORDS = 4 * 1024 * 1024
BATCH_CONTENT_TYPE = "application/x-splatd-batch"

#: One record on the wire: '<u4,<u4,<f4,<f4,<f4' with names, 20 bytes, packed.
RECORD_DTYPE = np.dtype(
    {"names": ["x", "y", "r", "g", "b"], "formats": ["<u4", "<u4", "<f4", "<f4", "<f4"]}
)
assert RECORD_DTYPE.itemsize == RECORD_SIZE

_PREAMBLE = struct.Struct("<4sHQ")  # magic, version, frame id length
_TAIL = struct.Struct("<QQQ")  # worker, seq, record count
_FRAME_ID_RE = re.compile(r"[A-Za-z0-9._-]+")
_U64_MAX = (1 << 64) - 1
_U32_MAX = (1 << 32) - 1


class WireError(ValueError):
    """A batch or frame id was refused; ``code`` matches the Rust crate's
    ``WireError::code()`` (e.g. ``"truncated_batch"``)."""

    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code


class SplatdError(Exception):
    """The server refused a request (4xx other than 408/429), or gave up."""

    def __init__(self, status: Optional[int], error: str, message: str):
        super().__init__(f"HTTP {status}: {error}: {message}" if status else f"{error}: {message}")
        self.status = status
        self.error = error
        self.message = message


class Batch(NamedTuple):
    """A decoded batch; arrays are fresh, writable copies."""

    frame: str
    worker: int
    seq: int
    xs: np.ndarray  # uint32, shape (n,)
    ys: np.ndarray  # uint32, shape (n,)
    rgb: np.ndarray  # float32, shape (n, 3)


def _aovs(aovs: List[Tuple[str, List[str]]]) -> List[Dict[str, Any]]:
    """The ``aovs`` field of a create request from ``(layer name, [channel names])`` pairs."""
    return [{"name": str(name), "channels": [str(c) for c in channels]} for name, channels in aovs]


def validate_frame_id(frame: str) -> None:
    """1..128 characters of [A-Za-z0-9._-], not "." or ".." (same rules as Rust)."""
    if not isinstance(frame, str):
        raise WireError("invalid_frame_id", f"invalid frame id: expected str, got {type(frame).__name__}")
    if not frame:
        raise WireError("invalid_frame_id", "invalid frame id: frame id is empty")
    m = _FRAME_ID_RE.match(frame)
    end = m.end() if m else 0
    if end != len(frame):
        raise WireError(
            "invalid_frame_id",
            f"invalid frame id: character {frame[end]!r} at position {end} is not allowed; "
            "use only A-Z, a-z, 0-9, '.', '_' and '-'",
        )
    if len(frame) > MAX_FRAME_ID_LEN:
        raise WireError(
            "invalid_frame_id",
            f"invalid frame id: frame id is {len(frame)} characters long; "
            f"at most {MAX_FRAME_ID_LEN} are allowed",
        )
    if frame in (".", ".."):
        raise WireError("invalid_frame_id", f"invalid frame id: {frame!r} is reserved as a path segment")


def _check_u64(name: str, value: int) -> int:
    value = int(value)
    if not 0 <= value <= _U64_MAX:
        raise ValueError(f"{name} {value} does not fit in an unsigned 64-bit integer")
    return value


def _pixel_column(name: str, values: Any) -> np.ndarray:
    a = np.asarray(values)
    if a.ndim != 1:
        raise ValueError(f"{name} must be one-dimensional, got shape {a.shape}")
    if a.size and not np.issubdtype(a.dtype, np.integer):
        raise ValueError(f"{name} must hold integers, got dtype {a.dtype}")
    if a.size and (int(a.min()) < 0 or int(a.max()) > _U32_MAX):
        raise ValueError(f"{name} has values outside 0..{_U32_MAX}")
    return a


def encode_batch(frame: str, worker: int, seq: int, xs: Any, ys: Any, rgb: Any) -> bytes:
    """Encodes one batch; ``xs``, ``ys``: n pixel coordinates, ``rgb``: n x 3 radiance."""
    validate_frame_id(frame)
    worker = _check_u64("worker", worker)
    seq = _check_u64("seq", seq)
    xs = _pixel_column("xs", xs)
    ys = _pixel_column("ys", ys)
    rgb = np.asarray(rgb, dtype="<f4")
    n = xs.shape[0]
    if ys.shape != (n,) or rgb.shape != (n, 3):
        raise ValueError(
            f"shape mismatch: xs {xs.shape}, ys {ys.shape}, rgb {rgb.shape}; expected (n,), (n,), (n, 3)"
        )
    records = np.empty(n, dtype=RECORD_DTYPE)
    records["x"] = xs
    records["y"] = ys
    records["r"] = rgb[:, 0]
    records["g"] = rgb[:, 1]
    records["b"] = rgb[:, 2]
    fid = frame.encode("ascii")
    return b"".join(
        (_PREAMBLE.pack(MAGIC, VERSION, len(fid)), fid, _TAIL.pack(worker, seq, n), records.tobytes())
    )


def decode_batch(
    data: bytes,
    max_records: int = DEFAULT_MAX_RECORDS,
    max_frame_id_len: int = MAX_FRAME_ID_LEN,
) -> Batch:
    """Decodes and checks a batch, with the same checks in the same order as Rust."""
    data = memoryview(data).cast("B")
    available = len(data)

    def truncated(needed: int) -> WireError:
        return WireError(
            "truncated_batch",
            f"batch is truncated: its header declares at least {needed} bytes, the body has {available}",
        )

    head = bytes(data[: len(MAGIC)])
    if head != MAGIC[: len(head)]:
        raise WireError("bad_magic", f'not a splatd batch: expected magic "SPLB", found {head!r}')
    if available < len(MAGIC) + 2:
        raise truncated(len(MAGIC) + 2)
    (version,) = struct.unpack_from("<H", data, len(MAGIC))
    if version != VERSION:
        raise WireError(
            "unsupported_version",
            f"unsupported batch format version {version}; this build reads version {VERSION}",
        )
    if available < _PREAMBLE.size:
        raise truncated(_PREAMBLE.size)
    _, _, id_len = _PREAMBLE.unpack_from(data, 0)
    max_id = min(max_frame_id_len, MAX_FRAME_ID_LEN)
    if id_len > max_id:
        raise WireError(
            "invalid_frame_id",
            f"invalid frame id: frame id is {id_len} bytes long; at most {max_id} are allowed",
        )
    pos = _PREAMBLE.size
    if available < pos + id_len:
        raise truncated(pos + id_len)
    try:
        frame = bytes(data[pos : pos + id_len]).decode("utf-8")
    except UnicodeDecodeError as e:
        raise WireError("malformed_batch", f"malformed batch: frame id is not valid UTF-8: {e}") from None
    pos += id_len
    if available < pos + _TAIL.size:
        # bincode reads field by field: report the end of the first missing one.
        missing = (available - pos) // 8
        raise truncated(pos + 8 * (missing + 1))
    validate_frame_id(frame)
    worker, seq, count = _TAIL.unpack_from(data, pos)
    pos += _TAIL.size
    needed = min(pos + count * RECORD_SIZE, _U64_MAX)
    if available < needed:
        raise truncated(needed)
    if count > max_records:
        raise WireError(
            "too_many_records", f"batch declares {count} records; at most {max_records} are accepted per batch"
        )
    if available > needed:
        raise WireError("trailing_bytes", f"batch has {available - needed} unexpected bytes after its last record")
    records = np.frombuffer(data, dtype=RECORD_DTYPE, count=count, offset=pos)
    rgb = np.column_stack((records["r"], records["g"], records["b"])).astype(np.float32, copy=False)
    return Batch(frame, worker, seq, records["x"].copy(), records["y"].copy(), rgb.reshape(count, 3))


def _is_transient(status: int) -> bool:
    # Not 501: the server lacks the feature (``denoiser_unavailable``); asking again won't help.
    return (status >= 500 and status != 501) or status in (408, 429)


class Client:
    """A blocking client of one splatd server (plain HTTP, urllib)."""

    def __init__(
        self,
        base_url: str,
        token: Optional[str] = None,
        *,
        timeout: float = 120.0,
        max_attempts: int = 10,
        initial_backoff: float = 0.1,
        max_backoff: float = 10.0,
        opener: Optional[urllib.request.OpenerDirector] = None,
    ):
        if not base_url.startswith("http://"):
            raise ValueError(f"invalid server URL {base_url!r}: only http:// is supported")
        self.base_url = base_url.rstrip("/")
        self.token = token
        self.timeout = timeout
        self.max_attempts = max(1, int(max_attempts))
        self.initial_backoff = initial_backoff
        self.max_backoff = max_backoff
        self._open = (opener or urllib.request.build_opener()).open

    def create_frame(
        self,
        id: str,
        width: int,
        height: int,
        cascades: Optional[dict] = None,
        resolve: Optional[dict] = None,
        aovs: Optional[List[Tuple[str, List[str]]]] = None,
        denoise: Optional[str] = None,
        denoise_guides: Optional[Dict[str, str]] = None,
    ) -> Dict[str, Any]:
        """``POST /v1/frames``; returns the FrameInfo as a dict. Omitted params take server defaults.

        ``cascades``: ``base``, ``cascades``, ``lowest_scale`` (the scale c0 of cascade 0; cascade j
        has scale c0 * base**j), ``luminance``. ``resolve``: ``variant`` (paper, shader, off, spread),
        ``kappa`` (support, in samples beyond ``kappa_min``, at which a brightness band gets full
        weight; bands with less are down-weighted, not rejected), ``kappa_min`` (subtracted from a
        band's support count; not a bound on kappa), ``kappa_exponent`` (kappa grows as
        kappa * N**kappa_exponent). ``aovs``: ``(layer name, [channel names])`` of the passes'
        other layers to keep as per-pixel means beside the beauty, e.g.
        ``[("ViewLayer.DiffCol", ["R", "G", "B"]), ("ViewLayer.Depth", ["Z"])]``; served as
        ``<layer>.<channel>`` channels of ``image.exr``. ``denoise``: ``"oidn"`` makes every
        ``image.exr`` of the frame carry OIDN's denoised final (layer ``denoised``) unless its
        query says ``denoise="none"``; ``denoise_guides``: ``{"albedo": AOV, "normal": AOV}``, the
        AOVs that guide it (``{}``: none; omitted, chosen by name, see PROTOCOL.md, "Denoised
        finals"). See proto/PROTOCOL.md and docs/ALGORITHM.md.
        """
        validate_frame_id(id)
        req: Dict[str, Any] = {"id": id, "width": int(width), "height": int(height)}
        if cascades is not None:
            req["cascades"] = cascades
        if resolve is not None:
            req["resolve"] = resolve
        if aovs:
            req["aovs"] = _aovs(aovs)
        if denoise is not None:
            req["denoise"] = denoise
        if denoise_guides is not None:
            req["denoise_guides"] = dict(denoise_guides)
        # The id also goes in a header, for proxies that route frames by id (deploy/nginx/).
        return self._request(
            "POST", "/v1/frames", json.dumps(req).encode(), "application/json", headers={"X-Splatd-Frame": id}
        )

    def create_or_get(
        self,
        id: str,
        width: int,
        height: int,
        cascades: Optional[Dict[str, Any]] = None,
        resolve: Optional[Dict[str, Any]] = None,
        aovs: Optional[List[Tuple[str, List[str]]]] = None,
        denoise: Optional[str] = None,
        denoise_guides: Optional[Dict[str, str]] = None,
    ) -> Dict[str, Any]:
        """``PUT /v1/frames/{id}``: creates the frame, or returns it when it exists with exactly
        these parameters (the FrameInfo as a dict). A frame with other parameters is refused with
        ``SplatdError`` 409 ``frame_exists`` naming each difference. Needs only a ``write`` token,
        and is safe to retry. Parameters as for ``create_frame``.
        """
        validate_frame_id(id)
        req: Dict[str, Any] = {"width": int(width), "height": int(height)}
        if cascades is not None:
            req["cascades"] = cascades
        if resolve is not None:
            req["resolve"] = resolve
        if aovs:
            req["aovs"] = _aovs(aovs)
        if denoise is not None:
            req["denoise"] = denoise
        if denoise_guides is not None:
            req["denoise_guides"] = dict(denoise_guides)
        return self._request("PUT", f"/v1/frames/{id}", json.dumps(req).encode(), "application/json")

    def frame_info(self, id: str, convergence: str = "fresh") -> Dict[str, Any]:
        """``GET /v1/frames/{id}?convergence=...``: ``"fresh"`` figures of a render of the frame
        as it is (on a frame that workers keep changing this waits for its render pace),
        ``"latest"`` the latest figures at once (their ``samples`` say what they saw), or
        ``"none"``: the counts alone, which never wait for a render."""
        validate_frame_id(id)
        if convergence not in ("fresh", "latest", "none"):
            raise ValueError(f"convergence must be 'fresh', 'latest' or 'none', not {convergence!r}")
        query = "" if convergence == "fresh" else f"?convergence={convergence}"
        return self._request("GET", f"/v1/frames/{id}{query}")

    def post_batch(self, frame: str, worker: int, seq: int, xs: Any, ys: Any, rgb: Any) -> Dict[str, Any]:
        """Encodes once and sends (retrying with the same bytes); returns the BatchAck.

        One request: it keeps nothing for after a server restart. A worker posts through
        :meth:`outbox` instead, which keeps every batch until it is on disk."""
        return self.post_encoded(frame, encode_batch(frame, worker, seq, xs, ys, rgb))

    def post_encoded(self, frame: str, body: bytes) -> Dict[str, Any]:
        """Sends an encoded batch for ``frame``; returns the BatchAck."""
        validate_frame_id(frame)
        return self._request("POST", f"/v1/frames/{frame}/samples", bytes(body), BATCH_CONTENT_TYPE)

    def outbox(self, frame: str, worker: int, **options: Any) -> "Outbox":
        """An :class:`Outbox` posting as ``worker`` to ``frame``: what a worker should post
        through, so that nothing it was told is applied is lost when the server restarts."""
        return Outbox(self, frame, worker, **options)

    def sync(self, frame: str) -> Dict[str, Any]:
        """``POST /v1/frames/{id}/sync``: returns (a SyncAck) once the frame is on disk.

        On its own this covers only what the *current* server process applied: a batch
        acknowledged by a process that was killed since is not covered. Workers post through an
        :class:`Outbox`, whose ``sync`` resends what a restart lost."""
        validate_frame_id(frame)
        return self._request("POST", f"/v1/frames/{frame}/sync")

    def post_pass(
        self, frame: str, worker: int, seq: int, exr: bytes, layer: Optional[str] = None
    ) -> Dict[str, Any]:
        """``POST /v1/frames/{id}/passes``: one rendered pass as OpenEXR bytes; returns the BatchAck.

        ``layer`` names the layer holding the beauty (``"ViewLayer.Combined"``); without it the
        server finds it (see proto/PROTOCOL.md, "Passes"). One request, like :meth:`post_batch`:
        a worker posts through :meth:`outbox`, which resends what a server restart lost.
        """
        return self._request("POST", _pass_path(frame, worker, seq, layer), bytes(exr), "image/x-exr")

    def image(self, frame: str, **query: Any) -> bytes:
        """``GET /v1/frames/{id}/image.exr`` with optional query parameters; returns the EXR bytes.

        ``image(frame, denoise="oidn")`` adds OIDN's denoised final as the layer ``denoised``
        (``denoised.R``, ``.G``, ``.B``; ``denoise_quality="fast"`` etc. picks OIDN's quality,
        ``denoise="none"`` turns a frame's default off); a server without OIDN refuses it with
        501 ``denoiser_unavailable`` (an ``Error``, not retried)."""
        validate_frame_id(frame)
        qs = "&".join(f"{k}={v}" for k, v in query.items())
        return self._request("GET", f"/v1/frames/{frame}/image.exr" + (f"?{qs}" if qs else ""), binary=True)

    def need(self, frame: str, tile: Optional[int] = None) -> dict:
        """``GET /v1/frames/{id}/need``: the need map (JSON ``NeedMap``), tiles row-major."""
        validate_frame_id(frame)
        qs = "" if tile is None else f"?tile={_check_u64('tile', tile)}"
        return self._request("GET", f"/v1/frames/{frame}/need{qs}")

    def delete_frame(self, frame: str) -> None:
        """``DELETE /v1/frames/{id}``."""
        validate_frame_id(frame)
        self._request("DELETE", f"/v1/frames/{frame}", binary=True)

    def _delay(self, retry: int, retry_after: Optional[float]) -> float:
        base = min(self.initial_backoff * (2 ** min(retry, 62)), self.max_backoff)
        delay = base / 2 + random.uniform(0, base / 2)  # "equal jitter"
        return min(max(delay, retry_after or 0.0), self.max_backoff)

    def _request(
        self,
        method: str,
        path: str,
        body: Optional[bytes] = None,
        content_type: Optional[str] = None,
        binary: bool = False,
        headers: Optional[dict] = None,
    ) -> Any:
        operation = f"{method} {path}"
        last = "none"
        retry_after: Optional[float] = None
        for attempt in range(self.max_attempts):
            if attempt:
                time.sleep(self._delay(attempt - 1, retry_after))
            retry_after = None
            req = urllib.request.Request(self.base_url + path, data=body, method=method)
            if content_type:
                req.add_header("Content-Type", content_type)
            if self.token:
                req.add_header("Authorization", f"Bearer {self.token}")
            for name, value in (headers or {}).items():
                req.add_header(name, value)
            try:
                with self._open(req, timeout=self.timeout) as resp:
                    raw = resp.read()
                    status = resp.status
            except urllib.error.HTTPError as e:
                raw = e.read()
                if _is_transient(e.code):
                    last = f"HTTP {e.code}: {raw[:512]!r}"
                    header = e.headers.get("Retry-After") if e.headers else None
                    if header and header.strip().isdigit():
                        retry_after = float(header.strip())
                    continue
                try:
                    err = json.loads(raw)
                    raise SplatdError(e.code, str(err["error"]), str(err["message"])) from None
                except (ValueError, KeyError, TypeError):
                    raise SplatdError(
                        e.code, f"http_{e.code}", f"HTTP {e.code} without a JSON error body: {raw[:512]!r}"
                    ) from None
            except (urllib.error.URLError, http.client.HTTPException, OSError) as e:
                last = f"{type(e).__name__}: {e}"
                continue
            if binary:
                return raw
            try:
                return json.loads(raw)
            except ValueError as e:
                raise SplatdError(status, "unexpected_response", f"{operation}: body is not JSON ({e})") from None
        raise SplatdError(None, "gave_up", f"{operation} failed after {self.max_attempts} attempts; last failure: {last}")


class Outbox:
    """The worker's side of the durability contract, for batches and passes alike
    (``proto/PROTOCOL.md``, "Exactly-once and durability").

    A ``200`` from a durable server means *applied*, not *on disk*: a server killed before its
    next snapshot comes back without what it applied since. So the outbox keeps every body it
    posted until the server reports it durable (the acknowledgement's ``durable_floor`` passes
    its sequence number, or a ``sync`` of the same server process answers ``durable``), and when
    an answer carries another ``boot`` than the one it was acknowledged under, it resends it,
    byte for byte: what the snapshot held comes back ``duplicate``, the rest is applied. What
    :meth:`sync` returns for is on disk, exactly once, across any number of restarts.

    Memory: kept bodies are bounded by ``max_kept_bytes``; past it the outbox syncs (which lets
    it forget everything). A server without ``--data-dir`` promises nothing beyond *applied*, and
    the outbox keeps nothing for it. Sequence numbers are the caller's: number a new worker id's
    batches from 0 so that ``durable_floor`` can advance (passes numbered otherwise are simply kept
    until the next sync).

    Example::

        outbox = client.outbox("shot010", worker)
        for k, exr in enumerate(passes):
            outbox.post_pass(k, exr)
        outbox.sync()  # every pass posted above is now on disk
    """

    #: How many server restarts one call rides out before it gives up.
    MAX_RESTARTS = 16

    def __init__(self, client: "Client", frame: str, worker: int, *, max_kept_bytes: int = 256 << 20):
        validate_frame_id(frame)
        self.client = client
        self.frame = frame
        self.worker = _check_u64("worker", worker)
        self.max_kept_bytes = int(max_kept_bytes)
        #: Bodies resent because the server restarted.
        self.resent = 0
        # seq -> [path, body, content type, boot it was last acknowledged under]
        self._kept: Dict[int, List[Any]] = {}
        self._kept_bytes = 0
        self._boot: Optional[int] = None

    @property
    def kept(self) -> int:
        """Bodies acknowledged as applied but not yet known to be on disk."""
        return len(self._kept)

    def post_batch(self, seq: int, xs: Any, ys: Any, rgb: Any) -> Dict[str, Any]:
        """Posts one batch (see :meth:`Client.post_batch`); returns its BatchAck."""
        body = encode_batch(self.frame, self.worker, seq, xs, ys, rgb)
        return self._post(seq, f"/v1/frames/{self.frame}/samples", body, BATCH_CONTENT_TYPE)

    def post_pass(self, seq: int, exr: bytes, layer: Optional[str] = None) -> Dict[str, Any]:
        """Posts one rendered pass (see :meth:`Client.post_pass`); returns its BatchAck."""
        return self._post(seq, _pass_path(self.frame, self.worker, seq, layer), bytes(exr), "image/x-exr")

    def sync(self) -> Dict[str, Any]:
        """Returns (the SyncAck) once everything this outbox had acknowledged is on disk,
        resending what a restart lost; then forgets it all."""
        for _ in range(self.MAX_RESTARTS):
            ack = self.client.sync(self.frame)
            if not ack["durable"]:
                self._forget(lambda seq: True)
                return ack
            stale = self._acknowledged_elsewhere(ack["boot"])
            if not stale:
                self._boot = ack["boot"]
                self._forget(lambda seq: True)
                return ack
            self._boot = ack["boot"]
            self._resend(stale)
        raise SplatdError(None, "restarting", f"{self.frame}: the server kept restarting while syncing")

    def _post(self, seq: int, path: str, body: bytes, content_type: str) -> Dict[str, Any]:
        seq = _check_u64("seq", seq)
        if seq in self._kept and self._kept[seq][1] != body:
            raise ValueError(f"seq {seq} of worker {self.worker} was already posted with other content")
        ack = self.client._request("POST", path, body, content_type)
        if ack.get("durable_floor") is not None:
            if seq not in self._kept:
                self._kept_bytes += len(body)
            self._kept[seq] = [path, body, content_type, ack["boot"]]
        self._heard(ack)
        if self._kept_bytes > self.max_kept_bytes:
            self.sync()
        return ack

    def _heard(self, ack: Dict[str, Any]) -> None:
        """Forgets what ``ack`` reports durable; resends the rest if the server restarted."""
        for _ in range(self.MAX_RESTARTS):
            floor = ack.get("durable_floor")
            if floor is not None:
                self._forget(lambda seq: seq < floor)
            restarted = self._boot is not None and ack["boot"] != self._boot
            self._boot = ack["boot"]
            if not restarted:
                return
            ack = self._resend(self._acknowledged_elsewhere(ack["boot"])) or ack
        raise SplatdError(None, "restarting", f"{self.frame}: the server kept restarting")

    def _resend(self, seqs: List[int]) -> Optional[Dict[str, Any]]:
        """Resends kept bodies, lowest number first; returns the last answer, or the first one
        from yet another server process (which the caller then handles as a restart)."""
        again = None
        for seq in sorted(seqs):
            path, body, content_type, _ = self._kept[seq]
            again = self.client._request("POST", path, body, content_type)
            self.resent += 1
            self._kept[seq][3] = again["boot"]
            if again["boot"] != self._boot:
                break
        return again

    def _acknowledged_elsewhere(self, boot: int) -> List[int]:
        """The kept bodies last acknowledged by another server process than ``boot``."""
        return [seq for seq, kept in self._kept.items() if kept[3] != boot]

    def _forget(self, durable: Any) -> None:
        for seq in [s for s in self._kept if durable(s)]:
            self._kept_bytes -= len(self._kept.pop(seq)[1])


def _pass_path(frame: str, worker: int, seq: int, layer: Optional[str]) -> str:
    validate_frame_id(frame)
    path = f"/v1/frames/{frame}/passes?worker={_check_u64('worker', worker)}&seq={_check_u64('seq', seq)}"
    if layer is not None:
        path += "&layer=" + urllib.parse.quote(layer, safe="")
    return path


def tile_windows(need_map: Dict[str, Any]) -> List[Tuple[int, int, int, int]]:
    """Every tile of a need map as a crop window ``(x, y, width, height)``, in the map's order
    (row-major; tiles at the right and bottom edge may be smaller than ``tile``)."""
    tile, tx, ty = int(need_map["tile"]), int(need_map["tiles_x"]), int(need_map["tiles_y"])
    width, height = int(need_map["width"]), int(need_map["height"])
    if len(need_map["need"]) != tx * ty:
        raise ValueError(f"need map has {len(need_map['need'])} scores for {tx}x{ty} tiles")
    windows = []
    for i in range(tx * ty):
        x, y = (i % tx) * tile, (i // tx) * tile
        windows.append((x, y, min(tile, width - x), min(tile, height - y)))
    return windows


def neediest_tiles(need_map: Dict[str, Any], count: int) -> List[Tuple[int, int, int, int]]:
    """The ``count`` neediest tiles of a need map as crop windows ``(x, y, width, height)``,
    neediest first (tiles at the right and bottom edge may be smaller than ``tile``)."""
    windows = tile_windows(need_map)
    need = need_map["need"]
    order = sorted(range(len(need)), key=lambda i: (-need[i], i))
    return [windows[i] for i in order[:count]]


def plan_samples(need_map: Dict[str, Any], samples: int) -> List[int]:
    """Spreads a budget of ``samples`` over the tiles of a need map: how many more samples each
    pixel of each tile should get (one number per tile, the map's order).

    The same rule as ``splatd_estimator::NeedMap::plan``: tile ``i`` gets a share of the budget in
    proportion to ``sqrt(need[i])`` (in proportion to its pixels when no tile has any need), as
    whole passes over its pixels: the whole parts first, then one more pass for the tiles with
    the largest fractions left (ties to the lower index) while it still fits. The plan never
    spends more than ``samples``; what it leaves is less than any tile that did not get one more
    pass.
    """
    samples = int(samples)
    if samples < 0:
        raise ValueError(f"a sample budget cannot be negative, got {samples}")
    windows = tile_windows(need_map)
    pixels = [w * h for (_, _, w, h) in windows]
    roots = [math.sqrt(max(float(n), 0.0)) for n in need_map["need"]]
    total = 0.0
    for r in roots:  # left to right, as Rust sums (Python 3.12's sum() compensates)
        total += r
    frame_pixels = int(need_map["width"]) * int(need_map["height"])
    passes, remainders, left = [], [], samples
    for i, n in enumerate(pixels):
        weight = roots[i] / total if total > 0 else n / frame_pixels
        share = samples * weight / n
        whole = min(math.floor(share), left // n)
        left -= whole * n
        passes.append(whole)
        remainders.append((share - whole, i))
    remainders.sort(key=lambda r: (-r[0], r[1]))
    for _, i in remainders:
        if pixels[i] <= left:
            passes[i] += 1
            left -= pixels[i]
    return passes


def selftest_batch() -> Tuple[str, int, int, np.ndarray, np.ndarray, np.ndarray]:
    """The fixed batch of ``--selftest-emit`` (mirrored in proto/tests/python_compat.rs)."""
    xs = np.array([0, 1919, _U32_MAX, 7], dtype=np.uint32)
    ys = np.array([0, 1079, _U32_MAX, 3], dtype=np.uint32)
    rgb = np.array(
        [
            [0.0, 0.5, 1.0],
            [0.1, 1e-3, 65504.0],
            [2.0**-149, 3.4028234663852886e38, 2.0**-20],  # f32 min subnormal, f32 max
            [123.456, 0.0, 1.0 / 3.0],
        ],
        dtype=np.float64,
    ).astype("<f4")
    return ("selftest.frame-01", 0x0102030405060708, (1 << 63) + 5, xs, ys, rgb)


def _main(argv: List[str]) -> int:
    if len(argv) == 2 and argv[0] == "--selftest-emit":
        with open(argv[1], "wb") as f:
            f.write(encode_batch(*selftest_batch()))
        return 0
    if len(argv) == 2 and argv[0] == "--selftest-check":
        with open(argv[1], "rb") as f:
            got = decode_batch(f.read())
        frame, worker, seq, xs, ys, rgb = selftest_batch()
        ok = (
            got.frame == frame
            and got.worker == worker
            and got.seq == seq
            and np.array_equal(got.xs, xs)
            and np.array_equal(got.ys, ys)
            and got.rgb.tobytes() == rgb.tobytes()
        )
        if not ok:
            sys.stderr.write(f"decoded batch differs from the self-test batch: {got!r}\n")
            return 1
        return 0
    sys.stderr.write(
        "usage: python3 -m splatd_client --selftest-emit PATH | --selftest-check PATH\n"
        "(import splatd_client to use the client)\n"
    )
    return 2


if __name__ == "__main__":
    sys.exit(_main(sys.argv[1:]))
