"""An S3 server of a test's own (moto's, on its own port) behind a gate the test can close: while it is closed,
connections to the store are refused and open ones dropped, as when the store's host or network is down; the
objects survive (moto keeps them in memory, so the server itself is never stopped)."""

from __future__ import annotations

import os
import socket
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path

from object_stores import port_answers
from worker_testing import free_port, wait_for

from navsim_lb.processes import child_process


class Gate:
    """Forwards connections from its own loopback port to `target_port` while open."""

    def __init__(self, target_port: int, host: str = "127.0.0.1") -> None:
        self.port, self.target_port, self.host = free_port(), target_port, host
        self.url = f"http://{host}:{self.port}"
        self._listener: socket.socket | None = None
        self._open: set[socket.socket] = set()
        self._lock = threading.Lock()

    def open(self) -> None:
        self._listener = socket.create_server((self.host, self.port))
        threading.Thread(target=self._accept, args=(self._listener,), daemon=True).start()

    def close(self) -> None:
        """Refuse new connections and drop the open ones."""
        assert self._listener is not None
        self._listener.close()
        with self._lock:
            for connection in self._open:
                with_shutdown(connection)
            self._open.clear()

    def _accept(self, listener: socket.socket) -> None:
        while True:
            try:
                client, _ = listener.accept()
            except OSError:  # closed
                return
            upstream = socket.create_connection(("127.0.0.1", self.target_port))
            with self._lock:
                self._open.update((client, upstream))
            for source, sink in ((client, upstream), (upstream, client)):
                threading.Thread(target=self._pump, args=(source, sink), daemon=True).start()

    def _pump(self, source: socket.socket, sink: socket.socket) -> None:
        try:
            while data := source.recv(1 << 16):
                sink.sendall(data)
        except OSError:  # dropped by close(), or by a side
            return
        finally:
            for connection in (source, sink):
                with_shutdown(connection)
                with self._lock:
                    self._open.discard(connection)


def with_shutdown(connection: socket.socket) -> None:
    with suppress(OSError):  # the other side closed it first
        connection.shutdown(socket.SHUT_RDWR)
    connection.close()


@contextmanager
def own_s3(directory: Path, host: str = "127.0.0.1") -> Iterator[Gate]:
    """Run a moto S3 server for the block; yield the open gate in front of it, listening on `host` (its `url`
    is the endpoint)."""
    directory.mkdir(parents=True, exist_ok=True)
    port = free_port()
    command = [sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)]
    with child_process(command, dict(os.environ), directory / "moto.log"):
        wait_for(lambda: port_answers(port), f"moto on port {port}")
        gate = Gate(port, host)
        gate.open()
        try:
            yield gate
        finally:
            gate.close()
