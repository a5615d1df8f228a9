"""What an estimator hands the finisher, and the fixes that come back.

An estimator computes :class:`Estimates` for a whole :class:`~core.problem.batch.ProblemBatch`:
positions, and where it has them its own covariances, iteration counts and
method-specific facts. :func:`core.estimators.finish.finish` turns them into a
:class:`FixBatch`, which adds what every fix reports. A single :class:`Fix` is
row ``b`` of a batch, squeezed (:meth:`FixBatch.fix`).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from core.errors import LocalizationError
from core.problem.batch import ProblemBatch

#: Warning codes a fix may carry, with what each means.
WARNING_CODES = {
    "ill_conditioned": "the geometry barely determines the position in some direction",
    "inefficient_method": "this method's own covariance is far above the CRLB here: use ml or weighted_eove",
    "collinear_geometry": "lines of sight or stations are nearly collinear with the target",
    "behind_station": "the fix lies behind a station's measured line of sight",
    "not_converged": "the iteration stopped before converging; the last good iterate is returned",
    "outlier_suspected": "a measurement's studentized residual exceeds 4 and singles it out (named in the message)",
    "fault_detected_not_isolable": "the measurements hold a fault (a studentized residual above 4, or failing the "
                                   "exclusion test) that no single measurement can be blamed for: too few degrees "
                                   "of freedom, or several explain it alike; none is named or excluded",
    "sigma_mismatch": "chi-square says the stated sigmas are too small for the residuals",
    "sigma_estimated": "sigmas were estimated from the residuals and scale the covariance",
    "reference_point_moved": "the linearisation point was moved onto a station's line of sight",
    "azimuth_undefined": "the target is nearly at a station's zenith, where azimuth is undefined",
    "coarse_polar_fallback": "stations at one height: the coarse fix used per-station polar points",
    "start_fallback": "the closed-form start failed; a fallback start was used",
    "measurement_excluded": "outlier exclusion removed this measurement from the fit (named in the message)",
    "ambiguous_solution": "another point fits the measurements as well; options.initial_guess picked this one "
                          "(the other is named in the message; without a guess such a tie is a 422 "
                          "ambiguous_geometry, except under a robust loss)",
    "second_solution_plausible": "a second solution (named in the message, with its probability from the two "
                                 "fits' likelihoods) fits worse but is not ruled out at 0.1 %; the covariance is "
                                 "the two-solution mixture's second moment about this fix, widened where needed so "
                                 "that its 99 % region holds 99 % of the mixture (a second solution more likely "
                                 "than 1 % lies inside it)",
    "curved_uncertainty": "the measurement model is far from linear over the fix's uncertainty (a line of sight "
                          "nearly tangent to a TDOA hyperbola): the covariance is the spread of the fixes of the "
                          "measurements moved by their sigmas (unscented transform of the estimator), not the "
                          "inverse information, which understates the error there; widened across the curve "
                          "where needed so that its 99 % region holds the curved error (it then states more "
                          "than the error's second moment)",
    "measurements_unused": "the method does not use some kinds of the given measurements (named in the message)",
    "measurement_downweighted": "the robust loss left this measurement under a tenth of its weight (named in the "
                                "message)",
    "toa_resolution": "TOAs sent as seconds since a distant epoch: float64 carries them more coarsely than their "
                      "sigma (send them relative to a recent reference)",
}

#: Covariance sources: the inverse information at the estimate (ML-type methods), first-order
#: propagation through a closed form, the CRLB at the estimate where the method has none of its own, or
#: (ML with a robust loss) the sandwich of the loss's final weights.
COVARIANCE_SOURCES = ("information", "propagated", "crlb", "robust")
#: Each source with ``_scaled``: multiplied by the fit's ``sigma_scale^2`` (``absolute_sigma`` false).
SCALED_COVARIANCE_SOURCES = tuple(f"{source}_scaled" for source in COVARIANCE_SOURCES)


@dataclass(frozen=True)
class FixWarning:
    code: str
    message: str


@dataclass(frozen=True)
class Estimates:
    """An estimator's output for a batch of B problems (leading axis B).

    Attributes
    ----------
    position_enu_m : ndarray, shape (B, 3)
        Rows of problems in ``errors`` are ignored.
    covariance_source : str
        One of :data:`COVARIANCE_SOURCES`. With ``"information"`` the
        covariance is the inverse information the finisher computes, and an
        unobservable problem is an error; with ``"crlb"`` it is the bound.
    covariance_enu_m2 : ndarray, shape (B, 3, 3), optional
        The estimator's own covariance (required with ``"propagated"``). With ``"information"``, rows that
        replace the inverse information (ML's two-solution mixture); NaN rows keep it.
    errors : dict of int to LocalizationError
        Problems the method could not solve.
    converged : ndarray of bool, shape (B,), optional
        Default all True.
    iterations : ndarray of int, shape (B,), optional
        Default all 0.
    warnings : list of tuple of FixWarning, length B, optional
        The method's own warnings, reported before the finisher's.
    coarse_position_enu_m : ndarray, shape (B, 3), optional
        NaN rows where a method with a coarse stage had none.
    estimated_bearing_errors_rad : list of ndarray or None, length B, optional
    sigmas : ndarray, shape (B, M), optional
        Sigmas the method estimated (problem units); they replace the given
        ones in the residual verdicts and the bound.
    bias_m : ndarray, shape (B,), optional
        TOA emission offset (metres); default the best one for each position.
    details : list of dict, length B, optional
    loss : tuple of (str, float), optional
        The robust loss (name, scale in sigmas) the estimate minimised; None for least squares. The finisher
        then gives the covariance as a sandwich of the loss's final weights (source ``"robust"``).
    """

    position_enu_m: np.ndarray
    covariance_source: str
    covariance_enu_m2: np.ndarray | None = None
    errors: dict[int, LocalizationError] = field(default_factory=dict)
    converged: np.ndarray | None = None
    iterations: np.ndarray | None = None
    warnings: list | None = None
    coarse_position_enu_m: np.ndarray | None = None
    estimated_bearing_errors_rad: list | None = None
    sigmas: np.ndarray | None = None
    bias_m: np.ndarray | None = None
    details: list | None = None
    loss: tuple | None = None


@dataclass(frozen=True)
class Fix:
    """The result of one estimator on one problem (common ENU frame).

    Attributes
    ----------
    method : str
    position_enu_m : ndarray, shape (3,)
    covariance_enu_m2 : ndarray, shape (3, 3)
    covariance_source : str
        See :data:`COVARIANCE_SOURCES`.
    crlb_enu_m2 : ndarray, shape (3, 3)
    residuals : ndarray, shape (M,)
        Measured minus predicted, in the problem's units (rad, m, s).
    normalized_residuals : ndarray, shape (M,)
    chi2 : float
    dof : int
    p_value : float or None
        None when ``dof`` is 0.
    sigma_scale : float or None
        ``sqrt(chi2 / dof)``; with a robust loss ``sqrt(sum rho / dof)`` (scipy's ``curve_fit`` under a loss).
    converged : bool
    iterations : int
    warnings : tuple of FixWarning
    coarse_position_enu_m : ndarray, shape (3,), or None
    estimated_bearing_errors_rad : ndarray, shape (K,), or None
    details : dict
        Method-specific facts (e.g. which start or coarse stage ran).
    used : ndarray of bool, shape (M,)
        The measurements that entered the fit (the others are reported, not judged).
    excluded : ndarray of bool, shape (M,)
        Those outlier exclusion removed.
    gdop : float
        Dimensionless, of the CRLB (:func:`core.crlb.gdop`); NaN where undefined.
    """

    method: str
    position_enu_m: np.ndarray
    covariance_enu_m2: np.ndarray
    covariance_source: str
    crlb_enu_m2: np.ndarray
    residuals: np.ndarray
    normalized_residuals: np.ndarray
    chi2: float
    dof: int
    p_value: float | None
    sigma_scale: float | None
    converged: bool
    iterations: int
    warnings: tuple[FixWarning, ...] = ()
    coarse_position_enu_m: np.ndarray | None = None
    estimated_bearing_errors_rad: np.ndarray | None = None
    details: dict = field(default_factory=dict)
    used: np.ndarray | None = None
    excluded: np.ndarray | None = None
    gdop: float = float("nan")


@dataclass(frozen=True)
class FixBatch:
    """Fixes of a batch of problems as arrays (leading axis B).

    Rows of problems in ``errors`` hold NaN or zeros. :meth:`fix` gives one
    :class:`Fix` (or its error); the service builds responses straight from
    the arrays.

    Attributes
    ----------
    method : str
    problems : ProblemBatch
    errors : dict of int to LocalizationError
    position_enu_m : ndarray, shape (B, 3)
    covariance_enu_m2, crlb_enu_m2 : ndarray, shape (B, 3, 3)
    covariance_source : str
    residuals, normalized_residuals : ndarray, shape (B, M)
        Problem units; zero on padding.
    studentized_residuals : ndarray, shape (B, M)
        The normalized residuals of the ML fit of the used measurements over their own standard deviation
        (leverage-corrected); zero where unused.
    chi2 : ndarray, shape (B,)
        Chi-square of the residuals of that ML fit (whatever the method: what ``dof`` counts).
    dof : ndarray of int, shape (B,)
    p_value, sigma_scale : ndarray, shape (B,)
        NaN where ``dof`` is 0 (None in a :class:`Fix`).
    converged : ndarray of bool, shape (B,)
    iterations : ndarray of int, shape (B,)
    warnings : list of tuple of FixWarning, length B
    coarse_position_enu_m : ndarray, shape (B, 3)
        NaN rows where the method has no coarse stage.
    estimated_bearing_errors_rad : list of ndarray or None, length B
    details : list of dict, length B
    used, excluded : ndarray of bool, shape (B, M)
        As in :class:`Fix`.
    gdop : ndarray, shape (B,)
        Dimensionless, of the CRLB at the fix (:func:`core.crlb.gdop`); NaN where undefined.
    isolated : ndarray of bool, shape (B,)
        Whether the largest studentized residual singles its request measurement out (two dof or more, and
        ahead of every other by :data:`~core.estimators.finish.ISOLATION_SIGMAS`): a fault there can be named.
    """

    method: str
    problems: ProblemBatch
    errors: dict[int, LocalizationError]
    position_enu_m: np.ndarray
    covariance_enu_m2: np.ndarray
    covariance_source: str
    crlb_enu_m2: np.ndarray
    residuals: np.ndarray
    normalized_residuals: np.ndarray
    studentized_residuals: np.ndarray
    chi2: np.ndarray
    dof: np.ndarray
    p_value: np.ndarray
    sigma_scale: np.ndarray
    converged: np.ndarray
    iterations: np.ndarray
    warnings: list
    coarse_position_enu_m: np.ndarray
    estimated_bearing_errors_rad: list
    details: list
    used: np.ndarray
    excluded: np.ndarray
    gdop: np.ndarray
    isolated: np.ndarray

    @property
    def size(self) -> int:
        return self.problems.size

    @property
    def ok(self) -> np.ndarray:
        """``(B,)``: True where the problem has a fix."""
        ok = np.ones(self.size, dtype=bool)
        if self.errors:
            ok[list(self.errors)] = False
        return ok

    def fix(self, b: int) -> Fix | LocalizationError:
        """Problem ``b``'s fix, or the error that stopped it."""
        if b in self.errors:
            return self.errors[b]
        m = int(self.problems.n_measurements[b])
        p_value, sigma_scale = float(self.p_value[b]), float(self.sigma_scale[b])
        coarse = self.coarse_position_enu_m[b]
        return Fix(
            method=self.method,
            position_enu_m=self.position_enu_m[b].copy(),
            covariance_enu_m2=self.covariance_enu_m2[b].copy(),
            covariance_source=self.covariance_source,
            crlb_enu_m2=self.crlb_enu_m2[b].copy(),
            residuals=self.residuals[b, :m].copy(),
            normalized_residuals=self.normalized_residuals[b, :m].copy(),
            chi2=float(self.chi2[b]),
            dof=int(self.dof[b]),
            p_value=None if np.isnan(p_value) else p_value,
            sigma_scale=None if np.isnan(sigma_scale) else sigma_scale,
            converged=bool(self.converged[b]),
            iterations=int(self.iterations[b]),
            warnings=self.warnings[b],
            coarse_position_enu_m=None if np.isnan(coarse[0]) else coarse.copy(),
            estimated_bearing_errors_rad=self.estimated_bearing_errors_rad[b],
            details=dict(self.details[b]),
            used=self.used[b, :m].copy(),
            excluded=self.excluded[b, :m].copy(),
            gdop=float(self.gdop[b]),
        )

    def fixes(self) -> list[Fix | LocalizationError]:
        """Every problem's :meth:`fix`, in order."""
        return [self.fix(b) for b in range(self.size)]

    @classmethod
    def concatenate(cls, problems: ProblemBatch, parts: list["FixBatch"]) -> "FixBatch":
        """One batch from consecutive parts of ``problems`` solved by the same method."""
        if len(parts) == 1:
            return parts[0]
        width = problems.kinds.shape[1]

        def joined(name):
            arrays = [getattr(p, name) for p in parts]
            if name in _MEASUREMENT_FIELDS:
                arrays = [np.pad(a, ((0, 0), (0, width - a.shape[1]))) for a in arrays]
            return np.concatenate(arrays)

        errors, offset = {}, 0
        for part in parts:
            errors.update({offset + b: e for b, e in part.errors.items()})
            offset += part.size
        arrays = {name: joined(name) for name in _ARRAY_FIELDS}
        lists = {name: [x for p in parts for x in getattr(p, name)] for name in _LIST_FIELDS}
        return cls(method=parts[0].method, problems=problems, errors=errors,
                   covariance_source=parts[0].covariance_source, **arrays, **lists)

    def take(self, rows) -> "FixBatch":
        """The fixes of ``rows`` as a batch of their own."""
        rows = np.asarray(rows, dtype=np.intp)
        if rows.size == self.size and np.all(rows == np.arange(self.size)):
            return self
        where = {int(b): j for j, b in enumerate(rows)}
        problems = self.problems.take(rows)
        width = problems.kinds.shape[1]
        return replace(
            self, problems=problems,
            errors={where[b]: e for b, e in self.errors.items() if b in where},
            **{name: getattr(self, name)[rows, :width] if name in _MEASUREMENT_FIELDS else getattr(self, name)[rows]
               for name in _ARRAY_FIELDS},
            **{name: [getattr(self, name)[b] for b in rows.tolist()] for name in _LIST_FIELDS})

    def replace_rows(self, rows, other: "FixBatch") -> "FixBatch":
        """A copy with rows ``rows`` taken from ``other`` (the fixes of those rows' problems, in order)."""
        rows = np.asarray(rows, dtype=np.intp)
        arrays = {}
        for name in _ARRAY_FIELDS:
            mine, theirs = getattr(self, name).copy(), getattr(other, name)
            if name in _MEASUREMENT_FIELDS:
                mine[rows] = 0
                mine[rows, :theirs.shape[1]] = theirs
            else:
                mine[rows] = theirs
            arrays[name] = mine
        lists = {name: list(getattr(self, name)) for name in _LIST_FIELDS}
        for j, b in enumerate(rows.tolist()):
            for name in _LIST_FIELDS:
                lists[name][b] = getattr(other, name)[j]
        errors = {b: e for b, e in self.errors.items() if b not in set(rows.tolist())}
        errors.update({int(rows[j]): e for j, e in other.errors.items()})
        return replace(self, errors=errors, **arrays, **lists)

    @classmethod
    def of(cls, **fields) -> "FixBatch":
        """A FixBatch of ``fields`` (every field, by name), without ``__init__``'s one frozen assignment per
        field: there is no derived state to compute, and the finisher builds one per batch it finishes."""
        if fields.keys() != _FIELD_NAMES:
            raise TypeError(f"FixBatch fields {sorted(fields.keys() ^ _FIELD_NAMES)} missing or unknown")
        out = object.__new__(cls)
        out.__dict__.update(fields)
        return out

    def scaled_by_fit(self) -> "FixBatch":
        """The covariances scaled by ``sigma_scale^2`` where the fit has degrees of freedom
        (scipy's ``curve_fit(absolute_sigma=False)``); ``covariance_source`` gains ``_scaled``."""
        scale = np.where((self.dof > 0) & ~np.isnan(self.sigma_scale), self.sigma_scale ** 2, 1.0)
        scaled = object.__new__(FixBatch)  # replace() without __init__'s 25 frozen assignments: no derived state
        scaled.__dict__.update(self.__dict__, covariance_enu_m2=self.covariance_enu_m2 * scale[:, None, None],
                               covariance_source=f"{self.covariance_source}_scaled")
        return scaled


_MEASUREMENT_FIELDS = ("residuals", "normalized_residuals", "studentized_residuals", "used", "excluded")
_ARRAY_FIELDS = ("position_enu_m", "covariance_enu_m2", "crlb_enu_m2", "chi2", "dof", "p_value", "sigma_scale",
                 "converged", "iterations", "coarse_position_enu_m", "gdop", "isolated", *_MEASUREMENT_FIELDS)
_LIST_FIELDS = ("warnings", "estimated_bearing_errors_rad", "details")
_FIELD_NAMES = frozenset(FixBatch.__dataclass_fields__)
