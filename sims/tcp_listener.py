"""A TCP listener for the simulated devices: 127.0.0.1, a port the OS chooses by default,
one callback per accepted connection, stopped by :meth:`TcpListener.close`."""

from __future__ import annotations

import socket
import threading
from typing import Callable


class TcpListener:
    """Accept connections on ``host:port`` (0: a free port) in a thread; ``on_connection(conn, addr)``
    gets each accepted socket (TCP_NODELAY set)."""

    def __init__(self, host: str, port: int, on_connection: Callable[[socket.socket, tuple], None], *,
                 name: str) -> None:
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((host, port))
        sock.listen(8)
        sock.settimeout(0.1)
        self._sock = sock
        self._on_connection = on_connection
        self._closing = threading.Event()
        self.port: int = sock.getsockname()[1]
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while not self._closing.is_set():
            try:
                conn, addr = self._sock.accept()
            except socket.timeout:
                continue
            except OSError:
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._on_connection(conn, addr)

    def close(self) -> None:
        self._closing.set()
        self._sock.close()
        self._thread.join(timeout=2.0)
