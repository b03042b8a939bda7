"""An embedded MQTT 3.1.1 broker (amqtt) for tests and zero-install runs.

    with EmbeddedBroker() as broker:      # a free port on 127.0.0.1
        print(broker.url)                 # mqtt://127.0.0.1:PORT

`EmbeddedBroker` runs on its own asyncio loop in a daemon thread; `BrokerProcess` runs
the same broker as a child process (``python -m ldm broker``), which keeps amqtt off the
caller's GIL: use it when the caller is busy (a demo with many clients). This module is
the only place that touches amqtt. The broker allows anonymous clients, no persistence.

``EmbeddedBroker.stop`` gives amqtt's ``shutdown()`` `_SHUTDOWN_TIMEOUT` seconds, then
closes the listening socket, aborts every connection left and cancels every task left
on the broker's loop. ``shutdown()`` can wait forever for a connection's reader task: a
packet that arrives as the task is cancelled makes Python 3.11's ``asyncio.wait_for``
return the packet and lose the cancellation. A stop that merely gave up on it left
the listening socket and the connections open: clients stayed connected to a broker
that no longer ran, and the restart found its port taken.
"""

from __future__ import annotations

import asyncio
import logging
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from typing import IO, Any

from ldm.errors import ConnectError

__all__ = ["BrokerProcess", "EmbeddedBroker", "read_line"]

_START_TIMEOUT = 10.0
_REBIND_TIMEOUT = 5.0  # s: how long a restart waits for its old port to be released
_SHUTDOWN_TIMEOUT = 2.0  # s: how long a stop lets amqtt shut down by itself
_HALT_TIMEOUT = 5.0  # s: how long a stop then waits for the cancelled tasks to end


def read_line(stream: IO[str], timeout: float) -> str:
    """One line from a child's pipe, or "" if none came within `timeout` seconds."""
    line: list[str] = []
    reader = threading.Thread(target=lambda: line.append(stream.readline()), daemon=True)
    reader.start()
    reader.join(timeout)
    return line[0] if line else ""


class EmbeddedBroker:
    """An amqtt broker on ``host:port`` (port 0 picks a free port; ``port`` tells which)."""

    def __init__(self, host: str = "127.0.0.1", port: int = 0) -> None:
        self.host = host
        self.port = port
        self._loop: asyncio.AbstractEventLoop | None = None
        self._broker: Any = None
        self._server: asyncio.Server | None = None
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        return f"mqtt://{self.host}:{self.port}"

    @property
    def running(self) -> bool:
        return self._broker is not None

    def start(self) -> EmbeddedBroker:
        """Start listening; after a stop, starts again on the same port (waiting up to
        `_REBIND_TIMEOUT` s for the old listening socket to be released)."""
        if self.running:
            return self
        for name in ("amqtt", "transitions"):
            logging.getLogger(name).setLevel(logging.WARNING)
        deadline = time.monotonic() + _REBIND_TIMEOUT
        while True:
            try:
                return self._start_once()
            except ConnectError as exc:
                if self.port == 0 or "in use" not in str(exc) or time.monotonic() > deadline:
                    raise
                time.sleep(0.1)

    def _start_once(self) -> EmbeddedBroker:
        ready = threading.Event()
        failure: list[BaseException] = []
        loop = asyncio.new_event_loop()

        def run() -> None:
            asyncio.set_event_loop(loop)
            try:
                loop.run_until_complete(self._open(loop))
            except BaseException as exc:
                failure.append(exc)
                ready.set()
                return
            ready.set()
            loop.run_forever()
            loop.close()

        self._loop = loop
        self._thread = threading.Thread(target=run, name=f"ldm-broker-{self.port}", daemon=True)
        self._thread.start()
        if not ready.wait(_START_TIMEOUT) or failure:
            self._broker = None
            raise ConnectError(
                f"embedded broker could not listen on {self.host}:{self.port}: "
                f"{failure[0] if failure else 'timeout'}; pick another port"
            )
        return self

    async def _open(self, loop: asyncio.AbstractEventLoop) -> None:
        config = {
            "listeners": {"default": {"type": "tcp", "bind": f"{self.host}:{self.port}"}},
            "plugins": {
                "amqtt.plugins.authentication.AnonymousAuthPlugin": {"allow_anonymous": True}
            },
        }
        broker = _broker_class()(config, loop=loop)
        await broker.start()
        server: asyncio.Server = broker._servers["default"].instance
        self.port = int(server.sockets[0].getsockname()[1])
        self._server = server
        self._broker = broker

    def stop(self) -> None:
        """Close every connection (no DISCONNECT, like a crash) and stop listening."""
        broker, server, loop, thread = self._broker, self._server, self._loop, self._thread
        if broker is None or server is None or loop is None or thread is None:
            return
        self._broker = self._server = None
        try:
            stopping = _stop(broker, server)
            asyncio.run_coroutine_threadsafe(stopping, loop).result(_START_TIMEOUT)
        except Exception:
            logging.getLogger(__name__).warning("embedded broker: unclean stop", exc_info=True)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(_START_TIMEOUT)

    def __enter__(self) -> EmbeddedBroker:
        return self.start()

    def __exit__(self, *_exc: object) -> None:
        self.stop()


