"""Closed-form starting points for the ML iteration, chosen by measurement mix, for a whole batch.

In order of preference, for each problem without an initial guess:

- bearings: weighted EOVE (:func:`core.estimators.methods.orthogonal_vector.solve_orthogonal_batch`);
- a station with a bearing with elevation and a range: its polar point
  ``s + R u``, fused over stations by inverse covariance;
- four or more TOAs: Bancroft's algebraic solution (exact without noise);
- three or more ranges: linear trilateration by differencing, with the
  mirror ambiguity of coplanar stations resolved upwards.

Each stage runs once over the problems still without a start; the
least-squares systems are solved by SVD per problem, all at once
(:func:`core.linalg.jacobi_svd`).
"""

from __future__ import annotations

import numpy as np

from core.angles import line_of_sight_enu
from core.errors import LocalizationError, TooFewMeasurements, UnobservableGeometry
from core.estimators.methods.orthogonal_vector import Normals, Weighting, normal_vectors, solve_orthogonal_batch
from core.linalg import jacobi_svd, last_dot, matvec
from core.measurements import AZIMUTH, RANGE, TOA
from core.problem.batch import ProblemBatch
from core.problem.frame import Problem

#: Smallest standard deviation (m) of a polar point along any axis.
MIN_POLAR_SD_M = 1e-9
#: ... and across its line of sight, at least this share of the range's along it: a range of (nearly) 0 m would
#: leave a covariance that float64 cannot invert (condition number 1e20 with 10 m along and 1e-9 m across).
MIN_POLAR_SD_RATIO = 1e-6
#: Relative singular value below which the trilateration rows are rank-deficient.
TRILATERATION_RANK_TOLERANCE = 1e-9
#: Relative singular value below which Bancroft's pseudo-inverse drops a direction (``np.linalg.pinv``'s).
PINV_CUTOFF = 1e-15
#: Weighted-EOVE passes of a start: one re-weighting brings it within a Gauss-Newton step of the ML fix, which
#: the iteration takes anyway (a third pass cost ~0.4-1.4 us of a ~3 us start per problem and saved no iteration).
START_PASSES = 2
#: Chi-square gap within which Bancroft's two roots are taken as equally good (the upper one wins).
MIRROR_CHI2 = 9.0


def station_polar_points(batch: ProblemBatch):
    """Per line of sight with elevation at a station with ranges, the polar fix ``s + R u``.

    The station's ranges are averaged with weights ``1 / sigma^2``.

    Returns
    -------
    points_enu_m : ndarray, shape (B, M, 3)
        On the azimuth row of each line; garbage where ``found`` is False.
    information_enu_per_m2 : ndarray, shape (B, M, 3, 3)
        The inverse of the first-order covariance, ``R^2 sigma_el^2`` and ``(R cos el)^2 sigma_az^2``
        across the line of sight and ``sigma_R^2`` along it, built from those axes (not by inverting the
        covariance, whose conditioning reaches 1e21 with a 1e9 m range of sigma 0.1 m and a broad azimuth).
    found : ndarray of bool, shape (B, M)
    """
    is_line, elevation, sigma_elevation = batch.lines_of_sight()
    has_el = ~np.isnan(elevation)
    size, width = is_line.shape
    n_stations = batch.stations_enu_m.shape[1]
    is_range = batch.valid & (batch.kinds == RANGE)
    slot = (np.arange(size)[:, None] * n_stations + batch.station_index)
    weight = 1.0 / np.where(is_range, batch.sigmas, 1.0) ** 2
    total = np.bincount(slot[is_range], weight[is_range], size * n_stations)
    weighted_sum = np.bincount(slot[is_range], (weight * batch.values)[is_range], size * n_stations)
    total, weighted_sum = total[slot], weighted_sum[slot]
    found = has_el & (np.bincount(slot[is_range], minlength=size * n_stations)[slot] > 0)
    safe_total = np.where(found, total, 1.0)
    range_m = np.where(found, weighted_sum, 1.0) / safe_total
    az, el = np.where(is_line, batch.values, 0.0), np.where(has_el, elevation, 0.0)
    along = line_of_sight_enu(az, el)
    across_el, across_az = normal_vectors(az, el)
    basis = np.stack([along, across_az, across_el], axis=-1)
    along_sd = np.sqrt(1.0 / safe_total)
    sd = np.stack([along_sd, range_m * np.cos(el) * batch.sigmas,
                   range_m * np.where(has_el, sigma_elevation, 1.0)], axis=-1)
    floor = np.maximum(MIN_POLAR_SD_M, MIN_POLAR_SD_RATIO * along_sd)
    info_local = (basis / np.square(np.maximum(sd, floor[..., None]))[..., None, :]) @ np.swapaxes(basis, -1, -2)
    stations, rotations = batch.measurement_stations()
    to_common = np.swapaxes(rotations, -1, -2)
    points = stations + matvec(to_common, range_m[..., None] * along)
    return points, to_common @ info_local @ rotations, found


