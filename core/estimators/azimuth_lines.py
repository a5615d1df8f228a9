"""Azimuth lines of sight as linear equations, shared by the pseudolinear estimators.

An azimuth ``az`` measured at station ``r_i`` puts the target in the vertical
plane of the line of sight, whose normal in the station's ENU is
``[cos az, -sin az, 0]`` (the ``c'`` row of paper 000). Rotated into the
common frame it is ``n_i``, and ``n_i . (p - r_i) = 0``. Its derivative with
respect to the azimuth is ``-h_i``, minus the horizontal line-of-sight unit
vector, so an azimuth error ``d`` turns into the equation error
``-d h_i . (p - r_i)``: the pseudolinear noise grows with the distance along
the line of sight.

For the azimuth-only methods with a known target altitude (TLS, CTLS) the
equations are written in two coordinates ``q`` of the tangent plane of the
altitude surface near the target, ``p = centre + axes^T q``; the solution is
put back on the surface and the plane re-taken there (exact on the ellipsoid
after a few passes, exact at once in a flat local frame).

Every pseudolinear method here also shares the test for the geometry they
cannot handle: azimuth lines that are parallel in the horizontal plane
within their noise (the stations' ground track in line with the target's
ground point).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.stats import chi2 as chi2_distribution

from core.errors import InvalidInput, TooFewMeasurements, UnobservableGeometry
from core.measurements import Kind
from core.problem import LinesOfSight, Problem

#: Probability with which azimuth lines from a truly collinear geometry are
#: recognised as such: the crossing test rejects collinearity only when the
#: lines' spread exceeds this quantile of what noise alone gives.
COLLINEAR_CONFIDENCE = 0.99
#: Relative singular value below which noise-free horizontal rows are rank 1.
RANK_TOLERANCE = 1e-9
#: Gauss-Newton steps of the point fit in the crossing test.
POINT_FIT_STEPS = 10
#: Step (rad) of the central differences in :func:`propagate_by_differences`.
DIFFERENCE_STEP_RAD = 1e-6


def azimuth_normals(los: LinesOfSight):
    """Normals of the azimuth planes and horizontal line-of-sight directions.

    Parameters
    ----------
    los : LinesOfSight

    Returns
    -------
    normals_enu : ndarray, shape (K, 3)
        ``n_i``: unit normal of line i's vertical plane, common frame.
    horizontal_enu : ndarray, shape (K, 3)
        ``h_i``: unit horizontal line-of-sight direction (station's
        horizontal plane), common frame; ``d n_i / d az_i = -h_i``.
    """
    az = los.azimuth_rad
    zero = np.zeros_like(az)
    normal_local = np.stack([np.cos(az), -np.sin(az), zero], axis=-1)
    horizontal_local = np.stack([np.sin(az), np.cos(az), zero], axis=-1)
    to_common = np.swapaxes(los.rotations, -1, -2)
    return (np.einsum("kij,kj->ki", to_common, normal_local),
            np.einsum("kij,kj->ki", to_common, horizontal_local))


def _point_chi2(los: LinesOfSight, normals_enu, weights) -> float:
    """Smallest chi-square of the azimuths, as undirected lines, through one horizontal point.

    Weighted pseudolinear start, then Gauss-Newton steps; the best point seen counts.
    """
    up = float(np.mean(los.origins_enu_m[:, 2]))
    rhs = np.einsum("ki,ki->k", normals_enu, los.origins_enu_m) - normals_enu[:, 2] * up
    point = np.append(np.linalg.lstsq(normals_enu[:, :2] * weights[:, None], rhs * weights, rcond=None)[0], up)
    best = np.inf
    for _ in range(POINT_FIT_STEPS):
        local = np.einsum("kij,kj->ki", los.rotations, point - los.origins_enu_m)
        horizontal2 = np.maximum(local[:, 0] ** 2 + local[:, 1] ** 2, 1e-18)
        miss = 0.5 * np.angle(np.exp(2j * (los.azimuth_rad - np.arctan2(local[:, 0], local[:, 1]))))
        chi2 = float(np.sum((miss * weights) ** 2))
        if not chi2 < best * (1.0 - 1e-9):
            best = min(best, chi2)
            break
        best = chi2
        gradient_local = np.stack([local[:, 1], -local[:, 0], np.zeros(los.count)], axis=-1) / horizontal2[:, None]
        jacobian = np.einsum("ki,kij->kj", gradient_local, los.rotations)[:, :2] * weights[:, None]
        point[:2] += np.linalg.lstsq(jacobian, miss * weights, rcond=None)[0]
    return best


def require_crossing(los: LinesOfSight, name: str) -> None:
    """Refuse azimuth lines that do not cross in the horizontal plane.

    Two hypotheses for the measured azimuths: all lines parallel to one
    direction (the stations' ground track in line with the target's ground
    point, or the target at infinity), or all through one point. The
    chi-square of the best parallel fit is the smallest eigenvalue of
    ``sum n n^T / sigma^2`` over the unit horizontal normals ``n``; that of the
    point fit is taken at the weighted pseudolinear intersection. When the
    point explains the azimuths no better than parallel lines do (the
    difference below the :data:`COLLINEAR_CONFIDENCE` quantile of chi-square
    with 1 degree of freedom, which it follows when the lines are truly
    parallel), the horizontal intersection is not determined. Without sigmas
    only exact rank deficiency is refused.

    Parameters
    ----------
    los : LinesOfSight
        Azimuth sigmas NaN where unknown.
    name : str
        The method, for messages.

    Raises
    ------
    TooFewMeasurements
        With fewer than 2 azimuth lines.
    UnobservableGeometry
        When the lines are parallel in the horizontal plane within the noise.
    """
    count = los.count
    if count < 2:
        raise TooFewMeasurements(f"{name} needs azimuths on at least 2 lines of sight; got {count}",
                                 ("measurements",))
    normals, _ = azimuth_normals(los)
    flat = normals[:, :2] / np.linalg.norm(normals[:, :2], axis=-1, keepdims=True)
    eigenvalues = np.linalg.eigvalsh(flat.T @ flat)
    rank_deficient = eigenvalues[0] <= RANK_TOLERANCE * eigenvalues[-1]
    spread_rad = np.sqrt(max(eigenvalues[0], 0.0) / count)
    sigma = los.sigma_azimuth_rad
    gain = threshold = None
    if np.all(np.isfinite(sigma)) and not rank_deficient:
        weighted = flat / sigma[:, None]
        parallel = float(np.linalg.eigvalsh(weighted.T @ weighted)[0])
        point = _point_chi2(los, normals, 1.0 / sigma)
        gain = parallel - point
        threshold = float(chi2_distribution.ppf(COLLINEAR_CONFIDENCE, 1))
    if rank_deficient or (gain is not None and gain < threshold):
        noise = (f"; a common point fits the azimuths better than parallel lines by only chi2 {gain:.2f}, below "
                 f"the {COLLINEAR_CONFIDENCE:.0%} quantile {threshold:.2f} of what noise alone gives"
                 if gain is not None else "")
        raise UnobservableGeometry(
            f"{name}: collinear horizontal geometry: the {count} azimuth lines of sight are parallel in the "
            f"horizontal plane (rms spread {np.rad2deg(spread_rad):.3f} deg{noise}), i.e. the stations' ground "
            "track is in line with the target's ground point, so the azimuths cannot intersect; "
            "eove or ml use the elevations and can")


def azimuth_only_lines(problem: Problem, name: str) -> LinesOfSight:
    """The lines of sight of an azimuth-only method that needs a known target altitude.

    Raises
    ------
    TooFewMeasurements
        Without ``problem.altitude_m``.
    InvalidInput
        With measurements other than bearings.
    """
    if problem.altitude_m is None:
        raise TooFewMeasurements(
            f"{name} locates from azimuths only, which do not determine the target's height: give the "
            "target altitude (constraints.altitude_m); with elevations use eove, taylor_wls or ml",
            ("constraints", "altitude_m"))
    other = np.flatnonzero((problem.kinds == Kind.RANGE) | (problem.kinds == Kind.TOA))
    if other.size:
        raise InvalidInput(
            f"{name} uses bearings only; measurement {int(problem.source_index[other[0]])} is a "
            f"{Kind(problem.kinds[other[0]]).name.lower()}: use ml for a mix",
            ("measurements", int(problem.source_index[other[0]])))
    return problem.lines_of_sight()


@dataclass(frozen=True)
class TangentPlane:
    """Two coordinates on a plane tangent to the target's altitude surface.

    Attributes
    ----------
    centre_enu_m : ndarray, shape (3,)
        Where ``q = 0`` lies: the foot of the stations' centroid on the plane.
    axes_enu : ndarray, shape (2, 3)
        Local east and north unit vectors of the surface, common frame.
    """

    centre_enu_m: np.ndarray
    axes_enu: np.ndarray

    def point(self, plane_m) -> np.ndarray:
        """Common-frame point ``(3,)`` of plane coordinates ``(2,)`` (metres)."""
        return self.centre_enu_m + np.asarray(plane_m) @ self.axes_enu

    def coordinates(self, position_enu_m) -> np.ndarray:
        """Plane coordinates ``(2,)`` of the foot of a point."""
        return self.axes_enu @ (np.asarray(position_enu_m) - self.centre_enu_m)


def tangent_plane(problem: Problem, position_enu_m, stations_enu_m) -> TangentPlane:
    """The plane tangent to the altitude surface at a point, centred under the stations."""
    axes = problem.frame.local_axes(np.asarray(position_enu_m, dtype=float))[:2]
    offset = np.mean(stations_enu_m, axis=0) - position_enu_m
    return TangentPlane(position_enu_m + (axes @ offset) @ axes, axes)


@dataclass(frozen=True)
class AzimuthEquations:
    """Azimuth lines as equations in tangent-plane coordinates.

    ``e_i(q) = A_i . q - b_i = n_i . (p(q) - r_i)`` is the signed distance of
    the plane point from line i's vertical plane, and
    ``rho_i(q) = D_i . q - d_i = h_i . (p(q) - r_i)`` its distance along the
    measured line of sight; ``e_i / rho_i = tan(az_i - azimuth of p)``.

    Attributes
    ----------
    rows, along_rows : ndarray, shape (K, 2)
        ``A`` and ``D``.
    rhs, along_rhs : ndarray, shape (K,)
        ``b`` and ``d`` (metres).
    """

    rows: np.ndarray
    rhs: np.ndarray
    along_rows: np.ndarray
    along_rhs: np.ndarray


def azimuth_equations(los: LinesOfSight, plane: TangentPlane) -> AzimuthEquations:
    """Write every azimuth line as a linear equation in the plane's coordinates."""
    normals, horizontal = azimuth_normals(los)
    relative = los.origins_enu_m - plane.centre_enu_m
    return AzimuthEquations(
        rows=normals @ plane.axes_enu.T,
        rhs=np.einsum("ki,ki->k", normals, relative),
        along_rows=horizontal @ plane.axes_enu.T,
        along_rhs=np.einsum("ki,ki->k", horizontal, relative),
    )


