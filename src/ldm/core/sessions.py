"""A core's participant sessions: grants, the pseudonyms bound to each session's
ephemeral keys, rotation, and expiry. `Sessions` decides; the core sends what it
decided (grants and ``rotate`` notices, through `ldm.core.notices.Notices`).

A session is one participant client id's use of one service. A grant shares a secret
with the participant (with which it tags its input, `ldm.security.crypto.input_tag`);
each ephemeral key the session's input comes under gets its own random pseudonym
(`new_pseudonym`), which is all that leaves the user cluster. A new key gets a new
pseudonym (rotation); the old one is honoured for ``grace`` seconds. Every pseudonym is
new state here, at the service core, the provider and the service, so keys may change
at most every ``rekey_interval`` (`Sessions.pseudonym`), with one exception that keeps
that rate: a fresh grant lets one new key in early (a participant restarted under its
client id, whose old process held the session's current key).

Only the core's dispatch thread calls it: nothing here is locked.
"""

from __future__ import annotations

import secrets
from collections.abc import Iterator

from ldm.config import CoreConfig
from ldm.core.admission import SessionKeys, tag_secret
from ldm.core.rotation import next_rotation
from ldm.core.state import Pseudonym, SessionSecret, SessionState, new_pseudonym
from ldm.core.stats import CoreStats
from ldm.security.crypto import KeyPair
from ldm.wire import topics
from ldm.wire.messages import (
    Envelope,
    ServiceDescription,
    SessionGrant,
    SessionNotice,
    SessionRequest,
)

__all__ = ["Sessions"]

_MAX_OLD = 4  # pseudonyms kept in their grace per session; a key-churning client gets no more
_MAX_SECRETS = 4  # grant secrets kept per session (`Sessions._keep_secret`)
_MAX_REKEYS = 2.0  # key changes a session may save up (`Sessions.pseudonym`)
_REKEY_SLACK = 0.1
"""A new key is taken 10 % before ``rekey_interval`` is over: the participant counts
from sending its first input under the current key, the core from its arrival, and
the two trips may differ (`Session.rotate`)."""


