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

The coarse stage runs over the whole batch at once, the polar points
included (the batched starts' :func:`~core.estimators.starting_points.station_polar_points`
and :func:`~core.estimators.starting_points.fuse_points`).

Fine stage: maximum likelihood (batched Levenberg-Marquardt, section 3) over
every angle and range, started at the coarse point. The covariance is the
inverse Fisher information at the fine fix.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from core.angles import station_to_common
from core.errors import LocalizationError, TooFewMeasurements
from core.estimators.base import SolveOptions, register
from core.estimators.methods.ml import estimate_from
from core.estimators.result import Estimates, FixWarning
from core.estimators.starting_points import fuse_points, initial_position, station_polar_points
from core.measurements import AZIMUTH, RANGE
from core.problem.batch import ProblemBatch

#: Relative eigenvalue below which the azimuth planes do not determine ``(x0, y0)``.
RANK_TOLERANCE = 1e-9
#: Alternations between ``(x0, y0)`` and ``z0`` (the azimuth planes of a
#: curved-earth frame tilt slightly, so ``x0, y0`` depend a little on ``z0``).
COARSE_ROUNDS = 3
#: Weighted spread of the range stations' heights (m) below which the
#: range-difference height is undefined.
MIN_HEIGHT_SPREAD_M = 1e-6


@dataclass(frozen=True)
class CoarseFixes:
    """The coarse stage's points for a batch of B problems, and how each was obtained.

    Attributes
    ----------
    position_enu_m : ndarray, shape (B, 3)
        NaN rows for problems in ``errors``.
    method : list of str or None, length B
        ``"range_difference"`` (the paper's), ``"polar"``, or the name of the
        closed-form start used otherwise.
    warnings : list of tuple of FixWarning, length B
    height_sigma_m : list of dict, length B
        First-order height sigmas of the candidates that were available.
    errors : dict of int to LocalizationError
        Problems without at least one bearing and one range, or whose mix has no coarse form.
    """

    position_enu_m: np.ndarray
    method: list
    warnings: list
    height_sigma_m: list
    errors: dict


def _column_sum(values):
    """``sum_m values[:, m]`` over axis 1, added in column order (padding adds exact zeros: no batch dependence)."""
    total = np.zeros(values.shape[:1] + values.shape[2:])
    for m in range(values.shape[1]):
        total = total + values[:, m]
    return total


class _RangeStations:
    """Per station slot ``(B, N)``: whether it has a range, and its ranges fused by inverse variance."""

    def __init__(self, batch: ProblemBatch):
        is_range = batch.valid & (batch.kinds == RANGE)
        weights = np.where(is_range, 1.0 / np.where(is_range, batch.sigmas, 1.0) ** 2, 0.0)
        slots = (batch.size, batch.stations_enu_m.shape[1])
        total, weighted, count = np.zeros(slots), np.zeros(slots), np.zeros(slots, dtype=int)
        rows = np.arange(batch.size)
        for m in range(batch.kinds.shape[1]):
            station = batch.station_index[:, m]
            total[rows, station] += weights[:, m]
            weighted[rows, station] += weights[:, m] * np.where(is_range[:, m], batch.values[:, m], 0.0)
            count[rows, station] += is_range[:, m]
        self.present = count > 0
        safe = np.where(self.present, total, 1.0)
        self.ranges_m = np.where(self.present, weighted / safe, 0.0)
        self.variances_m2 = 1.0 / safe
        self.positions_enu_m = batch.stations_enu_m
        self.count = np.count_nonzero(self.present, axis=-1)
        heights = self.positions_enu_m[..., 2]
        self.mean_height_m = _column_sum(np.where(self.present, heights, 0.0)) / np.maximum(self.count, 1)
        self.height_span_m = (np.where(self.present, heights, -np.inf).max(axis=-1)
                              - np.where(self.present, heights, np.inf).min(axis=-1))

    def height(self, horizontal_m, horizontal_covariance_m2):
        """``z0`` ``(B,)`` from the differences of squared ranges, its first-order sigma, and where it is defined.

        ``q_k = R_k^2 - r_k^2 - z_k^2 = z^2 - 2 z z_k``; eliminating ``z^2`` by
        the weighted mean over stations (weights ``1 / (2 R_k sigma_k)^2``)
        leaves ``z = sum_k g_k q_k`` with ``g_k = -w_k (z_k - zbar) / (2 sum w (z - zbar)^2)``.
        Undefined with fewer than two range stations or when their heights
        coincide (weighted spread below :data:`MIN_HEIGHT_SPREAD_M`).
        """
        s = self.positions_enu_m
        offset = horizontal_m[:, None, :] - s[..., :2]
        q = self.ranges_m**2 - np.sum(offset**2, axis=-1) - s[..., 2] ** 2
        q_sd = 2.0 * self.ranges_m * np.sqrt(self.variances_m2)
        w = np.where(self.present, 1.0 / np.where(self.present, q_sd, 1.0) ** 2, 0.0)
        total = _column_sum(w)
        safe_total = np.where(total > 0, total, 1.0)
        centred = s[..., 2] - (_column_sum(w * s[..., 2]) / safe_total)[:, None]
        spread = _column_sum(w * centred**2)
        defined = (self.count >= 2) & (spread > total * MIN_HEIGHT_SPREAD_M**2)
        gain = -w * centred / (2.0 * np.where(defined, spread, 1.0))[:, None]
        height = _column_sum(gain * q)
        slope = _column_sum(gain[..., None] * (-2.0 * offset))
        variance = (_column_sum((gain * q_sd) ** 2)
                    + np.einsum("bi,bij,bj->b", slope, horizontal_covariance_m2, slope))
        return height, np.sqrt(variance), defined


