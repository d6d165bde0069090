"""The viewer started as a user starts it (:class:`ViewerProcess`), and clients of its
WebSocket without a browser, for the benchmarks, the soak run, the protocol fuzz cases and the
tests: requests as text (well formed or not), replies read until one is wanted, raw handshakes
with any ``Host`` and ``Origin``, a client that sends and never reads, and the viewer
process's memory.
"""

from __future__ import annotations

import base64
import json
import os
import re
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from urllib.parse import urlsplit

from mi_amr.errors import AMRError


class ViewerProcess:
    """``python -m mi_amr view SCENE --no-browser --port 0 ...`` with its URL."""

    def __init__(self, scene, out_dir, *extra, env=None):
        cmd = [sys.executable, "-u", "-m", "mi_amr", "view", str(scene), "--no-browser",
               "--port", "0", "--out", str(out_dir), *extra]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                     text=True, env=env)
        self.output, self.url = [], None
        for line in self.proc.stdout:
            self.output.append(line)
            m = re.search(r"serving (http://\S+/)", line)
            if m:
                self.url = m.group(1)
                break
        if self.url is None:
            raise AMRError("the viewer did not start:\n" + "".join(self.output))
        threading.Thread(target=lambda: self.output.extend(self.proc.stdout), daemon=True).start()

    def status(self) -> dict:
        with urllib.request.urlopen(self.url + "api/status", timeout=30) as r:
            return json.loads(r.read().decode())

    def stop(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.proc.kill()


class ViewerClient:
    """One WebSocket to the viewer at ``url`` (``http://host:port/``), as the page opens it
    (same origin)."""

    def __init__(self, url: str, timeout: float = 60.0):
        from websockets.sync.client import connect

        self.url = url
        self._connection = connect(url.replace("http", "ws", 1) + "ws", origin=url.rstrip("/"),
                                   max_size=None, open_timeout=timeout, close_timeout=5)
        self.ws = self._connection.__enter__()
        self.texts, self.frames = [], []

    def send(self, request) -> None:
        """``request``: a dict (sent as JSON) or text/bytes sent as they are."""
        self.ws.send(json.dumps(request) if isinstance(request, dict) else request)

    def until(self, wanted, timeout: float = 60.0):
        """Read messages until ``wanted(message)`` (a text message as a dict, a frame as its
        JSON header with ``"type": "frame"``) is true, and return that message; None when
        ``timeout`` seconds pass first or the viewer closes the socket."""
        from websockets.exceptions import ConnectionClosed

        end = time.monotonic() + timeout
        while True:
            left = end - time.monotonic()
            if left <= 0:
                return None
            try:
                data = self.ws.recv(timeout=left)
            except TimeoutError:
                return None
            except ConnectionClosed:
                return None
            if isinstance(data, bytes):
                n = int.from_bytes(data[:4], "little")
                message = dict(json.loads(data[4:4 + n]), type="frame")
                self.frames.append(message)
            else:
                message = json.loads(data)
                self.texts.append(message)
            if wanted(message):
                return message

    def close(self) -> None:
        self._connection.__exit__(None, None, None)


def handshake(url: str, host: str | None = None, origin: str | None = None,
              timeout: float = 30.0) -> int:
    """The HTTP status of a raw WebSocket handshake to ``url``'s ``/ws`` with ``Host: host``
    and ``Origin: origin`` as given (101: opened; the socket is closed at once)."""
    parts = urlsplit(url)
    lines = [f"GET /ws HTTP/1.1", f"Host: {host or parts.netloc}", "Upgrade: websocket",
             "Connection: Upgrade", "Sec-WebSocket-Version: 13",
             f"Sec-WebSocket-Key: {base64.b64encode(os.urandom(16)).decode()}"]
    if origin is not None:
        lines.append(f"Origin: {origin}")
    with socket.create_connection((parts.hostname, parts.port), timeout=timeout) as s:
        s.sendall(("\r\n".join(lines) + "\r\n\r\n").encode())
        head = b""
        while b"\r\n" not in head:
            chunk = s.recv(4096)
            if not chunk:
                break
            head += chunk
    return int(head.split(b" ", 2)[1]) if head.startswith(b"HTTP/") else 0


class SilentClient:
    """A WebSocket that sends requests and never reads a reply (the raw protocol: masked
    text frames), as a stalled or hostile page does."""

    def __init__(self, url: str, timeout: float = 30.0):
        parts = urlsplit(url)
        self.sock = socket.create_connection((parts.hostname, parts.port), timeout=timeout)
        # A small receive window: the viewer's sends stall soon, as with a page that hangs.
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall((f"GET /ws HTTP/1.1\r\nHost: {parts.netloc}\r\nUpgrade: websocket"
                           f"\r\nConnection: Upgrade\r\nSec-WebSocket-Version: 13\r\n"
                           f"Sec-WebSocket-Key: {key}\r\nOrigin: {url.rstrip('/')}\r\n\r\n")
                          .encode())
        head = b""
        while b"\r\n\r\n" not in head:
            chunk = self.sock.recv(1)
            if not chunk:
                raise ConnectionError("the viewer closed the handshake")
            head += chunk
        if b" 101 " not in head.split(b"\r\n", 1)[0]:
            raise ConnectionError(f"handshake refused: {head.splitlines()[0]!r}")

    def send(self, text: str, timeout: float = 5.0) -> bool:
        """Send one text frame; False when the viewer no longer takes data (it stopped reading
        this socket, or closed it) within ``timeout`` seconds."""
        payload = text.encode()
        mask = os.urandom(4)
        n = len(payload)
        head = bytes([0x81]) + (bytes([0x80 | n]) if n < 126 else
                                bytes([0x80 | 126]) + n.to_bytes(2, "big") if n < 1 << 16 else
                                bytes([0x80 | 127]) + n.to_bytes(8, "big"))
        body = _masked(payload, mask)
        self.sock.settimeout(timeout)
        try:
            self.sock.sendall(head + mask + body)
        except OSError:             # a timeout, a reset or a broken pipe
            return False
        return True

    def close(self) -> None:
        self.sock.close()


def _masked(payload: bytes, mask: bytes) -> bytes:
    import numpy as np

    data = np.frombuffer(payload, dtype=np.uint8)
    key = np.resize(np.frombuffer(mask, dtype=np.uint8), data.size)
    return (data ^ key).tobytes()


def rss_bytes(pid: int) -> int:
    """Resident memory of process ``pid`` (Linux's /proc), bytes."""
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    raise OSError(f"no VmRSS for process {pid}")