def fuse_points(points_enu_m, information_enu_per_m2, used=None):
    """Inverse-covariance fusion of point estimates.

    Parameters
    ----------
    points_enu_m : ndarray, shape (..., P, 3)
    information_enu_per_m2 : ndarray, shape (..., P, 3, 3)
        Each point's inverse covariance (positive semi-definite; a point with a non-finite one takes no part).
    used : ndarray of bool, shape (..., P), optional
        Which points take part (default all); a set without any gets an arbitrary position and a covariance of
        about 1e307 m^2.

    Returns
    -------
    position_enu_m : ndarray, shape (..., 3)
    covariance_enu_m2 : ndarray, shape (..., 3, 3)
        The inverse of the summed information, through its eigen-decomposition: an eigenvalue that
        vanishes gives an astronomically large variance along its axis, never an error.
    """
    information = np.asarray(information_enu_per_m2, dtype=float)
    taking_part = np.isfinite(information).all(axis=(-2, -1)) & (True if used is None else used)
    information = np.where(taking_part[..., None, None], information, 0.0)
    values, vectors = np.linalg.eigh(information.sum(axis=-3))
    total = (vectors / np.maximum(values, np.finfo(float).tiny)[..., None, :]) @ np.swapaxes(vectors, -1, -2)
    return matvec(total, matvec(information, points_enu_m).sum(axis=-2)), total


def bancroft(stations_enu_m, pseudoranges_m, weights, used):
    """Bancroft's closed-form solution of ``rho_i = |p - s_i| + b`` for a batch.

    Parameters
    ----------
    stations_enu_m : ndarray, shape (B, N, 3)
    pseudoranges_m, weights : ndarray, shape (B, N)
    used : ndarray of bool, shape (B, N)
        At least 4 per problem.

    Returns
    -------
    position_enu_m : ndarray, shape (B, 3)
    bias_m : ndarray, shape (B,)
    singular : ndarray of bool, shape (B,)
        True where ``[s, -rho]`` has rank below 4 (stations coplanar or too few).
    """
    count = np.count_nonzero(used, axis=-1)
    s = np.where(used[..., None], stations_enu_m, 0.0)
    rho = np.where(used, pseudoranges_m, 0.0)
    w = np.sqrt(np.where(used, weights, 0.0))
    # The linear system is singular when the stations lie in a plane through the origin
    # (ground receivers of a local frame): solve from a point below their centroid instead.
    centroid = s.sum(axis=-2) / count[:, None]
    spread, axes, _ = jacobi_svd(np.where(used[..., None], s - centroid[:, None, :], 0.0))
    normal = np.take_along_axis(axes, np.argmin(spread, axis=-1)[:, None, None], axis=-1)[..., 0]
    below = centroid - np.copysign(1.0, normal[:, 2])[:, None] * normal * np.maximum(spread.max(axis=-1), 1.0)[:, None]
    s = np.where(used[..., None], s - below[:, None, :], 0.0)
    m = np.concatenate([s, -rho[..., None]], axis=-1)
    half_norm = 0.5 * (np.sum(s * s, axis=-1) - rho * rho)
    plain, _, _ = jacobi_svd(m)
    rank_tolerance = plain.max(axis=-1) * np.maximum(count, 4) * np.finfo(float).eps
    singular = np.count_nonzero(plain > rank_tolerance[:, None], axis=-1) < 4
    sv, v, projected = jacobi_svd(m * w[..., None], np.stack([w, w * half_norm], axis=-1))
    kept = sv > PINV_CUTOFF * sv.max(axis=-1, keepdims=True)
    inverse_s2 = np.where(kept, 1.0 / np.where(kept, sv, 1.0) ** 2, 0.0)
    u, vv = np.moveaxis(v @ (inverse_s2[..., None] * projected), -1, 0)

    def lorentz(a, b):
        return last_dot(a[:, :3], b[:, :3]) - a[:, 3] * b[:, 3]

    qa, qb, qc = 0.5 * lorentz(u, u), lorentz(u, vv) - 1.0, 0.5 * lorentz(vv, vv)
    single = np.abs(qa) < 1e-300
    safe_qa = np.where(single, 1.0, qa)
    root = np.sqrt(np.maximum(qb * qb - 4 * qa * qc, 0.0))
    lam_plus = np.where(single, -qc / np.where(qb != 0, qb, 1.0), (-qb + root) / (2 * safe_qa))
    lam_minus = (-qb - root) / (2 * safe_qa)
    candidates = [lam[:, None] * u + vv for lam in (lam_plus, lam_minus)]

    def misfit(y):
        r = np.linalg.norm(s - y[:, None, :3], axis=-1) + y[:, 3:4] - rho
        return np.sum(w * w * r * r * used, axis=-1)

    fit_plus, fit_minus = misfit(candidates[0]), np.where(single, np.inf, misfit(candidates[1]))
    plus_best = fit_plus <= fit_minus
    best = np.where(plus_best[:, None], candidates[0], candidates[1])
    other = np.where(plus_best[:, None], candidates[1], candidates[0])
    # Near-coplanar stations barely tell a point from its mirror image through their plane:
    # when the other root fits as well (chi-square within 9), take the upper one, as trilaterate does.
    mirror = ~single & (np.abs(fit_plus - fit_minus) < MIRROR_CHI2) & (other[:, 2] > best[:, 2])
    best = np.where(mirror[:, None], other, best)
    return best[:, :3] + below, best[:, 3], singular


