"""The session filter's state: an immutable value that round-trips through JSON exactly.

One state vector and one covariance carry everything. Their layout depends on
the model and on whether the position filter has started (``stage``):

============  ====================  ===================================================
model         stage                 state vector
============  ====================  ===================================================
any           ``"velocity"``        ``[vx, vy, vz, (period_error_m), toa_noise_m]`` (K)
velocity_     ``"tracking"``        ``[x, y, z, vx, vy, vz]`` (step 3) followed by the
kinematic                           K step-1 components above
joint_ukf     ``"tracking"``        ``[x, y, z, vx, vy, vz, (period_error_m), toa_noise_m]``
joint_ukf     ``"mixture"``         as ``"tracking"``: the moments of ``components``
joint_ukf     ``"imm"``             as ``"tracking"``: the moments of ``components``
============  ====================  ===================================================

In the ``"mixture"`` stage (``joint_ukf`` started over a range interval, see
:mod:`core.tracking.range_mixture`) ``components`` holds the Gaussian sum,
each component a joint state as above whose ``period_error_m`` stays relative
to ``pulse_period_s`` (it is folded in when the sum collapses to one). In the
``"imm"`` stage (``TrackerConfig.imm_accel_sigmas_mps2``) ``components`` holds
one joint state per process-noise mode, its weight the mode probability.

``period_error_m`` is ``c`` times the error of ``pulse_period_s`` (present
only when the period is unknown; it is folded into ``pulse_period_s`` after
every update, so its mean is zero between epochs). ``toa_noise_m`` is ``c``
times the noise of the reference TOA: successive TOA differences share one
TOA, and carrying its noise keeps that correlation exact.

For ``velocity_kinematic`` the covariance is that of the errors of both
filters: the off-diagonal block is the correlation that step 3's pseudo-ranges
inherit from the step-1 velocity (zero with ``pseudo_range_errors="independent"``).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import numpy as np

from core.errors import InvalidInput
from core.linalg import symmetrized
from core.tracking.config import MODELS

#: Version of the :meth:`TrackState.to_dict` layout.
STATE_FORMAT = 1

STAGES = ("velocity", "mixture", "tracking", "imm")

#: Warning codes a state may carry, with what each means.
WARNING_CODES = {
    "range_unobservable": "the azimuth rate is too small for its noise (near-radial motion), or the "
                          "range pseudo-measurement has the wrong sign or is too uncertain: velocity_kinematic "
                          "feeds no range this epoch (the position is predicted only); joint_ukf keeps "
                          "updating with the raw measurements",
    "covariance_repaired": "a covariance lost positive definiteness numerically; its eigenvalues were floored",
    "pulse_count_ambiguous": "the TOA difference is not close to a whole number of pulse periods; "
                             "the TOA was not used and becomes the new reference",
    "pulse_count_mismatch": "the pulse count from the TOA difference disagrees with the time_s interval",
    "numerical_failure": "an update produced non-finite numbers and was skipped",
    "innovation_outlier": "the epoch's measurements disagree with the prediction beyond the chi-square "
                          "99.9 % point: a manoeuvre (the model is constant velocity) or a bad measurement; "
                          "the update is still applied",
    "toa_resolution": "toa_s is sent as seconds since a distant epoch: float64 carries it more coarsely than "
                      "sigma_toa_s (send it relative to a recent reference)",
}


@dataclass(frozen=True, eq=False)
class TrackState:
    """Everything a session filter carries from one epoch to the next.

    Frames and units: the observer's ENU (m, m/s); times in s. Arrays are
    read-only float64. Equality compares :meth:`to_dict` (exact floats).

    Attributes
    ----------
    model : str
        The model that produced the state (see :data:`core.tracking.config.MODELS`).
    stage : str
        ``"velocity"`` (no position yet) or ``"tracking"``; see the module docstring.
    updates : int
        Number of epochs applied.
    time_s : float or None
        ``time_s`` of the last applied epoch.
    toa_s : float or None
        TOA of the reference pulse the next TOA is differenced against.
    pulse_period_s : float
        Current estimate of the pulse period (s).
    mean : ndarray, shape (n,)
        State vector (layout in the module docstring).
    covariance : ndarray, shape (n, n)
    last_range_measurement_m : float or None
        The last range pseudo-measurement (``velocity_kinematic``), for diagnostics.
    warnings : tuple of (str, str)
        ``(code, message)`` raised by the last step (or batch); codes in :data:`WARNING_CODES`.
    components : Components or None
        The Gaussian sum of the ``"mixture"`` stage, the modes of the ``"imm"`` stage; None otherwise.
    """

    model: str
    stage: str
    updates: int
    time_s: float | None
    toa_s: float | None
    pulse_period_s: float
    mean: np.ndarray
    covariance: np.ndarray
    last_range_measurement_m: float | None = None
    warnings: tuple[tuple[str, str], ...] = ()
    components: "Components | None" = None

    @property
    def initialized(self) -> bool:
        """True once the filter has a position."""
        return self.stage != "velocity"

    @property
    def position_enu_m(self) -> np.ndarray | None:
        """Emitter position ``(3,)`` in the observer's ENU (m), None before initialisation."""
        return self.mean[:3].copy() if self.initialized else None

    @property
    def velocity_enu_mps(self) -> np.ndarray | None:
        """Emitter velocity ``(3,)`` in the observer's ENU (m/s), None before initialisation."""
        return self.mean[3:6].copy() if self.initialized else None

    @property
    def covariance_enu(self) -> np.ndarray | None:
        """Covariance ``(6, 6)`` of ``[position (m), velocity (m/s)]`` in ENU, None before initialisation."""
        return self.covariance[:6, :6].copy() if self.initialized else None

    @property
    def range_m(self) -> float | None:
        """Estimated range from the observer (m), None before initialisation."""
        if not self.initialized:
            return None
        x, y, z = self.mean[:3].tolist()
        return math.sqrt(x * x + y * y + z * z)

    @property
    def range_sigma_m(self) -> float | None:
        """Standard deviation of :attr:`range_m` (m), to first order."""
        if not self.initialized:
            return None
        p = self.mean[:3]
        u = p / np.linalg.norm(p)
        return float(np.sqrt(max(u @ self.covariance[:3, :3] @ u, 0.0)))

    @property
    def mode_probabilities(self) -> list[float] | None:
        """Probability of each process-noise level in the ``"imm"`` stage, else None."""
        return self.components.weights.tolist() if self.stage == "imm" else None

    @property
    def kinematic_velocity_enu_mps(self) -> np.ndarray | None:
        """The step-1 velocity estimate ``(3,)`` (m/s), when that filter runs."""
        if self.stage == "velocity":
            return self.mean[:3].copy()
        if self.model == "velocity_kinematic":
            return self.mean[6:9].copy()
        return None

    def to_dict(self) -> dict:
        """Plain JSON-able data (str, int, float, None, lists); exact inverse of :meth:`from_dict`.

        ``components`` appears only in the ``"mixture"`` and ``"imm"`` stages (a state stored before it existed has none)."""
        data = {
            "format": STATE_FORMAT,
            "model": self.model,
            "stage": self.stage,
            "updates": self.updates,
            "time_s": self.time_s,
            "toa_s": self.toa_s,
            "pulse_period_s": self.pulse_period_s,
            "mean": self.mean.tolist(),
            "covariance": self.covariance.tolist(),
            "last_range_measurement_m": self.last_range_measurement_m,
            "warnings": [[code, message] for code, message in self.warnings],
        }
        if self.components is not None:
            data["components"] = {"weights": self.components.weights.tolist(),
                                  "means": self.components.means.tolist(),
                                  "covariances": self.components.covariances.tolist()}
        return data

    @classmethod
    def from_dict(cls, data: dict) -> "TrackState":
        """Rebuild a state from :meth:`to_dict` output (after a JSON round trip).

        Raises
        ------
        InvalidInput
            When the data is not a state of a known format, model and stage.
        """
        if not isinstance(data, dict) or data.get("format") != STATE_FORMAT:
            raise InvalidInput(f"tracker state must be a mapping with format {STATE_FORMAT}")
        model = data.get("model")
        if model not in MODELS:
            raise InvalidInput(f"tracker state has unknown model {model!r}", ("model",))
        stage = data.get("stage")
        if stage not in STAGES:
            raise InvalidInput(f"tracker state has unknown stage {stage!r}", ("stage",))
        updates = data.get("updates")
        if isinstance(updates, bool) or not isinstance(updates, int) or updates < 0:
            raise InvalidInput("tracker state updates must be a non-negative integer", ("updates",))
        mean = _finite_array(data.get("mean"), "mean")
        covariance = _finite_array(data.get("covariance"), "covariance")
        if mean.ndim != 1 or covariance.shape != (mean.size, mean.size):
            raise InvalidInput("tracker state covariance must be n x n for a mean of n", ("covariance",))
        pulse_period_s = _real(data, "pulse_period_s")
        if pulse_period_s is None or pulse_period_s <= 0.0:
            raise InvalidInput("tracker state pulse_period_s must be positive", ("pulse_period_s",))
        warnings = data.get("warnings", [])
        if not isinstance(warnings, list) or not all(
                isinstance(w, (list, tuple)) and len(w) == 2 and all(isinstance(s, str) for s in w) for w in warnings):
            raise InvalidInput("tracker state warnings must be a list of [code, message]", ("warnings",))
        components = _components(data.get("components"), mean.size)
        if (stage in ("mixture", "imm")) != (components is not None):
            raise InvalidInput("tracker state components must be given in the mixture and imm stages only",
                               ("components",))
        return cls(model, stage, updates, _real(data, "time_s"), _real(data, "toa_s"), pulse_period_s, mean,
                   covariance, _real(data, "last_range_measurement_m"),
                   tuple((code, message) for code, message in warnings), components)

    def __eq__(self, other):
        if not isinstance(other, TrackState):
            return NotImplemented
        return self.to_dict() == other.to_dict()

    __hash__ = None


