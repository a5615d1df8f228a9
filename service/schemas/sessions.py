"""Request and response models of the session API (API.md, "Sessions" and "Network sessions"). Field names
are binding.

A session created with an ``observer`` tracks one moving emitter from one fixed observer (paper 001); one
created with ``stations`` tracks emitters from the reports of a sensor network.
Angles are degrees at the API; every float is finite.
"""

from __future__ import annotations

from typing import Annotated, Literal, Union

from pydantic import BaseModel, Discriminator, Field, Tag, model_validator

from core.tracking import WARNING_CODES as TRACKING_WARNING_CODES
from core.tracking.association_types import AssociationConfig
from core.tracking.network import NETWORK_WARNING_CODES
from service.schemas import (MAX_ABS_TIME_S, MAX_FIX_MEASUREMENTS, MAX_RANGE_M, MIN_SIGMA_DEG, MIN_SIGMA_S, CotOptions,
                             ErrorSummary, FeatureCollection, GeodeticPosition, GeodeticPositionResult, LocalPosition,
                             LocalPositionResult, Measurement, Position, Station, Strict, Warning, codes_in_use)

#: JavaScript's largest exact integer: a seq above it would be mangled by many JSON clients.
MAX_SEQ = 2**53 - 1
MAX_TTL_S = 366 * 86400.0
#: Below a second a session would expire before its first post could reach it.
MIN_TTL_S = 1.0
MAX_EPOCHS_PER_POST = 10_000
#: The track id of a labelled network session's reports that name no emitter.
DEFAULT_EMITTER_ID = "default"


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


def seq_increasing(items: list, field: str, what: str) -> None:
    """A posted batch lists its items (epochs or reports) in increasing ``seq`` order: the order the client
    sends them, which makes ``seq`` the session's idempotency high-water mark."""
    for i in range(1, len(items)):
        if items[i].seq <= items[i - 1].seq:
            raise ValueError(f"{field}[{i}].seq must be above {field}[{i - 1}].seq (a batch lists {what} in "
                             "increasing seq order)")


class MeasurementBatch(Strict):
    measurements: list[Epoch] = Field(min_length=1, max_length=MAX_EPOCHS_PER_POST,
                                      description="epochs in increasing seq order")

    @model_validator(mode="after")
    def _seq_increasing(self):
        seq_increasing(self.measurements, "measurements", "epochs")
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


# -- network sessions (API.md, "Network sessions") ------------------------------------------------------------

MAX_REPORTS_PER_POST = 1_000
#: Emitter and track ids: printable ASCII without spaces (they become CoT uids and callsigns).
EmitterId = Annotated[str, Field(min_length=1, max_length=128, pattern=r"^[!-~]+$")]


class NetworkStation(Station):
    moving: bool = Field(False, description="true: a platform that moves; every report that measures from it "
                                            "carries its position at that report's time_s in the report's "
                                            "stations (false: the position given here, until a report moves it)")


class NetworkProcessNoise(Strict):
    accel_sigma_mps2: float = Field(1.0, gt=0.0, le=1e4,
                                    description="white acceleration noise of the constant-velocity model, per "
                                                "axis: the velocity random walk grows by this many m/s per sqrt(s)")
    imm_accel_sigmas_mps2: list[Annotated[float, Field(gt=0.0, le=1e4)]] | None = Field(
        None, min_length=2, max_length=4,
        description="increasing acceleration-noise levels of an interacting multiple model (for targets that "
                    "switch between quiet and manoeuvring legs); absent: one constant-velocity model at "
                    "accel_sigma_mps2 (which then serves a track's start only)")
    imm_mean_sojourn_s: float = Field(60.0, gt=0.0, le=1e6, description="mean time a target stays at one level "
                                                                       "(the IMM's Markov switching matrix)")
    vertical_accel_sigma_mps2: float | None = Field(None, gt=0.0, le=1e4,
                                                    description="the up axis's white acceleration when it differs "
                                                                "from the horizontal (an aircraft holding its "
                                                                "altitude: small); absent: accel_sigma_mps2 on "
                                                                "every axis")