class _SnapshotDict(dict[str, Any]):
    """A dict whose iteration walks a copy of its keys and items, so a loop that awaits
    may see it change."""

    def __iter__(self) -> Iterator[str]:
        return iter(list(super().__iter__()))

    def items(self) -> Any:
        return list(super().items())


def _broker_class() -> Any:
    """amqtt's broker, keeping its client connections so that a stop can drop them."""
    from amqtt.broker import Broker  # the one amqtt import

    class _Broker(Broker):  # type: ignore[misc]  # amqtt is untyped here
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            self.connections: set[asyncio.BaseTransport] = set()
            # amqtt 0.12 iterates its subscription table with awaits inside the loop
            # (a connect's retained re-send, a broadcast), so a subscribe in between
            # raised "dictionary changed size during iteration": iterate a copy.
            self._subscriptions = _SnapshotDict(self._subscriptions)  # type: ignore[has-type]

        async def stream_connected(
            self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, listener_name: str
        ) -> None:
            self.connections.add(writer.transport)
            try:
                await super().stream_connected(reader, writer, listener_name=listener_name)
            finally:
                self.connections.discard(writer.transport)

    return _Broker


async def _stop(broker: Any, server: asyncio.Server) -> None:
    """On the broker's loop: amqtt's shutdown, within a bound; then stop listening,
    abort every connection and end every task that is left."""
    try:
        await asyncio.wait_for(broker.shutdown(), _SHUTDOWN_TIMEOUT)
    except TimeoutError:
        logging.getLogger(__name__).info("embedded broker: shutdown stuck; dropping the rest")
    server.close()
    for transport in list(broker.connections):
        if isinstance(transport, asyncio.WriteTransport):
            transport.abort()
    tasks = asyncio.all_tasks() - {asyncio.current_task()}
    for task in tasks:
        task.cancel()
    if tasks:
        done, _ = await asyncio.wait(tasks, timeout=_HALT_TIMEOUT)
        for task in done:
            if not task.cancelled():
                task.exception()  # retrieved: the broker is gone, its errors with it


class BrokerProcess:
    """The embedded broker in a child process; same API as `EmbeddedBroker`."""

    def __init__(self, host: str = "127.0.0.1", port: int = 0) -> None:
        self.host = host
        self.port = port
        self._process: subprocess.Popen[str] | None = None

    @property
    def url(self) -> str:
        return f"mqtt://{self.host}:{self.port}"

    @property
    def running(self) -> bool:
        return self._process is not None and self._process.poll() is None

    def start(self) -> BrokerProcess:
        """Start the child and wait until it listens; restarts on the same port."""
        if self.running:
            return self
        command = [sys.executable, "-m", "ldm", "broker", "--host", self.host]
        process = subprocess.Popen(
            [*command, "--port", str(self.port)], stdout=subprocess.PIPE, text=True
        )
        line = read_line(process.stdout, _START_TIMEOUT) if process.stdout else ""
        if not line.startswith("ldm broker listening on"):
            process.kill()
            process.wait(_START_TIMEOUT)
            raise ConnectError(f"broker process did not start: {line.strip()}")
        self.port = int(line.rsplit(":", 1)[1])
        self._process = process
        return self

    def stop(self) -> None:
        """Kill the child (clients see a dropped connection)."""
        process, self._process = self._process, None
        if process is not None:
            process.kill()
            process.wait(_START_TIMEOUT)
            if process.stdout:
                process.stdout.close()

    def __enter__(self) -> BrokerProcess:
        return self.start()

    def __exit__(self, *_exc: object) -> None:
        self.stop()
