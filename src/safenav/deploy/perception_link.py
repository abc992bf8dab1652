"""A tiny loopback wire format for perception data: depth images, point clouds, tracked obstacles.

The vehicle simulator serves it over TCP; on a real drone the camera driver and the obstacle
tracker would feed :class:`~safenav.deploy.runtime.OnboardRuntime` directly (or through this
format from another process). One frame on the wire::

    uint32 big-endian  total length L of what follows
    uint32 big-endian  header length J
    J bytes            header, UTF-8 JSON
    L - 4 - J bytes    payload: the arrays the header describes, back to back

Header fields: ``stamp`` (seconds, the sender's ``time.monotonic()``; one clock on one computer),
``depth`` (list of images: ``shape`` (H, W), ``dtype`` ``"uint16"`` (millimetres, 0 = no return,
the RealSense convention) or ``"float32"`` (metres, NaN/0 = no return), ``scale`` (metres per unit),
intrinsics ``fx fy cx cy``, camera-to-world rotation ``R`` (row-major 3x3, optical frame: x right,
y down, z forward) and translation ``t``, and ``offset``/``nbytes`` into the payload), ``points``
(optional ``{"n", "offset", "nbytes"}``: float32 ``(n, 3)`` world points), ``obstacles`` (tracked
moving obstacles: ``p``, ``v`` (world, m and m/s), ``width``, ``height``, optional ``cuboid``), and
free-form ``truth`` (the simulator's ground truth for logs; a runtime never reads it).
"""

from __future__ import annotations

import contextlib
import json
import socket
import struct
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

MAX_FRAME_BYTES = 32 * 1024 * 1024


@dataclass
class DepthImage:
    """One depth image with its pinhole intrinsics and camera-to-world pose (optical frame)."""

    depth: np.ndarray  # (H, W) float32 metres (NaN / 0 = no return)
    fx: float
    fy: float
    cx: float
    cy: float
    R: np.ndarray  # (3, 3) camera-to-world rotation
    t: np.ndarray  # (3,) camera position in the world


@dataclass
class TrackedObstacle:
    """A moving obstacle from a tracker: centre ``p`` and velocity ``v`` in the world (ENU)."""

    p: np.ndarray
    v: np.ndarray
    width: float
    height: float
    cuboid: bool | None = None  # None: derived from the height (see runtime)


@dataclass
class PerceptionFrame:
    stamp: float
    depth: list[DepthImage] = field(default_factory=list)
    points: np.ndarray | None = None  # (N, 3) float32 world points
    obstacles: list[TrackedObstacle] | None = None  # None: this frame has no tracker output
    truth: dict[str, Any] = field(default_factory=dict)


def encode_frame(frame: PerceptionFrame, depth_as_uint16: bool = True) -> bytes:
    header: dict[str, Any] = {"stamp": float(frame.stamp), "depth": [], "truth": frame.truth}
    chunks: list[bytes] = []
    offset = 0

    def add(buf: bytes) -> tuple[int, int]:
        nonlocal offset
        chunks.append(buf)
        start, offset = offset, offset + len(buf)
        return start, len(buf)

    for img in frame.depth:
        d = np.asarray(img.depth, dtype=np.float32)
        if depth_as_uint16:
            mm = np.where(np.isfinite(d) & (d > 0), np.round(d * 1000.0), 0.0)
            raw, dtype, scale = np.clip(mm, 0, 65535).astype(">u2").tobytes(), "uint16", 0.001
        else:
            raw, dtype, scale = d.astype(">f4").tobytes(), "float32", 1.0
        off, nb = add(raw)
        header["depth"].append({
            "shape": list(d.shape), "dtype": dtype, "scale": scale, "fx": img.fx, "fy": img.fy,
            "cx": img.cx, "cy": img.cy, "R": np.asarray(img.R, dtype=float).reshape(-1).tolist(),
            "t": np.asarray(img.t, dtype=float).reshape(-1).tolist(), "offset": off, "nbytes": nb,
        })  # fmt: skip
    if frame.points is not None:
        pts = np.asarray(frame.points, dtype=">f4").reshape(-1, 3)
        off, nb = add(pts.tobytes())
        header["points"] = {"n": int(pts.shape[0]), "offset": off, "nbytes": nb}
    if frame.obstacles is not None:
        header["obstacles"] = [
            {"p": np.asarray(o.p, dtype=float).tolist(), "v": np.asarray(o.v, dtype=float).tolist(),
             "width": float(o.width), "height": float(o.height), "cuboid": o.cuboid}
            for o in frame.obstacles
        ]  # fmt: skip
    hdr = json.dumps(header, allow_nan=True).encode()
    body = struct.pack(">I", len(hdr)) + hdr + b"".join(chunks)
    return struct.pack(">I", len(body)) + body


def decode_frame(body: bytes) -> PerceptionFrame:
    """Inverse of :func:`encode_frame` (``body`` without the leading total length); any malformed
    frame raises ``ValueError`` (``tests/test_deploy_fuzz.py`` feeds it random bytes)."""
    try:
        return _decode(body)
    except (KeyError, TypeError, IndexError, AttributeError, OverflowError, RecursionError) as err:
        # OverflowError: int() of an infinite JSON number; RecursionError: absurdly nested JSON.
        raise ValueError(f"malformed perception frame: {err!r}") from None


