"""A network camera for tests: an MJPEG stream over HTTP (``multipart/x-mixed-replace`` JPEG frames, as IP cameras
and ``mjpg-streamer`` serve it, read by OpenCV through FFmpeg) that can go away and come back.

``down()`` closes the listening socket and every connection (a camera unplugged or rebooting: connection refused);
``stall()`` keeps sockets open and sends nothing, to new connections neither (a stream dead behind a NAT or a hung
encoder: reads block); ``serve()`` sends frames again (after ``down()``, listening on the same port).
"""

from __future__ import annotations

import socket
import threading
import time

import cv2
import numpy as np

from tests.service.conftest import tcp_listener

BOUNDARY = b"frame"


class MjpegServer:
    def __init__(self, size: tuple[int, int] = (64, 48), fps: float = 20.0, port: int = 0):
        self.size, self.period, self.port = size, 1.0 / fps, port
        width, height = size
        gradient = np.repeat(np.linspace(0, 255, width, dtype=np.uint8)[None, :, None], 3, axis=2)
        self.jpeg = cv2.imencode(".jpg", np.repeat(gradient, height, axis=0))[1].tobytes()
        self.mode = "down"
        self.sent = 0  # frames sent, over every connection
        self._listener: socket.socket | None = None
        self._connections: list[socket.socket] = []
        self._lock = threading.Lock()

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}/stream.mjpg"

    def serve(self) -> None:
        with self._lock:
            if self._listener is None:
                listener = tcp_listener(self.port)
                self.port = listener.getsockname()[1]
                self._listener = listener
                threading.Thread(target=self._accept, args=(listener,), daemon=True).start()
            self.mode = "serving"

    def stall(self) -> None:
        self.mode = "stalled"

    def down(self) -> None:
        with self._lock:
            self.mode = "down"
            # shutdown() first: close() alone leaves the socket listening while the accepting thread is in accept()
            for connection in [*([self._listener] if self._listener is not None else []), *self._connections]:
                try:
                    connection.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
            if self._listener is not None:
                self._listener.close()
                self._listener = None
            self._connections = []

    def _accept(self, listener: socket.socket) -> None:
        while True:
            try:
                connection, _ = listener.accept()
            except OSError:
                return  # closed by down()
            with self._lock:
                if self.mode == "down":
                    connection.close()
                    return
                self._connections.append(connection)
            threading.Thread(target=self._stream, args=(connection,), daemon=True).start()

    def _wait_while_stalled(self) -> bool:
        while self.mode == "stalled":
            time.sleep(0.01)
        return self.mode == "serving"

    def _stream(self, connection: socket.socket) -> None:
        try:
            connection.recv(65536)  # the request; any path will do
            if not self._wait_while_stalled():
                return
            connection.sendall(b"HTTP/1.0 200 OK\r\nCache-Control: no-cache\r\n"
                               b"Content-Type: multipart/x-mixed-replace; boundary=" + BOUNDARY + b"\r\n\r\n")
            part = (b"--" + BOUNDARY + b"\r\nContent-Type: image/jpeg\r\nContent-Length: %d\r\n\r\n" % len(self.jpeg)
                    + self.jpeg + b"\r\n")
            while self._wait_while_stalled():
                connection.sendall(part)
                self.sent += 1
                time.sleep(self.period)
        except OSError:
            pass  # the client went away, or down()
        finally:
            connection.close()
