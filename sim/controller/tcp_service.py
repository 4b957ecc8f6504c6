"""A small threaded TCP service: one accept thread, one reader thread per connection, and sends that never block.

``Connection.send`` is safe to call from any thread (the 500 Hz tick included): it writes what the kernel
accepts at once and keeps the rest in a per-connection pending buffer, which the reader thread and later sends
flush. Messages marked ``droppable`` (state packages) are dropped whole, never cut, while that buffer is over
``MAX_PENDING_BYTES``, so a client that stops reading costs memory up to that limit and never time on the tick. A
message that may not be dropped (a reply) that would take the buffer over ``MAX_QUEUED_BYTES`` closes the
connection instead (a client that sends requests and never reads the replies), and a closed connection's buffer is
released.

Line-based services (dashboard, gripper) read through ``TcpService.lines``: a line longer than ``MAX_LINE_BYTES``
raises ``LineTooLongError`` after reading at most that much more than one ``recv``, so a client sending an endless
line costs neither memory nor copying; ``Connection.close_after_reply`` then answers it and closes.
"""

from __future__ import annotations

import contextlib
import logging
import select
import socket
import threading
import time
from collections.abc import Callable, Iterator

log = logging.getLogger(__name__)

_ACCEPT_POLL_S = 0.2  # how often blocked accept/recv calls look at the stop flag
MAX_PENDING_BYTES = 256 * 1024  # above this, droppable messages are discarded
MAX_QUEUED_BYTES = 1024 * 1024  # a reply that would take the pending buffer above this closes the connection
MAX_LINE_BYTES = 4096  # the longest line a line-based client (dashboard, gripper) may send
_RECV_BYTES = 65536
_DRAIN_S = 0.5  # how long ``close_after_reply`` reads and discards what the client still sends


class LineTooLongError(ValueError):
    """A line-based client sent more than ``MAX_LINE_BYTES`` without a newline."""


class Connection:
    """One accepted client socket (non-blocking)."""

    def __init__(self, sock: socket.socket, peer: tuple[str, int], service_name: str) -> None:
        self.sock = sock
        self.peer = peer
        self.service_name = service_name
        self.sock.setblocking(False)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._lock = threading.Lock()
        self._pending = bytearray()
        self.closed = False
        self.dropped_messages = 0
        self.sent_messages = 0

    def __repr__(self) -> str:
        return f"<{self.service_name} connection from {self.peer[0]}:{self.peer[1]}>"

    def send(self, data: bytes, droppable: bool = False) -> bool:
        """Queues ``data`` and writes as much as the socket takes now. False when dropped or closed."""
        with self._lock:
            if self.closed:
                return False
            if droppable and len(self._pending) > MAX_PENDING_BYTES:
                self.dropped_messages += 1
                return False
            if not droppable and len(self._pending) + len(data) > MAX_QUEUED_BYTES:
                log.warning(
                    "%r: the client does not read its replies (%d bytes waiting); closing the connection",
                    self,
                    len(self._pending),
                )
                self._close_locked()
                return False
            self._pending += data
            self.sent_messages += 1
            self._flush_locked()
            return not self.closed

    def flush(self) -> None:
        with self._lock:
            self._flush_locked()

    @property
    def has_pending(self) -> bool:
        return bool(self._pending)

    def _flush_locked(self) -> None:
        while self._pending and not self.closed:
            try:
                n = self.sock.send(self._pending)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:
                log.debug("%r: send failed (%s); closing", self, exc)
                self._close_locked()
                return
            del self._pending[:n]

    def recv(self, timeout_s: float = _ACCEPT_POLL_S) -> bytes | None:
        """Bytes received, ``None`` when nothing came within the timeout, ``b""`` when the peer closed."""
        if self.closed:
            return b""
        want_write = [self.sock] if self._pending else []
        try:
            readable, writable, _ = select.select([self.sock], want_write, [], timeout_s)
        except (OSError, ValueError):
            return b""
        if writable:
            self.flush()
        if not readable:
            return None
        try:
            return self.sock.recv(_RECV_BYTES)
        except (BlockingIOError, InterruptedError):
            return None
        except OSError:
            return b""

    def send_blocking(self, data: bytes, timeout_s: float = 2.0) -> bool:
        """For request/reply services (dashboard, gripper): waits up to ``timeout_s`` for the data to go out."""
        if not self.send(data):
            return False
        end_s = time.monotonic() + timeout_s
        while self.has_pending and not self.closed and time.monotonic() < end_s:
            try:
                select.select([], [self.sock], [], 0.05)
            except (OSError, ValueError):
                break
            self.flush()
        return not self.has_pending

    def close(self) -> None:
        with self._lock:
            self._close_locked()

    def close_after_reply(self, data: bytes, drain_s: float = _DRAIN_S) -> None:
        """Sends ``data`` (up to ``drain_s`` waiting for it to go out), ends the sending side, reads and discards what
        the client still sends for up to ``drain_s`` (closing with unread input would reset the connection, and the
        client could lose the reply), then closes."""
        self.send_blocking(data, timeout_s=drain_s)
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_WR)
        scratch = bytearray(4 * _RECV_BYTES)
        end_s = time.monotonic() + drain_s
        while not self.closed and (left := end_s - time.monotonic()) > 0:
            try:
                readable, _, _ = select.select([self.sock], [], [], left)
                if readable and not self.sock.recv_into(scratch):
                    break  # the client closed
            except (BlockingIOError, InterruptedError):
                continue
            except (OSError, ValueError):
                break
        self.close()

    def _close_locked(self) -> None:
        if self.closed:
            return
        self.closed = True
        self._pending = bytearray()  # a client that stopped reading may have left a large buffer: release it
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)
        self.sock.close()


