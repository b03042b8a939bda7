"""A participant's own answer while its session keeps quiet after a change of pseudonym.

The LDM's rotation policy may ask a participant to send nothing for a few seconds after
each change (`ldm.wire.rotation`, ``silence``). A positioning client then answers itself: the
correction of its last answer (the answer minus the fix it answered: mostly the common
error, which drifts slowly) applied to its current fix, on the same lane.
"""

from __future__ import annotations

from laas.models import CorrectedPosition, GpsMeasurement

__all__ = ["dead_reckon"]


def dead_reckon(
    answer: CorrectedPosition, answered: GpsMeasurement, now: GpsMeasurement
) -> CorrectedPosition:
    """The answer to fix `now` from the last answer `answer` to fix `answered`."""
    return answer.model_copy(
        update={
            "timestamp": now.timestamp,
            "latitude": now.latitude + (answer.latitude - answered.latitude),
            "longitude": now.longitude + (answer.longitude - answered.longitude),
        }
    )
