"""Angle and range, coarse then fine (paper 003, ALGORITHMS.md section 7).

Coarse stage, in the common frame:

- ``x0, y0`` from the intersection of the azimuth lines (each azimuth is a
  vertical plane through its station; with more than two, their weighted
  least-squares intersection, weights ``1 / (sigma_az rho_i)``);
- ``z0`` from the differences of squared ranges,
  ``R_k^2 - r_k^2 - z_k^2 = z^2 - 2 z z_k`` with ``r_k`` the horizontal
  distance from ``(x0, y0)``: linear in ``(z^2, z)``, and for two stations
  exactly the paper's ``z0 = (R1^2 - R2^2 - r1^2 + r2^2 - z1^2 + z2^2) / (2 (z2 - z1))``.

That height divides by the stations' height differences. Its first-order
sigma (range noise and the horizontal error through ``r_k``) is compared
with the height sigma of the per-station polar points ``s_k + R_k u_k``
(stations with a bearing with elevation and a range, fused by inverse
covariance); when the stations are so nearly at one height that the polar
points are better, they are the coarse fix instead, with the warning
``coarse_polar_fallback``. Mixes without two azimuth lines or two range
stations use the polar points, else the usual closed-form start
(:func:`core.estimators.starting_points.initial_position`). ``details["coarse"]``
says which ran.

Fine stage: maximum likelihood (batched Levenberg-Marquardt, section 3) over
every angle and range, started at the coarse point. The covariance is the
inverse Fisher information at the fine fix.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from core.errors import LocalizationError, TooFewMeasurements
from core.batch import ProblemBatch
from core.estimators.base import SolveOptions, register
from core.estimators.result import Estimates, FixWarning
from core.estimators.ml import estimate_from
from core.estimators.orthogonal_vector import orthogonal_rows
from core.estimators.starting_points import fuse_points, initial_position, polar_points
from core.measurements import Kind
from core.problem import Problem

#: Relative eigenvalue below which the azimuth planes do not determine ``(x0, y0)``.
RANK_TOLERANCE = 1e-9
#: Alternations between ``(x0, y0)`` and ``z0`` (the azimuth planes of a
#: curved-earth frame tilt slightly, so ``x0, y0`` depend a little on ``z0``).
COARSE_ROUNDS = 3
#: Weighted spread of the range stations' heights (m) below which the
#: range-difference height is undefined.
MIN_HEIGHT_SPREAD_M = 1e-6


@dataclass(frozen=True)
class CoarseFix:
    """The coarse stage's point and how it was obtained.

    Attributes
    ----------
    position_enu_m : ndarray, shape (3,)
    method : str
        ``"range_difference"`` (the paper's), ``"polar"``, or the name of the
        closed-form start used otherwise.
    warnings : tuple of FixWarning
    height_sigma_m : dict
        First-order height sigmas of the candidates that were available.
    """

    position_enu_m: np.ndarray
    method: str
    warnings: tuple[FixWarning, ...] = ()
    height_sigma_m: dict | None = None


@dataclass(frozen=True)
class _RangeStations:
    """Stations with a range, each range fused over the station by inverse variance.

    Attributes
    ----------
    index : ndarray of int, shape (S,)
    positions_enu_m : ndarray, shape (S, 3)
    ranges_m, sigmas_m : ndarray, shape (S,)
    """

    index: np.ndarray
    positions_enu_m: np.ndarray
    ranges_m: np.ndarray
    sigmas_m: np.ndarray

    @classmethod
    def from_problem(cls, problem: Problem) -> "_RangeStations":
        is_range = problem.kinds == Kind.RANGE
        index = np.unique(problem.station_index[is_range])
        weights = 1.0 / problem.sigmas[is_range] ** 2
        slot = np.searchsorted(index, problem.station_index[is_range])
        total = np.bincount(slot, weights, minlength=index.size)
        ranges = np.bincount(slot, weights * problem.values[is_range], minlength=index.size) / total
        return cls(index, problem.stations_enu_m[index], ranges, 1.0 / np.sqrt(total))


@dataclass(frozen=True)
class _AzimuthPlanes:
    """The vertical plane of each azimuth, ``normals_enu . p = offsets_m`` (common frame).

    Attributes
    ----------
    normals_enu : ndarray, shape (K, 3)
    offsets_m : ndarray, shape (K,)
    origins_enu_m : ndarray, shape (K, 3)
    rotations : ndarray, shape (K, 3, 3)
    sigma_azimuth_rad : ndarray, shape (K,)
    """

    normals_enu: np.ndarray
    offsets_m: np.ndarray
    origins_enu_m: np.ndarray
    rotations: np.ndarray
    sigma_azimuth_rad: np.ndarray

    @classmethod
    def from_problem(cls, problem: Problem) -> "_AzimuthPlanes":
        los = problem.lines_of_sight()
        rows, rhs, line, _ = orthogonal_rows(los, use_vertical=False, use_horizontal=True)
        return cls(rows, rhs, los.origins_enu_m[line], los.rotations[line], los.sigma_azimuth_rad[line])

    def intersection(self, height_m: float, previous_m=None):
        """``(x0, y0)`` at a given height and its covariance ``(2, 2)``; None if undetermined.

        Rows are weighted by ``1 / (sigma_az rho_i)`` with horizontal distances
        ``rho_i`` from ``previous_m`` (unweighted without it).
        """
        if np.unique(self.origins_enu_m, axis=0).shape[0] < 2:
            return None
        a = self.normals_enu[:, :2]
        b = self.offsets_m - self.normals_enu[:, 2] * height_m
        if previous_m is None:
            noise_sd = np.ones(a.shape[0])
        else:
            seen = np.einsum("kij,kj->ki", self.rotations, np.append(previous_m, height_m) - self.origins_enu_m)
            noise_sd = self.sigma_azimuth_rad * np.maximum(np.hypot(seen[:, 0], seen[:, 1]), 1.0)
        w = 1.0 / noise_sd**2
        normal = a.T @ (a * w[:, None])
        eig = np.linalg.eigvalsh(normal)
        if eig[0] <= RANK_TOLERANCE * eig[-1]:
            return None
        covariance = np.linalg.inv(normal)
        return covariance @ (a.T @ (w * b)), covariance


def _height_from_ranges(stations: _RangeStations, horizontal_m, horizontal_covariance_m2):
    """``z0`` from the differences of squared ranges, and its first-order sigma.

    ``q_k = R_k^2 - r_k^2 - z_k^2 = z^2 - 2 z z_k``; eliminating ``z^2`` by
    the weighted mean over stations (weights ``1 / (2 R_k sigma_k)^2``) leaves
    ``z = sum_k g_k q_k`` with ``g_k = -w_k (z_k - zbar) / (2 sum w (z - zbar)^2)``.

    Returns None with fewer than two range stations or when their heights
    coincide (weighted spread below :data:`MIN_HEIGHT_SPREAD_M`).
    """
    if stations.index.size < 2:
        return None
    s = stations.positions_enu_m
    offset = horizontal_m - s[:, :2]
    q = stations.ranges_m**2 - np.sum(offset**2, axis=1) - s[:, 2] ** 2
    q_sd = 2.0 * stations.ranges_m * stations.sigmas_m
    w = 1.0 / q_sd**2
    centred = s[:, 2] - np.sum(w * s[:, 2]) / np.sum(w)
    spread = np.sum(w * centred**2)
    if spread <= np.sum(w) * MIN_HEIGHT_SPREAD_M**2:
        return None
    gain = -w * centred / (2.0 * spread)
    height = float(gain @ q)
    d_height_d_horizontal = gain @ (-2.0 * offset)
    variance = float(np.sum((gain * q_sd) ** 2) + d_height_d_horizontal @ horizontal_covariance_m2 @ d_height_d_horizontal)
    return height, np.sqrt(variance)


def coarse_fix(problem: Problem) -> CoarseFix:
    """The coarse stage of paper 003 for any number of stations.

    Parameters
    ----------
    problem : Problem
        Bearings (with or without elevation) and ranges; other measurements
        are not used by this stage.

    Returns
    -------
    CoarseFix

    Raises
    ------
    TooFewMeasurements
        Without at least one bearing and one range.
    LocalizationError
        When no coarse form applies to the mix.
    """
    if problem.count(Kind.AZIMUTH) == 0 or problem.count(Kind.RANGE) == 0:
        raise TooFewMeasurements(
            "angle_range needs at least one bearing and one range (use ml for other mixes); got "
            f"{problem.count(Kind.AZIMUTH)} bearing(s) and {problem.count(Kind.RANGE)} range(s)", ("measurements",))
    range_stations = _RangeStations.from_problem(problem)
    heights = range_stations.positions_enu_m[:, 2]
    planes = _AzimuthPlanes.from_problem(problem)
    horizontal = planes.intersection(float(np.mean(heights)))
    by_ranges = None
    if horizontal is not None:
        for _ in range(COARSE_ROUNDS):
            by_ranges = _height_from_ranges(range_stations, *horizontal)
            if by_ranges is None:
                break
            horizontal = planes.intersection(by_ranges[0], horizontal[0]) or horizontal

    points, covariances = polar_points(problem)
    polar = fuse_points(points, covariances) if len(points) else None
    sigmas = {}
    if by_ranges is not None:
        sigmas["range_difference"] = float(by_ranges[1])
    if polar is not None:
        sigmas["polar"] = float(np.sqrt(polar[1][2, 2]))

    if by_ranges is not None and (polar is None or sigmas["range_difference"] <= sigmas["polar"]):
        return CoarseFix(np.append(horizontal[0], by_ranges[0]), "range_difference", (), sigmas)
    if polar is not None:
        warnings = ()
        if horizontal is not None and range_stations.index.size >= 2:
            spread = float(np.ptp(heights))
            if by_ranges is None:
                why = "the range-difference height is undefined"
            else:
                why = (f"too little for the range-difference height (sigma {sigmas['range_difference']:.0f} m "
                       f"against {sigmas['polar']:.0f} m from the polar points)")
            warnings = (FixWarning("coarse_polar_fallback",
                                   f"the range stations' heights span {spread:.0f} m, {why}"),)
        return CoarseFix(polar[0], "polar", warnings, sigmas)
    try:
        position, name = initial_position(replace(problem, initial_guess_enu_m=None))
    except LocalizationError as error:
        raise type(error)(
            "angle_range has no coarse fix for this mix: it needs azimuths from 2 stations with ranges from 2 "
            "stations at different heights, or a bearing with elevation and a range at one station, or bearings "
            f"that fix a point on their own ({error.message})", error.loc) from error
    return CoarseFix(np.asarray(position, dtype=float), name, (), sigmas)


@register("angle_range", "bearings and ranges: analytic coarse fix, then ML from it (paper 003)")
def angle_range(batch: ProblemBatch, options: SolveOptions) -> Estimates:
    """Coarse-then-fine fixes from bearings and ranges (see the module docstring).

    ``coarse_position_enu_m`` holds the coarse point and ``details["coarse"]``
    the coarse form used. A problem without at least one bearing and one
    range, or whose mix has no coarse form, carries a LocalizationError.
    """
    size = batch.size
    starts = np.full((size, 3), np.nan)
    failures: dict[int, LocalizationError] = {}
    coarse: dict[int, CoarseFix] = {}
    for b in range(size):
        try:
            coarse[b] = coarse_fix(batch.problem(b))
            starts[b] = coarse[b].position_enu_m
        except LocalizationError as error:
            failures[b] = error
    fine = estimate_from(batch, starts, options, [None] * size, failures)
    warnings = [coarse[b].warnings if b in coarse else () for b in range(size)]
    details = [{"coarse": coarse[b].method, "coarse_height_sigma_m": coarse[b].height_sigma_m, "fine": "ml"}
               if b in coarse else {} for b in range(size)]
    return replace(fine, coarse_position_enu_m=starts, warnings=warnings, details=details)
