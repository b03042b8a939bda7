"""Engine configuration: validated once, then passed around as a frozen object."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    ValidatorFunctionWrapHandler,
    model_validator,
)

from laas.errors import ConfigError

__all__ = ["EngineConfig", "Mode", "Settings"]

Mode = Literal["default", "paper"]
"""`paper`: the joint-hypothesis discrete Bayes filter of the paper (section IV-D).
`default`: the cooperative estimate of the common GNSS error with a scalable lane search."""

Positive = Annotated[float, Field(gt=0.0, allow_inf_nan=False)]
NonNegative = Annotated[float, Field(ge=0.0, allow_inf_nan=False)]
Probability = Annotated[float, Field(ge=0.0, le=0.5, allow_inf_nan=False)]


class Settings(BaseModel):
    """A frozen configuration object whose refusals are `ConfigError`s naming each setting.

    >>> EngineConfig(sigma_pos=-1.0)
    Traceback (most recent call last):
    ...
    laas.errors.ConfigError: invalid EngineConfig: sigma_pos: Input should be greater than 0
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    @model_validator(mode="wrap")
    @classmethod
    def _named_refusal(cls, data: Any, handler: ValidatorFunctionWrapHandler) -> Any:
        try:
            return handler(data)
        except ValidationError as exc:
            found = "; ".join(
                f"{'.'.join(str(x) for x in e['loc']) or 'value'}: {e['msg']}" for e in exc.errors()
            )
            raise ConfigError(f"invalid {cls.__name__}: {found}") from None


LIAR_EVIDENCE_CAP = 16.0
"""`EngineConfig.max_user_evidence` for a deployment that expects lying participants."""


class EngineConfig(Settings):
    """Everything the positioning engine can be tuned by.

    The sensor sigmas describe the receivers (the paper tunes its Kalman filter
    "by approximating the sensor accuracy"); the rest are model constants.
    """

    mode: Mode = "default"
    kalman: bool = Field(default=True, description="smooth each track with a Kalman filter")

    # Sensors (1-sigma).
    sigma_pos: Positive = Field(default=1.0, description="receiver position noise per axis, m")
    sigma_vel: Positive = Field(default=0.25, description="receiver speed noise, m/s")
    sigma_heading: Positive = Field(default=0.5, description="receiver heading noise, degrees")
    sigma_accel: Positive = Field(
        default=0.7, description="Kalman process noise: white acceleration, m/s^2"
    )

    # Tracks.
    track_multipath: Probability = Field(
        default=0.05,
        description=(
            "default mode: the share of fixes a Kalman track takes to be in multipath "
            "(metres off, see laas.engine.tracking); 0 gives the plain Kalman filter"
        ),
    )
    track_timeout: Positive = Field(
        default=5.0, description="a gap longer than this (s) restarts a user's track"
    )
    group_timeout: Positive = Field(
        default=3.0, description="a user silent for longer (s) leaves its segment's group"
    )
    max_map_distance: Positive = Field(
        default=15.0, description="fixes farther than this (m) from every lane are off the map"
    )

    # Lane model.
    sigma_lane: Positive = Field(
        default=0.25, description="spread of a user's lateral position about its lane centre, m"
    )
    lane_change_rate: NonNegative = Field(
        default=0.02,
        description=(
            "default mode: lane changes per second, to each side, that lateral motion does "
            "not announce"
        ),
    )
    sigma_receiver: NonNegative = Field(
        default=0.5,
        description=(
            "default mode: 1-sigma of a receiver's own lasting error across the road (its "
            "bias and multipath, which no filtering removes), m"
        ),
    )
    evidence_interval: Positive = Field(
        default=3.0,
        description=(
            "default mode: how long (s) a receiver's lasting errors (its place in the lane, "
            "its bias, its multipath) persist: the fixes within it share them, so their lane "
            "evidence counts as fewer independent fixes (laas.engine.cooperative)"
        ),
    )
    motion_memory: Positive = Field(
        default=1.0,
        description=(
            "default mode: how long (s) a user's direction and speed stay what they were; "
            "their evidence about lanes counts once per this many seconds, not once per fix"
        ),
    )
    calibrated: bool = Field(
        default=True,
        description=(
            "default mode: report the lane probability through the calibration map fitted "
            "on the development suite (laas.engine.calibration), so that it is the rate at "
            "which such answers are right"
        ),
    )
    max_lane_change: Probability = Field(
        default=0.45, description="largest probability of leaving a lane to one side in one step"
    )

    # Paper mode.
    max_hypotheses: Annotated[int, Field(ge=1)] = Field(
        default=1 << 20,
        description="paper mode: users beyond this many joint hypotheses (L^N) are placed alone",
    )
    paper_lane_change_rate: NonNegative = Field(
        default=0.2,
        description=(
            "paper mode: lane changes per second, to each side, that heading does not "
            "announce; also how fast an old lane decision fades"
        ),
    )

    # Default mode: the common GNSS error, a 2-D random walk per area.
    bias_prior: Positive = Field(
        default=10.0, description="1-sigma of the common error before any evidence, m"
    )
    bias_drift: NonNegative = Field(
        default=0.1,
        description=(
            "random-walk drift of the common error, m/sqrt(s): the mean of the development "
            "families' U(0, 0.2); a drift assumed too slow lets old evidence pin the "
            "estimate after the error has moved (a lock-in), and triangulates it wrongly "
            "along a gently curving road"
        ),
    )
    evidence_memory: Positive | None = Field(
        default=30.0,
        description=(
            "default mode: how long (s) evidence about the common error is remembered: "
            "older evidence fades, log p <- e^(-dt / tau) log p + (1 - e^(-dt / tau)) "
            "log p0, so a receiver's lasting error counts about tau / evidence_interval "
            "times, not without bound; None keeps all evidence, and so does an area that "
            "doubts its participants (max_user_evidence)"
        ),
    )
    bias_area: Positive = Field(
        default=2_000.0, description="size of the area that shares one common error, m"
    )
    bias_resolution: Positive = Field(
        default=0.3, description="cell size of the common error's grid posterior, m"
    )
    max_user_evidence: Positive | None = Field(
        default=None,
        description=(
            "default mode: K, nats, or None (off, the default). With K, one participant of an "
            "area may be lying: where its own evidence is more than K nats below its best, "
            "it is more likely that than honest, and it counts against that value of the "
            "common error by K at most, so it moves the estimate by at most sqrt(2 K) "
            "standard deviations of the others' (laas.engine.common_error). "
            "LIAR_EVIDENCE_CAP = 16 is the value to use: 94 % of the honest receivers of the "
            "dev suite never come that far from the true common error "
            "(scripts/liar_deficits.py). Off by default: it costs about 1.9x the engine's "
            "CPU per fix (docs/security.md)"
        ),
    )