class TrackStart(Strict):
    """How a track starts from its first report."""

    velocity_sigma_mps: float = Field(100.0, gt=0.0, le=1e5, description="standard deviation of each velocity "
                                                                         "component at a track's start (zero "
                                                                         "mean): about the fastest target speed")
    range_min_m: float = Field(1e3, gt=0.0, le=MAX_RANGE_M, description="a track started from one bearing: the "
                                                                         "nearest the emitter may be")
    range_max_m: float = Field(200e3, gt=0.0, le=MAX_RANGE_M, description="... and the farthest (a Gaussian sum "
                                                                           "along the line of sight covers these)")
    vertical_velocity_sigma_mps: float | None = Field(None, gt=0.0, le=1e5,
                                                      description="the up velocity's standard deviation at the "
                                                                  "start when it differs; absent: "
                                                                  "velocity_sigma_mps")


#: The association's defaults are core's (:class:`core.tracking.association_types.AssociationConfig`).
_ASSOCIATION = AssociationConfig()


class AssociationSettings(Strict):
    """How an ``"auto"`` session decides which bearings are one emitter's and manages its tracks (the rules:
    :mod:`core.tracking.association`). Every field defaults to core's setting."""

    method: Literal["jpda", "gnn"] = Field(_ASSOCIATION.method, description="jpda: each track weighs every "
                                                                            "bearing in its gate by its "
                                                                            "probability (two emitters passing "
                                                                            "close by keep their tracks); gnn: "
                                                                            "each bearing to at most one track, "
                                                                            "the likeliest pairing of a scan")
    detection_probability: float = Field(_ASSOCIATION.detection_probability, gt=0.0, lt=1.0,
                                         description="probability that a station measures a bearing of an "
                                                     "emitter in one scan")
    false_density_per_rad2: float = Field(_ASSOCIATION.false_density_per_rad2, gt=0.0, le=1e6,
                                          description="false bearings (multipath, noise) per scan per rad^2 of "
                                                      "azimuth and elevation (per rad for bearings without "
                                                      "elevation)")
    gate_probability: float = Field(_ASSOCIATION.gate_probability, ge=0.5, le=0.999999,
                                    description="chi-square probability of a track's gate: a bearing outside it "
                                                "is not that track's")
    confirm_hits: int = Field(_ASSOCIATION.confirm_hits, ge=1, le=100,
                              description="M of M-of-N: a tentative track is confirmed once M of its last N scans "
                                          "gave it a bearing, and dropped as soon as it no longer can; at most "
                                          "confirm_window")
    confirm_window: int = Field(_ASSOCIATION.confirm_window, ge=1, le=100, description="N of M-of-N: scans (one "
                                                                                       "station's bearings at one "
                                                                                       "time) counted")
    frequency_tolerance_hz: float = Field(_ASSOCIATION.frequency_tolerance_hz, gt=0.0, le=1e12,
                                          description="two bearings whose frequency_hz differ by more are never "
                                                      "one emitter's (a bearing without frequency_hz passes)")
    range_min_m: float = Field(_ASSOCIATION.range_min_m, gt=0.0, le=MAX_RANGE_M,
                               description="a track starts where three or more stations' bearings cross; a "
                                           "crossing nearer than this to a station is not a candidate")
    range_max_m: float = Field(_ASSOCIATION.range_max_m, gt=0.0, le=MAX_RANGE_M,
                               description="... nor one farther than this (above range_min_m)")