def trilaterate(stations_enu_m, ranges_m, used):
    """Linear trilateration by differencing squared ranges, for a batch; coplanar mirror resolved upwards.

    Each problem's first used range is the reference subtracted from the others.

    Parameters
    ----------
    stations_enu_m : ndarray, shape (B, N, 3)
    ranges_m : ndarray, shape (B, N)
    used : ndarray of bool, shape (B, N)
        At least 3 per problem.

    Returns
    -------
    position_enu_m : ndarray, shape (B, 3)
    collinear : ndarray of bool, shape (B,)
        True where the stations are collinear (the target lies on a circle).
    """
    rows = np.arange(used.shape[0])
    first = np.argmax(used, axis=-1)
    s0, r0 = stations_enu_m[rows, first], ranges_m[rows, first]
    others = used.copy()
    others[rows, first] = False
    a = np.where(others[..., None], 2.0 * (stations_enu_m - s0[:, None, :]), 0.0)
    b = np.where(others, (r0**2)[:, None] - ranges_m**2 + np.sum(stations_enu_m**2, axis=-1)
                 - np.sum(s0**2, axis=-1)[:, None], 0.0)
    sv, v, projected = jacobi_svd(a, b[..., None])
    kept = sv > TRILATERATION_RANK_TOLERANCE * sv.max(axis=-1, keepdims=True)
    rank = np.count_nonzero(kept, axis=-1)
    inverse_s2 = np.where(kept, 1.0 / np.where(kept, sv, 1.0) ** 2, 0.0)
    point = matvec(v, inverse_s2 * projected[..., 0])
    normal = np.take_along_axis(v, np.argmin(sv, axis=-1)[:, None, None], axis=-1)[..., 0]
    normal = normal * np.copysign(1.0, normal[:, 2])[:, None]
    gap = r0**2 - np.sum((point - s0) ** 2, axis=-1)
    lift = (rank == 2) & (gap > 0)
    point = point + np.where(lift, np.sqrt(np.where(lift, gap, 0.0)), 0.0)[:, None] * normal
    return point, rank < 2