class _AzimuthPlanes:
    """The vertical plane of each azimuth row ``(B, M)``, ``normals . p = offsets`` (common frame)."""

    def __init__(self, batch: ProblemBatch):
        self.used = batch.valid & (batch.kinds == AZIMUTH)
        stations, rotations = batch.measurement_stations()
        azimuth = np.where(self.used, batch.values, 0.0)
        cos_az, sin_az = np.cos(azimuth), np.sin(azimuth)
        self.normals = station_to_common(np.stack([cos_az, -sin_az, np.zeros_like(azimuth)], axis=-1), rotations)
        self.offsets = np.sum(self.normals * stations, axis=-1)
        self.origins, self.rotations = stations, rotations
        self.sigmas = np.where(self.used, batch.sigmas, 1.0)
        first = stations[np.arange(batch.size), np.argmax(self.used, axis=-1)]
        self.distinct = np.any(self.used & np.any(stations != first[:, None, :], axis=-1), axis=-1)

    def intersection(self, height_m, previous_m=None):
        """``(x0, y0)`` ``(B, 2)`` at given heights, its covariance ``(B, 2, 2)``, and where it is determined.

        Rows are weighted by ``1 / (sigma_az rho_i)`` with horizontal distances
        ``rho_i`` from ``previous_m`` (unweighted without it).
        """
        a = self.normals[..., :2]
        b = self.offsets - self.normals[..., 2] * height_m[:, None]
        if previous_m is None:
            noise_sd = np.ones(self.used.shape)
        else:
            point = np.concatenate([previous_m, height_m[:, None]], axis=-1)
            seen = np.einsum("bmij,bmj->bmi", self.rotations, point[:, None, :] - self.origins)
            noise_sd = self.sigmas * np.maximum(np.hypot(seen[..., 0], seen[..., 1]), 1.0)
        w = np.where(self.used, 1.0 / noise_sd**2, 0.0)
        normal = _column_sum(a[..., :, None] * (a * w[..., None])[..., None, :])
        finite = np.all(np.isfinite(normal), axis=(-2, -1))
        normal = np.where(finite[:, None, None], normal, np.eye(2))
        eig = np.linalg.eigvalsh(normal)
        determined = self.distinct & finite & (eig[:, 0] > RANK_TOLERANCE * eig[:, -1])
        covariance = np.linalg.inv(np.where(determined[:, None, None], normal, np.eye(2)))
        right = _column_sum(a * (w * b)[..., None])
        return np.einsum("bij,bj->bi", covariance, right), covariance, determined


def _polar_points(batch: ProblemBatch):
    """The per-station polar fixes ``s + R u`` (:func:`~core.estimators.starting_points.station_polar_points`)
    fused by inverse covariance, per problem.

    Returns
    -------
    point_enu_m : ndarray, shape (B, 3)
    covariance_enu_m2 : ndarray, shape (B, 3, 3)
    exists : ndarray of bool, shape (B,)
    """
    points, information, found = station_polar_points(batch)
    exists = np.any(found, axis=-1)
    point, covariance = fuse_points(points, information, found)
    return point, covariance, exists


