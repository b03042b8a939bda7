"""Container health checks for the LDM cores, the LaaS worker and the bridges (exit 0
healthy, 1 not).

    python deploy/healthcheck.py core mqtt://broker-backbone:1883 user \
        --username ldm-core-user --password-env LDM_BACKBONE_PASSWORD
    python deploy/healthcheck.py service mqtt://broker-service:1883 laas \
        --username laas-worker --password-env LAAS_PASSWORD
    python deploy/healthcheck.py ready --metrics-port-env LAAS_METRICS_PORT

`ready`: the process's own /readyz (on 127.0.0.1 and the port in the environment
variable --metrics-port-env names) answers 200: a bridge is connected to its broker.

`core NAME`: the core's retained status on the backbone (`ldm/bb/core/NAME`) says
online; its last will turns it offline when the process dies or loses the broker.
`service NAME`: the service's retained announcement on its cluster broker
(`ldm/svc/NAME/announce`) is an announcement; the provider's last will replaces it
with its signed withdrawal.
Both read one retained message through the LDM's own transport, so the check sees
what the other cores and participants see. On a broker with accounts the check logs in
with the checked container's own account (its password from the environment variable
--password-env names) under a random client id; those brokers do not set
use_username_as_clientid, so the check never displaces the container's own connection.
"""

from __future__ import annotations

import argparse
import json
import os
import queue
import secrets
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

from ldm import BrokerSettings, LdmError
from ldm.config import build
from ldm.transport import Event, Message, Transport
from ldm.wire.messages import CoreStatus
from ldm.wire.topics import announce, bb_core


def retained(broker: BrokerSettings | str, topic: str, timeout: float) -> bytes | None:
    """The retained payload of `topic`, or None if none arrives within `timeout` s."""
    events: queue.SimpleQueue[Event] = queue.SimpleQueue()
    transport = Transport(
        BrokerSettings.of(broker), client_id=f"health-{secrets.token_hex(4)}", sink=events.put
    )
    transport.subscribe(topic, 1)
    deadline = time.monotonic() + timeout
    try:
        transport.start(timeout)
        while (left := deadline - time.monotonic()) > 0:
            try:
                event = events.get(timeout=left)
            except queue.Empty:
                break
            if isinstance(event, Message) and event.topic == topic:
                return event.payload
    finally:
        transport.stop()
    return None


def ready(port_env: str, timeout: float) -> int:
    """0 if http://127.0.0.1:$port_env/readyz answers 200, else 1 (and why)."""
    port = os.environ.get(port_env, "")
    if not port.isdigit() or int(port) == 0:
        print(f"unhealthy: {port_env} does not name the metrics port ({port!r})")
        return 1
    url = f"http://127.0.0.1:{port}/readyz"
    try:
        with urllib.request.urlopen(url, timeout=timeout) as response:
            status = response.status
    except urllib.error.HTTPError as exc:
        status = exc.code
    except OSError as exc:
        print(f"unhealthy: {url}: {exc}")
        return 1
    print(f"{'healthy' if status == 200 else 'unhealthy'}: {url} answered {status}")
    return 0 if status == 200 else 1


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("kind", choices=["core", "service", "ready"])
    parser.add_argument(
        "url", nargs="?", help="broker that carries the retained message, mqtt://HOST:PORT"
    )
    parser.add_argument("name", nargs="?", help="core name or service name")
    parser.add_argument(
        "--metrics-port-env",
        default="LAAS_METRICS_PORT",
        help="ready: the environment variable holding the process's metrics port",
    )
    parser.add_argument("--timeout", type=float, default=3.0, help="seconds")
    parser.add_argument("--username", help="account on the broker (default: anonymous)")
    parser.add_argument("--password-env", help="environment variable holding its password")
    parser.add_argument("--ca-file", type=Path, help="CA certificates for an mqtts:// broker")
    a = parser.parse_args(argv)
    if a.kind == "ready":
        return ready(a.metrics_port_env, a.timeout)
    if a.url is None or a.name is None:
        parser.error(f"{a.kind} needs the broker URL and the {a.kind}'s name")
    topic = bb_core(a.name) if a.kind == "core" else announce(a.name)
    try:
        broker = build(
            BrokerSettings,
            url=a.url,
            username=a.username,
            password_env=a.password_env if a.username else None,
            ca_file=a.ca_file,
        )
        payload = retained(broker, topic, a.timeout)
    except LdmError as exc:
        print(f"unhealthy: {exc}")
        return 1
    if not payload:
        print(f"unhealthy: no retained message on {topic}")
        return 1
    if a.kind == "core" and not CoreStatus.model_validate_json(payload).online:
        print(f"unhealthy: core {a.name} is marked offline")
        return 1
    if a.kind == "service" and b'"withdrawn"' in payload and "withdrawn" in json.loads(payload):
        print(f"unhealthy: service {a.name} withdrew its announcement")
        return 1
    print(f"healthy: {topic}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
