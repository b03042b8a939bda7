"""The LDM topic layout, in one place.

User-cluster topics carry the participant's MQTT client id at level 3, so a Mosquitto
ACL can confine a participant with ``pattern write ldm/p/%c/up/#`` and
``pattern read ldm/p/%c/down/#``: the service list comes on its own topics too.
Topics that leave the user cluster carry only pseudonyms.

    ldm/services                                   retained service list of this cluster
    ldm/p/{client}/up/services                     participant -> core: list request
    ldm/p/{client}/down/services                   core -> participant: the service list
    ldm/p/{client}/up/session                      participant -> core: session request
    ldm/p/{client}/up/data/{service}               participant -> core: encrypted input
    ldm/p/{client}/down/session                    core -> participant: grants and notices
    ldm/p/{client}/down/data/{service}             core -> participant: encrypted replies
    ldm/svc/{service}/announce                     provider -> core: retained announcement
    ldm/svc/{service}/in/{pseudonym}               core -> provider: encrypted input
    ldm/svc/{service}/out/{pseudonym}              provider -> core: encrypted replies
    ldm/svc/{family}/note/{service}                provider -> the family's other providers:
                                                   a sealed note (no core reads it)
    ldm/bb/announce/{service}                      core -> cores: retained announcement
    ldm/bb/core/{core}                             core -> cores: retained liveness (will)
    ldm/bb/in/{svc_core}/{service}/{user_core}/{pseudonym}   user core -> service core
    ldm/bb/out/{user_core}/{service}/{pseudonym}             service core -> user core

Between the cores, and between a service core and its provider, envelopes travel as
batches (`ldm.wire.batch`; of one when an envelope waits alone, so that one topic keeps
each participant's order) on the same topic without its pseudonym level (the
pseudonyms are in the batch); the single topics above are still read:

    ldm/svc/{service}/in                           core -> provider: a batch of input
    ldm/svc/{service}/out                          provider -> core: a batch of replies
    ldm/bb/in/{svc_core}/{service}/{user_core}     user core -> service core: a batch
    ldm/bb/out/{user_core}/{service}               service core -> user core: a batch

`parse` is the one place that takes a topic apart.
"""

from __future__ import annotations

import re
from typing import Final, Literal, NamedTuple

from ldm.errors import ConfigError

__all__ = [
    "NAME_PATTERN",
    "PSEUDONYM_PATTERN",
    "SERVICES",
    "TOKEN_PATTERN",
    "Kind",
    "Topic",
    "check_name",
    "parse",
]

NAME_PATTERN: Final = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._:-]{0,127}$")
"""Client ids, service names, core names and pseudonyms: one safe topic level each."""

PSEUDONYM_PATTERN: Final = re.compile(r"^[A-Za-z0-9._:-]{1,128}$")
"""Pseudonyms as a core makes them (random URL-safe tokens, which may begin with ``-``
or ``_``): one topic level each, no wildcard."""

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


def services_request(client: str) -> str:
    return f"ldm/p/{client}/up/services"


def services_reply(client: str) -> str:
    return f"ldm/p/{client}/down/services"


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


def family_note(family: str, service: str) -> str:
    """A note of provider `service` to the other providers of its `family`."""
    return f"ldm/svc/{family}/note/{service}"


def family_note_filter(family: str) -> str:
    return f"ldm/svc/{family}/note/+"


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


def provider_input_batch(service: str) -> str:
    return f"ldm/svc/{service}/in"


def provider_reply_batch(service: str) -> str:
    return f"ldm/svc/{service}/out"


PROVIDER_REPLY_BATCH_FILTER: Final = "ldm/svc/+/out"


def bb_input_batch(service_core: str, service: str, user_core: str) -> str:
    return f"ldm/bb/in/{service_core}/{service}/{user_core}"


def bb_input_batch_filter(core: str) -> str:
    return f"ldm/bb/in/{core}/+/+"


def bb_reply_batch(user_core: str, service: str) -> str:
    return f"ldm/bb/out/{user_core}/{service}"


