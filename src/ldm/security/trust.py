"""Which services a participant or a core trusts: pinned identities and trust anchors.

A service description is trusted when

1. it carries a valid signature by its ``identity`` key, and
2. that identity is pinned for the service's name (``service_keys``), or a trust
   anchor (``anchors``) endorsed it for that name; for a regional provider, the name of
   its family will do as well.

A `Trust` with neither pins nor anchors is *open*: it takes any description, signed or
not, which is how a participant behaved before identities existed (it then trusts the
core and the brokers with its keys; see docs/security.md).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

from ldm.security.identity import endorsement_text, verify
from ldm.wire.messages import Announcement, ServiceDescription

__all__ = ["Trust"]


class Trust:
    """Checks service descriptions and announcements against pins and anchors."""

    __slots__ = ("anchors", "service_keys")

    def __init__(
        self, service_keys: Mapping[str, str] | None = None, anchors: Iterable[str] = ()
    ) -> None:
        self.service_keys = dict(service_keys or {})
        self.anchors = tuple(anchors)

    @property
    def open(self) -> bool:
        """True when nothing is pinned: every description is taken."""
        return not self.service_keys and not self.anchors

    def problem(self, desc: ServiceDescription) -> str | None:
        """Why ``desc`` is not trusted, or None if it is."""
        if self.open:
            return None
        if desc.identity is None or not verify(desc.identity, desc.signed_text(), desc.signature):
            return f"service {desc.name!r} is not signed by its identity key"
        # A regional provider may be pinned or endorsed under its family's name: the
        # signature covers the family and the coverage it announces.
        for name in (desc.name, desc.family):
            if name is None:
                continue
            pinned = self.service_keys.get(name)
            if pinned is not None and pinned == desc.identity:
                return None
            text = endorsement_text(name, desc.identity)
            if any(verify(anchor, text, desc.endorsement) for anchor in self.anchors):
                return None
        return (
            f"service {desc.name!r} is signed by identity {desc.identity}, which is neither "
            "pinned for it nor endorsed by a trusted anchor"
        )

    def trusts(self, desc: ServiceDescription) -> bool:
        return self.problem(desc) is None

    def announcement(self, ann: Announcement) -> bool:
        """A trusted description, announced (``t`` signed) by the same identity."""
        if self.open:
            return True
        desc = ann.service
        return (
            self.trusts(desc)
            and desc.identity is not None
            and verify(desc.identity, ann.signed_text(), ann.sig)
        )
