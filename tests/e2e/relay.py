"""A TCP forwarder standing for the radio link between two machines: what connects to its port is forwarded to
``target``. ``cut()`` drops the link: ``"refuse"`` closes every connection (both ends see a reset) and resets new
ones (their times in ``refused``), as a machine whose router is down answers; ``"freeze"`` forwards nothing and
closes nothing, as a radio out of range does (the ends notice only by their lease, new connections get no answer).
``restore()`` brings it back (tests/e2e/test_link_loss.py). ``rate_bps`` makes it a thin link: each direction carries at
most that many bits a second (a token bucket), and holds at most ``buffer_bytes`` in its receive buffer, as a radio's
queue does; the rest waits in the sender's socket (tests/e2e/test_thin_link.py). ``buffer_bytes`` without a rate: a
frozen link fills as a radio's would, after that much, not after the megabytes a loopback socket takes."""

from __future__ import annotations

import contextlib
import select
import socket
import struct
import threading
import time

from tests.service.conftest import tcp_listener

CHUNK = 1 << 16


class Relay:
    def __init__(self, target_port: int, target_host: str = "127.0.0.1", rate_bps: float | None = None,
                 buffer_bytes: int | None = None):
        self.target = (target_host, target_port)
        # a thin link's radio queue: 32 KB unless given
        self.rate_bps, self.buffer_bytes = rate_bps, buffer_bytes or (32 << 10 if rate_bps else None)
        self.port = 0
        self.cut_mode: str | None = None  # None: the link is up
        self.accepted = 0  # connections forwarded, over its life
        self.refused: list[float] = []  # when (monotonic) a connection was reset while cut with "refuse"
        self._pairs: list[tuple[socket.socket, socket.socket]] = []
        self._held: list[socket.socket] = []  # connections accepted while frozen, forwarded on restore
        self._listener: socket.socket | None = None
        self._lock = threading.Lock()
        self._flowing = threading.Event()
        self._flowing.set()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []

    def __enter__(self) -> "Relay":
        self._listen()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._flowing.set()
        if self._listener is not None:
            _close(self._listener)
        with self._lock:
            pairs, held, self._pairs, self._held = self._pairs, self._held, [], []
        for sock in [*held, *(s for pair in pairs for s in pair)]:
            _close(sock)
        for thread in self._threads:
            thread.join(timeout=5)

    def _listen(self) -> None:
        listener = tcp_listener(self.port)
        self.port = listener.getsockname()[1]
        self._listener = listener
        self._spawn(self._accept, listener)

    def _spawn(self, target, *args) -> None:
        thread = threading.Thread(target=target, args=args, daemon=True)
        thread.start()
        self._threads.append(thread)

    def _accept(self, listener: socket.socket) -> None:
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([listener], [], [], 0.1)
                if not ready:
                    continue
                inbound, _ = listener.accept()
            except (OSError, ValueError):
                return  # the relay stops
            with self._lock:
                mode = self.cut_mode
                if mode == "freeze":
                    self._held.append(inbound)
                    continue
                if mode == "refuse":
                    self.refused.append(time.monotonic())
            if mode == "refuse":
                _reset(inbound)
                continue
            self._forward(inbound)

    def _forward(self, inbound: socket.socket) -> None:
        try:
            outbound = socket.create_connection(self.target, timeout=5)
        except OSError:
            _close(inbound)  # nothing listens there (the base station's router is down): the caller sees a close
            return
        outbound.settimeout(None)
        if self.buffer_bytes:
            for sock in (inbound, outbound):
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, self.buffer_bytes)
        with self._lock:
            self._pairs.append((inbound, outbound))
            self.accepted += 1
        self._spawn(self._pump, inbound, outbound)
        self._spawn(self._pump, outbound, inbound)

    def _pump(self, source: socket.socket, sink: socket.socket) -> None:
        bucket = _TokenBucket(self.rate_bps) if self.rate_bps else None
        while not self._stop.is_set():
            self._flowing.wait()  # frozen: neither read nor write, the bytes wait in the kernel's buffers
            try:
                ready, _, _ = select.select([source], [], [], 0.1)
                if not ready or not self._flowing.is_set():
                    continue
                data = source.recv(bucket.burst if bucket else CHUNK)
                if not data:
                    break
                if bucket:
                    bucket.take(len(data))
                sink.sendall(data)
            except (OSError, ValueError):
                break
        for sock in (source, sink):
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)

    def cut(self, mode: str = "refuse") -> None:
        """Drop the link until :meth:`restore` (see the module docstring for the modes)."""
        if mode not in ("refuse", "freeze"):
            raise ValueError(mode)
        with self._lock:
            self.cut_mode = mode
            pairs = list(self._pairs) if mode == "refuse" else []
            if mode == "refuse":
                self._pairs = []
        if mode == "freeze":
            self._flowing.clear()
            return
        for pair in pairs:
            for sock in pair:
                _reset(sock)

    def restore(self) -> None:
        with self._lock:
            self.cut_mode = None
            held, self._held = self._held, []
        self._flowing.set()
        for inbound in held:
            self._forward(inbound)


class _TokenBucket:
    """``rate_bps`` bits a second on average, in bursts of at most 10 ms' worth (at least one TCP segment)."""

    def __init__(self, rate_bps: float):
        self.rate = rate_bps / 8  # bytes a second
        self.burst = max(1500, int(self.rate * 0.01))
        self.tokens, self.at = float(self.burst), time.monotonic()

    def take(self, size: int) -> None:
        now = time.monotonic()
        self.tokens = min(self.burst, self.tokens + (now - self.at) * self.rate) - size
        self.at = now
        if self.tokens < 0:
            time.sleep(-self.tokens / self.rate)


def _reset(sock: socket.socket) -> None:
    """Close with a reset (SO_LINGER 0), as a vanished peer's stack answers."""
    with contextlib.suppress(OSError):
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    _close(sock)


def _close(sock: socket.socket) -> None:
    with contextlib.suppress(OSError):
        sock.close()