class NetworkSessionCreate(Strict):
    frame: Literal["wgs84", "local"] = "wgs84"
    origin: GeodeticPosition | None = Field(None, description="the session's common frame's tangent point; "
                                                              "with a local frame it places the plane on the "
                                                              "earth. Default: wgs84 the stations' centroid on "
                                                              "the ellipsoid, local a flat plane")
    stations: list[NetworkStation] = Field(min_length=1, max_length=256,
                                           description="the network's stations (unique ids); a report may add "
                                                       "stations or move them")
    model: Literal["ukf"] = Field("ukf", description="ukf: unscented Kalman filter on east, north, up and their "
                                                     "rates in the session's common frame (exact geodesy), updated "
                                                     "with the fix measurement models")
    process_noise: NetworkProcessNoise = Field(default_factory=NetworkProcessNoise)
    start: TrackStart = Field(default_factory=TrackStart)
    association: Literal["labelled", "auto"] = Field(
        "labelled", description="labelled: each report names its emitter (emitter_id; absent = the session's "
                                f"single emitter, track id {DEFAULT_EMITTER_ID!r}). auto: reports are bearings "
                                "with no emitter_id (any number of emitters; frequency_hz helps); the service "
                                "associates them, starts a track where three or more stations' bearings cross, "
                                "confirms it M of N, and ends it after end_after_s without a bearing "
                                "(association_config)")
    association_config: AssociationSettings | None = Field(
        None, description="with association auto only: its settings (absent: core's defaults)")
    reorder_window_s: float = Field(2.0, ge=0.0, le=3600.0,
                                    description="a report up to this much older than the newest applied one is "
                                                "still applied in time order; older ones are counted as late "
                                                "and not applied (auto: every post re-runs the association "
                                                "over the window's reports, so the number it keeps open is "
                                                "bounded: older ones settle early, and a report older than the "
                                                "settled ones is late)")
    coast_after_s: float = Field(10.0, gt=0.0, le=1e6, description="a track without a report for longer than "
                                                                   "this is coasting (predicted only; auto: a "
                                                                   "confirmed track without a bearing)")
    end_after_s: float = Field(60.0, gt=0.0, le=1e7, description="a track without a report for longer than this "
                                                                 "ends: it leaves tracks (the event stream and the "
                                                                 "TAK feed say so); above coast_after_s and "
                                                                 "reorder_window_s")
    ttl_s: float = Field(86400.0, ge=MIN_TTL_S, le=MAX_TTL_S,
                         description="idle lifetime: the session is deleted ttl_s after its last write")
    cot: CotOptions | None = Field(None, description="CoT uid, type and stale time of the tracks' events: a "
                                                     "track's uid is uid (the single emitter's track) or "
                                                     "uid-<track id>; default passive-locator-session-<id>-"
                                                     "<track id>")

    @model_validator(mode="after")
    def _stations(self):
        wanted = GeodeticPosition if self.frame == "wgs84" else LocalPosition
        seen = set()
        for station in self.stations:
            if station.id in seen:
                raise ValueError(f"station id {station.id!r} is given twice")
            seen.add(station.id)
            if not isinstance(station.position, wanted):
                raise ValueError(f"frame {self.frame!r} needs {wanted.__name__} station positions; station "
                                 f"{station.id!r} differs")
        return self


class Report(Strict):
    seq: int = Field(ge=0, le=MAX_SEQ, description="increases in the order the client sends reports (not in "
                                                   "time_s order); not above the last applied one = a duplicate, "
                                                   "acknowledged and not applied")
    time_s: float = Field(ge=-MAX_ABS_TIME_S, le=MAX_ABS_TIME_S,
                          description="when the measurements were taken, on the session's clock")
    emitter_id: EmitterId | None = Field(None, description="labelled sessions: the emitter (track id); absent = "
                                                           f"the session's single emitter, {DEFAULT_EMITTER_ID!r}. "
                                                           "An auto session refuses it (422 at the report's "
                                                           "emitter_id: the service decides which reports belong "
                                                           "together)")
    frequency_hz: float | None = Field(None, gt=0.0, le=1e13, description="the signal's frequency. auto: a "
                                                                          "frequency gate (bearings more than "
                                                                          "association_config."
                                                                          "frequency_tolerance_hz apart are "
                                                                          "never one emitter's; absent: no "
                                                                          "gate); unused by labelled sessions")
    stations: list[Station] = Field(default_factory=list, max_length=256,
                                    description="positions at time_s of moving stations, and new stations "
                                                "(in the session's frame)")
    measurements: list[Measurement] = Field(
        min_length=1, max_length=MAX_FIX_MEASUREMENTS,
        description="the /v1/fixes measurement objects, every sigma given; the TOAs of one report share one "
                    "unknown emission time, so a report's TOAs come from at least two stations")