class Sessions:
    """The sessions of one core's participants, by (client, service), and their
    pseudonyms (current and in their grace), by name."""

    def __init__(self, config: CoreConfig, stats: CoreStats) -> None:
        self._config = config
        self._stats = stats
        self._sessions: dict[tuple[str, str], SessionState] = {}
        self._pseudonyms: dict[str, SessionState] = {}

    def get(self, client: str, service: str) -> SessionState | None:
        return self._sessions.get((client, service))

    def of(self, pseudonym: str) -> SessionState | None:
        """The session a live pseudonym (current or in its grace) belongs to."""
        return self._pseudonyms.get(pseudonym)

    def pseudonyms(self, session: SessionState) -> list[str]:
        """The session's live pseudonyms, current last."""
        return [p.name for p in (*session.old, session.current) if p is not None]

    def __contains__(self, key: object) -> bool:
        return key in self._sessions

    def __iter__(self) -> Iterator[SessionState]:
        return iter(list(self._sessions.values()))

    def __len__(self) -> int:
        return len(self._sessions)

    @property
    def pseudonym_count(self) -> int:
        """Live pseudonyms (current and in their grace)."""
        return len(self._pseudonyms)

    # --- grants -----------------------------------------------------------------------

    def grant(
        self, client: str, req: SessionRequest, service: ServiceDescription, now: float
    ) -> SessionNotice:
        """The grant that answers `req` (a service the cluster offers): the session is
        opened if it is new, and a request with the last one's ``c`` (a duplicate, at
        QoS 1) gets the same answer again."""
        session = self._sessions.get((client, req.service))
        if session is None:
            session = SessionState(client, req.service, now)
            self._sessions[(client, req.service)] = session
        session.last_seen = now
        self._stats.granted += 1
        last = session.last_grant
        if last is not None and last.c == req.c:
            return last
        session.granted = now
        cfg = self._config
        auth_key = None
        if req.k is not None:
            ours = KeyPair()
            self._keep_secret(session, ours.session_secret(req.k))
            auth_key = ours.public
        grant = SessionGrant(
            service=service,
            session=secrets.token_urlsafe(9),
            input_topic=topics.participant_input(client, req.service),
            reply_topic=topics.participant_reply(client, req.service),
            rotation_period=cfg.rotation_period,
            grace=cfg.grace,
            idle_timeout=cfg.idle_timeout,
            max_age=cfg.max_age,
            data_qos=cfg.data_qos,
            rekey_interval=cfg.rekey_interval,
            auth_key=auth_key,
            rotation=cfg.rotation,
        )
        session.last_grant = SessionNotice(kind="grant", service=req.service, c=req.c, grant=grant)
        return session.last_grant

    @staticmethod
    def _keep_secret(session: SessionState, secret: bytes) -> None:
        """Add a grant's secret to the session's, keeping those before it.

        On a broker without ACL anyone can send a well-formed request on a participant's
        topic; had its secret replaced the session's, the participant's correctly tagged
        input would be dropped until its request timed out (issue 25: one forged request
        every 2 s left 22-26 % answered). So the secrets in use stay: at most
        ``_MAX_SECRETS`` are kept, and the one dropped to make room is the oldest never
        used by tagged input, else the least recently used. A forged request's secret is
        used only by its forger's tagged input: see docs/security.md for what remains.
        """
        held = session.secrets
        held.append(SessionSecret(secret))
        if len(held) > _MAX_SECRETS:
            unused = [s for s in held[:-1] if s.used == 0.0]
            victim = unused[0] if unused else min(held[:-1], key=lambda s: s.used)
            held.remove(victim)

    def keys(self, client: str, service: str) -> SessionKeys | None:
        """What admission needs to know of the session (`ldm.core.admission.Admission.know`):
        its keys (current, and old ones until their grace ends) and its secrets; None
        for no session, or one with neither yet."""
        session = self._sessions.get((client, service))
        if session is None or (session.current is None and not session.secrets):
            return None
        current = [] if session.current is None else [session.current]
        keys = tuple((p.key.encode(), p.until) for p in (*current, *session.old))
        return SessionKeys(keys, tuple(s.value for s in session.secrets))

    # --- input ------------------------------------------------------------------------

    @staticmethod
    def authentic(session: SessionState, env: Envelope, checked: bytes | None, now: float) -> bool:
        """Whether `env` is tagged with one of the session's secrets (`checked`: the one
        admission checked it with, taken as it is while the session still holds it); the
        secret is then marked used, which keeps it when a new grant comes."""
        held = [s.value for s in session.secrets]
        secret = checked if checked is not None and checked in held else tag_secret(env, held)
        if secret is None:
            return False
        for s in session.secrets:
            if s.value == secret:
                s.used = now
        return True

    def pseudonym(
        self, session: SessionState, key: str, service_key: str, now: float
    ) -> str | None:
        """The pseudonym bound to this ephemeral key; a new key means a new pseudonym.

        A session may change keys at most every ``rekey_interval`` seconds (None:
        refused), except when the service's own key changed (a restarted service), or
        early, once, after a grant made since the current key came (a participant
        restarted under its client id: its new process has a new key and a new grant).

        So the rate stays bounded with early changes too, every change is paid from one
        bucket, refilled at one per ``rekey_interval`` and holding at most 2: a change
        on time always finds a token there (it comes an interval after the last); an
        early one needs one left. Over any time T a session takes at most
        2 + T / ``rekey_interval`` keys, one more than without early changes, however
        many grants it asks for.
        """
        session.last_seen = now
        current = session.current
        if current is not None and current.key == key:
            return current.name
        for old in session.old:
            if old.key == key and old.until > now:
                return old.name  # input sent before the rotation, still in its grace
        cfg = self._config
        interval = cfg.rekey_interval * (1.0 - _REKEY_SLACK)
        if current is not None:
            tokens = min(_MAX_REKEYS, session.rekeys + (now - session.rekeys_at) / interval)
            on_time = now - current.created >= interval or current.service_key != service_key
            early = session.granted > current.created and tokens >= 1.0
            if not (on_time or early):
                return None
            session.rekeys, session.rekeys_at = max(0.0, tokens - 1.0), now
        else:
            session.rekeys_at = now  # the session's first key is free
        fresh = Pseudonym(new_pseudonym(), key, now, service_key)
        if current is not None:
            current.until = now + cfg.grace
            session.old.append(current)
            if len(session.old) > _MAX_OLD:  # a client that churns keys keeps only a few
                self._pseudonyms.pop(session.old.pop(0).name, None)
            self._stats.rotations += 1
        session.current = fresh
        session.next_rotate = next_rotation(cfg.rotation.strategy, cfg.rotation_period, now)
        self._pseudonyms[fresh.name] = session
        return fresh.name

    # --- time -------------------------------------------------------------------------

    def expire(self, now: float) -> list[SessionState]:
        """Drop idle sessions and pseudonyms past their grace; the sessions due a
        ``rotate`` notice (sent again every period until a new key arrives: a lost
        notice, or a participant that reconnected with a clean session, only delays
        rotation)."""
        cfg = self._config
        due: list[SessionState] = []
        for key, session in list(self._sessions.items()):
            if now - session.last_seen > cfg.idle_timeout:
                del self._sessions[key]
                for p in [session.current, *session.old]:
                    if p is not None:
                        self._pseudonyms.pop(p.name, None)
                self._stats.sessions_expired += 1
                continue
            for old in [p for p in session.old if p.until <= now]:
                session.old.remove(old)
                self._pseudonyms.pop(old.name, None)
            if session.current is not None and now >= session.next_rotate:
                session.next_rotate = next_rotation(cfg.rotation.strategy, cfg.rotation_period, now)
                due.append(session)
        return due
