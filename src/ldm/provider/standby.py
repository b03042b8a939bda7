"""A standby provider: wait until the active one is gone, then take its place.

`wait_until_vacant` watches the service's announce topic on the service cluster's
broker. The service is vacant once

- its announcement is withdrawn: the active provider's goodbye, or its last will,
  which the broker publishes when the provider's connection dies without one; or
- no announcement has come for ``quiet`` seconds (a provider re-announces every
  ``announce_interval``, so a live one is never quiet for long), which covers a broker
  that lost the will.

The standby then starts as the provider, under the same identity (participants and
cores pin it), with a new session key: participants see the new key in the service
list and open their sessions again (`ldm.Participant`). One standby per active
provider: two standbys would both take over.
"""

from __future__ import annotations

import secrets
import threading
import time

from pydantic import ValidationError

from ldm.config import BrokerSettings
from ldm.transport.mqtt import Event, Message, Transport
from ldm.wire import topics
from ldm.wire.messages import Announcement, Withdrawal

__all__ = ["wait_until_vacant"]


def wait_until_vacant(
    broker: BrokerSettings | str,
    service: str,
    *,
    quiet: float = 30.0,
    stop: threading.Event | None = None,
    connect_timeout: float = 10.0,
) -> bool:
    """Block until `service` is vacant (module docstring); False if `stop` was set first."""
    settings = BrokerSettings.of(broker)
    last = time.monotonic()  # a fresh standby gives the active one `quiet` s to show up
    vacant = threading.Event()
    lock = threading.Lock()

    def sink(event: Event) -> None:  # paho's thread
        nonlocal last
        if not isinstance(event, Message):
            return
        if not event.payload:
            vacant.set()
            return
        try:
            Withdrawal.model_validate_json(event.payload)
        except ValidationError:
            pass
        else:
            vacant.set()
            return
        try:
            Announcement.model_validate_json(event.payload)
        except ValidationError:
            return  # not ours to judge: a malformed retained message is no announcement
        with lock:
            last = time.monotonic()

    watcher = Transport(
        settings,
        client_id=f"ldm-standby-{secrets.token_hex(4)}",
        sink=sink,
        name=f"standby-{service}",
    )
    watcher.subscribe(topics.announce(service), 1)
    watcher.start(connect_timeout)
    try:
        while not vacant.is_set():
            if stop is not None and stop.is_set():
                return False
            with lock:
                silent = time.monotonic() - last
            if silent > quiet:
                return True
            vacant.wait(0.1)
        return True
    finally:
        watcher.stop()
