"""Maximum likelihood by Levenberg-Marquardt over a batch of problems (section 3).

Minimises ``sum (z - h(p))^2 / sigma^2`` for any mix of azimuth, elevation,
range and TOA. Problems of different sizes are padded with zero-weight
measurements and iterated together: every step is one batched solve of
``(B, 4, 4)`` Jacobi-scaled normal equations in the common frame (metres of
order 1e5 at most, never ECEF's 6.4e6), with the Marquardt damping
``lambda diag(J^T W J)`` per problem. Problems that have converged leave the
working set, so late iterations cost only what is still moving. A known
altitude is a constraint: the position moves along the local east/north at
the current point and is put back on the altitude surface after each step.
The covariance is the inverse information at the solution.

Everything a fix reports (residuals, chi-square, the bound, studentized
outliers, geometry warnings) is computed for the whole batch at once by
:func:`finish_batch`, which gives what :func:`~core.estimators.base.finish_fix`
gives one problem at a time.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.special import chdtrc

from core.angles import line_of_sight_enu
from core.batch import AZIMUTH, ELEVATION, TOA, ProblemBatch, size_groups
from core.crlb import Information, invert_information
from core.errors import LocalizationError, UnobservableGeometry
from core.estimators.base import (
    COLLINEAR_SPREAD_RAD,
    ILL_CONDITIONED_EIGENVALUE,
    OUTLIER_SIGMAS,
    SIGMA_MISMATCH_P,
    Fix,
    FixWarning,
    SolveOptions,
    register,
)
from core.estimators.start import initial_positions
from core.measurements import MIN_HORIZONTAL_DISTANCE_M, Kind
from core.problem import Problem, local_axes, onto_altitude

_EYE4 = np.eye(4)
_LAMBDA_START = 1e-3
_LAMBDA_MIN = 1e-12
_LAMBDA_MAX = 1e12
#: The working set is compacted when fewer than this share of it is still active.
_COMPACT_BELOW = 0.5
#: A batch is solved in chunks of about this many measurement slots (problems x padded width),
#: and of at least ``CHUNK_MIN_PROBLEMS`` problems.
CHUNK_ENTRIES = 1 << 15
CHUNK_MIN_PROBLEMS = 64
#: Pairwise line-of-sight cosines are formed for at most this many entries at once.
_GRAM_ENTRIES = 1 << 21


@dataclass(frozen=True)
class ProblemStack:
    """Problems padded to one measurement count (zero weight fills the gaps).

    Attributes
    ----------
    stations_enu_m : ndarray, shape (B, M, 3)
        Station of each measurement.
    rotations : ndarray, shape (B, M, 3, 3)
    kinds : ndarray of int, shape (B, M)
    values : ndarray, shape (B, M)
        Model units (TOA as pseudo-range metres).
    weights : ndarray, shape (B, M)
        ``1 / sigma^2`` in model units; 0 for padding.
    altitude_m : ndarray, shape (B,)
        NaN where unconstrained.
    origin : ndarray, shape (B, 3)
        Each problem's frame origin ``(lat_rad, lon_rad, alt_m)``.
    geodetic : ndarray of bool, shape (B,)
    has_toa : ndarray of bool, shape (B,)
    """

    stations_enu_m: np.ndarray
    rotations: np.ndarray
    kinds: np.ndarray
    values: np.ndarray
    weights: np.ndarray
    altitude_m: np.ndarray
    origin: np.ndarray
    geodetic: np.ndarray
    has_toa: np.ndarray

    @classmethod
    def from_batch(cls, batch: ProblemBatch) -> "ProblemStack":
        stations, rotations = batch.measurement_stations()
        scale = batch.unit_scale()
        known = batch.valid & np.isfinite(batch.sigmas)
        sigmas = np.where(known, batch.sigmas, 1.0) * scale
        return cls(
            stations_enu_m=stations,
            rotations=rotations,
            kinds=batch.kinds,
            values=batch.values * scale,
            weights=np.where(known, 1.0 / sigmas**2, 0.0),
            altitude_m=batch.altitude_m,
            origin=batch.origin,
            geodetic=batch.geodetic,
            has_toa=batch.has_toa,
        )

    @classmethod
    def from_problems(cls, problems: list[Problem]) -> "ProblemStack":
        return cls.from_batch(ProblemBatch.from_problems(problems))

    def take(self, indices) -> "ProblemStack":
        """The stack of the problems ``indices``."""
        return ProblemStack(*(getattr(self, name)[indices] for name in self.__dataclass_fields__))

    @property
    def constrained(self) -> np.ndarray:
        return ~np.isnan(self.altitude_m)

    def optimal_bias(self, positions_enu_m):
        """Weighted-mean TOA offset ``(B,)`` given positions; 0 without TOA."""
        is_toa = (self.kinds == TOA) & (self.weights > 0)
        ranges = np.linalg.norm(positions_enu_m[:, None, :] - self.stations_enu_m, axis=-1)
        w = self.weights * is_toa
        total = w.sum(axis=-1)
        return np.where(total > 0, np.einsum("bm,bm->b", w, self.values - ranges) / np.where(total > 0, total, 1), 0.0)


@dataclass(frozen=True)
class BatchSolution:
    """Raw ML output for a batch (arrays with leading axis B).

    Attributes
    ----------
    positions_enu_m : ndarray, shape (B, 3)
    bias_m : ndarray, shape (B,)
    iterations : ndarray of int, shape (B,)
    converged : ndarray of bool, shape (B,)
    information : Information
        Inverted at the solution.
    residuals : ndarray, shape (B, M)
        Model units at the solution, zero on padding.
    jacobian : ndarray, shape (B, M, 4)
        At the solution, w.r.t. the local parameters (east, north, up, bias)
        at the solution; zero for frozen ones.
    """

    positions_enu_m: np.ndarray
    bias_m: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    information: Information
    residuals: np.ndarray | None = None
    jacobian: np.ndarray | None = None


class _Model:
    """A stack in component-first layout for the iteration: ``(3, B, M)`` and ``(3, 3, B, M)`` arrays.

    Element-wise arithmetic on whole ``(B, M)`` planes is several times faster
    than ``einsum`` or ``matmul`` over ``(B, M, 3, 3)`` blocks of 3x3 matrices.
    """

    def __init__(self, stack: ProblemStack | None = None, **arrays):
        if stack is None:
            self.__dict__.update(arrays)
            return
        self.stations = np.ascontiguousarray(np.moveaxis(stack.stations_enu_m, -1, 0))
        self.rotations = np.ascontiguousarray(np.moveaxis(stack.rotations, (-2, -1), (0, 1)))
        self.values = stack.values
        self.weights = stack.weights
        self.is_az = stack.kinds == AZIMUTH
        self.is_el = stack.kinds == ELEVATION
        self.is_toa = (stack.kinds == TOA).astype(float)
        self.used = stack.weights > 0
        self.ranged = bool(np.any(self.used & ~self.is_az & ~self.is_el))
        self.constrained = stack.constrained
        self.any_constrained = bool(np.any(self.constrained))
        self.altitude_m = np.nan_to_num(stack.altitude_m)
        self.origin = stack.origin
        self.geodetic = stack.geodetic
        self.has_toa = stack.has_toa

    def take(self, rows) -> "_Model":
        out = dict(self.__dict__)
        for name in ("values", "weights", "is_az", "is_el", "is_toa", "used", "constrained", "altitude_m",
                     "origin", "geodetic", "has_toa"):
            out[name] = self.__dict__[name][rows]
        out["stations"] = self.stations[:, rows]
        out["rotations"] = self.rotations[:, :, rows]
        out["any_constrained"] = bool(np.any(out["constrained"]))
        out["ranged"] = bool(np.any(out["used"] & ~out["is_az"] & ~out["is_el"]))
        return _Model(**out)

    def project(self, positions_enu_m):
        if not self.any_constrained:
            return positions_enu_m
        moved = onto_altitude(positions_enu_m, self.altitude_m, self.origin, self.geodetic)
        return np.where(self.constrained[:, None], moved, positions_enu_m)

    def parameterisation(self, positions_enu_m):
        """Local axes ``(B, 3, 3)`` (None when no problem is constrained) and free parameters ``(B, 4)``."""
        free = np.empty((positions_enu_m.shape[0], 4), dtype=bool)
        free[:, :2] = True
        free[:, 2] = ~self.constrained
        free[:, 3] = self.has_toa
        if not self.any_constrained:
            return None, free
        axes = np.where(self.constrained[:, None, None],
                        local_axes(positions_enu_m, self.origin, self.geodetic), np.eye(3))
        return axes, free

    def evaluate(self, positions_enu_m, bias_m):
        """Residuals ``(B, M)`` (model units, zero on padding), cost ``(B,)`` and Jacobian ``(B, 4, M)``.

        The measurement model and its derivatives are those of
        :func:`core.measurements.predict`; the Jacobian is w.r.t. (east,
        north, up, bias) of the common frame.
        """
        s, rot = self.stations, self.rotations
        dx = positions_enu_m[:, 0, None] - s[0]
        dy = positions_enu_m[:, 1, None] - s[1]
        dz = positions_enu_m[:, 2, None] - s[2]
        e = rot[0, 0] * dx + rot[0, 1] * dy + rot[0, 2] * dz
        n = rot[1, 0] * dx + rot[1, 1] * dy + rot[1, 2] * dz
        u = rot[2, 0] * dx + rot[2, 1] * dy + rot[2, 2] * dz
        rho2 = np.maximum(e * e + n * n, MIN_HORIZONTAL_DISTANCE_M**2)
        rho = np.sqrt(rho2)
        r2 = rho2 + u * u
        r = np.sqrt(r2)
        is_az, is_el = self.is_az, self.is_el
        elevation = np.arctan2(u, rho)
        elevation_factor = u / (r2 * rho)
        if self.ranged:
            inv_r = 1.0 / r
            far = np.where(is_el, elevation, r + bias_m[:, None] * self.is_toa)
            ge_far = np.where(is_el, -e * elevation_factor, e * inv_r)
            gn_far = np.where(is_el, -n * elevation_factor, n * inv_r)
            gu_far = np.where(is_el, rho / r2, u * inv_r)
        else:
            far, ge_far, gn_far, gu_far = elevation, -e * elevation_factor, -n * elevation_factor, rho / r2
        predicted = np.where(is_az, np.arctan2(e, n), far)
        raw = self.values - predicted
        wrapped = np.mod(raw + np.pi, 2.0 * np.pi) - np.pi
        wrapped[wrapped == -np.pi] = np.pi
        residual = (np.where(is_az | is_el, wrapped, raw) if self.ranged else wrapped) * self.used
        cost = np.einsum("bm,bm->b", self.weights, residual * residual)
        ge = np.where(is_az, n / rho2, ge_far)
        gn = np.where(is_az, -e / rho2, gn_far)
        gu = np.where(is_az, 0.0, gu_far)
        jacobian = np.empty((e.shape[0], 4, e.shape[1]))
        jacobian[:, 0] = ge * rot[0, 0] + gn * rot[1, 0] + gu * rot[2, 0]
        jacobian[:, 1] = ge * rot[0, 1] + gn * rot[1, 1] + gu * rot[2, 1]
        jacobian[:, 2] = ge * rot[0, 2] + gn * rot[1, 2] + gu * rot[2, 2]
        jacobian[:, 3] = self.is_toa
        return residual, cost, jacobian

    def normal_equations(self, jacobian, residual, axes, free):
        """Information ``(B, 4, 4)`` (identity on frozen parameters), gradient ``(B, 4)`` and local Jacobian."""
        local = jacobian
        if axes is not None:
            local = jacobian.copy()
            local[:, :3] = axes @ jacobian[:, :3]
        local = local * free[:, :, None]
        weighted = local * self.weights[:, None, :]
        information = weighted @ np.swapaxes(local, -1, -2)
        information += _EYE4 * ~free[:, None, :]
        gradient = np.einsum("bim,bm->bi", weighted, residual)
        return information, gradient, local


def levenberg_marquardt(stack: ProblemStack, start_enu_m, max_iterations=50, tolerance_m=1e-3) -> BatchSolution:
    """Iterate every problem of a stack to its ML position.

    Parameters
    ----------
    stack : ProblemStack
    start_enu_m : ndarray, shape (B, 3)
    max_iterations : int
    tolerance_m : float

    Returns
    -------
    BatchSolution
        With the residuals and the Jacobian ``(B, M, 4)`` at the solution.
    """
    model = _Model(stack)
    x_all = model.project(np.asarray(start_enu_m, dtype=float).copy())
    bias_all = stack.optimal_bias(x_all)
    batch = x_all.shape[0]
    converged_all = np.zeros(batch, dtype=bool)
    iterations_all = np.zeros(batch, dtype=int)

    work = np.arange(batch)
    sub = model
    x, bias = x_all, bias_all
    damping = np.full(batch, _LAMBDA_START)
    active = np.ones(batch, dtype=bool)
    converged = np.zeros(batch, dtype=bool)
    iterations = np.zeros(batch, dtype=int)
    r, cost, jacobian = sub.evaluate(x, bias)
    r_all, jacobian_all = r.copy(), jacobian.copy()

    def store():
        x_all[work], bias_all[work] = x, bias
        converged_all[work], iterations_all[work] = converged, iterations
        r_all[work], jacobian_all[work] = r, jacobian

    eye = _EYE4
    for _ in range(max_iterations):
        n_active = np.count_nonzero(active)
        if n_active == 0:
            break
        if n_active < _COMPACT_BELOW * work.size:
            store()
            keep = np.flatnonzero(active)
            work, sub = work[keep], sub.take(keep)
            x, bias, r, cost, jacobian = x[keep], bias[keep], r[keep], cost[keep], jacobian[keep]
            damping, converged, iterations = damping[keep], converged[keep], iterations[keep]
            active = active[keep]
        axes, free = sub.parameterisation(x)
        information, gradient, _ = sub.normal_equations(jacobian, r, axes, free)
        diag = np.einsum("bii->bi", information)
        scale = 1.0 / np.sqrt(np.where(diag > 0, diag, 1.0))
        scaled = information * scale[:, :, None] * scale[:, None, :] + damping[:, None, None] * eye
        scaled[~active] = eye
        step = scale * np.linalg.solve(scaled, (scale * gradient)[..., None])[..., 0]
        step = np.where(active[:, None], step * free, 0.0)
        delta = step[:, :3] if axes is None else np.einsum("bi,bij->bj", step[:, :3], axes)
        x_new = sub.project(x + delta)
        bias_new = bias + step[:, 3]
        r_new, cost_new, jacobian_new = sub.evaluate(x_new, bias_new)
        accept = active & np.isfinite(cost_new) & (cost_new <= cost * (1.0 + 1e-12) + 1e-300)
        x = np.where(accept[:, None], x_new, x)
        bias = np.where(accept, bias_new, bias)
        r = np.where(accept[:, None], r_new, r)
        cost = np.where(accept, cost_new, cost)
        jacobian = np.where(accept[:, None, None], jacobian_new, jacobian)
        iterations += active
        damping = np.where(accept, np.maximum(damping / 10.0, _LAMBDA_MIN), damping * 10.0)
        done = active & (np.sqrt(np.einsum("bi,bi->b", delta, delta)) < tolerance_m)
        stuck = active & (damping > _LAMBDA_MAX)
        converged |= done
        active &= ~(done | stuck)
    store()
    axes, free = model.parameterisation(x_all)
    information, _, local = model.normal_equations(jacobian_all, r_all, axes, free)
    full_axes = np.broadcast_to(np.eye(3), (batch, 3, 3)) if axes is None else axes
    return BatchSolution(x_all, bias_all, iterations_all, converged_all,
                         invert_information(information, full_axes, free), r_all, np.swapaxes(local, -1, -2))


@dataclass(frozen=True)
class FixBatch:
    """Fixes of a batch of problems as arrays (leading axis B).

    Rows of problems in ``errors`` hold NaN. :meth:`fix` gives one
    :class:`~core.estimators.base.Fix` (or its error); the service builds
    responses straight from the arrays.

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
    chi2 : ndarray, shape (B,)
    dof : ndarray of int, shape (B,)
    p_value, sigma_scale : ndarray, shape (B,)
        NaN where ``dof`` is 0 (None in a :class:`Fix`).
    converged : ndarray of bool, shape (B,)
    iterations : ndarray of int, shape (B,)
    warnings : list of tuple of FixWarning, length B
    details : list of dict, length B
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
    chi2: np.ndarray
    dof: np.ndarray
    p_value: np.ndarray
    sigma_scale: np.ndarray
    converged: np.ndarray
    iterations: np.ndarray
    warnings: list = field(default_factory=list)
    details: list = field(default_factory=list)

    def fix(self, b: int) -> Fix | LocalizationError:
        """Problem ``b``'s fix, or the error that stopped it."""
        if b in self.errors:
            return self.errors[b]
        m = int(self.problems.n_measurements[b])
        p_value, sigma_scale = float(self.p_value[b]), float(self.sigma_scale[b])
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
            details=dict(self.details[b]),
        )