class TcpService:
    """Listens on ``host:port`` and runs ``handler(connection)`` in a thread per accepted connection."""

    def __init__(self, name: str, host: str, port: int, handler: Callable[[Connection], None]) -> None:
        self.name = name
        self.host = host
        self.port = port
        self._handler = handler
        self._listener: socket.socket | None = None
        self._accept_thread: threading.Thread | None = None
        self._threads: set[threading.Thread] = set()
        self.connections: set[Connection] = set()
        self._lock = threading.Lock()
        self._stopping = threading.Event()

    def start(self) -> None:
        listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            listener.bind((self.host, self.port))
        except OSError as exc:
            listener.close()
            raise OSError(
                exc.errno,
                f"{self.name}: cannot listen on {self.host}:{self.port} ({exc.strerror}); is another emulator "
                f"running there? Pick another 127.0.0.x host or port",
            ) from exc
        listener.listen(16)
        listener.settimeout(_ACCEPT_POLL_S)
        self.port = listener.getsockname()[1]
        self._listener = listener
        self._accept_thread = threading.Thread(target=self._accept_loop, name=f"{self.name}-accept", daemon=True)
        self._accept_thread.start()
        log.debug("%s listening on %s:%d", self.name, self.host, self.port)

    def _accept_loop(self) -> None:
        assert self._listener is not None
        while not self._stopping.is_set():
            try:
                sock, peer = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                break
            conn = Connection(sock, peer, self.name)
            thread = threading.Thread(target=self._serve, args=(conn,), name=f"{self.name}-{peer[1]}", daemon=True)
            with self._lock:
                self.connections.add(conn)
                self._threads.add(thread)
            thread.start()

    def _serve(self, conn: Connection) -> None:
        log.debug("%r opened", conn)
        try:
            self._handler(conn)
        except Exception:
            log.exception("%r: handler failed", conn)
        finally:
            conn.close()
            with self._lock:
                self.connections.discard(conn)
                self._threads.discard(threading.current_thread())
            log.debug("%r closed", conn)

    @property
    def stopping(self) -> bool:
        return self._stopping.is_set()

    def stop(self, timeout_s: float = 2.0) -> None:
        """Closes the listener and every connection, then joins the threads (bounded by ``timeout_s`` each)."""
        self._stopping.set()
        if self._listener is not None:
            self._listener.close()
        if self._accept_thread is not None:
            self._accept_thread.join(timeout_s)
        with self._lock:
            conns, threads = list(self.connections), list(self._threads)
        for conn in conns:
            conn.close()
        for thread in threads:
            thread.join(timeout_s)

    def lines(
        self, conn: Connection, encoding: str = "utf-8", max_line_bytes: int = MAX_LINE_BYTES
    ) -> Iterator[list[str]]:
        """The non-empty, stripped text lines a line-based client (dashboard, gripper) sends, one list per read,
        until the client closes or the service stops. ``LineTooLongError`` when a line (or the unfinished rest)
        grows past ``max_line_bytes``: the caller answers and closes. Only the unfinished line is kept between
        reads, so each read costs its own length."""
        partial = bytearray()
        while not self.stopping:
            data = conn.recv()
            if data is None:
                continue
            if not data:
                return
            if b"\n" not in data:
                partial += data
                if len(partial) > max_line_bytes:
                    raise LineTooLongError(f"a line longer than {max_line_bytes} bytes")
                continue
            *complete, rest = data.split(b"\n")
            complete[0] = bytes(partial) + complete[0]
            partial = bytearray(rest)
            if len(partial) > max_line_bytes or any(len(raw) > max_line_bytes for raw in complete):
                raise LineTooLongError(f"a line longer than {max_line_bytes} bytes")
            batch = [raw.decode(encoding, errors="replace").strip() for raw in complete]
            if any(batch):
                yield [line for line in batch if line]


def start_all(services: list) -> None:
    """Starts each service (anything with ``start``/``stop``); if one cannot bind its port, stops those already
    started and re-raises, so a failed start leaves no port taken."""
    started = []
    try:
        for service in services:
            service.start()
            started.append(service)
    except OSError:
        for service in started:
            service.stop()
        raise