def coarse_fix(batch: ProblemBatch) -> CoarseFixes:
    """The coarse stage of paper 003 for every problem of a batch, any number of stations.

    Bearings (with or without elevation) and ranges are used; other
    measurements only by the closed-form start of a mix that has no coarse
    form of its own.

    Returns
    -------
    CoarseFixes
        With ``errors``: TooFewMeasurements without at least one bearing and
        one range; a LocalizationError when no coarse form applies to the mix.
    """
    size = batch.size
    n_azimuth, n_range = batch.kind_counts[:, AZIMUTH], batch.kind_counts[:, RANGE]
    errors: dict[int, LocalizationError] = {}
    for b in np.flatnonzero((n_azimuth == 0) | (n_range == 0)).tolist():
        errors[b] = TooFewMeasurements(
            "angle_range needs at least one bearing and one range (use ml for other mixes); got "
            f"{n_azimuth[b]} bearing(s) and {n_range[b]} range(s)", ("measurements",))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        stations = _RangeStations(batch)
        planes = _AzimuthPlanes(batch)
        horizontal, horizontal_covariance, has_horizontal = planes.intersection(stations.mean_height_m)
        height, height_sd, by_ranges = stations.height(horizontal, horizontal_covariance)
        by_ranges &= has_horizontal
        for _ in range(COARSE_ROUNDS):
            height, height_sd, _ = stations.height(horizontal, horizontal_covariance)
            moved, moved_covariance, determined = planes.intersection(height, horizontal)
            update = by_ranges & determined
            horizontal = np.where(update[:, None], moved, horizontal)
            horizontal_covariance = np.where(update[:, None, None], moved_covariance, horizontal_covariance)
        polar, polar_covariance, has_polar = _polar_points(batch)
    polar_sd = np.sqrt(polar_covariance[:, 2, 2])

    use_ranges = by_ranges & (~has_polar | (height_sd <= polar_sd))
    use_polar = ~use_ranges & has_polar
    position = np.where(use_ranges[:, None], np.concatenate([horizontal, height[:, None]], axis=-1),
                        np.where(use_polar[:, None], polar, np.nan))
    failed = np.zeros(size, dtype=bool)
    failed[list(errors)] = True
    method = np.where(failed, None, np.where(use_ranges, "range_difference", np.where(use_polar, "polar", None))).tolist()
    sigmas = [{} if no else {"range_difference": rd, "polar": p} if rd_ok and p_ok else {"range_difference": rd}
              if rd_ok else {"polar": p} if p_ok else {}
              for no, rd_ok, p_ok, rd, p in zip(failed.tolist(), by_ranges.tolist(), has_polar.tolist(),
                                                height_sd.tolist(), polar_sd.tolist())]
    warnings: list[tuple] = [()] * size
    for b in np.flatnonzero(use_polar & has_horizontal & (stations.count >= 2) & ~failed).tolist():
        why = ("the range-difference height is undefined" if not by_ranges[b] else
               f"too little for the range-difference height (sigma {height_sd[b]:.0f} m against {polar_sd[b]:.0f} m "
               "from the polar points)")
        warnings[b] = (FixWarning("coarse_polar_fallback",
                                  f"the range stations' heights span {stations.height_span_m[b]:.0f} m, {why}"),)
    fallback = np.flatnonzero(~use_ranges & ~use_polar & ~failed).tolist()  # no coarse form: closed-form start (rare)
    for b in fallback:
        try:
            start, method[b] = initial_position(replace(batch.problem(b), initial_guess_enu_m=None))
            position[b] = start
        except LocalizationError as error:
            errors[b] = type(error)(
                "angle_range has no coarse fix for this mix: it needs azimuths from 2 stations with ranges from 2 "
                "stations at different heights, or a bearing with elevation and a range at one station, or "
                f"bearings that fix a point on their own ({error.message})", error.loc)
    position[list(errors)] = np.nan
    return CoarseFixes(position, method, warnings, sigmas, errors)


@register("angle_range", "bearings and ranges: analytic coarse fix, then ML from it (paper 003)")
def angle_range(batch: ProblemBatch, options: SolveOptions) -> Estimates:
    """Coarse-then-fine fixes from bearings and ranges (see the module docstring).

    ``coarse_position_enu_m`` holds the coarse point and ``details["coarse"]``
    the coarse form used. A problem without at least one bearing and one
    range, or whose mix has no coarse form, carries a LocalizationError.
    """
    coarse = coarse_fix(batch)
    fine = estimate_from(batch, coarse.position_enu_m, options, [None] * batch.size, coarse.errors)
    details = [{"coarse": name, "coarse_height_sigma_m": sigma, "fine": "ml"} if name is not None else {}
               for name, sigma in zip(coarse.method, coarse.height_sigma_m)]
    return replace(fine, coarse_position_enu_m=coarse.position_enu_m, warnings=coarse.warnings, details=details)
