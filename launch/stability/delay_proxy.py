"""A TCP proxy on loopback that delays what it forwards: network latency and jitter between the picking runtime and
the UR controller emulator, for the controller-timing axis.

``DelayProxy`` listens on ``listen_host`` at each of ``ports`` and forwards every connection to ``target_host`` at
the same port. Each chunk read from either side is sent on after ``latency_s`` plus a uniform draw in ``[-jitter_s,
+jitter_s]`` (at least 0), never before the chunk read before it in the same direction (TCP keeps the order, so a
late chunk holds back the ones behind it). Both directions are delayed alike, so a round trip takes twice the
latency. The proxy runs an asyncio loop in its own process (spawned), so that the runtime's threads and GIL do not
add their own delays; draws come from ``seed``.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import multiprocessing
import random
import socket
from collections.abc import Callable, Sequence

READ_BYTES = 65536


class DelayProxy:
    """A context manager: the proxy's process runs between ``__enter__`` (which waits until every port listens)
    and ``__exit__``."""

    def __init__(
        self,
        listen_host: str,
        target_host: str,
        ports: Sequence[int],
        latency_s: float,
        jitter_s: float = 0.0,
        seed: int = 0,
        start_timeout_s: float = 20.0,
    ) -> None:
        if latency_s < 0 or jitter_s < 0:
            raise ValueError(f"DelayProxy: latency_s and jitter_s must be >= 0, got {latency_s}, {jitter_s}")
        self.args = (listen_host, target_host, tuple(ports), float(latency_s), float(jitter_s), int(seed))
        self.start_timeout_s = start_timeout_s
        self.process: multiprocessing.Process | None = None

    def __enter__(self) -> DelayProxy:
        context = multiprocessing.get_context("spawn")
        receive, send = context.Pipe(duplex=False)
        self.process = context.Process(target=_serve, args=(*self.args, send), daemon=True, name="delay-proxy")
        self.process.start()
        send.close()
        if not receive.poll(self.start_timeout_s):
            self.__exit__(None, None, None)
            raise RuntimeError(f"DelayProxy on {self.args[0]}: not listening after {self.start_timeout_s} s")
        status = receive.recv()
        if status != "ready":
            self.__exit__(None, None, None)
            raise RuntimeError(f"DelayProxy on {self.args[0]}: {status}")
        return self

    def __exit__(self, *exc) -> None:
        if self.process is not None and self.process.is_alive():
            self.process.terminate()
            self.process.join(5.0)
            if self.process.is_alive():
                self.process.kill()
                self.process.join(5.0)
        self.process = None


def _serve(listen_host: str, target_host: str, ports: tuple[int, ...], latency_s: float, jitter_s: float, seed: int,
           conn) -> None:  # fmt: skip
    """The proxy process's main: serves until terminated; sends "ready" (or the error) on ``conn`` once listening."""
    rng = random.Random(seed)

    def delay() -> float:
        return max(0.0, latency_s + (rng.uniform(-jitter_s, jitter_s) if jitter_s else 0.0))

    async def main() -> None:
        try:
            servers = [await asyncio.start_server(functools.partial(_handle, target_host=target_host, port=port,
                                                                    delay=delay), listen_host, port)
                       for port in ports]  # fmt: skip
        except OSError as exc:
            conn.send(f"cannot listen: {exc}")
            return
        conn.send("ready")
        async with contextlib.AsyncExitStack() as stack:
            for server in servers:
                await stack.enter_async_context(server)
            await asyncio.Event().wait()

    asyncio.run(main())


async def _handle(reader, writer, target_host: str, port: int, delay: Callable[[], float]) -> None:
    """One client connection: open the target's, then pump both ways until either side closes."""
    try:
        up_reader, up_writer = await asyncio.open_connection(target_host, port)
    except OSError:
        writer.close()
        return
    for w in (writer, up_writer):
        sock = w.get_extra_info("socket")
        if sock is not None:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    await asyncio.gather(_pump(reader, up_writer, delay), _pump(up_reader, writer, delay), return_exceptions=True)
    for w in (writer, up_writer):
        w.close()


async def _pump(reader, writer, delay: Callable[[], float]) -> None:
    """Forwards ``reader`` to ``writer``, each chunk at its due time (``delay`` after it was read, in order)."""
    loop = asyncio.get_running_loop()
    queue: asyncio.Queue = asyncio.Queue()

    async def send() -> None:
        try:
            while True:
                due, data = await queue.get()
                if not data:
                    break
                wait = due - loop.time()
                if wait > 0:
                    await asyncio.sleep(wait)
                writer.write(data)
                await writer.drain()
        finally:
            with contextlib.suppress(OSError):
                writer.close()

    sender = asyncio.create_task(send())
    last_due = 0.0
    try:
        while not sender.done():
            data = await reader.read(READ_BYTES)
            last_due = max(loop.time() + delay(), last_due)
            await queue.put((last_due, data))
            if not data:
                break
    except OSError:
        await queue.put((0.0, b""))
    await sender
