"""The LDM's MQTT API as an AsyncAPI 3.0 document, built from the code it describes.

Channel addresses come from `ldm.wire.topics` (each topic function called with
``{parameter}`` placeholders), message payloads from the pydantic models of
`ldm.wire.messages` (``models_json_schema``), so the document cannot drift from either.
A service adds its own messages (`ServiceApi`): the plaintext its participants send and
get back, carried encrypted in the ``d`` of an `ldm.wire.messages.Envelope`.

    document(title="...", version="1.0", services=[ServiceApi("echo", In, (Out,))])
    render(doc)  # JSON text, stable from run to run
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from pydantic import BaseModel
from pydantic.json_schema import models_json_schema

from ldm.wire import topics
from ldm.wire.messages import (
    Announcement,
    CoreStatus,
    Envelope,
    ServiceList,
    ServicesRequest,
    SessionNotice,
    SessionRequest,
    Withdrawal,
)

__all__ = ["ASYNCAPI_VERSION", "ServiceApi", "document", "render"]

ASYNCAPI_VERSION = "3.0.0"

_MQTT_BINDING = "0.2.0"
_SCHEMAS = "#/components/schemas/"
_DATA = "data QoS (CoreConfig.data_qos, default 0) on every hop"


@dataclass(frozen=True, slots=True)
class ServiceApi:
    """A service's messages: what a participant sends (``input``) and what it may get
    back (``outputs``), as pydantic models, plus one line on what the service does."""

    name: str
    description: str
    input: type[BaseModel]
    outputs: tuple[type[BaseModel], ...]


_PARAMETERS: dict[str, str] = {
    "client": "The participant's MQTT client id (its user name where the broker enforces "
    "it). Seen only in the user cluster.",
    "service": "A service name (letters, digits and . _ : -).",
    "pseudonym": "A random 96-bit pseudonym the user core gave the participant's current "
    "ephemeral key; it changes on every rotation.",
    "core": "An LDM core's name.",
    "svc_core": "The name of the core in whose cluster the service runs.",
    "user_core": "The name of the participant's core.",
    "family": "A service family: the providers that share one service, each for a region.",
}

_LDM_MODELS: tuple[type[BaseModel], ...] = (
    ServiceList,
    ServicesRequest,
    SessionRequest,
    SessionNotice,
    Envelope,
    Announcement,
    Withdrawal,
    CoreStatus,
)


def _ref(model: type[BaseModel]) -> dict[str, str]:
    return {"$ref": _SCHEMAS + model.__name__}


def _schemas(models: Sequence[type[BaseModel]]) -> dict[str, Any]:
    """Every model's JSON schema (and those they use) under components/schemas."""
    _, top = models_json_schema(
        [(m, "validation") for m in models], ref_template=_SCHEMAS + "{model}"
    )
    defs: dict[str, Any] = top.get("$defs", {})
    return dict(sorted(defs.items()))


def _message(name: str, title: str, summary: str, payload: Any, **extra: Any) -> dict[str, Any]:
    return {
        "name": name,
        "title": title,
        "summary": summary,
        "contentType": "application/json",
        "payload": payload,
        **extra,
    }


def _channel(
    address: str, servers: Sequence[str], messages: Sequence[str], description: str
) -> dict[str, Any]:
    params = [p for p in _PARAMETERS if "{" + p + "}" in address]
    channel: dict[str, Any] = {
        "address": address,
        "description": description,
        "servers": [{"$ref": f"#/servers/{s}"} for s in servers],
        "messages": {m: {"$ref": f"#/components/messages/{m}"} for m in messages},
    }
    if params:
        channel["parameters"] = {p: {"description": _PARAMETERS[p]} for p in params}
    return channel


