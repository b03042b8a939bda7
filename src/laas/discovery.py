"""How a laas client finds the service: one rule, used by the bridges and the simulator.

A provider offers `name` when it is the service of that name (one worker for the whole
map) or serves a region of it (a regional worker, ``laas-1of2`` of ``laas``:
`laas.worker.regions`). A client waits until the cluster's retained service list shows
one, then routes each fix to the provider whose coverage holds it
(`ldm.RoutedSession`).
"""

from __future__ import annotations

import time

from laas.worker.service import SERVICE_NAME
from ldm import Participant, ServiceDescription

__all__ = ["offers", "wait_for_service"]


def offers(description: ServiceDescription, name: str = SERVICE_NAME) -> bool:
    """Whether the listed provider serves `name`: by its own name or as a region of it."""
    return name in (description.name, description.family)


def wait_for_service(
    participant: Participant, timeout: float, name: str = SERVICE_NAME
) -> list[ServiceDescription]:
    """Wait until the cluster's service list holds a provider of `name` (`offers`); the
    providers found. TimeoutError, saying what to check, if none appears in `timeout` s."""
    deadline = time.monotonic() + timeout
    while True:
        found = [s for s in participant.services(timeout=0.5) if offers(s, name)]
        if found:
            return found
        if time.monotonic() >= deadline:
            raise TimeoutError(
                f"no {name!r} service (nor a regional worker of it) "
                f"appeared in the cluster's service list within {timeout:g} s; is `laas "
                "worker` running and are both LDM cores connected?"
            )
        time.sleep(0.1)
