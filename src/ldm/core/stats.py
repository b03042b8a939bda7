"""What a core counts: every message it takes ends in exactly one counter."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["CoreStats"]


@dataclass(slots=True)
class CoreStats:
    """Counters a test or an operator can read (``Core.stats``)."""

    forwarded_in: int = 0
    forwarded_out: int = 0
    dropped_stale: int = 0
    dropped_unroutable: int = 0
    dropped_invalid: int = 0
    dropped_overload: int = 0
    rejected_rate: int = 0
    rejected_size: int = 0
    rejected_clock: int = 0
    rejected_rekey: int = 0
    """Input under a new ephemeral key too soon after the last one (answered ``rate_limited``)."""
    rejected_unavailable: int = 0
    """Input for another cluster's service while the backbone broker is unreachable
    (`ldm.core.routing.Router.backbone_problem`; answered ``unavailable``)."""
    granted: int = 0
    answered_nosession: int = 0
    """Input or requests for a session the core does not hold (answered ``nosession``)."""
    answered_refused: int = 0
    """Requests or input for a service the cluster does not offer (answered ``refused``)."""
    notices_suppressed: int = 0
    """Refusals not answered because the client's notice bucket was empty."""
    control: int = 0
    """Announcements, withdrawals and core statuses taken (valid, fresh), and this
    core's own service list seen back from the broker."""
    dropped_untrusted: int = 0
    """Announcements not signed by a pinned or endorsed identity, or bound to no
    cluster (with trust set)."""
    dropped_elsewhere: int = 0
    """Announcements signed for another cluster than the one they came from (replays)."""
    repaired_list: int = 0
    """Service lists on the cluster that were not this core's own, replaced by it."""
    dropped_unauthentic: int = 0
    """Input without the tag of its session's secret: forged on the participant's topics
    (a broker without ACL). Not answered: an answer would spend the participant's
    notice budget; a participant whose secret a forged request replaced opens its
    session again when its request times out."""
    rotations: int = 0
    sessions_expired: int = 0
    batches_sent: int = 0
    """Messages that carried more than one envelope to a provider or another core."""
    batched: int = 0
    """Envelopes forwarded in those batches (the rest went one per message)."""
    dropped_retained: int = 0
    """Participant messages the broker delivered as retained (each cleared on the
    broker with an empty retained publish; old, so never taken as input), and empty
    ones (MQTT's deletion of a retained message, such as the echo of that clearing):
    dropped at intake, unanswered."""