def _operation(
    role: str,
    action: str,
    channel: str,
    messages: Sequence[str],
    summary: str,
    qos: int,
    retain: bool = False,
) -> dict[str, Any]:
    return {
        "action": action,
        "channel": {"$ref": f"#/channels/{channel}"},
        "summary": summary,
        "tags": [{"name": role}],
        "messages": [{"$ref": f"#/channels/{channel}/messages/{m}"} for m in messages],
        "bindings": {"mqtt": {"qos": qos, "retain": retain, "bindingVersion": _MQTT_BINDING}},
    }


def document(
    *, title: str, version: str, description: str, services: Sequence[ServiceApi] = ()
) -> dict[str, Any]:
    """The AsyncAPI 3.0 document of the LDM's topics, plus each service's own channels."""
    models = list(_LDM_MODELS)
    for api in services:
        models += [api.input, *api.outputs]
    channels, operations, messages = _ldm_part()
    for api in services:
        _service_part(api, channels, operations, messages)
    servers = {
        "user-cluster": (
            "broker-user:1883",
            "A user cluster's broker: participants connect here (the compose host name).",
        ),
        "service-cluster": (
            "broker-service:1883",
            "A service cluster's broker: providers connect here.",
        ),
        "backbone": (
            "broker-backbone:1883",
            "The inter-cluster broker: every core connects here, nothing else.",
        ),
    }
    return {
        "asyncapi": ASYNCAPI_VERSION,
        "info": {
            "title": title,
            "version": version,
            "description": description,
            "license": {
                "name": "Apache-2.0",
                "url": "https://www.apache.org/licenses/LICENSE-2.0",
            },
        },
        "defaultContentType": "application/json",
        "servers": {
            name: {
                "host": host,
                "protocol": "mqtt",
                "protocolVersion": "3.1.1",
                "description": text,
            }
            for name, (host, text) in servers.items()
        },
        "channels": channels,
        "operations": operations,
        "components": {"schemas": _schemas(models), "messages": messages},
    }


