"""Hostile TCP peers on 127.0.0.1 for the tests of every client that talks to a
server (a Dask scheduler, an OpenIGTLink server): real sockets, no mocks.

``TCPPeer(behaviour)`` listens on a free port and, for every connection it
accepts, runs ``behaviour(conn, stop)`` in a thread of its own (``stop`` is a
``threading.Event`` set by :meth:`TCPPeer.close`). The behaviours of issue #34:
:func:`silent` (accepts and never answers), :func:`random_bytes` (sends bytes
that are no protocol's, then holds), :func:`close_at_once`.
"""

from __future__ import annotations

import os
import socket
import threading


def silent(conn, stop):
    """Accept, read nothing, send nothing, hold the connection open."""
    stop.wait(60)


def random_bytes(conn, stop, n=4096):
    """Send ``n`` random bytes, then hold the connection open."""
    conn.sendall(os.urandom(n))
    stop.wait(60)


def close_at_once(conn, stop):
    """Close the connection as soon as it is accepted."""


class TCPPeer:
    """A server on 127.0.0.1 (a free port) running ``behaviour`` per connection;
    ``address`` is ``tcp://127.0.0.1:PORT``, ``connections`` counts the accepted ones."""

    def __init__(self, behaviour):
        self.behaviour = behaviour
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(16)
        self.port = self.sock.getsockname()[1]
        self.address = f"tcp://127.0.0.1:{self.port}"
        self.connections = 0
        self.stop = threading.Event()
        self._threads = []
        self._accept = threading.Thread(target=self._serve, daemon=True)
        self._accept.start()

    def _serve(self):
        # a short accept time-out: close() ends this loop without relying on a close
        # from another thread waking accept()
        self.sock.settimeout(0.2)
        while not self.stop.is_set():
            try:
                conn, _ = self.sock.accept()
            except socket.timeout:
                continue
            except OSError:        # closed: the test is over
                return
            conn.settimeout(None)
            self.connections += 1
            t = threading.Thread(target=self._one, args=(conn,), daemon=True)
            t.start()
            self._threads.append(t)

    def _one(self, conn):
        with conn:
            try:
                self.behaviour(conn, self.stop)
            except OSError:        # the client went away first: what a peer sees too
                pass

    def close(self):
        self.stop.set()
        self._accept.join(5)
        self.sock.close()
        for t in self._threads:
            t.join(5)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
