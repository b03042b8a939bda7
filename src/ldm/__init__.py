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

from ldm.broker import BrokerProcess, EmbeddedBroker
from ldm.config import BrokerSettings, CoreConfig, ParticipantConfig, ProviderConfig
from ldm.core import Core, CoreStats
from ldm.crypto import KeyPair
from ldm.errors import (
    ConfigError,
    ConnectError,
    CryptoError,
    LdmError,
    RequestRejected,
    RequestTimeout,
    ServiceNotFound,
    SessionError,
    TrustError,
)
from ldm.identity import SigningKey
from ldm.messages import ServiceDescription, ServiceSpec, SessionGrant
from ldm.participant import Participant, Session
from ldm.provider import BatchHandler, Handler, Provider, ProviderStats, Request
from ldm.routing import RoutedSession
from ldm.trust import Trust

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
    "RoutedSession",
    "ServiceDescription",
    "ServiceNotFound",
    "ServiceSpec",
    "Session",
    "SessionError",
    "SessionGrant",
    "SigningKey",
    "Trust",
    "TrustError",
]