def _ldm_part() -> tuple[dict[str, Any], dict[str, Any], dict[str, Any]]:
    c, s, p, bb = "{client}", "{service}", "{pseudonym}", "{core}"
    user, svc, backbone = "user-cluster", "service-cluster", "backbone"
    messages = {
        "ServiceList": _message(
            "ServiceList",
            "Service list",
            "The services a cluster offers, signed by its core; retained.",
            _ref(ServiceList),
        ),
        "ServicesRequest": _message(
            "ServicesRequest",
            "Service list request",
            "A participant asks its core for the service list on its own topics (at each "
            "connect, then every 10 minutes); the core sends it, then each change.",
            _ref(ServicesRequest),
        ),
        "SessionRequest": _message(
            "SessionRequest",
            "Session request",
            "A participant asks its core for a session with a service.",
            _ref(SessionRequest),
        ),
        "SessionNotice": _message(
            "SessionNotice",
            "Session notice",
            "The core's grant, refusal, rotate, nosession or rejected notice, signed.",
            _ref(SessionNotice),
        ),
        "InputEnvelope": _message(
            "InputEnvelope",
            "Encrypted input",
            "A participant's input: d is the ciphertext, k its ephemeral key; m, its tag "
            "for the core, never leaves the user cluster.",
            _ref(Envelope),
        ),
        "ReplyEnvelope": _message(
            "ReplyEnvelope",
            "Encrypted reply",
            "A service's reply to one input (same c), encrypted for the participant.",
            _ref(Envelope),
        ),
        "EnvelopeBatch": _message(
            "EnvelopeBatch",
            "Envelopes in a batch",
            "Envelopes that waited together for one destination (ldm.wire.batch): one "
            "line per envelope, joined by a newline, each `{pseudonym} {envelope}` with "
            "the envelope's compact JSON as a single message carries it (InputEnvelope "
            "or ReplyEnvelope). A lone envelope is sent as a single message instead.",
            {
                "type": "string",
                "pattern": r"^[A-Za-z0-9._:-]{1,128} \{.*\}(\n[A-Za-z0-9._:-]{1,128} \{.*\})*$",
            },
            contentType="text/plain",
        ),
        "Announcement": _message(
            "Announcement",
            "Service announcement",
            "A provider's signed service description; retained. An empty payload, or "
            "a signed Withdrawal, withdraws the service.",
            _ref(Announcement),
        ),
        "Withdrawal": _message(
            "Withdrawal",
            "Service withdrawal",
            "A provider's signed goodbye (also its last will).",
            _ref(Withdrawal),
        ),
        "FamilyNote": _message(
            "FamilyNote",
            "Family note",
            "What one provider of a family passes the others (a regional LaaS worker: its "
            "users' evidence about the common error of its areas): d sealed with the "
            "region key (ldm.security.crypto.region_cipher), t and the sender bound as "
            "associated data. No core reads it.",
            {
                "type": "object",
                "properties": {"t": {"type": "number"}, "d": {"type": "string"}},
                "required": ["t", "d"],
            },
        ),
        "CoreStatus": _message(
            "CoreStatus",
            "Core status",
            "A core's retained liveness on the backbone; its last will says offline.",
            _ref(CoreStatus),
        ),
    }
    channels = {
        "services": _channel(
            topics.SERVICES,
            [user, svc],
            ["ServiceList"],
            "The retained service list of a cluster.",
        ),
        "servicesRequest": _channel(
            topics.services_request(c),
            [user],
            ["ServicesRequest"],
            "Participant -> its core: send me the service list.",
        ),
        "servicesReply": _channel(
            topics.services_reply(c),
            [user],
            ["ServiceList"],
            "Core -> one participant: the service list, and each change of it.",
        ),
        "sessionRequest": _channel(
            topics.session_request(c), [user], ["SessionRequest"], "Participant -> its core."
        ),
        "sessionNotice": _channel(
            topics.session_notice(c), [user], ["SessionNotice"], "Core -> one participant."
        ),
        "participantInput": _channel(
            topics.participant_input(c, s),
            [user],
            ["InputEnvelope"],
            "A participant's encrypted input to a service.",
        ),
        "participantReply": _channel(
            topics.participant_reply(c, s),
            [user],
            ["ReplyEnvelope"],
            "Replies to a participant, delivered by its core.",
        ),
        "announce": _channel(
            topics.announce(s),
            [svc],
            ["Announcement", "Withdrawal"],
            "A provider's retained announcement (its last will withdraws it).",
        ),
        "providerInput": _channel(
            topics.provider_input(s, p),
            [svc],
            ["InputEnvelope"],
            "Input for a service under a pseudonym (one wildcard subscription per service).",
        ),
        "providerReply": _channel(
            topics.provider_reply(s, p),
            [svc],
            ["ReplyEnvelope"],
            "A provider's reply to a pseudonym.",
        ),
        "familyNote": _channel(
            topics.family_note("{family}", s),
            [svc],
            ["FamilyNote"],
            "A provider's note to the other providers of its family.",
        ),
        "providerInputBatch": _channel(
            topics.provider_input_batch(s),
            [svc],
            ["EnvelopeBatch"],
            "Input for a service, many pseudonyms' envelopes in one message.",
        ),
        "providerReplyBatch": _channel(
            topics.provider_reply_batch(s),
            [svc],
            ["EnvelopeBatch"],
            "A provider's replies to many pseudonyms in one message.",
        ),
        "backboneAnnounce": _channel(
            topics.bb_announce(s),
            [backbone],
            ["Announcement"],
            "A service announced to every core by the core of its cluster (origin set).",
        ),
        "coreStatus": _channel(
            topics.bb_core(bb),
            [backbone],
            ["CoreStatus"],
            "Each core's retained liveness.",
        ),
        "backboneInput": _channel(
            topics.bb_input("{svc_core}", s, "{user_core}", p),
            [backbone],
            ["InputEnvelope"],
            "Input crossing from the user core to the service's core, under the pseudonym.",
        ),
        "backboneReply": _channel(
            topics.bb_reply("{user_core}", s, p),
            [backbone],
            ["ReplyEnvelope"],
            "Replies crossing back to the participant's core.",
        ),
        "backboneInputBatch": _channel(
            topics.bb_input_batch("{svc_core}", s, "{user_core}"),
            [backbone],
            ["EnvelopeBatch"],
            "Input crossing to the service's core, many pseudonyms' envelopes in one message.",
        ),
        "backboneReplyBatch": _channel(
            topics.bb_reply_batch("{user_core}", s),
            [backbone],
            ["EnvelopeBatch"],
            "Replies crossing back to the participant's core, many in one message.",
        ),
    }
    op = _operation
    operations = {
        "participantReadsServices": op(
            "participant", "receive", "services", ["ServiceList"], "Read the service list.", 1
        ),
        "participantAsksForServices": op(
            "participant",
            "send",
            "servicesRequest",
            ["ServicesRequest"],
            "Ask for the service list (needs no right to ldm/services).",
            1,
        ),
        "participantReceivesServices": op(
            "participant",
            "receive",
            "servicesReply",
            ["ServiceList"],
            "The service list on the participant's own topic.",
            1,
        ),
        "participantRequestsSession": op(
            "participant",
            "send",
            "sessionRequest",
            ["SessionRequest"],
            "Open (or reopen) a session.",
            1,
        ),
        "participantReceivesNotices": op(
            "participant",
            "receive",
            "sessionNotice",
            ["SessionNotice"],
            "Grants and notices from the core.",
            1,
        ),
        "participantSendsInput": op(
            "participant",
            "send",
            "participantInput",
            ["InputEnvelope"],
            f"Send encrypted input ({_DATA}).",
            0,
        ),
        "participantReceivesReplies": op(
            "participant",
            "receive",
            "participantReply",
            ["ReplyEnvelope"],
            f"Receive encrypted replies ({_DATA}).",
            0,
        ),
        "providerAnnounces": op(
            "provider",
            "send",
            "announce",
            ["Announcement", "Withdrawal"],
            "Announce the service (retained), withdraw it when leaving.",
            1,
            retain=True,
        ),
        "providerSendsNotes": op(
            "provider",
            "send",
            "familyNote",
            ["FamilyNote"],
            "Pass the family's other providers a note (Provider.note).",
            0,
        ),
        "providerReceivesNotes": op(
            "provider",
            "receive",
            "familyNote",
            ["FamilyNote"],
            "Take the family's other providers' notes (ldm/svc/{family}/note/+).",
            0,
        ),
        "providerReceivesInput": op(
            "provider",
            "receive",
            "providerInput",
            ["InputEnvelope"],
            f"Take every participant's input by wildcard ({_DATA}).",
            0,
        ),
        "providerReceivesInputBatches": op(
            "provider",
            "receive",
            "providerInputBatch",
            ["EnvelopeBatch"],
            f"Take input that waited together at the core, in one message ({_DATA}).",
            0,
        ),
        "providerRepliesInBatches": op(
            "provider",
            "send",
            "providerReplyBatch",
            ["EnvelopeBatch"],
            f"Reply to the input of one batch in one message ({_DATA}).",
            0,
        ),
        "providerReplies": op(
            "provider",
            "send",
            "providerReply",
            ["ReplyEnvelope"],
            f"Reply to a pseudonym ({_DATA}).",
            0,
        ),
        "coreSendsServices": op(
            "core",
            "send",
            "servicesReply",
            ["ServiceList"],
            "Send the list to a participant that asked, and each change for 30 minutes.",
            1,
        ),
        "corePublishesServices": op(
            "core",
            "send",
            "services",
            ["ServiceList"],
            "Keep the cluster's signed list retained.",
            1,
            retain=True,
        ),
        "coreAnnouncesOnBackbone": op(
            "core",
            "send",
            "backboneAnnounce",
            ["Announcement"],
            "Pass a local service on to every core (retained).",
            1,
            retain=True,
        ),
        "coreReportsStatus": op(
            "core",
            "send",
            "coreStatus",
            ["CoreStatus"],
            "Say online (retained; the last will says offline).",
            1,
            retain=True,
        ),
        "coreForwardsInput": op(
            "core",
            "send",
            "backboneInput",
            ["InputEnvelope"],
            f"Forward input to the service's core ({_DATA}).",
            0,
        ),
        "coreForwardsInputBatches": op(
            "core",
            "send",
            "backboneInputBatch",
            ["EnvelopeBatch"],
            f"Forward input that waited together to the service's core ({_DATA}).",
            0,
        ),
        "coreReturnsReplyBatches": op(
            "core",
            "send",
            "backboneReplyBatch",
            ["EnvelopeBatch"],
            f"Return replies that waited together to the participant's core ({_DATA}).",
            0,
        ),
        "coreReturnsReplies": op(
            "core",
            "send",
            "backboneReply",
            ["ReplyEnvelope"],
            f"Return replies to the participant's core ({_DATA}).",
            0,
        ),
    }
    return channels, operations, messages


