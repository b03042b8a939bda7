"""Brokers on this machine, for local deployments, the demo, benchmarks and tests: the
embedded amqtt broker or a real Mosquitto on a free port.

    with start_broker("mosquitto") as broker:   # or "embedded"
        core = Core.create("user", broker.url)

Both kinds share the `RunningBroker` protocol (``url``, ``port``, ``start``, ``stop``;
``stop`` then ``start`` restarts on the same port). Mosquitto gets a generated config
with ``set_tcp_nodelay true``. For pytest fixtures see `ldm.local.pytest_plugin`.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import tempfile
import time
import weakref
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, Literal, Protocol, Self

from ldm.errors import ConnectError
from ldm.local.embedded import BrokerProcess, EmbeddedBroker

__all__ = [
    "BrokerKind",
    "MosquittoBroker",
    "RunningBroker",
    "find_mosquitto",
    "free_port",
    "mosquitto_acl",
    "mosquitto_required",
    "start_broker",
    "wait_for",
]

BrokerKind = Literal["embedded", "embedded-process", "mosquitto"]


class RunningBroker(Protocol):
    """What a local deployment or a test needs from a broker."""

    @property
    def url(self) -> str: ...

    @property
    def port(self) -> int: ...

    def start(self) -> Self: ...

    def stop(self) -> None: ...


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that was free a moment ago."""
    with socket.socket() as sock:
        sock.bind((host, 0))
        return int(sock.getsockname()[1])


def find_mosquitto() -> str | None:
    """The mosquitto binary: $LDM_MOSQUITTO if set, else PATH, /usr/sbin, /usr/local/sbin."""
    chosen = os.environ.get("LDM_MOSQUITTO")
    if chosen is not None:
        return chosen if os.access(chosen, os.X_OK) else None
    extra = os.pathsep.join(["/usr/sbin", "/usr/local/sbin", "/sbin"])
    return shutil.which("mosquitto", path=os.environ.get("PATH", "") + os.pathsep + extra)


def mosquitto_required() -> bool:
    """True when LDM_REQUIRE_MOSQUITTO=1: a missing mosquitto must fail, not skip."""
    return os.environ.get("LDM_REQUIRE_MOSQUITTO", "") == "1"


def wait_for(condition: Callable[[], object], timeout: float = 5.0, interval: float = 0.01) -> bool:
    """Poll a zero-argument callable until it is truthy; False on timeout."""
    deadline = time.monotonic() + timeout
    while True:
        if condition():
            return True
        if time.monotonic() > deadline:
            return False
        time.sleep(interval)


def mosquitto_acl(core_user: str, providers: Mapping[str, str]) -> str:
    """Mosquitto ACL lines for one cluster: participants are confined by client id (%c).

    ``providers`` maps a provider's user name to its service name; the core's user may
    read and write every ``ldm/`` topic (and the backbone's, on that broker).
    """
    lines = [
        "# participants (any client): their own topics, where the service list comes too",
        "pattern write ldm/p/%c/up/#",
        "pattern read ldm/p/%c/down/#",
        f"user {core_user}",
        "topic readwrite ldm/#",
    ]
    for user, service in providers.items():
        lines += [f"user {user}", f"topic readwrite ldm/svc/{service}/#"]
    return "\n".join(lines) + "\n"


class MosquittoBroker:
    """A Mosquitto process on 127.0.0.1 with a generated config (anonymous by default).

    ``acl`` is the text of an ACL file (see `mosquitto_acl`); ``extra_config`` is
    appended to the config verbatim. ``run_as``: a user id (and group id) to run mosquitto
    as, when started by root, e.g. 1883 as in the eclipse-mosquitto image.
    """

    def __init__(
        self,
        port: int = 0,
        *,
        extra_config: str = "",
        allow_anonymous: bool = True,
        acl: str | None = None,
        run_as: int | None = None,
    ) -> None:
        binary = find_mosquitto()
        if binary is None:
            raise ConnectError("mosquitto is not installed (apt-get install mosquitto)")
        self.binary = binary
        self.port = port or free_port()
        self.host = "127.0.0.1"
        self.directory = Path(tempfile.mkdtemp(prefix="ldm-mosquitto-"))
        # Kept across stop() and start() (a restart needs the config); removed with the object.
        self._cleanup = weakref.finalize(self, shutil.rmtree, self.directory, ignore_errors=True)
        self.directory.chmod(0o755)  # mosquitto started as root reads it as "mosquitto"
        self.config_file = self.directory / "mosquitto.conf"
        if acl is not None:
            acl_file = self.directory / "acl"
            acl_file.write_text(acl)
            acl_file.chmod(0o644)
            extra_config += f"acl_file {acl_file}\n"
        self.config_file.write_text(
            f"listener {self.port} {self.host}\n"
            f"allow_anonymous {'true' if allow_anonymous else 'false'}\n"
            "set_tcp_nodelay true\n"
            "persistence false\n"
            "log_dest stderr\n"
            "log_type error\n"
            "log_type warning\n" + extra_config
        )
        self._process: subprocess.Popen[bytes] | None = None
        self.run_as = run_as

    @property
    def url(self) -> str:
        return f"mqtt://{self.host}:{self.port}"

    @property
    def pid(self) -> int | None:
        """The mosquitto process's id while it runs."""
        return None if self._process is None else self._process.pid

    def start(self) -> Self:
        """Start mosquitto and wait until it accepts connections."""
        if self._process is not None:
            return self
        ids: dict[str, Any] = {}
        if self.run_as is not None:
            ids = {"user": self.run_as, "group": self.run_as, "extra_groups": []}
        self._process = subprocess.Popen(
            [self.binary, "-c", str(self.config_file)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            **ids,
        )
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            if self._process.poll() is not None:
                err = self._process.stderr.read().decode() if self._process.stderr else ""
                self._process = None
                raise ConnectError(f"mosquitto exited at start: {err.strip()}")
            try:
                with socket.create_connection((self.host, self.port), timeout=0.2):
                    return self
            except OSError:
                time.sleep(0.02)
        self.stop()
        raise ConnectError(f"mosquitto did not listen on port {self.port} within 10 s")

    def stop(self) -> None:
        """Kill the process (clients see a dropped connection, as in a crash)."""
        process, self._process = self._process, None
        if process is not None:
            process.kill()
            process.wait(5)
            if process.stderr:
                process.stderr.close()

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *_exc: object) -> None:
        self.stop()
        self._cleanup()


def start_broker(kind: BrokerKind) -> RunningBroker:
    """Start a broker of the given kind on a free port."""
    if kind == "embedded":
        return EmbeddedBroker().start()
    if kind == "embedded-process":
        return BrokerProcess().start()
    return MosquittoBroker().start()