def bb_reply_batch_filter(core: str) -> str:
    return f"ldm/bb/out/{core}/+"


# --- parsing -------------------------------------------------------------------------

Kind = Literal[
    "services",
    "services_request",
    "services_reply",
    "session_request",
    "participant_input",
    "participant_up",
    "session_notice",
    "participant_reply",
    "announce",
    "provider_input",
    "provider_input_batch",
    "provider_reply",
    "provider_reply_batch",
    "bb_announce",
    "bb_core",
    "bb_input",
    "bb_input_batch",
    "bb_reply",
    "bb_reply_batch",
    "family_note",
    "other",
]


class Topic(NamedTuple):
    """A topic taken apart (`parse`): its kind and the names its levels carry.

    ``client``: the participant's client id (``ldm/p/...``); ``service``; ``pseudonym``
    (single data messages); ``core``: the core a backbone topic is addressed to (or
    whose liveness it carries); ``user_core``: the sender's core of backbone input;
    ``family``: the family a note is for (its sender is ``service``).
    ``participant_up`` is any other topic under ``ldm/p/{client}/up/``; ``other`` any
    topic outside the layout.
    """

    kind: Kind
    client: str = ""
    service: str = ""
    pseudonym: str = ""
    core: str = ""
    user_core: str = ""
    family: str = ""


_OTHER: Final = Topic("other")


def parse(topic: str) -> Topic:
    """The kind of `topic` and the names in its levels; ``other`` if it is none of the
    layout's (the module docstring). Names are not checked against `NAME_PATTERN`:
    a subscription's wildcard fills one level, so each is one level of some name."""
    levels = topic.split("/")
    n = len(levels)
    if n < 2 or levels[0] != "ldm":
        return _OTHER
    area = levels[1]
    if area == "p" and n >= 4:
        client, way = levels[2], levels[3]
        if way == "up":
            if n == 5 and levels[4] == "session":
                return Topic("session_request", client=client)
            if n == 5 and levels[4] == "services":
                return Topic("services_request", client=client)
            if n == 6 and levels[4] == "data":
                return Topic("participant_input", client=client, service=levels[5])
            return Topic("participant_up", client=client)
        if way == "down" and n == 5 and levels[4] == "session":
            return Topic("session_notice", client=client)
        if way == "down" and n == 5 and levels[4] == "services":
            return Topic("services_reply", client=client)
        if way == "down" and n == 6 and levels[4] == "data":
            return Topic("participant_reply", client=client, service=levels[5])
    elif area == "svc" and n in (4, 5):
        service, what = levels[2], levels[3]
        if n == 4:
            if what == "announce":
                return Topic("announce", service=service)
            if what == "in":
                return Topic("provider_input_batch", service=service)
            if what == "out":
                return Topic("provider_reply_batch", service=service)
        elif what == "in":
            return Topic("provider_input", service=service, pseudonym=levels[4])
        elif what == "note":
            return Topic("family_note", service=levels[4], family=service)
        elif what == "out":
            return Topic("provider_reply", service=service, pseudonym=levels[4])
    elif area == "bb" and n >= 4:
        what = levels[2]
        if what == "in" and n == 7:
            return Topic(
                "bb_input",
                core=levels[3],
                service=levels[4],
                user_core=levels[5],
                pseudonym=levels[6],
            )
        if what == "in" and n == 6:
            return Topic("bb_input_batch", core=levels[3], service=levels[4], user_core=levels[5])
        if what == "out" and n == 6:
            return Topic("bb_reply", core=levels[3], service=levels[4], pseudonym=levels[5])
        if what == "out" and n == 5:
            return Topic("bb_reply_batch", core=levels[3], service=levels[4])
        if what == "announce" and n == 4:
            return Topic("bb_announce", service=levels[3])
        if what == "core" and n == 4:
            return Topic("bb_core", core=levels[3])
    elif topic == SERVICES:
        return Topic("services")
    return _OTHER