def propagate_by_differences(problem: Problem, position_of_values: Callable[[np.ndarray], np.ndarray],
                             rows=None) -> np.ndarray:
    """First-order covariance of an estimator by central differences in its inputs.

    ``C = G diag(sigma^2) G^T`` with ``G = d position / d measurement``; for
    a closed form this is the first-order propagation of the measurement
    noise through the estimator (evaluated at the measured values).

    Parameters
    ----------
    problem : Problem
    position_of_values : callable
        Measured values ``(M,)`` (problem units) -> position ``(3,)``.
    rows : ndarray of int, optional
        Measurements the estimator reads; default every angle with a sigma.

    Returns
    -------
    ndarray, shape (3, 3)
    """
    if rows is None:
        is_angle = (problem.kinds == Kind.AZIMUTH) | (problem.kinds == Kind.ELEVATION)
        rows = np.flatnonzero(is_angle & np.isfinite(problem.sigmas))
    gain = np.zeros((3, rows.size))
    for column, row in enumerate(rows):
        plus, minus = problem.values.copy(), problem.values.copy()
        plus[row] += DIFFERENCE_STEP_RAD
        minus[row] -= DIFFERENCE_STEP_RAD
        gain[:, column] = (position_of_values(plus) - position_of_values(minus)) / (2 * DIFFERENCE_STEP_RAD)
    return (gain * problem.sigmas[rows] ** 2) @ gain.T