@dataclass(frozen=True, eq=False)
class Components:
    """A Gaussian sum of joint states.

    Attributes
    ----------
    weights : ndarray, shape (M,)
        Positive, summing to one.
    means : ndarray, shape (M, F)
    covariances : ndarray, shape (M, F, F)
    """

    weights: np.ndarray
    means: np.ndarray
    covariances: np.ndarray


def _components(value, size: int) -> Components | None:
    if value is None:
        return None
    if not isinstance(value, dict) or set(value) != {"weights", "means", "covariances"}:
        raise InvalidInput("tracker state components must hold weights, means and covariances", ("components",))
    weights, means, covariances = (_finite_array(value[key], "components") for key in
                                   ("weights", "means", "covariances"))
    m = weights.shape[0]
    if (weights.ndim != 1 or means.shape != (m, size) or covariances.shape != (m, size, size)
            or not np.all(weights > 0.0)):
        raise InvalidInput("tracker state components do not match the state", ("components",))
    return Components(weights, means, covariances)


def frozen_array(values) -> np.ndarray:
    """A C-contiguous read-only float64 copy (one memory layout, so replays are bit-identical)."""
    array = np.array(values, dtype=float, order="C")
    array.flags.writeable = False
    return array


def freeze(array: np.ndarray) -> np.ndarray:
    """Make a freshly computed array read-only, copying only when it is not a C-contiguous owner."""
    if not (array.flags.c_contiguous and array.flags.owndata):
        array = np.array(array, order="C")
    array.flags.writeable = False
    return array


def symmetric(cov: np.ndarray) -> np.ndarray:
    """:func:`core.linalg.symmetrized` as a new read-only array (the filters' updates are symmetric
    only to rounding; this is done once per step)."""
    out = symmetrized(cov)
    out.flags.writeable = False
    return out


def _real(data: dict, key: str) -> float | None:
    value = data.get(key)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        raise InvalidInput(f"tracker state {key} must be a finite number or null", (key,))
    return float(value)


def _finite_array(value, key: str) -> np.ndarray:
    if value is None:
        raise InvalidInput(f"tracker state {key} is missing", (key,))
    try:
        array = frozen_array(value)
    except (TypeError, ValueError):
        raise InvalidInput(f"tracker state {key} must hold numbers", (key,)) from None
    if array.size == 0 or not np.all(np.isfinite(array)):
        raise InvalidInput(f"tracker state {key} must be non-empty and finite", (key,))
    return array
