"""The positioning engine: pure, no MQTT, no files, no clock of its own.

tracking       one Kalman filter per user: [e, n, v_e, v_n], constant velocity
transition     the lane prediction step: heading against the lane direction
lanefilter     the interface both modes implement
paper          paper mode: discrete Bayes filter over all L^N joint hypotheses
common_error   default mode: the shared GNSS error per area, a grid posterior
cooperative    default mode: the common error and every user's lane, jointly
stacked        default mode's arithmetic for all users of an area at once, as arrays
jit            the compiled arithmetic's decorator (numba); warm: compile it before
               the first fix that counts
calibration    the lane probability mapped to how often it is right
engine         map -> tracks -> segments -> lane filter -> corrected positions, and
               `make_lane_filter`, the lane filter of a mode
handover       what one regional worker hands the next: a user's state, area evidence
"""

from laas.engine.engine import Engine, EngineStats

__all__ = ["Engine", "EngineStats"]
