"""A core's notices to its participants, on ``ldm/p/{client}/down/session``.

Every notice is addressed to one client id, stamped with its send time and signed by
the core's identity, so a participant that pinned the core's key acts on no other.
Refusals (``rejected``, ``refused``, ``nosession``) are answered within the notice
bucket of the budget that paid for the message they answer (`ldm.core.budgets`,
``Admission.notice``): refusing costs little, and a flood's refusals are not answered.
"""

from __future__ import annotations

import json
import time

from pydantic import ValidationError

from ldm.config import CoreConfig
from ldm.core.admission import Admission
from ldm.core.budgets import Charge
from ldm.security.identity import SigningKey
from ldm.transport.mqtt import Transport
from ldm.wire import topics
from ldm.wire.messages import Rejection, SessionNotice

__all__ = ["Notices", "correlation", "describe"]


class Notices:
    """Signs and sends one core's notices (the dispatch thread's)."""

    def __init__(
        self, config: CoreConfig, identity: SigningKey, cluster: Transport, admission: Admission
    ) -> None:
        self._config = config
        self._identity = identity
        self._cluster = cluster
        self._admission = admission

    def send(self, client: str, notice: SessionNotice) -> None:
        """Send a notice to one participant, addressed, timed and signed by this core."""
        notice = notice.model_copy(update={"to": client, "t": time.time()})
        notice = notice.model_copy(update={"sig": self._identity.sign(notice.signed_text())})
        payload = notice.model_dump_json(exclude_none=True).encode()
        self._cluster.publish(topics.session_notice(client), payload, qos=1)

    def answer(self, charge: Charge, client: str, notice: SessionNotice) -> None:
        """Send a ``refused`` or ``nosession`` notice within the notice bucket of the
        budget that paid for the message it answers (`charge`)."""
        if self._admission.notice(charge, client):
            self.send(client, notice)

    def reject(
        self,
        charge: Charge,
        client: str,
        service: str,
        reason: Rejection,
        error: str,
        *,
        c: str | None = None,
        payload: bytes = b"",
        paid: bool = False,
    ) -> None:
        """Answer a refused message with a ``rejected`` notice, within the notice bucket
        of the budget that paid for it (`charge`; ``paid``: admission took the token
        already).

        The correlation id is ``c``, or read from ``payload`` only once the notice is
        admitted and only if the payload is within ``max_payload``, so a flood costs no
        parsing.
        """
        if not paid and not self._admission.notice(charge, client):
            return
        if c is None and len(payload) <= self._config.max_payload:
            c = correlation(payload)
        notice = SessionNotice(kind="rejected", service=service, c=c, reason=reason, error=error)
        self.send(client, notice)


def describe(error: ValidationError) -> str:
    """pydantic's errors as ``field: problem; ...`` (the field dotted, or ``payload``)."""
    return "; ".join(
        f"{'.'.join(str(x) for x in e['loc']) or 'payload'}: {e['msg']}" for e in error.errors()
    )


def correlation(payload: bytes) -> str | None:
    """The correlation id ``c`` of a JSON object payload, if it has a well-formed one."""
    try:
        value = json.loads(payload).get("c")
    except (ValueError, AttributeError, RecursionError):
        return None
    return value if isinstance(value, str) and topics.TOKEN_PATTERN.fullmatch(value) else None