class ReportBatch(Strict):
    reports: list[Report] = Field(min_length=1, max_length=MAX_REPORTS_PER_POST,
                                  description="reports in increasing seq order (any time_s order)")

    @model_validator(mode="after")
    def _seq_increasing(self):
        seq_increasing(self.reports, "reports", "reports")
        return self


class NetworkStationState(BaseModel):
    id: str = Field(description="the station id")
    position: GeodeticPositionResult | LocalPositionResult = Field(description="the latest known position")
    moving: bool = Field(description="true: every report that measures from it gives its position")
    time_s: float | None = Field(description="report time of that position; null: as given at creation")


class NetworkTrack(BaseModel):
    id: str = Field(description="labelled: the emitter_id; auto: the service's id (t1, t2, ... in start order, "
                                "never reused, the same while the track lives)")
    status: Literal["tentative", "confirmed", "coasting"] = Field(
        description="tentative: the reports so far do not determine the position well (e.g. one platform that "
                    "has not manoeuvred; auto: not yet confirmed M of N); confirmed; coasting: not reported "
                    "lately, predicted only")
    time_s: float = Field(description="the time of the estimate")
    position: GeodeticPositionResult | None = Field(description="when the session's frame is geodetic")
    position_local: LocalPositionResult = Field(description="in the session's local frame, or ENU metres at "
                                                            "the frame's origin when the frame is wgs84")
    velocity_enu_mps: list[float] = Field(description="[east, north, up] in the axes at the track")
    covariance_enu: Matrix6 = Field(description="6x6 covariance of [east_m, north_m, up_m, east_mps, north_mps, "
                                                "up_mps] in the east/north/up axes at the track")
    error: ErrorSummary = Field(description="the position's error, as a fix's (gdop null)")
    updates: int = Field(description="reports applied to this track")
    warnings: list[Warning] = Field(description="raised by the track's last report; codes: "
                                                + codes_in_use(NETWORK_WARNING_CODES))
    cot: str | None = Field(None, description="with ?formats=cot: the track as a CoT 2.0 track event (how m-p, "
                                              "track course and speed, contact callsign, ce/le one-sigma; null "
                                              "in a flat local frame, and in an auto session for a tentative "
                                              "track: a map shows no track before it is confirmed)")
    mode_probabilities: list[float] | None = Field(None, description="with process_noise.imm_accel_sigmas_mps2, "
                                                                     "once the track is one Gaussian: the "
                                                                     "probability of each level, in their order")


class EndedTrack(BaseModel):
    id: str = Field(description="the track (emitter) id")
    time_s: float = Field(description="the time of its last estimate")
    version: int = Field(description="the session version whose post ended it")


class NetworkSessionState(BaseModel):
    """A network session: the stations and one track per emitter."""

    id: str = Field(description="the session id (in its URL)")
    version: int = Field(description="+1 on every write; the ETag is the quoted version")
    model: Literal["ukf"] = Field(description="the tracker (as created)")
    frame: Literal["wgs84", "local"] = Field(description="the frame of the stations' positions (as created)")
    origin: GeodeticPositionResult | None = Field(description="the common frame's tangent point (null: a flat "
                                                              "local plane)")
    association: Literal["labelled", "auto"] = Field(description="how reports are assigned to tracks (as created)")
    reorder_window_s: float = Field(description="as created: how much older than the newest applied report a "
                                                "report may be and still be applied in time order")
    stations: list[NetworkStationState] = Field(description="every station the session knows, with its latest "
                                                            "position")
    last_seq: int | None = Field(description="highest seq seen; null before the first")
    last_time_s: float | None = Field(description="newest report time applied")
    updates: int = Field(description="reports applied")
    association_config: AssociationSettings | None = Field(None, description="auto: the association's settings "
                                                                             "in use; null for labelled")
    tracks: list[NetworkTrack] = Field(description="one per emitter (auto: every track, tentative ones too, with "
                                                   "its status), each at its own time (or, with at_time_s, "
                                                   "predicted to that time)")
    ended_tracks: list[EndedTrack] = Field(description="the latest tracks that ended (coasted out), newest last "
                                                       "(auto: confirmed tracks; a tentative one that fails M of "
                                                       "N leaves tracks unannounced, it was never on a map)")
    at_time_s: float | None = Field(None, description="with ?at_time_s=: the time the tracks were predicted to "
                                                      "(constant velocity, IMM-mixed; a track already newer is "
                                                      "given as it is)")
    warnings: list[Warning] = Field(description="raised by the last post that applied reports; codes: "
                                                + codes_in_use(NETWORK_WARNING_CODES))
    created_at: str = Field(description="RFC 3339, UTC")
    updated_at: str = Field(description="RFC 3339, UTC")
    expires_at: str = Field(description="RFC 3339, UTC; moves forward by ttl_s on every write")
    ttl_s: float = Field(description="idle lifetime (as created)")
    geojson: FeatureCollection | None = Field(None, description="with ?formats=geojson: every track's point "
                                                                "(course, speed), its 95 % ellipse and its "
                                                                "course line (60 s at its velocity); an auto "
                                                                "session's tentative tracks left out")


