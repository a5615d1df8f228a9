"""The one interface every estimator implements, the fix it returns, and the registry.

An estimator is a function ``solve(problem, options) -> Fix`` registered under
its API name. It computes a position (and, for closed forms, a covariance by
first-order propagation, or the CRLB where that is what the method is);
:func:`finish_fix` then adds what every fix reports: residuals, chi-square,
the CRLB at the estimate and the geometry warnings.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy.stats import chi2 as chi2_distribution

from core.angles import line_of_sight_enu
from core.crlb import Information, information_at, local_parameterisation, normal_matrix
from core.errors import InvalidInput, LocalizationError
from core.measurements import Kind, predict, residuals
from core.problem import Problem

#: Studentized residual above which a measurement is flagged as a suspected outlier.
OUTLIER_SIGMAS = 4.0
#: Chi-square p-value below which the stated sigmas are reported as too small.
SIGMA_MISMATCH_P = 1e-3
#: Lines of sight closer than this to parallel (rad) make a fix collinear.
COLLINEAR_SPREAD_RAD = np.deg2rad(2.0)
#: Ratio of a closed form's covariance trace to the CRLB's above which the method is flagged as inefficient.
INEFFICIENCY_RATIO = 10.0
#: Minimum unit-diagonal information eigenvalue below which a fix is ill-conditioned.
ILL_CONDITIONED_EIGENVALUE = 1e-6

#: Warning codes a fix may carry, with what each means.
WARNING_CODES = {
    "ill_conditioned": "the geometry barely determines the position in some direction",
    "inefficient_method": "this method's own covariance is far above the CRLB here: use ml or weighted_eove",
    "collinear_geometry": "lines of sight or stations are nearly collinear with the target",
    "behind_station": "the fix lies behind a station's measured line of sight",
    "not_converged": "the iteration stopped before converging; the last good iterate is returned",
    "outlier_suspected": "a measurement's studentized residual exceeds 4 (named in the message)",
    "sigma_mismatch": "chi-square says the stated sigmas are too small for the residuals",
    "sigma_estimated": "sigmas were estimated from the residuals and scale the covariance",
    "reference_point_moved": "the linearisation point was moved onto a station's line of sight",
    "azimuth_undefined": "the target is nearly at a station's zenith, where azimuth is undefined",
    "coarse_polar_fallback": "stations at one height: the coarse fix used per-station polar points",
    "start_fallback": "the closed-form start failed; a fallback start was used",
}


@dataclass(frozen=True)
class FixWarning:
    code: str
    message: str


@dataclass(frozen=True)
class SolveOptions:
    """Options shared by the estimators.

    Attributes
    ----------
    max_iterations : int
    tolerance_m : float
        Iterations stop when the position step is below this.
    variant : str or None
        Method-specific variant (e.g. ``"projected"`` or ``"newton"`` for CTLS).
    """

    max_iterations: int = 50
    tolerance_m: float = 1e-3
    variant: str | None = None


@dataclass(frozen=True)
class Fix:
    """The result of one estimator on one problem (common ENU frame).

    Attributes
    ----------
    method : str
    position_enu_m : ndarray, shape (3,)
    covariance_enu_m2 : ndarray, shape (3, 3)
    covariance_source : str
        ``"information"`` (inverse Fisher information at the ML fix),
        ``"propagated"`` (first-order propagation through a closed form) or
        ``"crlb"`` (the bound at the estimate, where no better is available).
    crlb_enu_m2 : ndarray, shape (3, 3)
    residuals : ndarray, shape (M,)
        Measured minus predicted, in the problem's units (rad, m, s).
    normalized_residuals : ndarray, shape (M,)
    chi2 : float
    dof : int
    p_value : float or None
        None when ``dof`` is 0.
    sigma_scale : float or None
        ``sqrt(chi2 / dof)``.
    converged : bool
    iterations : int
    warnings : tuple of FixWarning
    coarse_position_enu_m : ndarray, shape (3,), or None
    estimated_bearing_errors_rad : ndarray, shape (K,), or None
    details : dict
        Method-specific facts (e.g. which start or coarse stage ran).
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


def n_parameters(problem: Problem) -> int:
    return (2 if problem.altitude_m is not None else 3) + int(problem.has_toa)


def best_bias_m(problem: Problem, position_enu_m) -> float:
    """Weighted-mean TOA emission offset (metres) given the position; 0 without TOA."""
    is_toa = problem.kinds == Kind.TOA
    if not np.any(is_toa):
        return 0.0
    s = problem.station_index[is_toa]
    ranges = np.linalg.norm(np.asarray(position_enu_m) - problem.stations_enu_m[s], axis=-1)
    w = 1.0 / problem.model_sigmas()[is_toa] ** 2
    return float(np.sum(w * (problem.model_values()[is_toa] - ranges)) / np.sum(w))