def _service_part(
    api: ServiceApi,
    channels: dict[str, Any],
    operations: dict[str, Any],
    messages: dict[str, Any],
) -> None:
    """A service's own channels: its participant and provider data topics, whose
    envelopes carry its models encrypted (``x-ldm-plaintext``)."""
    name = api.name
    title = name[:1].upper() + name[1:]
    fix, answer = f"{title}Input", f"{title}Reply"
    outputs = [_ref(m) for m in api.outputs]
    plain_out = outputs[0] if len(outputs) == 1 else {"oneOf": outputs}
    messages[fix] = _message(
        fix,
        f"{name} input",
        f"{api.description} Its d decrypts to a {api.input.__name__}.",
        _ref(Envelope),
        **{"x-ldm-plaintext": _ref(api.input)},
    )
    out_names = " or ".join(m.__name__ for m in api.outputs)
    messages[answer] = _message(
        answer,
        f"{name} reply",
        f"The {name} service's reply; its d decrypts to a {out_names}.",
        _ref(Envelope),
        **{"x-ldm-plaintext": plain_out},
    )
    c, p = "{client}", "{pseudonym}"
    places = [
        ("participantInput", topics.participant_input(c, name), "user-cluster", fix),
        ("participantReply", topics.participant_reply(c, name), "user-cluster", answer),
        ("providerInput", topics.provider_input(name, p), "service-cluster", fix),
        ("providerReply", topics.provider_reply(name, p), "service-cluster", answer),
    ]
    for kind, address, server, message in places:
        what = "input" if message == fix else "replies"
        channels[f"{name}{kind[:1].upper()}{kind[1:]}"] = _channel(
            address, [server], [message], f"The {name} service's {what} ({kind})."
        )
    sends = [
        ("participant", "send", "ParticipantInput", fix, f"Send a {api.input.__name__}."),
        ("participant", "receive", "ParticipantReply", answer, f"Receive a {out_names}."),
        ("provider", "receive", "ProviderInput", fix, f"Take a {api.input.__name__}."),
        ("provider", "send", "ProviderReply", answer, f"Answer with a {out_names}."),
    ]
    for role, action, kind, message, summary in sends:
        channel = f"{name}{kind}"
        operations[f"{name}{role.title()}{action.title()}s"] = _operation(
            role, action, channel, [message], f"{summary} ({_DATA}).", 0
        )


def render(doc: dict[str, Any]) -> str:
    """The document as JSON text (two-space indent, a final newline)."""
    return json.dumps(doc, indent=2, ensure_ascii=False) + "\n"
