"""The Local Dynamic Map (LDM): a generic service architecture over MQTT.

Clusters (a broker and a core each), joined by an inter-cluster broker; retained
service lists for discovery; rotating pseudonyms and end-to-end encryption between
participants and services. The LDM knows nothing about positioning.

    Participant   the client library: list services, open a session, request
    Provider      the service library: announce, take all input by wildcard, reply
    Core          one per cluster: discovery, pseudonyms, routing of ciphertext
    SigningKey    an Ed25519 identity: services sign their keys, cores their notices
    Trust         which service identities a participant or core accepts
    EmbeddedBroker  an in-process MQTT broker for tests and zero-install runs
"""

from ldm.client.participant import Participant, Session
from ldm.client.routing import RoutedSession
from ldm.config import BrokerSettings, CoreConfig, ParticipantConfig, ProviderConfig
from ldm.core.core import Core, CoreStats
from ldm.errors import (
    ConfigError,
    ConnectError,
    CryptoError,
    LdmError,
    RequestRejected,
    RequestTimeout,
    ServiceNotFound,
    SessionError,
    SessionSilent,
    TrustError,
)
from ldm.local.embedded import BrokerProcess, EmbeddedBroker
from ldm.provider.provider import BatchHandler, Handler, Provider, ProviderStats, Request
from ldm.security.crypto import KeyPair
from ldm.security.identity import SigningKey
from ldm.security.trust import Trust
from ldm.wire.messages import ServiceDescription, ServiceSpec, SessionGrant
from ldm.wire.rotation import RotationPolicy

__all__ = [
    "BatchHandler",
    "BrokerProcess",
    "BrokerSettings",
    "ConfigError",
    "ConnectError",
    "Core",
    "CoreConfig",
    "CoreStats",
    "CryptoError",
    "EmbeddedBroker",
    "Handler",
    "KeyPair",
    "LdmError",
    "Participant",
    "ParticipantConfig",
    "Provider",
    "ProviderConfig",
    "ProviderStats",
    "Request",
    "RequestRejected",
    "RequestTimeout",
    "RotationPolicy",
    "RoutedSession",
    "ServiceDescription",
    "ServiceNotFound",
    "ServiceSpec",
    "Session",
    "SessionError",
    "SessionGrant",
    "SessionSilent",
    "SigningKey",
    "Trust",
    "TrustError",
]