def _decode(body: bytes) -> PerceptionFrame:
    if len(body) < 4:
        raise ValueError("perception frame too short")
    (hlen,) = struct.unpack(">I", body[:4])
    if hlen > len(body) - 4:
        raise ValueError("perception frame header length exceeds the frame")
    header = json.loads(body[4 : 4 + hlen].decode())
    payload = memoryview(body)[4 + hlen :]

    def chunk(spec: dict, dtype: str) -> np.ndarray:
        off, nb = int(spec["offset"]), int(spec["nbytes"])
        if off < 0 or nb < 0 or off + nb > len(payload):
            raise ValueError("perception frame array lies outside the payload")
        return np.frombuffer(payload[off : off + nb], dtype=dtype)

    truth = header.get("truth") or {}
    if not isinstance(truth, dict):
        raise ValueError(f"perception frame truth is a {type(truth).__name__}, not an object")
    frame = PerceptionFrame(stamp=float(header["stamp"]), truth=truth)
    for d in header.get("depth", []):
        h, w = (int(x) for x in d["shape"])
        if d["dtype"] == "uint16":
            arr = chunk(d, ">u2").astype(np.float32).reshape(h, w) * float(d["scale"])
        elif d["dtype"] == "float32":
            arr = chunk(d, ">f4").astype(np.float32).reshape(h, w) * float(d["scale"])
        else:
            raise ValueError(f"unknown depth dtype {d['dtype']!r}")
        frame.depth.append(DepthImage(
            depth=arr, fx=float(d["fx"]), fy=float(d["fy"]), cx=float(d["cx"]), cy=float(d["cy"]),
            R=np.asarray(d["R"], dtype=np.float64).reshape(3, 3),
            t=np.asarray(d["t"], dtype=np.float64).reshape(3),
        ))  # fmt: skip
    if "points" in header:
        frame.points = chunk(header["points"], ">f4").astype(np.float32).reshape(-1, 3)
    if "obstacles" in header:
        vec3 = lambda x: np.asarray(x, dtype=np.float64).reshape(3)  # noqa: E731
        frame.obstacles = [
            TrackedObstacle(p=vec3(o["p"]), v=vec3(o["v"]), width=float(o["width"]),
                            height=float(o["height"]), cuboid=o.get("cuboid"))
            for o in header["obstacles"]
        ]  # fmt: skip
    return frame


class PerceptionClient:
    """Connects to a perception server and calls ``on_frame`` for every frame, in its own thread.

    Reconnects while :meth:`close` has not been called; bad frames are dropped (``on_error``),
    and so are frames whose ``on_frame`` raises (reported to ``on_error``; the link goes on).
    """

    def __init__(
        self,
        host: str,
        port: int,
        on_frame: Callable[[PerceptionFrame], None],
        on_error: Callable[[str], None] | None = None,
    ) -> None:
        self.host, self.port = host, port
        self.on_frame, self.on_error = on_frame, on_error or (lambda msg: None)
        self._stop = threading.Event()
        self._sock: socket.socket | None = None
        self.frames = 0
        self.connected = threading.Event()
        self._thread = threading.Thread(target=self._run, name="perception-client", daemon=True)

    def start(self) -> PerceptionClient:
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        sock = self._sock
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)
        self._thread.join(timeout=2.0)

    def _recv_exact(self, sock: socket.socket, n: int) -> bytes:
        buf = bytearray()
        while len(buf) < n:
            try:
                part = sock.recv(min(n - len(buf), 1 << 20))
            except TimeoutError:
                if self._stop.is_set():
                    raise ConnectionError("closed") from None
                continue
            if not part:
                raise ConnectionError("perception server closed the connection")
            buf += part
        return bytes(buf)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                sock = socket.create_connection((self.host, self.port), timeout=1.0)
            except OSError:
                self._stop.wait(0.2)
                continue
            sock.settimeout(1.0)
            self._sock = sock
            self.connected.set()
            try:
                while not self._stop.is_set():
                    (length,) = struct.unpack(">I", self._recv_exact(sock, 4))
                    if length > MAX_FRAME_BYTES:
                        raise ConnectionError(f"perception frame of {length} bytes is too large")
                    body = self._recv_exact(sock, length)
                    try:
                        frame = decode_frame(body)
                    except ValueError as err:
                        self.on_error(f"bad perception frame dropped: {err}")
                        continue
                    self.frames += 1
                    try:
                        self.on_frame(frame)
                    except Exception as err:  # noqa: BLE001 -- one frame must not end the link
                        self.on_error(f"perception frame handler failed: {err!r}")
            except (OSError, ConnectionError) as err:
                if not self._stop.is_set():
                    self.on_error(f"perception link: {err}")
            finally:
                self.connected.clear()
                self._sock = None
                sock.close()


__all__ = [
    "DepthImage",
    "PerceptionClient",
    "PerceptionFrame",
    "TrackedObstacle",
    "decode_frame",
    "encode_frame",
]
