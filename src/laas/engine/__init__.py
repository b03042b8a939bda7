"""The positioning engine: pure, no MQTT, no files, no clock of its own.

tracking       one Kalman filter per user: [e, n, v_e, v_n], constant velocity
transition     the lane prediction step: heading against the lane direction
paper          paper mode: discrete Bayes filter over all L^N joint hypotheses
common_error   default mode: the shared GNSS error per area, a grid posterior
assignment     default mode: the exact joint lane search in O(N^2 L^3)
lanefilter     the two modes behind one lane-filter interface
engine         map -> tracks -> segments -> lane filter -> corrected positions
handover       what one regional worker hands the next: a user's state, area evidence
"""

from laas.engine.engine import Engine, EngineStats

__all__ = ["Engine", "EngineStats"]