def geometry_warnings(problem: Problem, position_enu_m) -> list[FixWarning]:
    """Warnings that depend only on where the fix is relative to the stations."""
    found: list[FixWarning] = []
    los = problem.lines_of_sight()
    if los.count:
        to_target = np.asarray(position_enu_m) - los.origins_enu_m
        distance = np.linalg.norm(to_target, axis=-1)
        local = np.einsum("kij,kj->ki", los.rotations, to_target)
        measured = line_of_sight_enu(los.azimuth_rad, np.where(los.has_elevation, los.elevation_rad, 0.0))
        seen_in_plane = np.where(los.has_elevation[:, None], local, local * [1.0, 1.0, 0.0])
        behind = np.flatnonzero(np.einsum("ki,ki->k", measured, seen_in_plane) < 0)
        if behind.size:
            ids = sorted({problem.station_ids[i] for i in los.station_index[behind]})
            found.append(FixWarning("behind_station", f"the fix is behind the line of sight of {', '.join(ids)}"))
        seen = to_target / np.maximum(distance, 1e-9)[:, None]
        if los.count >= 2:
            cosines = np.clip(np.abs(seen @ seen.T), 0.0, 1.0)
            spread = np.arccos(cosines.min())
            if spread < COLLINEAR_SPREAD_RAD:
                found.append(FixWarning(
                    "collinear_geometry",
                    f"lines of sight to the fix span only {np.rad2deg(spread):.2f} deg: range is poorly determined"))
        zenith = np.hypot(local[:, 0], local[:, 1]) < 1e-4 * np.maximum(distance, 1e-9)
        if np.any(zenith):
            ids = sorted({problem.station_ids[i] for i in los.station_index[zenith]})
            found.append(FixWarning("azimuth_undefined", f"the fix is at the zenith of {', '.join(ids)}"))
    return found