class ReportResult(NetworkSessionState):
    """The state after a post of reports, and what the post did."""

    applied: int = Field(description="reports of this post applied (in time order, late ones within "
                                     "reorder_window_s included)")
    duplicates: int = Field(description="reports whose seq was not above the last applied one (acknowledged, "
                                        "not applied)")
    late: int = Field(description="reports older than the newest applied time less reorder_window_s (auto: "
                                  "or than the settled reports): acknowledged, counted, not applied")


AnySessionState = Annotated[Union[SessionState, NetworkSessionState], Field(union_mode="left_to_right")]


def _create_kind(value) -> str:
    """Which create request a body is: one with ``stations`` is a network session's, else paper 001's."""
    if isinstance(value, dict):
        return "network_session" if "stations" in value and "observer" not in value else "observer_session"
    return "network_session" if isinstance(value, NetworkSessionCreate) else "observer_session"


AnySessionCreate = Annotated[
    Union[Annotated[SessionCreate, Tag("observer_session")], Annotated[NetworkSessionCreate, Tag("network_session")]],
    Discriminator(_create_kind),
]


class SessionList(BaseModel):
    sessions: list[AnySessionState] = Field(description="oldest first (ids begin with the creation time in ms)")
    next_cursor: str | None = Field(description="pass as cursor for the next page; null on the last page")


# -- network tracking evaluation (POST /v1/evaluations with "network", passive-locator evaluate) ------------------

NetworkScene = Literal["df_network", "toa_network", "airborne_df"]


class NetworkEvaluationSpec(Strict):
    scene: NetworkScene = Field(description="df_network: four direction finders 25-35 km apart, a ground vehicle "
                                            "at 15-25 m/s, a tenth of the reports up to 1.5 s late; toa_network: "
                                            "five TOA stations (20-50 ns) timing an aircraft at 5-10 km, "
                                            "150-250 m/s; airborne_df: one airborne direction finder flying "
                                            "straight, then turning, past a slow ground emitter")
    trials: int = Field(20, ge=1, le=500, description="Monte Carlo runs (run r draws from seed + r)")
    seed: int = Field(0, ge=0, le=2**32)
    process_noise: NetworkProcessNoise | None = Field(None, description="the tracker's process noise (default: "
                                                                        "the scene's, matched to its truth)")
    reorder_window_s: float | None = Field(None, ge=0.0, le=3600.0, description="default: the scene's")


class NetworkEvaluationRequest(Strict):
    network: NetworkEvaluationSpec


class NetworkEpochs(BaseModel):
    time_s: list[float] = Field(description="evaluation epochs (session clock)")
    rmse_position_m: list[float | None] = Field(description="over the trials with a track (null: none has one)")
    pcrb_position_m: list[float | None] = Field(description="sqrt(trace) of the posterior CRLB's position block "
                                                            "(null while the position is not determined)")
    rmse_velocity_mps: list[float | None] = Field(description="velocity RMSE (m/s), as rmse_position_m")
    pcrb_velocity_mps: list[float | None] = Field(description="sqrt(trace) of the bound's velocity block (m/s)")
    nees_position: list[float | None] = Field(description="mean position NEES over the trials (3 if honest)")
    nees_state: list[float | None] = Field(description="mean 6-state NEES over the trials (6 if honest)")
    tracked_fraction: list[float] = Field(description="fraction of the trials with a track at the epoch")
    confirmed_fraction: list[float] = Field(description="fraction of the trials with a confirmed track")


