"""Configuration and input epoch of the moving-emitter session filter (paper 001).

Everything here is in SI units and radians, in the observer's local ENU frame
(east, north, up, origin at the observer). Degrees belong to the service.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import asdict, dataclass, fields

from core.errors import InvalidInput

SPEED_OF_LIGHT_MPS = 299_792_458.0

#: Filter models a session may run, with what each is.
MODELS = {
    "velocity_kinematic": "paper 001: velocity KF from TOA differences, range from the azimuth rate, UKF on position",
    "joint_ukf": "one UKF on position, velocity and period error fed with the raw measurements (paper 001's "
                 "baseline), started over a range interval; the sessions' default: at the posterior CRLB",
}

#: How ``velocity_kinematic`` treats the errors of successive range pseudo-measurements.
PSEUDO_RANGE_ERRORS = ("correlated", "independent")

#: Where ``joint_ukf`` gets its first range (see :class:`TrackerConfig`).
JOINT_INITIAL_RANGES = ("range_mixture", "kinematic", "prior")

#: Default range prior of ``joint_initial_range="prior"`` (m): the middle of a 0-300 km detection range.
DEFAULT_RANGE_PRIOR_M = 150e3
#: Its default standard deviation (m): a third of the mean (see :class:`TrackerConfig`).
DEFAULT_RANGE_PRIOR_SIGMA_M = 50e3

#: Default range interval of ``joint_initial_range="range_mixture"`` (m).
DEFAULT_RANGE_MIN_M = 10e3
DEFAULT_RANGE_MAX_M = 400e3

#: Default mean time the target stays in one process-noise mode of the IMM (s).
DEFAULT_IMM_MEAN_SOJOURN_S = 120.0
#: Number of process-noise levels an IMM may have.
IMM_LEVELS = (2, 4)

#: Default prior standard deviation of the period, as a fraction of ``period_s``, when the period is unknown.
DEFAULT_PERIOD_PRIOR_FRACTION = 1e-4


class TimeNotIncreasing(InvalidInput):
    """An epoch's ``time_s`` is not after the last applied epoch's."""

    code = "time_not_increasing"


@dataclass(frozen=True)
class TrackerConfig:
    """Settings of one session filter; validated on construction.

    Attributes
    ----------
    model : str
        One of :data:`MODELS`.
    period_s : float
        Pulse repetition period (s): the truth when ``period_known``, else the
        initial estimate.
    period_known : bool
    pulses_per_observation : int
        Nominal pulses ``N`` between reports (``T = N period_s``). Gaps are
        allowed: the pulse count between two TOAs is measured, not assumed.
    sigma_azimuth_rad, sigma_elevation_rad : float
        Standard deviation of the azimuth and elevation measurements (rad).
    sigma_azimuth_rate_rad_s : float
        Standard deviation of the azimuth-rate measurement (rad/s).
    sigma_toa_s : float
        Standard deviation of one time of arrival (s).
    accel_sigma_mps2 : float
        Intensity of the white acceleration noise of the constant-velocity
        model: a continuous white noise of power spectral density
        ``accel_sigma_mps2**2 * 1 s`` (m^2/s^3), so the velocity random walk
        grows by ``accel_sigma_mps2`` m/s per square-root second, whatever the
        report interval (a gap of k intervals equals k steps). The default,
        1 m/s^2 (the API's example), suits manoeuvring targets but leaves the
        tangential velocity, hence the range, poorly determined: at the
        paper's geometry 0.05-0.2 m/s^2 gives a few percent of range within
        a minute or two, 1 m/s^2 some 20 % after 200 s.
    velocity_prior_sigma_mps : float
        Prior standard deviation of each velocity component (m/s).
    period_prior_sigma_s : float or None
        Prior standard deviation of the period when it is unknown (s);
        None means ``DEFAULT_PERIOD_PRIOR_FRACTION * period_s``.
    min_azimuth_rate_snr : float
        ``|azimuth rate| / sigma_azimuth_rate_rad_s`` below which the range is
        declared unobservable (near-radial motion).
    max_initial_range_fraction : float
        The filter initialises once the range pseudo-measurement's standard
        deviation is below this fraction of the range.
    pseudo_range_errors : str
        ``velocity_kinematic`` only. ``"correlated"`` (default): step 3 knows
        that successive range pseudo-measurements share the slowly changing
        error of the step-1 velocity and carries that correlation (a consider
        update). ``"independent"``: each pseudo-measurement is treated as
        independent, as the paper writes it; the covariance is then
        optimistic (see the tests for the figures).
    joint_initial_range : str
        ``joint_ukf`` only: where its first range comes from.
        ``"range_mixture"`` (default): from the first epoch, a Gaussian sum of
        joint UKFs over ``range_min_m`` .. ``range_max_m`` (sub-intervals of
        ratio 2, see :mod:`core.tracking.range_mixture`), reweighted by each
        one's innovation density and pruned until one is left. On paper
        001's geometry, with truths drawn from the filter's own model, its
        position RMSE over the last 50 of 200 s is 1.02x / 1.01x (known /
        unknown period) the posterior CRLB (:mod:`core.tracking.bound`) at
        q = 0.05 m/s^2 and 1.02x / 1.04x at 0.5, 200 runs, with a consistent NEES
        (``tests/core/tracking/test_at_the_bound.py`` has the table).
        ``"kinematic"``: from the first range that ``velocity_kinematic``'s
        steps 1-2 give (the state is ``velocity`` until then); the joint UKF
        borrows the paper's method to start, then runs on the raw measurements
        alone. It ends 1.65x the bound at q = 0.5 with a NEES of 3.6-5.6 (a
        single UKF started from a range known to 30 % converges slowly and
        overconfidently when the target manoeuvres). It was the default before ``"range_mixture"``; a
        stored config without this field keeps it. ``"prior"``: the paper's
        baseline as it stands, the direct joint UKF started at the first epoch
        from the measured angles, a range of ``range_prior_m`` +-
        ``range_prior_sigma_m`` along them, zero velocity +-
        ``velocity_prior_sigma_mps`` and the period prior. How well depends on
        where the prior lies: close to the truth or beyond it, it ends ahead of
        ``velocity_kinematic``; short of it by two sigma, it converges three
        times slower and is overconfident for minutes
        (``tests/core/tracking/test_monte_carlo.py`` has the figures).
    range_min_m, range_max_m : float
        ``joint_initial_range="range_mixture"`` only: the interval of ranges the
        emitter may be at (m); 10-400 km by default (a passive sensor's detection
        range of the order of 300 km, with margin). Each factor 1.5 of the span
        costs one more filter for the first tens of epochs.
    range_prior_m, range_prior_sigma_m : float
        ``joint_initial_range="prior"`` only: mean and standard deviation of the
        initial range (m). The defaults, 150 km +- 50 km, stand for an emitter
        somewhere inside a passive sensor's detection range of the order of
        300 km (the middle of it, and a third of the mean as the spread: a
        Gaussian range prior in Cartesian coordinates should keep its mass,
        and the unscented transform's sigma points at ``sqrt(n)`` ~ 2.8
        standard deviations, in front of the observer). Halving or doubling
        the sigma changes the paper scenario's figures little; where the mean
        lies matters (see ``tests/core/tracking/test_monte_carlo.py``).

    Raises
    ------
    InvalidInput
        On an unknown model or a value outside its domain.
    """

    model: str
    period_s: float
    period_known: bool
    pulses_per_observation: int
    sigma_azimuth_rad: float
    sigma_elevation_rad: float
    sigma_azimuth_rate_rad_s: float
    sigma_toa_s: float
    accel_sigma_mps2: float = 1.0
    velocity_prior_sigma_mps: float = 500.0
    period_prior_sigma_s: float | None = None
    min_azimuth_rate_snr: float = 4.0
    max_initial_range_fraction: float = 0.3
    pseudo_range_errors: str = "correlated"
    joint_initial_range: str = "range_mixture"
    range_prior_m: float = DEFAULT_RANGE_PRIOR_M
    range_prior_sigma_m: float = DEFAULT_RANGE_PRIOR_SIGMA_M
    range_min_m: float = DEFAULT_RANGE_MIN_M
    range_max_m: float = DEFAULT_RANGE_MAX_M
    imm_accel_sigmas_mps2: tuple[float, ...] | None = None
    imm_mean_sojourn_s: float = DEFAULT_IMM_MEAN_SOJOURN_S

    def __post_init__(self):
        if not isinstance(self.model, str) or self.model not in MODELS:
            raise InvalidInput(f"unknown model {self.model!r}; known: {', '.join(sorted(MODELS))}", ("model",))
        if self.pseudo_range_errors not in PSEUDO_RANGE_ERRORS:
            raise InvalidInput(f"pseudo_range_errors must be one of {', '.join(PSEUDO_RANGE_ERRORS)}",
                               ("pseudo_range_errors",))
        if self.joint_initial_range not in JOINT_INITIAL_RANGES:
            raise InvalidInput(f"joint_initial_range must be one of {', '.join(JOINT_INITIAL_RANGES)}",
                               ("joint_initial_range",))
        if not isinstance(self.period_known, bool):
            raise InvalidInput("period_known must be a boolean", ("period_known",))
        n = self.pulses_per_observation
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise InvalidInput("pulses_per_observation must be an integer >= 1", ("pulses_per_observation",))
        positive = ("period_s", "sigma_azimuth_rad", "sigma_elevation_rad", "sigma_azimuth_rate_rad_s",
                    "sigma_toa_s", "velocity_prior_sigma_mps", "max_initial_range_fraction", "range_prior_m",
                    "range_prior_sigma_m", "range_min_m", "range_max_m")
        for name in positive:
            _check_real(name, getattr(self, name), minimum=0.0, strict=True)
        _check_real("accel_sigma_mps2", self.accel_sigma_mps2, minimum=0.0, strict=False)
        _check_real("min_azimuth_rate_snr", self.min_azimuth_rate_snr, minimum=0.0, strict=False)
        if self.period_prior_sigma_s is not None:
            _check_real("period_prior_sigma_s", self.period_prior_sigma_s, minimum=0.0, strict=True)
        for name in positive + ("accel_sigma_mps2", "min_azimuth_rate_snr"):
            object.__setattr__(self, name, float(getattr(self, name)))
        if self.period_prior_sigma_s is not None:
            object.__setattr__(self, "period_prior_sigma_s", float(self.period_prior_sigma_s))
        _check_real("imm_mean_sojourn_s", self.imm_mean_sojourn_s, minimum=0.0, strict=True)
        object.__setattr__(self, "imm_mean_sojourn_s", float(self.imm_mean_sojourn_s))
        if self.imm_accel_sigmas_mps2 is not None:
            levels = self.imm_accel_sigmas_mps2
            if (isinstance(levels, (str, bytes)) or not hasattr(levels, "__len__")
                    or not IMM_LEVELS[0] <= len(levels) <= IMM_LEVELS[1]):
                raise InvalidInput(f"imm_accel_sigmas_mps2 must list {IMM_LEVELS[0]} to {IMM_LEVELS[1]} levels",
                                   ("imm_accel_sigmas_mps2",))
            for level in levels:
                _check_real("imm_accel_sigmas_mps2", level, minimum=0.0, strict=False)
            levels = tuple(float(level) for level in levels)
            if any(b <= a for a, b in zip(levels, levels[1:])):
                raise InvalidInput("imm_accel_sigmas_mps2 must increase", ("imm_accel_sigmas_mps2",))
            if self.model != "joint_ukf":
                raise InvalidInput("imm_accel_sigmas_mps2 needs the joint_ukf model", ("imm_accel_sigmas_mps2",))
            object.__setattr__(self, "imm_accel_sigmas_mps2", levels)
        if not self.range_max_m > self.range_min_m:
            raise InvalidInput("range_max_m must be above range_min_m", ("range_max_m",))
        if self.max_initial_range_fraction >= 1.0:
            raise InvalidInput("max_initial_range_fraction must be below 1", ("max_initial_range_fraction",))
        for name in ("sigma_azimuth_rad", "sigma_elevation_rad"):
            if getattr(self, name) >= 0.5:
                raise InvalidInput(f"{name} must be below 0.5 rad", (name,))

    @property
    def period_prior_sigma(self) -> float:
        """Prior standard deviation of the period (s) actually used."""
        if self.period_prior_sigma_s is None:
            return DEFAULT_PERIOD_PRIOR_FRACTION * self.period_s
        return self.period_prior_sigma_s

    def to_dict(self) -> dict:
        """Plain JSON-able fields, for storing a session next to its state."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "TrackerConfig":
        """Inverse of :meth:`to_dict`; unknown keys raise :class:`InvalidInput`.

        A mapping without ``joint_initial_range`` was stored before that field
        existed, when ``joint_ukf`` always started from the kinematic range: it
        gets ``"kinematic"`` whatever the default is then, so a stored session
        goes on as it began.
        """
        if not isinstance(data, dict):
            raise InvalidInput("tracker config must be a mapping")
        known = {f.name for f in fields(cls)}
        extra = sorted(set(data) - known)
        if extra:
            raise InvalidInput(f"unknown tracker config fields: {', '.join(extra)}", (extra[0],))
        if "joint_initial_range" not in data:
            data = {**data, "joint_initial_range": "kinematic"}
        try:
            return cls(**data)
        except TypeError as error:
            raise InvalidInput(f"incomplete tracker config: {error}") from None


@dataclass(frozen=True)
class Epoch:
    """One report of the observer.

    Attributes
    ----------
    time_s : float
        Observer time of the report (s); must increase from epoch to epoch.
    azimuth_rad : float
        Compass azimuth of the emitter, clockwise from north (rad).
    elevation_rad : float
        Elevation above the observer's horizontal plane (rad), in (-pi/2, pi/2).
    azimuth_rate_rad_s : float
        Measured rate of change of the azimuth (rad/s).
    toa_s : float
        Time of arrival of the report's pulse (s) on a clock of any epoch;
        only differences are used.
    """

    time_s: float
    azimuth_rad: float
    elevation_rad: float
    azimuth_rate_rad_s: float
    toa_s: float


_EPOCH_FIELDS = ("time_s", "azimuth_rad", "elevation_rad", "azimuth_rate_rad_s", "toa_s")


def validate_epoch(epoch: Epoch) -> tuple[float, float, float, float, float]:
    """The epoch's values as floats, or :class:`InvalidInput` naming the bad field."""
    values = []
    for name in _EPOCH_FIELDS:
        value = getattr(epoch, name, None)
        if type(value) is not float:
            if isinstance(value, bool) or not isinstance(value, numbers.Real):
                raise InvalidInput(f"epoch {name} must be a finite number, got {value!r}", (name,))
            value = float(value)
        if not math.isfinite(value):
            raise InvalidInput(f"epoch {name} must be a finite number, got {value!r}", (name,))
        values.append(value)
    if not -0.5 * math.pi < values[2] < 0.5 * math.pi:
        raise InvalidInput("epoch elevation_rad must be inside (-pi/2, pi/2)", ("elevation_rad",))
    return tuple(values)


def _check_real(name: str, value, minimum: float, strict: bool) -> None:
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        raise InvalidInput(f"{name} must be a finite number, got {value!r}", (name,))
    if value < minimum or (strict and value == minimum):
        raise InvalidInput(f"{name} must be {'>' if strict else '>='} {minimum}, got {value!r}", (name,))