def finish_fix(
    problem: Problem,
    method: str,
    position_enu_m,
    covariance_enu_m2=None,
    *,
    covariance_source: str = "propagated",
    converged: bool = True,
    iterations: int = 0,
    warnings: list[FixWarning] | tuple = (),
    coarse_position_enu_m=None,
    estimated_bearing_errors_rad=None,
    sigmas=None,
    bias_m: float | None = None,
    crlb: Information | None = None,
    details: dict | None = None,
) -> Fix:
    """Build a :class:`Fix`: residuals, chi-square, CRLB and warnings for a position.

    Parameters
    ----------
    problem : Problem
    method : str
    position_enu_m : ndarray, shape (3,)
    covariance_enu_m2 : ndarray, shape (3, 3), optional
        The estimator's own covariance; default the CRLB at the estimate
        (``covariance_source`` is then ``"crlb"``).
    sigmas : ndarray, shape (M,), optional
        Sigmas to normalise with (problem units) when the estimator estimated them.
    bias_m : float, optional
        TOA emission offset (metres); default the best one for the position.
    crlb : Information, optional
        Already computed bound at this position.

    Raises
    ------
    LocalizationError
        If the position is not finite: no estimator may return a silent NaN.
    """
    position = np.asarray(position_enu_m, dtype=float).reshape(3)
    if not np.all(np.isfinite(position)):
        raise LocalizationError(f"{method} produced no finite position for this geometry")
    sig = problem.sigmas if sigmas is None else np.asarray(sigmas, dtype=float)
    bias = best_bias_m(problem, position) if bias_m is None else bias_m
    s = problem.station_index
    predicted, jacobian = predict(position[None], np.array([bias]), problem.stations_enu_m[s][None],
                                  problem.station_rotations[s][None], problem.kinds[None])
    raw = residuals(problem.model_values(), predicted[0], problem.kinds) / problem.unit_scale()
    known = np.isfinite(sig)
    normalized = np.where(known, raw / np.where(known, sig, 1.0), 0.0)
    chi2 = float(np.sum(normalized**2))
    dof = int(np.count_nonzero(known)) - n_parameters(problem)
    p_value = float(chi2_distribution.sf(chi2, dof)) if dof > 0 else None
    sigma_scale = float(np.sqrt(chi2 / dof)) if dof > 0 else None

    if crlb is None:
        crlb = information_at(problem, position, sigmas=np.where(known, sig, np.nan) if sigmas is not None else None)
    studentized = _studentized(problem, position, jacobian, normalized, np.where(known, sig, np.inf), crlb)
    if covariance_enu_m2 is None:
        covariance_enu_m2, covariance_source = crlb.covariance_enu_m2[0], "crlb"
    covariance = np.asarray(covariance_enu_m2, dtype=float)
    covariance = 0.5 * (covariance + covariance.T)

    found = list(warnings)
    if not converged and not any(w.code == "not_converged" for w in found):
        found.append(FixWarning("not_converged", f"{method} did not converge in {iterations} iterations"))
    if crlb.min_eigenvalue[0] < ILL_CONDITIONED_EIGENVALUE:
        found.append(FixWarning("ill_conditioned",
                                f"information matrix nearly singular (min scaled eigenvalue {crlb.min_eigenvalue[0]:.1e})"))
    bound_trace = float(np.trace(crlb.covariance_enu_m2[0]))
    if covariance_source == "propagated" and np.trace(covariance) > INEFFICIENCY_RATIO * bound_trace > 0:
        found.append(FixWarning(
            "inefficient_method",
            f"{method}'s covariance is {np.trace(covariance) / bound_trace:.0f} x the CRLB in this geometry "
            "(its equations are nearly degenerate here); ml or weighted_eove reach the bound"))
    found.extend(geometry_warnings(problem, position))
    worst = int(np.argmax(np.abs(studentized))) if studentized.size else 0
    if dof > 0 and abs(studentized[worst]) > OUTLIER_SIGMAS:
        found.append(FixWarning(
            "outlier_suspected",
            f"measurement {int(problem.source_index[worst])} ({Kind(problem.kinds[worst]).name.lower()} at "
            f"{problem.station_ids[s[worst]]}) has a studentized residual of {studentized[worst]:.1f}"))
    if p_value is not None and p_value < SIGMA_MISMATCH_P:
        found.append(FixWarning(
            "sigma_mismatch",
            f"chi2 = {chi2:.1f} on {dof} dof (p = {p_value:.1e}): residuals are {sigma_scale:.2f} x what the stated sigmas allow"))
    return Fix(
        method=method,
        position_enu_m=position,
        covariance_enu_m2=covariance,
        covariance_source=covariance_source,
        crlb_enu_m2=crlb.covariance_enu_m2[0],
        residuals=raw,
        normalized_residuals=normalized,
        chi2=chi2,
        dof=dof,
        p_value=p_value,
        sigma_scale=sigma_scale,
        converged=bool(converged),
        iterations=int(iterations),
        warnings=tuple(found),
        coarse_position_enu_m=None if coarse_position_enu_m is None else np.asarray(coarse_position_enu_m, float),
        estimated_bearing_errors_rad=estimated_bearing_errors_rad,
        details=dict(details or {}),
    )


def _studentized(problem: Problem, position, jacobian, normalized, sigmas, crlb: Information) -> np.ndarray:
    """Internally studentized residuals ``r_i / (sigma_i sqrt(1 - h_i))``, ``h`` the leverages.

    A gross error on a high-leverage measurement is partly absorbed by the fit
    and spread over the others; dividing by the residual's own standard
    deviation undoes that, so the largest value points at the culprit.
    """
    axes, free = local_parameterisation(problem, position[None])
    weights = (1.0 / (sigmas * problem.unit_scale()) ** 2)[None]
    _, local = normal_matrix(jacobian, weights, axes, free)
    leverage = weights[0] * np.einsum("mi,ij,mj->m", local[0], crlb.covariance_params[0], local[0])
    return normalized / np.sqrt(np.clip(1.0 - leverage, 1e-12, None))


Estimator = Callable[[Problem, SolveOptions], Fix]


@dataclass(frozen=True)
class EstimatorSpec:
    """A registered estimator.

    Attributes
    ----------
    name : str
        The API's ``method`` value.
    solve : Estimator
    summary : str
    needs_sigmas : bool
        False when the method can estimate missing bearing sigmas.
    """

    name: str
    solve: Estimator
    summary: str
    needs_sigmas: bool = True


REGISTRY: dict[str, EstimatorSpec] = {}


def register(name: str, summary: str, needs_sigmas: bool = True):
    """Decorator adding an estimator to :data:`REGISTRY` under its API name."""

    def add(solve: Estimator) -> Estimator:
        if name in REGISTRY:
            raise RuntimeError(f"estimator {name!r} registered twice")
        REGISTRY[name] = EstimatorSpec(name, solve, summary, needs_sigmas)
        return solve

    return add


def get_estimator(name: str) -> EstimatorSpec:
    try:
        return REGISTRY[name]
    except KeyError:
        raise InvalidInput(f"unknown method {name!r}; known: {', '.join(sorted(REGISTRY))}", ("method",)) from None