class NetworkEvaluationResponse(BaseModel):
    scene: str = Field(description="the scene evaluated")
    trials: int = Field(description="Monte Carlo runs")
    seed: int = Field(description="run r drew from seed + r")
    converged_after_s: float = Field(description="epochs from this long after the start are judged")
    rmse_over_pcrb: float | None = Field(description="position RMSE over the judged epochs / the PCRB's (1 is at "
                                                     "the bound)")
    nees_after: float | None = Field(description="mean position NEES over the judged epochs and trials")
    nees_interval_99: list[float] = Field(description="the chi-square 99 % interval of a per-epoch mean "
                                                      "position NEES over the trials")
    late_reports: int = Field(description="reports counted late (older than the reorder window), over all trials")
    epochs: NetworkEpochs = Field(description="per evaluation epoch, every list in time order")


class MultiEmitterEvaluationSpec(Strict):
    variant: int = Field(0, ge=0, le=10_000, description="the multi-emitter scene: 0 the base scene (four direction "
                                                         "finders, four ground emitters, two of them on one "
                                                         "frequency passing within 1.5 km); any other number a "
                                                         "held-out variant drawn from it (speeds, headings, where "
                                                         "and when the pair meets)")
    trials: int = Field(5, ge=1, le=200, description="Monte Carlo runs (run r draws from seed + r)")
    seed: int = Field(0, ge=0, le=2**32)
    duration_s: float | None = Field(None, ge=10.0, le=300.0, description="seconds simulated from the scene's "
                                                                          "start (default: all of its 300)")


class MultiEmitterEvaluationRequest(Strict):
    multi_emitter: MultiEmitterEvaluationSpec


class GospaParts(BaseModel):
    gospa_m: float = Field(description="mean over epochs and trials of GOSPA (c = gospa_cutoff_m, p = 2, alpha = 2, "
                                       "east-north)")
    localisation_m2: float = Field(description="mean of GOSPA^2's part from assigned pairs (m^2)")
    missed_m2: float = Field(description="mean of GOSPA^2's part from missed emitters, c^2 / 2 each (m^2)")
    false_m2: float = Field(description="mean of GOSPA^2's part from false estimates, c^2 / 2 each (m^2)")
    gospa_per_trial_m: list[float] = Field(description="each trial's mean over its epochs")


class MultiEmitterEvaluationResponse(BaseModel):
    scene: str = Field(description="the scene evaluated")
    variant: int = Field(description="its variant")
    trials: int = Field(description="Monte Carlo runs")
    seed: int = Field(description="run r drew from seed + r")
    duration_s: float = Field(description="seconds simulated")
    gospa_cutoff_m: float = Field(description="GOSPA's c: an error beyond it counts as a miss and a false estimate")
    tracker: GospaParts = Field(description="the association tracker's confirmed tracks, scored once a second")
    baseline: GospaParts = Field(description="pairwise bearing intersections clustered with DBSCAN on the same "
                                             "bearings, scored at the same epochs")
    gospa_over_baseline: float | None = Field(description="tracker's mean GOSPA / the baseline's")
    emitters: list[str] = Field(description="the scene's emitter ids, the order of confirm_delay_s's rows")
    confirm_delay_s: list[list[float | None]] = Field(
        description="per trial, per emitter: seconds from its first detection to the first epoch a confirmed "
                    "track is assigned to it (null: never; 0 for an emitter never detected)")
    false_tracks: list[int] = Field(description="per trial: confirmed tracks assigned to no emitter at most of the "
                                                "epochs they were reported")
    identity_switches: list[int] = Field(description="per trial: changes of the track that stands for an emitter")