def _station_list(batch: ProblemBatch, b: int, rows) -> str:
    ids = batch.station_ids[b]
    return ", ".join(sorted({ids[i] for i in batch.station_index[b, rows]}))


def _collinear_spread(seen, is_line):
    """Smallest pairwise angle spread ``(B,)`` of unit vectors ``(B, M, 3)`` on line rows (rad)."""
    size, width = is_line.shape
    smallest = np.ones(size)
    chunk = max(1, _GRAM_ENTRIES // max(width * width, 1))
    for start in range(0, size, chunk):
        part = slice(start, start + chunk)
        cosines = np.clip(np.abs(seen[part] @ np.swapaxes(seen[part], -1, -2)), 0.0, 1.0)
        pair = is_line[part, :, None] & is_line[part, None, :]
        smallest[part] = np.where(pair, cosines, 1.0).min(axis=(-2, -1))
    return np.arccos(smallest)


def _singular_reason(batch: ProblemBatch, b: int, position_enu_m, min_eigenvalue: float) -> str:
    """Why the information is singular at an ML iterate, as specifically as can be told."""
    n = int(batch.n_stations[b])
    local = np.einsum("nij,nj->ni", batch.station_rotations[b, :n], position_enu_m - batch.stations_enu_m[b, :n])
    horizontal = np.hypot(local[:, 0], local[:, 1])
    at_zenith = horizontal < 1e-6 * np.maximum(np.linalg.norm(local, axis=-1), 1.0)
    if np.any(at_zenith):
        ids = ", ".join(batch.station_ids[b][i] for i in np.flatnonzero(at_zenith))
        return ("the bearings contradict each other: the iteration ran onto the vertical of station "
                f"{ids}, where azimuth is undefined (typically the lines of sight meet only behind a station); "
                "check the bearings, or use eove to see where the lines meet")
    stations = batch.stations_enu_m[b, :n]
    spread_m = float(np.max(np.linalg.norm(stations - stations.mean(axis=0), axis=-1))) + 1e3
    if np.linalg.norm(position_enu_m - stations.mean(axis=0)) > 1e4 * spread_m:
        return ("the bearings have no common point in front of the stations: the fit runs off to infinity "
                "(lines of sight diverge, or meet only behind a station); check the bearings, or use eove "
                "to see where the lines meet")
    return ("the measurements do not determine the position: the information matrix is singular "
            f"(min scaled eigenvalue {min_eigenvalue:.1e}); add stations, elevations or an altitude constraint")


def finish_batch(batch: ProblemBatch, solution: BatchSolution, starts, method: str = "ml",
                 stack: ProblemStack | None = None) -> FixBatch:
    """Everything a fix reports, for a whole batch of ML solutions.

    The batched counterpart of :func:`~core.estimators.base.finish_fix` for an
    estimator whose covariance is the inverse information at its solution:
    residuals, chi-square and p-value, studentized outliers, the
    conditioning and geometry warnings, with the same values and messages.

    Parameters
    ----------
    batch : ProblemBatch
    solution : BatchSolution
        With ``residuals`` and ``jacobian`` at the solution.
    starts : sequence of str
        The start each problem used (``details["start"]``).
    method : str
    stack : ProblemStack, optional
        The stack the solution was computed on.

    Returns
    -------
    FixBatch
    """
    stack = stack or ProblemStack.from_batch(batch)
    info = solution.information
    size = batch.size
    position = solution.positions_enu_m
    errors: dict[int, LocalizationError] = {}
    for b in np.flatnonzero(~info.observable):
        errors[int(b)] = UnobservableGeometry(_singular_reason(batch, int(b), position[b], info.min_eigenvalue[b]))
    for b in np.flatnonzero(info.observable & ~np.all(np.isfinite(position), axis=-1)):
        errors[int(b)] = LocalizationError(f"{method} produced no finite position for this geometry")

    valid = batch.valid
    unit = batch.unit_scale()
    known = valid & np.isfinite(batch.sigmas)
    raw = solution.residuals / unit
    normalized = np.where(known, raw / np.where(known, batch.sigmas, 1.0), 0.0)
    chi2 = np.sum(normalized**2, axis=-1)
    n_parameters = np.where(batch.constrained, 2, 3) + batch.has_toa
    dof = np.count_nonzero(known, axis=-1) - n_parameters
    positive = dof > 0
    p_value = np.where(positive, chdtrc(np.maximum(dof, 1), chi2), np.nan)
    sigma_scale = np.where(positive, np.sqrt(chi2 / np.maximum(dof, 1)), np.nan)

    local = solution.jacobian
    leverage = stack.weights * np.einsum("bmi,bij,bmj->bm", local, info.covariance_params, local)
    studentized = normalized / np.sqrt(np.clip(1.0 - leverage, 1e-12, None))
    worst = np.argmax(np.abs(studentized), axis=-1)
    worst_value = studentized[np.arange(size), worst]
    outlier = positive & (np.abs(worst_value) > OUTLIER_SIGMAS)
    mismatch = positive & (p_value < SIGMA_MISMATCH_P)
    ill = info.min_eigenvalue < ILL_CONDITIONED_EIGENVALUE

    is_line, elevation, _ = batch.lines_of_sight()
    has_el = ~np.isnan(elevation)
    stations, rotations = stack.stations_enu_m, stack.rotations
    to_target = position[:, None, :] - stations
    distance = np.linalg.norm(to_target, axis=-1)
    local_target = np.einsum("bmij,bmj->bmi", rotations, to_target)
    measured = line_of_sight_enu(batch.values, np.where(has_el, elevation, 0.0))
    in_plane = np.where(has_el[..., None], local_target, local_target * [1.0, 1.0, 0.0])
    behind = is_line & (np.einsum("bmi,bmi->bm", measured, in_plane) < 0)
    n_lines = np.count_nonzero(is_line, axis=-1)
    spread = np.full(size, np.pi / 2)
    several = n_lines >= 2
    if np.any(several):
        seen = to_target / np.maximum(distance, 1e-9)[..., None]
        spread[several] = _collinear_spread(seen[several], is_line[several])
    collinear = several & (spread < COLLINEAR_SPREAD_RAD)
    zenith = is_line & (np.hypot(local_target[..., 0], local_target[..., 1]) < 1e-4 * np.maximum(distance, 1e-9))

    flagged = ~solution.converged | ill | outlier | mismatch | collinear | np.any(behind | zenith, axis=-1)
    warnings: list[tuple[FixWarning, ...]] = [()] * size
    for b in np.flatnonzero(flagged):
        found = []
        if not solution.converged[b]:
            found.append(FixWarning("not_converged", f"no convergence in {int(solution.iterations[b])} iterations; "
                                                     "last accepted iterate returned"))
        if ill[b]:
            found.append(FixWarning("ill_conditioned", "information matrix nearly singular "
                                                       f"(min scaled eigenvalue {info.min_eigenvalue[b]:.1e})"))
        if np.any(behind[b]):
            found.append(FixWarning("behind_station",
                                    f"the fix is behind the line of sight of {_station_list(batch, b, behind[b])}"))
        if collinear[b]:
            found.append(FixWarning(
                "collinear_geometry",
                f"lines of sight to the fix span only {np.rad2deg(spread[b]):.2f} deg: range is poorly determined"))
        if np.any(zenith[b]):
            found.append(FixWarning("azimuth_undefined",
                                    f"the fix is at the zenith of {_station_list(batch, b, zenith[b])}"))
        if outlier[b]:
            w = worst[b]
            station = batch.station_ids[b][batch.station_index[b, w]]
            found.append(FixWarning(
                "outlier_suspected",
                f"measurement {int(batch.source_index[b, w])} ({Kind(batch.kinds[b, w]).name.lower()} at "
                f"{station}) has a studentized residual of {worst_value[b]:.1f}"))
        if mismatch[b]:
            found.append(FixWarning(
                "sigma_mismatch",
                f"chi2 = {chi2[b]:.1f} on {dof[b]} dof (p = {p_value[b]:.1e}): residuals are "
                f"{sigma_scale[b]:.2f} x what the stated sigmas allow"))
        warnings[b] = tuple(found)

    covariance = info.covariance_enu_m2
    return FixBatch(
        method=method,
        problems=batch,
        errors=errors,
        position_enu_m=position,
        covariance_enu_m2=0.5 * (covariance + np.swapaxes(covariance, -1, -2)),
        covariance_source="information",
        crlb_enu_m2=covariance,
        residuals=np.where(valid, raw, 0.0),
        normalized_residuals=normalized,
        chi2=chi2,
        dof=dof,
        p_value=p_value,
        sigma_scale=sigma_scale,
        converged=solution.converged,
        iterations=solution.iterations,
        warnings=warnings,
        details=[{"start": s} for s in starts],
    )


def solve_ml_problem_batch(batch: ProblemBatch, options: SolveOptions, method: str = "ml") -> FixBatch:
    """ML fixes for every problem of a batch: batched start, one batched iteration, batched finish.

    A large batch is solved in chunks of about ``CHUNK_ENTRIES`` measurement
    slots, so that the working planes stay in cache (twice as fast as one
    pass over 10,000 problems); results do not depend on the chunking.

    Returns
    -------
    FixBatch
        A problem without a start (too few or unobservable measurements) or
        without an observable solution carries its error.
    """
    rows = max(CHUNK_MIN_PROBLEMS, CHUNK_ENTRIES // max(batch.kinds.shape[1], 1))
    if batch.size <= rows:
        return _solve_chunk(batch, options, method)
    parts = [_solve_chunk(batch.take(np.arange(start, min(start + rows, batch.size))), options, method)
             for start in range(0, batch.size, rows)]
    return _concatenate(batch, parts)


def _concatenate(batch: ProblemBatch, parts: list[FixBatch]) -> FixBatch:
    width = batch.kinds.shape[1]

    def joined(name):
        arrays = [getattr(p, name) for p in parts]
        if arrays[0].ndim == 2 and name in ("residuals", "normalized_residuals"):
            arrays = [np.pad(a, ((0, 0), (0, width - a.shape[1]))) for a in arrays]
        return np.concatenate(arrays)

    errors, offset = {}, 0
    for part in parts:
        errors.update({offset + b: e for b, e in part.errors.items()})
        offset += part.problems.size
    arrays = {name: joined(name) for name in ("position_enu_m", "covariance_enu_m2", "crlb_enu_m2", "residuals",
                                              "normalized_residuals", "chi2", "dof", "p_value", "sigma_scale",
                                              "converged", "iterations")}
    return FixBatch(method=parts[0].method, problems=batch, errors=errors,
                    covariance_source=parts[0].covariance_source,
                    warnings=[w for p in parts for w in p.warnings], details=[d for p in parts for d in p.details],
                    **arrays)


def _solve_chunk(batch: ProblemBatch, options: SolveOptions, method: str) -> FixBatch:
    starts, names, failures = initial_positions(batch)
    missing = ~np.all(np.isfinite(starts), axis=-1)
    for b in np.flatnonzero(missing):
        failures.setdefault(int(b), LocalizationError(f"{method}: no starting point for this geometry"))
    starts[missing] = batch.stations_enu_m[missing, 0] + [0.0, 0.0, 1.0]
    stack = ProblemStack.from_batch(batch)
    solution = levenberg_marquardt(stack, starts, options.max_iterations, options.tolerance_m)
    result = finish_batch(batch, solution, names, method, stack)
    result.errors.update(failures)
    return result


def solve_ml_batch(problems: list[Problem], options: SolveOptions, method: str = "ml") -> list[Fix | LocalizationError]:
    """ML fixes for many problems, batched (grouped by size so padding stays small).

    Returns
    -------
    list of Fix or LocalizationError
        In input order; a problem that cannot be solved gets its error.
    """
    results: list[Fix | LocalizationError | None] = [None] * len(problems)
    if not problems:
        return []
    sizes = np.array([p.kinds.size for p in problems])
    stations = np.array([p.stations_enu_m.shape[0] for p in problems])
    for group in size_groups(sizes, stations):
        batch = ProblemBatch.from_problems([problems[i] for i in group])
        fixes = solve_ml_problem_batch(batch, options, method)
        for j, i in enumerate(group):
            results[i] = fixes.fix(j)
    return results


@register("ml", "maximum likelihood (Levenberg-Marquardt) over any mix of measurements; the reference")
def ml(problem: Problem, options: SolveOptions) -> Fix:
    (result,) = solve_ml_batch([problem], options)
    if isinstance(result, LocalizationError):
        raise result
    return result
