"""The LDM topic layout, in one place.

User-cluster topics carry the participant's MQTT client id at level 3, so a Mosquitto
ACL can confine a participant with ``pattern write ldm/p/%c/up/#`` and
``pattern read ldm/p/%c/down/#`` (plus ``pattern read ldm/services``).
Topics that leave the user cluster carry only pseudonyms.

    ldm/services                                   retained service list of this cluster
    ldm/p/{client}/up/session                      participant -> core: session request
    ldm/p/{client}/up/data/{service}               participant -> core: encrypted input
    ldm/p/{client}/down/session                    core -> participant: grants and notices
    ldm/p/{client}/down/data/{service}             core -> participant: encrypted replies
    ldm/svc/{service}/announce                     provider -> core: retained announcement
    ldm/svc/{service}/in/{pseudonym}               core -> provider: encrypted input
    ldm/svc/{service}/out/{pseudonym}              provider -> core: encrypted replies
    ldm/bb/announce/{service}                      core -> cores: retained announcement
    ldm/bb/core/{core}                             core -> cores: retained liveness (will)
    ldm/bb/in/{svc_core}/{service}/{user_core}/{pseudonym}   user core -> service core
    ldm/bb/out/{user_core}/{service}/{pseudonym}             service core -> user core
"""

from __future__ import annotations

import re
from typing import Final

from ldm.errors import ConfigError

__all__ = [
    "NAME_PATTERN",
    "SERVICES",
    "TOKEN_PATTERN",
    "check_name",
]

NAME_PATTERN: Final = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._:-]{0,127}$")
"""Client ids, service names, core names and pseudonyms: one safe topic level each."""

TOKEN_PATTERN: Final = re.compile(r"^[A-Za-z0-9_-]{1,64}$")
"""Correlation ids: random tokens chosen by the sender."""

SERVICES: Final = "ldm/services"


def check_name(value: str, what: str) -> str:
    """Return `value` if it can be one topic level, else raise ConfigError naming `what`."""
    if not NAME_PATTERN.match(value):
        raise ConfigError(
            f"{what} {value!r} cannot be used in a topic: use 1-128 characters from "
            "letters, digits and . _ : - (starting with a letter or digit)"
        )
    return value


# --- user cluster: participants ------------------------------------------------------


def participant_down(client: str) -> str:
    """Filter for everything a participant receives."""
    return f"ldm/p/{client}/down/#"


def session_request(client: str) -> str:
    return f"ldm/p/{client}/up/session"


def session_notice(client: str) -> str:
    return f"ldm/p/{client}/down/session"


def participant_input(client: str, service: str) -> str:
    return f"ldm/p/{client}/up/data/{service}"


def participant_reply(client: str, service: str) -> str:
    return f"ldm/p/{client}/down/data/{service}"


PARTICIPANT_UP_FILTER: Final = "ldm/p/+/up/#"

# --- any cluster: providers ----------------------------------------------------------


def announce(service: str) -> str:
    return f"ldm/svc/{service}/announce"


def provider_input(service: str, pseudonym: str) -> str:
    return f"ldm/svc/{service}/in/{pseudonym}"


def provider_input_filter(service: str) -> str:
    """One wildcard subscription covers every participant of a service."""
    return f"ldm/svc/{service}/in/+"


def provider_reply(service: str, pseudonym: str) -> str:
    return f"ldm/svc/{service}/out/{pseudonym}"


ANNOUNCE_FILTER: Final = "ldm/svc/+/announce"
PROVIDER_REPLY_FILTER: Final = "ldm/svc/+/out/+"

# --- backbone ------------------------------------------------------------------------


def bb_announce(service: str) -> str:
    return f"ldm/bb/announce/{service}"


def bb_core(core: str) -> str:
    return f"ldm/bb/core/{core}"


def bb_input(service_core: str, service: str, user_core: str, pseudonym: str) -> str:
    return f"ldm/bb/in/{service_core}/{service}/{user_core}/{pseudonym}"


def bb_input_filter(core: str) -> str:
    return f"ldm/bb/in/{core}/+/+/+"


def bb_reply(user_core: str, service: str, pseudonym: str) -> str:
    return f"ldm/bb/out/{user_core}/{service}/{pseudonym}"


def bb_reply_filter(core: str) -> str:
    return f"ldm/bb/out/{core}/+/+"


BB_ANNOUNCE_FILTER: Final = "ldm/bb/announce/+"
BB_CORE_FILTER: Final = "ldm/bb/core/+"
