"""The network tracker's values: its settings, a report, a track.

:mod:`core.tracking.network` (the public API and the session state) and :mod:`core.tracking.network_update`
(one report on one track) both build on these; this module imports neither. Everything is in the session's
common ENU frame (metres); statuses and stages are those of :mod:`core.tracking.network`.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import numpy as np

from core.errors import InvalidInput
from core.tracking.state import frozen_array

STATUSES = ("tentative", "confirmed", "coasting")
#: A track's filter: a Gaussian sum along the first line of sight, one Gaussian, or IMM modes.
STAGES = ("mixture", "single", "imm")

@dataclass(frozen=True)
class NetworkConfig:
    """Settings of a network session's tracker; validated on construction.

    Attributes
    ----------
    accel_sigma_mps2 : float
        White-acceleration intensity of the constant-velocity model: power spectral density
        ``accel_sigma_mps2**2`` (m^2/s^3) on each axis (and the model of a track's start before an IMM).
    imm_accel_sigmas_mps2 : tuple of float
        Non-empty (2 to 4 levels): once a track is one Gaussian, an IMM over these intensities.
    reorder_window_s : float
        A report up to this much older than the newest applied one is applied in time order; older: late.
    imm_mean_sojourn_s : float
        Mean time in one IMM mode (the Markov switching matrix, :func:`core.tracking.imm.switching_matrix`).
    velocity_prior_sigma_mps : float
        Standard deviation of each velocity component at a track's start (zero mean).
    range_min_m, range_max_m : float
        The ranges along a first line of sight the emitter may be at.
    azimuth_only_elevation_sigma_rad : float
        A first bearing without elevation: the line of sight's elevation is taken as 0 with this sigma.
    confirm_updates : int
        Consecutive agreeing updates (NIS inside the 99 % point) needed to confirm.
    confirm_relative_sigma : float
        Largest position standard deviation, as a fraction of the distance to the nearest reporting station,
        at which a track may be confirmed.
    coast_after_s, end_after_s : float
        Without a report for longer than these, a track is ``coasting``, then ended.
    linearisation_passes : int
        Passes of the iterated posterior linearisation of each update with bearings (1: the plain unscented
        update; see :mod:`core.tracking.network_kernel`); a report of ranges and TOAs alone takes one.
    start_altitudes_m : tuple of 2 floats
        Heights (the common frame's up, m) a track started from ranges and TOAs alone may be at, when its first
        fix does not place it in height (:mod:`core.tracking.network_update`).
    start_altitude_step_m : float
        Their spacing, and the vertical standard deviation a first fix must reach to be used alone.
    vertical_accel_sigma_mps2 : float or None
        The white acceleration's intensity on the up axis (aircraft and ground vehicles hold their height far
        better than their course); None: ``accel_sigma_mps2`` (isotropic). An IMM scales each level's up axis
        by the same ratio.
    vertical_velocity_prior_sigma_mps : float or None
        The start's up-velocity standard deviation; None: ``velocity_prior_sigma_mps``.
    """

    accel_sigma_mps2: float = 1.0
    imm_accel_sigmas_mps2: tuple[float, ...] = ()
    reorder_window_s: float = 2.0
    imm_mean_sojourn_s: float = 60.0
    velocity_prior_sigma_mps: float = 100.0
    range_min_m: float = 1e3
    range_max_m: float = 200e3
    azimuth_only_elevation_sigma_rad: float = 0.25
    confirm_updates: int = 3
    confirm_relative_sigma: float = 0.05
    coast_after_s: float = 10.0
    end_after_s: float = 60.0
    linearisation_passes: int = 3
    start_altitudes_m: tuple[float, float] = (-500.0, 20_000.0)
    vertical_accel_sigma_mps2: float | None = None
    vertical_velocity_prior_sigma_mps: float | None = None
    start_altitude_step_m: float = 500.0

    def __post_init__(self):
        for name in ("accel_sigma_mps2", "velocity_prior_sigma_mps", "range_min_m", "range_max_m",
                     "azimuth_only_elevation_sigma_rad", "confirm_relative_sigma", "coast_after_s",
                     "end_after_s", "imm_mean_sojourn_s"):
            check_positive(name, getattr(self, name))
        check_real("reorder_window_s", self.reorder_window_s)
        if self.reorder_window_s < 0.0:
            raise InvalidInput("reorder_window_s must be >= 0", ("reorder_window_s",))
        levels = tuple(self.imm_accel_sigmas_mps2)
        object.__setattr__(self, "imm_accel_sigmas_mps2", tuple(float(v) for v in levels))
        if levels and not 2 <= len(levels) <= 4:
            raise InvalidInput("imm_accel_sigmas_mps2 must hold 2 to 4 levels", ("imm_accel_sigmas_mps2",))
        for i, value in enumerate(levels):
            check_positive("imm_accel_sigmas_mps2", value, ("imm_accel_sigmas_mps2", i))
        check_positive("start_altitude_step_m", self.start_altitude_step_m)
        for name in ("vertical_accel_sigma_mps2", "vertical_velocity_prior_sigma_mps"):
            if getattr(self, name) is not None:
                check_positive(name, getattr(self, name))
        low, high = (float(v) for v in self.start_altitudes_m)
        object.__setattr__(self, "start_altitudes_m", (low, high))
        if not (math.isfinite(low) and math.isfinite(high) and high >= low):
            raise InvalidInput("start_altitudes_m must be finite, low to high", ("start_altitudes_m",))
        if not self.range_max_m > self.range_min_m:
            raise InvalidInput("range_max_m must be above range_min_m", ("range_max_m",))
        for name in ("confirm_updates", "linearisation_passes"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= 20:
                raise InvalidInput(f"{name} must be an integer from 1 to 20", (name,))
        if not self.end_after_s > max(self.coast_after_s, self.reorder_window_s):
            raise InvalidInput("end_after_s must be above coast_after_s and reorder_window_s", ("end_after_s",))


@dataclass(frozen=True, eq=False)
class Report:
    """One report: measurements taken at one time, each by a station at its position then.

    Attributes
    ----------
    seq : int
        The client's sequence number (ties in ``time_s`` are applied in ``seq`` order).
    time_s : float
        Session clock (s).
    emitter_id : str
        The track it belongs to.
    station_ids : tuple of str, length M
        Which station took each measurement.
    stations_enu_m : ndarray, shape (M, 3)
        That station's position at ``time_s``, common frame.
    rotations : ndarray, shape (M, 3, 3)
        Station ENU <- common ENU.
    kinds : ndarray of int, shape (M,)
        :class:`core.measurements.Kind` codes.
    values : ndarray, shape (M,)
        Radians (angles), metres (range), seconds (TOA, as the client sent them).
    sigmas : ndarray, shape (M,)
        Radians, metres, seconds.
    """

    seq: int
    time_s: float
    emitter_id: str
    station_ids: tuple[str, ...]
    stations_enu_m: np.ndarray
    rotations: np.ndarray
    kinds: np.ndarray
    values: np.ndarray
    sigmas: np.ndarray

    def __post_init__(self):
        object.__setattr__(self, "stations_enu_m", frozen_array(self.stations_enu_m))
        object.__setattr__(self, "rotations", frozen_array(self.rotations))
        kinds = np.array(self.kinds, dtype=np.int64)
        kinds.flags.writeable = False
        object.__setattr__(self, "kinds", kinds)
        object.__setattr__(self, "values", frozen_array(self.values))
        object.__setattr__(self, "sigmas", frozen_array(self.sigmas))
        object.__setattr__(self, "station_ids", tuple(self.station_ids))

    @property
    def order_key(self) -> tuple[float, int]:
        """Where the report belongs in time: ``(time_s, seq)``."""
        return (self.time_s, self.seq)

    def to_dict(self) -> dict:
        """Plain JSON-able data; exact inverse of :meth:`from_dict`.

        Made once per report and shared by every later call (read it, never change it), as
        :meth:`Track.to_dict` is: a report is an immutable value, and a state's history carries it through
        every post of its reorder window.
        """
        made = self.__dict__.get("_as_dict")
        if made is None:
            made = {"seq": self.seq, "time_s": self.time_s, "emitter_id": self.emitter_id,
                    "station_ids": list(self.station_ids), "stations_enu_m": self.stations_enu_m.tolist(),
                    "rotations": self.rotations.tolist(), "kinds": self.kinds.tolist(),
                    "values": self.values.tolist(), "sigmas": self.sigmas.tolist()}
            object.__setattr__(self, "_as_dict", made)
        return made

    @classmethod
    def from_dict(cls, data: dict) -> "Report":
        m = len(data["kinds"])
        return cls(int(data["seq"]), float(data["time_s"]), str(data["emitter_id"]), tuple(data["station_ids"]),
                   np.array(data["stations_enu_m"], dtype=float).reshape(m, 3),
                   np.array(data["rotations"], dtype=float).reshape(m, 3, 3), data["kinds"], data["values"],
                   data["sigmas"])


@dataclass(frozen=True, eq=False)
class Track:
    """One emitter's track.

    Attributes
    ----------
    id : str
    status : str
        ``"tentative"``, ``"confirmed"`` or ``"coasting"`` (:mod:`core.tracking.network`).
    time_s : float
        Time of the estimate (its last report, or the time it was predicted to).
    mean_enu : ndarray, shape (6,)
        ``[east_m, north_m, up_m, east_mps, north_mps, up_mps]``, common frame: the moments of the filter.
    covariance_enu : ndarray, shape (6, 6)
    updates : int
        Reports applied to it.
    warnings : tuple of (str, str)
        ``(code, message)`` raised by its last report; codes in :data:`NETWORK_WARNING_CODES`.
    stage : str
        ``"mixture"``, ``"single"`` or ``"imm"``.
    weights : ndarray, shape (C,)
        Component weights (mixture) or mode probabilities (IMM); ``[1.0]`` for one Gaussian.
    means : ndarray, shape (C, 6)
    covariances : ndarray, shape (C, 6, 6)
    agreeing : int
        Consecutive updates whose NIS was inside its 99 % point.
    confirmed : bool
        Whether the track has met the confirmation rule.
    reference_range_m : float
        Distance from the estimate to the nearest station of its last report before confirmation (for the
        confirmation rule; kept from then on).
    """

    id: str
    status: str
    time_s: float
    mean_enu: np.ndarray
    covariance_enu: np.ndarray
    updates: int
    warnings: tuple
    stage: str
    weights: np.ndarray
    means: np.ndarray
    covariances: np.ndarray
    agreeing: int = 0
    confirmed: bool = False
    reference_range_m: float = math.inf

    @property
    def mode_probabilities(self) -> list[float] | None:
        """The IMM's mode probabilities (in ``imm_accel_sigmas_mps2`` order), None before it runs."""
        return self.weights.tolist() if self.stage == "imm" else None

    def to_dict(self) -> dict:
        """Plain JSON-able data; exact inverse of :meth:`from_dict`.

        Made once per track and shared by every later call (read it, never change it): a track is an
        immutable value (frozen arrays), and a state's history repeats most of its tracks from one post to
        the next, so a state's :meth:`~core.tracking.network.NetworkState.to_dict` converts only its new ones.
        A track of one component whose moments are that component, bit for bit (every ``single`` track), leaves
        ``mean_enu`` and ``covariance_enu`` out: they would repeat ``means[0]`` and ``covariances[0]``, and a
        session's record carries a track per report of its reorder window.
        """
        made = self.__dict__.get("_as_dict")
        if made is None:
            made = {"id": self.id, "status": self.status, "time_s": self.time_s, "updates": self.updates,
                    "warnings": [list(w) for w in self.warnings], "stage": self.stage,
                    "weights": self.weights.tolist(), "means": self.means.tolist(),
                    "covariances": self.covariances.tolist(), "agreeing": self.agreeing, "confirmed": self.confirmed,
                    "reference_range_m": None if math.isinf(self.reference_range_m) else self.reference_range_m}
            if not self._moments_are_component():
                made["mean_enu"] = self.mean_enu.tolist()
                made["covariance_enu"] = self.covariance_enu.tolist()
            object.__setattr__(self, "_as_dict", made)
        return made

    def _moments_are_component(self) -> bool:
        """Whether the track is one component and its moments are that component's, bit for bit."""
        return (self.means.shape[0] == 1 and self.mean_enu.tobytes() == self.means[0].tobytes()
                and self.covariance_enu.tobytes() == self.covariances[0].tobytes())

    @classmethod
    def from_dict(cls, data: dict) -> "Track":
        reference = data.get("reference_range_m")
        means, covariances = frozen_array(data["means"]), frozen_array(data["covariances"])
        if "mean_enu" in data:
            mean, covariance = frozen_array(data["mean_enu"]), frozen_array(data["covariance_enu"])
        else:
            mean, covariance = frozen_array(means[0]), frozen_array(covariances[0])
        return cls(str(data["id"]), str(data["status"]), float(data["time_s"]), mean, covariance,
                   int(data["updates"]), tuple(tuple(w) for w in data["warnings"]), str(data["stage"]),
                   frozen_array(data["weights"]), means, covariances, int(data["agreeing"]), bool(data["confirmed"]),
                   math.inf if reference is None else float(reference))


def check_real(name: str, value, loc=None) -> None:
    """Raise :class:`~core.errors.InvalidInput` (``loc`` or ``(name,)``) unless ``value`` is a finite real
    number (a bool is not one)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        raise InvalidInput(f"{name} must be a finite number, got {value!r}", loc or (name,))


def check_positive(name: str, value, loc=None) -> None:
    """Raise :class:`~core.errors.InvalidInput` unless ``value`` is a finite real number above 0."""
    check_real(name, value, loc)
    if not value > 0.0:
        raise InvalidInput(f"{name} must be > 0, got {value!r}", loc or (name,))


__all__ = ["STAGES", "STATUSES", "NetworkConfig", "Report", "Track", "check_positive", "check_real"]
