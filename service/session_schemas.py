"""Request and response models of the session API (API.md, "Sessions"). Field names are binding.

A session tracks one moving emitter from one fixed observer (paper 001).
Angles are degrees at the API; every float is finite.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, Field, model_validator

from core.tracking import WARNING_CODES as TRACKING_WARNING_CODES
from service.schemas import (MAX_ABS_TIME_S, MIN_SIGMA_DEG, MIN_SIGMA_S, CotOptions, FeatureCollection,
                             GeodeticPosition, GeodeticPositionResult, LocalPosition, LocalPositionResult, Position,
                             Strict, Warning, codes_in_use)

#: JavaScript's largest exact integer: a seq above it would be mangled by many JSON clients.
MAX_SEQ = 2**53 - 1
MAX_TTL_S = 366 * 86400.0
#: Below a second a session would expire before its first post could reach it.
MIN_TTL_S = 1.0
MAX_EPOCHS_PER_POST = 10_000


class Observer(Strict):
    position: Position = Field(description="the fixed observer; its ENU frame is the filter's frame")


class Pulse(Strict):
    period_s: float = Field(ge=1e-7, le=10.0, description="pulse repetition period: the truth when period_known, "
                                                         "else the initial estimate")
    period_known: bool = False
    pulses_per_observation: int = Field(ge=1, le=10**9, description="nominal pulses N between two reports "
                                                                    "(report interval T = N period_s)")


class Noise(Strict):
    sigma_azimuth_deg: float = Field(ge=MIN_SIGMA_DEG, lt=28.0, description="azimuth standard deviation")
    sigma_elevation_deg: float = Field(ge=MIN_SIGMA_DEG, lt=28.0, description="elevation standard deviation")
    sigma_azimuth_rate_deg_s: float = Field(ge=1e-9, le=360.0, description="azimuth-rate standard deviation")
    sigma_toa_s: float = Field(ge=MIN_SIGMA_S, le=1.0, description="standard deviation of one time of arrival")


class ProcessNoise(Strict):
    accel_sigma_mps2: float = Field(1.0, ge=0.0, le=1e4,
                                    description="white acceleration noise of the constant-velocity model: "
                                                "the velocity random walk grows by this many m/s per sqrt(s)")
    imm_accel_sigmas_mps2: list[Annotated[float, Field(ge=0.0, le=1e4)]] | None = Field(
        None, min_length=2, max_length=4,
        description="joint_ukf only: increasing acceleration-noise levels of an interacting multiple model, for a "
                    "target that switches between quiet and manoeuvring legs without guessing one level "
                    "(accel_sigma_mps2 then serves the start only). On paper 001's geometry, a target "
                    "alternating 0.05 and 1 m/s^2 legs, levels [0.05, 1]: position RMSE 1.12-1.15x the "
                    "posterior CRLB of the true switching model")
    imm_mean_sojourn_s: float = Field(120.0, gt=0.0, le=1e6,
                                      description="mean time the target stays at one level (the IMM's Markov "
                                                  "switching matrix)")


Model = Literal["velocity_kinematic", "joint_ukf"]


class SessionCreate(Strict):
    frame: Literal["wgs84", "local"] = "wgs84"
    observer: Observer
    model: Model = Field("joint_ukf", description="joint_ukf (default): one UKF on position, velocity and period "
                                                  "error fed with the raw measurements, started over 10-400 km as a "
                                                  "range-parameterised Gaussian sum; it is the default because it is "
                                                  "at the bound: on paper 001's geometry (truths from the model, "
                                                  "RMSE over the last 50 of 200 s) 1.01-1.02x the posterior CRLB at "
                                                  "accel_sigma 0.05 m/s^2 and 1.02-1.04x at 0.5 (200 runs), where "
                                                  "velocity_kinematic is 1.3-2.3x. velocity_kinematic: paper 001's "
                                                  "method (velocity from TOA differences, range from the azimuth "
                                                  "rate, UKF on position)")
    pulse: Pulse
    noise: Noise
    process_noise: ProcessNoise = Field(default_factory=ProcessNoise)
    ttl_s: float = Field(86400.0, ge=MIN_TTL_S, le=MAX_TTL_S,
                         description="idle lifetime: the session is deleted ttl_s after its last write "
                                     "(creation or a post that applied measurements)")
    cot: CotOptions | None = Field(None, description="CoT uid (default passive-locator-session-<id>: one uid per "
                                                     "session), callsign (default the uid), type and stale time "
                                                     "of the session's track events")

    @model_validator(mode="after")
    def _observer_matches_frame(self):
        wanted = GeodeticPosition if self.frame == "wgs84" else LocalPosition
        if not isinstance(self.observer.position, wanted):
            raise ValueError(f"frame {self.frame!r} needs a {wanted.__name__} observer position")
        return self


class Epoch(Strict):
    seq: int = Field(ge=0, le=MAX_SEQ, description="per-session sequence number; not above the last applied "
                                                   "one = a duplicate, acknowledged and not applied")
    time_s: float = Field(ge=-MAX_ABS_TIME_S, le=MAX_ABS_TIME_S,
                          description="observer time of the report; must increase with seq")
    azimuth_deg: float = Field(ge=-360.0, le=720.0, description="clockwise from true north")
    elevation_deg: float = Field(gt=-90.0, lt=90.0, description="above the observer's horizontal plane")
    azimuth_rate_deg_s: float = Field(ge=-1e5, le=1e5, description="rate of change of the azimuth")
    toa_s: float = Field(ge=-MAX_ABS_TIME_S, le=MAX_ABS_TIME_S, description="time of arrival of the report's pulse, on any fixed clock epoch (only "
                                     "differences are used; keep it small enough that float64 resolves sigma_toa_s)")


class MeasurementBatch(Strict):
    measurements: list[Epoch] = Field(min_length=1, max_length=MAX_EPOCHS_PER_POST,
                                      description="epochs in increasing seq order")

    @model_validator(mode="after")
    def _seq_increasing(self):
        for i in range(1, len(self.measurements)):
            if self.measurements[i].seq <= self.measurements[i - 1].seq:
                raise ValueError(f"measurements[{i}].seq must be above measurements[{i - 1}].seq "
                                 "(a batch lists epochs in increasing seq order)")
        return self


Matrix6 = list[list[float]]


class SessionState(BaseModel):
    """The session's filter state. Before initialisation (the filter needs a few epochs to see the
    velocity and range) the position, velocity, range and covariance fields are null."""

    id: str = Field(description="the session id: its URL is /v1/sessions/{id}")
    version: int = Field(description="+1 on every write; the ETag is the quoted version")
    model: Model = Field(description="the tracking model, as created")
    frame: Literal["wgs84", "local"] = Field(description="the frame of the positions, as created")
    observer: Observer = Field(description="the observer, as created")
    last_seq: int | None = Field(description="highest seq applied; null before the first")
    last_time_s: float | None = Field(description="time_s of that epoch")
    updates: int = Field(description="epochs applied")
    initialized: bool = Field(description="false until the filter has an estimate (the estimate fields are null "
                                          "until then)")
    position: GeodeticPositionResult | None = Field(description="emitter position; when the frame is wgs84")
    position_local: LocalPositionResult | None = Field(description="emitter position: in the request's local plane, or "
                                                             "ENU metres at the observer when the frame is wgs84")
    velocity_enu_mps: list[float] | None = Field(description="[east, north, up] at the observer")
    range_m: float | None = Field(description="distance from the observer")
    range_sigma_m: float | None = Field(description="standard deviation of range_m")
    pulse_period_s: float = Field(description="current pulse-period estimate (the given one when known)")
    covariance_enu: Matrix6 | None = Field(description="6x6 covariance of [east_m, north_m, up_m, east_mps, "
                                                       "north_mps, up_mps] at the observer")
    warnings: list[Warning] = Field(description="raised by the last post that applied epochs; codes: "
                                                + codes_in_use(TRACKING_WARNING_CODES))
    mode_probabilities: list[float] | None = Field(None, description="with process_noise.imm_accel_sigmas_mps2, "
                                                                     "once the start has settled: the probability "
                                                                     "of each level, in their order")
    created_at: str = Field(description="RFC 3339, UTC")
    updated_at: str = Field(description="RFC 3339, UTC")
    expires_at: str = Field(description="RFC 3339, UTC; moves forward by ttl_s on every write")
    ttl_s: float = Field(description="idle lifetime, seconds, as created")
    cot: str | None = Field(None, description="with ?formats=cot: the estimate as a CoT 2.0 track event (how m-p, "
                                              "detail/track course and speed, ce/le one-sigma; null before the "
                                              "filter is initialised or in a local frame)")
    geojson: FeatureCollection | None = Field(None, description="with ?formats=geojson: the track point (course, "
                                                                "speed) and its 95 % ellipse")


class MeasurementResult(SessionState):
    """The state after a post, and what the post did."""

    applied: int = Field(description="epochs of this post that were applied")
    duplicates: int = Field(description="epochs of this post whose seq was not above the last applied one "
                                        "(acknowledged, not applied)")


class SessionList(BaseModel):
    sessions: list[SessionState] = Field(description="oldest first (ids begin with the creation time in ms)")
    next_cursor: str | None = Field(description="pass as cursor for the next page; null on the last page")