def initial_positions(batch: ProblemBatch):
    """A closed-form start for every problem of a batch, by measurement mix (see the module docstring).

    Returns
    -------
    position_enu_m : ndarray, shape (B, 3)
        NaN rows where no start could be found.
    names : list of str or None
        Which start was used (``initial_guess``, ``weighted_eove``, ``polar``,
        ``bancroft``, ``trilateration``); None where none could be found.
    failures : dict of int to LocalizationError
        Why a problem has no start: the weighted EOVE's error for a problem
        with bearings that no other form starts, Bancroft's or
        trilateration's, else TooFewMeasurements.
    """
    found = _Starts(batch)
    for stage in (found.weighted_eove, found.polar, found.bancroft, found.trilateration):
        if not np.count_nonzero(found.pending):
            break
        stage()
    for b in found.pending.nonzero()[0].tolist():
        found.failures[b] = found.eove_failures.get(b) or TooFewMeasurements(
            "too few measurements for a fix: need bearings from 2 stations, a bearing and a range, "
            "4 TOAs or 3 ranges", ("measurements",))
    return found.positions, found.names, found.failures


class _Starts:
    """The starts of a batch's problems, filled stage by stage; each stage takes the problems still pending."""

    def __init__(self, batch: ProblemBatch):
        self.batch = batch
        self.pending = np.isnan(batch.initial_guess_enu_m[:, 0])
        self.positions = np.array(batch.initial_guess_enu_m, dtype=float)  # NaN rows where none was given
        self.names: list[str | None] = [None if p else "initial_guess" for p in self.pending.tolist()]
        self.failures: dict[int, LocalizationError] = {}
        self.eove_failures: dict[int, LocalizationError] = {}

    def settle(self, k, found, name, start):
        """Problems ``k`` take their ``start`` ``(len(k), 3)`` from stage ``name`` where ``found`` (a mask over
        ``k``; None: all of them)."""
        if found is not None:
            k, start = k[found], start[found]
        self.positions[k] = start
        for b in k.tolist():
            self.names[b] = name
        self.pending[k] = False

    def sub(self, k):
        return self.batch if k.size == self.batch.size else self.batch.take(k)

    def _pending_with(self, kind, at_least=1):
        batch = self.batch
        return self.pending & (batch.kind_counts[:, kind] >= at_least)

    def weighted_eove(self):
        k = self._pending_with(AZIMUTH).nonzero()[0]
        if k.size:
            estimates = solve_orthogonal_batch(self.sub(k), normals=Normals.BOTH, weighting=Weighting.FIRST_ORDER,
                                               name="weighted_eove", with_covariance=False, passes=START_PASSES)
            solved = None
            if estimates.errors:
                solved = np.ones(k.size, dtype=bool)
                for j, error in estimates.errors.items():
                    solved[j] = False
                    self.eove_failures[int(k[j])] = error
            self.settle(k, solved, "weighted_eove", estimates.position_enu_m)

    def polar(self):
        k = (self._pending_with(RANGE) & (~np.isnan(self.batch.lines_of_sight()[1])).any(axis=-1)).nonzero()[0]
        if k.size:
            points, information, found = station_polar_points(self.sub(k))
            has = np.any(found, axis=-1)
            if np.any(has):
                fused = np.full((k.size, 3), np.nan)
                fused[has] = fuse_points(points[has], information[has], found[has])[0]
                self.settle(k, has, "polar", fused)

    def bancroft(self):
        k = self._pending_with(TOA, 4).nonzero()[0]
        if k.size:
            part = self.sub(k)
            stations, _ = part.measurement_stations()
            toa = part.valid & (part.kinds == TOA)
            start, _, singular = bancroft(stations, part.model_values(), part.weights(), toa)
            for b in k[singular].tolist():
                self.failures[b] = UnobservableGeometry(
                    "TOA stations are coplanar or too few for an algebraic TDOA solution")
            self.pending[k[singular]] = False
            self.settle(k, ~singular, "bancroft", start)

    def trilateration(self):
        k = self._pending_with(RANGE, 3).nonzero()[0]
        if k.size:
            part = self.sub(k)
            stations, _ = part.measurement_stations()
            start, collinear = trilaterate(stations, part.values, part.valid & (part.kinds == RANGE))
            for b in k[collinear].tolist():
                self.failures[b] = UnobservableGeometry("range stations are collinear: the target lies on a circle")
            self.pending[k[collinear]] = False
            self.settle(k, ~collinear, "trilateration", start)

def initial_position(problem: Problem):
    """One problem's :func:`initial_positions` (a batch of one).

    Returns
    -------
    position_enu_m : ndarray, shape (3,)
    name : str

    Raises
    ------
    LocalizationError
        When no closed form applies.
    """
    positions, names, failures = initial_positions(ProblemBatch.from_problems([problem]))
    if failures:
        raise failures[0]
    return positions[0], names[0]
