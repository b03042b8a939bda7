"""An embedded MQTT 3.1.1 broker (amqtt) for tests and zero-install runs.

    with EmbeddedBroker() as broker:      # a free port on 127.0.0.1
        print(broker.url)                 # mqtt://127.0.0.1:PORT

`EmbeddedBroker` runs on its own asyncio loop in a daemon thread; `BrokerProcess` runs
the same broker as a child process (``python -m ldm broker``), which keeps amqtt off the
caller's GIL: use it when the caller is busy (a demo with many clients). This module is
the only place that touches amqtt. The broker allows anonymous clients, no persistence.
"""

from __future__ import annotations

import asyncio
import logging
import subprocess
import sys
import threading
import time
from typing import IO, Any

from ldm.errors import ConnectError

__all__ = ["BrokerProcess", "EmbeddedBroker", "read_line"]

_START_TIMEOUT = 10.0
_REBIND_TIMEOUT = 5.0  # s: how long a restart waits for its old port to be released


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
        from amqtt.broker import Broker  # the one amqtt import

        config = {
            "listeners": {"default": {"type": "tcp", "bind": f"{self.host}:{self.port}"}},
            "plugins": {
                "amqtt.plugins.authentication.AnonymousAuthPlugin": {"allow_anonymous": True}
            },
        }
        broker = Broker(config, loop=loop)
        await broker.start()
        server = broker._servers["default"].instance
        self.port = int(server.sockets[0].getsockname()[1])
        self._broker = broker

    def stop(self) -> None:
        """Close every connection (no DISCONNECT, like a crash) and stop listening."""
        broker, loop, thread = self._broker, self._loop, self._thread
        if broker is None or loop is None or thread is None:
            return
        self._broker = None
        try:
            asyncio.run_coroutine_threadsafe(broker.shutdown(), loop).result(_START_TIMEOUT)
        except Exception:
            logging.getLogger(__name__).info("embedded broker: unclean shutdown")
        loop.call_soon_threadsafe(loop.stop)
        thread.join(_START_TIMEOUT)

    def __enter__(self) -> EmbeddedBroker:
        return self.start()

    def __exit__(self, *_exc: object) -> None:
        self.stop()


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
