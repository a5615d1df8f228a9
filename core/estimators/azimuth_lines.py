"""Azimuth lines of sight as linear equations, shared by the pseudolinear estimators, for a whole batch.

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

Everything works on :class:`Lines`, the lines of sight of B problems packed
to K lines each (``mask`` marks the real ones); a function that can refuse a
problem returns ``{row: LocalizationError}`` instead of raising.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
from scipy.stats import chi2 as chi2_distribution

from core.errors import InvalidInput, LocalizationError, TooFewMeasurements, UnobservableGeometry
from core.linalg import gram_eigenvalues_2x2, row_sums
from core.measurements import ELEVATION, KIND_NAMES, RANGE, TOA
from core.problem.batch import ProblemBatch
from core.problem.frame import frame_placements, local_axes_point, onto_altitude

#: Probability with which azimuth lines from a truly collinear geometry are
#: recognised as such: the crossing test rejects collinearity only when the
#: lines' spread exceeds this quantile of what noise alone gives.
COLLINEAR_CONFIDENCE = 0.99
#: Relative singular value below which noise-free horizontal rows are rank 1.
RANK_TOLERANCE = 1e-9
#: Gauss-Newton steps of the point fit in the crossing test.
POINT_FIT_STEPS = 10


@dataclass(frozen=True)
class Lines:
    """The lines of sight of B problems, packed to K per problem in request order.

    Attributes
    ----------
    mask : ndarray of bool, shape (B, K)
        True on real lines; padding holds an identity rotation, zero angles and unit sigmas.
    count : ndarray of int, shape (B,)
    origins_enu_m : ndarray, shape (B, K, 3)
    rotations : ndarray, shape (B, K, 3, 3)
        Station ENU <- common ENU.
    azimuth_rad : ndarray, shape (B, K)
    elevation_rad : ndarray, shape (B, K)
        0 where the bearing has no elevation.
    has_elevation : ndarray of bool, shape (B, K)
    sigma_azimuth_rad, sigma_elevation_rad : ndarray, shape (B, K)
        NaN where not given (1 on padding).
    altitude_m : ndarray, shape (B,)
        NaN where unconstrained.
    origin : ndarray, shape (B, 3)
    geodetic : ndarray of bool, shape (B,)
    """

    mask: np.ndarray
    count: np.ndarray
    origins_enu_m: np.ndarray
    rotations: np.ndarray
    azimuth_rad: np.ndarray
    elevation_rad: np.ndarray
    has_elevation: np.ndarray
    sigma_azimuth_rad: np.ndarray
    sigma_elevation_rad: np.ndarray
    altitude_m: np.ndarray
    origin: np.ndarray
    geodetic: np.ndarray

    @classmethod
    def of(cls, batch: ProblemBatch) -> "Lines":
        """The packed lines of sight of a batch (from :meth:`ProblemBatch.lines_of_sight`)."""
        is_line, elevation, sigma_elevation = batch.lines_of_sight()
        count = np.count_nonzero(is_line, axis=-1)
        # at least 3, so that the SVD of a 2-line TLS matrix [A | b] (K x 3) includes its null vector
        width = max(int(count.max(initial=0)), 3)
        order = np.argsort(~is_line, axis=-1, kind="stable")[:, :width]
        order = np.pad(order, ((0, 0), (0, width - order.shape[1])))
        rows = np.arange(batch.size)[:, None]
        mask = np.arange(width) < count[:, None]
        stations, rotations = batch.measurement_stations()

        def packed(values, fill):
            return np.where(mask, values[rows, order], fill)

        elevation = packed(elevation, np.nan)
        has_elevation = ~np.isnan(elevation)
        return cls(
            mask=mask,
            count=count,
            origins_enu_m=np.where(mask[..., None], stations[rows, order], 0.0),
            rotations=np.where(mask[..., None, None], rotations[rows, order], np.eye(3)),
            azimuth_rad=packed(batch.values, 0.0),
            elevation_rad=np.where(has_elevation, elevation, 0.0),
            has_elevation=has_elevation,
            sigma_azimuth_rad=packed(batch.sigmas, 1.0),
            sigma_elevation_rad=np.where(has_elevation, packed(sigma_elevation, 1.0), 1.0),
            altitude_m=batch.altitude_m,
            origin=batch.origin,
            geodetic=batch.geodetic,
        )

    @property
    def constrained(self) -> np.ndarray:
        return ~np.isnan(self.altitude_m)

    def take(self, rows) -> "Lines":
        """The lines of the problems ``rows``."""
        return Lines(**{name: getattr(self, name)[rows] for name in self.__dataclass_fields__})

    def onto_altitude(self, position_enu_m) -> np.ndarray:
        """Points ``(B, ..., 3)`` moved onto each problem's known altitude."""
        extra = np.ndim(position_enu_m) - 2
        index = (slice(None),) + (None,) * extra
        return onto_altitude(position_enu_m, self.altitude_m[index], self.origin[index], self.geodetic[index])


def azimuth_normals(lines: Lines):
    """Normals of the azimuth planes and horizontal line-of-sight directions (:func:`azimuth_directions_point`).

    Returns
    -------
    normals_enu : ndarray, shape (B, K, 3)
        ``n_i``: unit normal of line i's vertical plane, common frame.
    horizontal_enu : ndarray, shape (B, K, 3)
        ``h_i``: unit horizontal line-of-sight direction (station's
        horizontal plane), common frame; ``d n_i / d az_i = -h_i``.
    """
    normals, horizontal = np.empty(lines.origins_enu_m.shape), np.empty(lines.origins_enu_m.shape)
    _azimuth_directions_kernel(np.ascontiguousarray(lines.azimuth_rad), np.ascontiguousarray(lines.rotations),
                               normals, horizontal)
    return normals, horizontal


@numba.njit(cache=True, nogil=True, error_model="numpy")
def azimuth_directions_point(azimuth_rad, rotation, normal, horizontal):
    """One line's azimuth-plane normal and horizontal line-of-sight direction in the common frame, written
    into ``normal`` and ``horizontal`` ``(3,)``, from its azimuth and its station's rotation ``(3, 3)``
    (station ENU <- common ENU); the one coding of both (compiled)."""
    c, s = math.cos(azimuth_rad), math.sin(azimuth_rad)
    for i in range(3):
        normal[i] = c * rotation[0, i] - s * rotation[1, i]
        horizontal[i] = s * rotation[0, i] + c * rotation[1, i]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _azimuth_directions_kernel(azimuth_rad, rotations, normals, horizontal):
    size, width = azimuth_rad.shape
    for b in range(size):
        for k in range(width):
            azimuth_directions_point(azimuth_rad[b, k], rotations[b, k], normals[b, k], horizontal[b, k])


def _point_chi2(lines: Lines, normals_enu, weights) -> np.ndarray:
    """Smallest chi-square ``(B,)`` of the azimuths, as undirected lines, through one horizontal point.

    Weighted pseudolinear start, then Gauss-Newton steps; the best point seen counts (compiled, one
    problem at a time).
    """
    best = np.empty(lines.mask.shape[0])
    _point_chi2_kernel(lines.count, np.ascontiguousarray(lines.origins_enu_m), np.ascontiguousarray(lines.rotations),
                       np.ascontiguousarray(lines.azimuth_rad), np.ascontiguousarray(normals_enu),
                       np.ascontiguousarray(weights, dtype=float), best)
    return best


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _weighted_fit_point(column0, column1, rhs, weights):
    """Weighted least squares ``(x0, x1)`` of ``[column0 column1] x = rhs``, all ``(n,)``, by its normal
    equations (a singular system gives inf or NaN)."""
    a00 = a01 = a11 = r0 = r1 = 0.0
    for k in range(column0.size):
        w2 = weights[k] * weights[k]
        a00 += w2 * column0[k] * column0[k]
        a11 += w2 * column1[k] * column1[k]
        a01 += w2 * column0[k] * column1[k]
        r0 += w2 * column0[k] * rhs[k]
        r1 += w2 * column1[k] * rhs[k]
    inverse_det = 1.0 / (a00 * a11 - a01 * a01)
    return (a11 * r0 - a01 * r1) * inverse_det, (a00 * r1 - a01 * r0) * inverse_det


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _point_chi2_kernel(count, origins, rotations, azimuth, normals, weights, best):
    """:func:`_point_chi2` of every problem into ``best`` ``(B,)``."""
    for b in range(count.size):
        n = count[b]
        up = 0.0
        for k in range(n):
            up += origins[b, k, 2]
        up /= max(n, 1)
        rhs = np.empty(n)
        for k in range(n):
            rhs[k] = (normals[b, k, 0] * origins[b, k, 0] + normals[b, k, 1] * origins[b, k, 1]
                      + normals[b, k, 2] * origins[b, k, 2]) - normals[b, k, 2] * up
        east0, north0 = _weighted_fit_point(normals[b, :n, 0], normals[b, :n, 1], rhs, weights[b, :n])
        point = np.array([east0, north0, up])
        miss, jacobian0, jacobian1 = np.empty(n), np.empty(n), np.empty(n)
        best[b] = np.inf
        for _ in range(POINT_FIT_STEPS):
            chi2 = 0.0
            for k in range(n):
                east = north = 0.0
                for i in range(3):
                    delta = point[i] - origins[b, k, i]
                    east += rotations[b, k, 0, i] * delta
                    north += rotations[b, k, 1, i] * delta
                horizontal2 = max(east * east + north * north, 1e-18)
                twice = 2.0 * (azimuth[b, k] - math.atan2(east, north))
                miss[k] = 0.5 * math.atan2(math.sin(twice), math.cos(twice))
                chi2 += (miss[k] * weights[b, k]) ** 2
                jacobian0[k] = (north * rotations[b, k, 0, 0] - east * rotations[b, k, 1, 0]) / horizontal2
                jacobian1[k] = (north * rotations[b, k, 0, 1] - east * rotations[b, k, 1, 1]) / horizontal2
            if not chi2 < best[b] * (1.0 - 1e-9):
                best[b] = min(best[b], chi2)
                break
            best[b] = chi2
            step0, step1 = _weighted_fit_point(jacobian0, jacobian1, miss, weights[b, :n])
            point[0] += step0
            point[1] += step1


def crossing_errors(lines: Lines, name: str) -> dict[int, LocalizationError]:
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
    lines : Lines
        Azimuth sigmas NaN where unknown.
    name : str
        The method, for messages.

    Returns
    -------
    dict of int to LocalizationError
        ``TooFewMeasurements`` with fewer than 2 azimuth lines,
        ``UnobservableGeometry`` when the lines are parallel in the horizontal
        plane within the noise.
    """
    errors: dict[int, LocalizationError] = {}
    count = lines.count
    for b in np.flatnonzero(count < 2).tolist():
        errors[b] = TooFewMeasurements(f"{name} needs azimuths on at least 2 lines of sight; got {int(count[b])}",
                                       ("measurements",))
    mask = lines.mask
    normals, _ = azimuth_normals(lines)
    flat = normals[..., :2] / np.linalg.norm(normals[..., :2], axis=-1, keepdims=True) * mask[..., None]
    eigenvalues = gram_eigenvalues_2x2(flat)
    rank_deficient = (eigenvalues[:, 0] <= RANK_TOLERANCE * eigenvalues[:, -1]) & (count >= 2)
    spread_rad = np.sqrt(np.maximum(eigenvalues[:, 0], 0.0) / np.maximum(count, 1))
    sigma = lines.sigma_azimuth_rad
    tested = np.all(np.isfinite(sigma), axis=-1) & ~rank_deficient & (count >= 2)
    gain = np.full(count.shape, np.nan)
    threshold = float(chi2_distribution.ppf(COLLINEAR_CONFIDENCE, 1))
    rows = np.flatnonzero(tested)
    if rows.size:
        part = lines.take(rows)
        weights = np.where(part.mask, 1.0 / part.sigma_azimuth_rad, 0.0)
        weighted = flat[rows] * weights[..., None]
        parallel = gram_eigenvalues_2x2(weighted)[:, 0]
        gain[rows] = parallel - _point_chi2(part, normals[rows], weights)
    refused = rank_deficient | (tested & (gain < threshold))
    for b in np.flatnonzero(refused).tolist():
        noise = (f"; a common point fits the azimuths better than parallel lines by only chi2 {gain[b]:.2f}, below "
                 f"the {COLLINEAR_CONFIDENCE:.0%} quantile {threshold:.2f} of what noise alone gives"
                 if tested[b] else "")
        errors[b] = UnobservableGeometry(
            f"{name}: collinear horizontal geometry: the {int(count[b])} azimuth lines of sight are parallel in the "
            f"horizontal plane (rms spread {np.rad2deg(spread_rad[b]):.3f} deg{noise}), i.e. the stations' ground "
            "track is in line with the target's ground point, so the azimuths cannot intersect; "
            "eove or ml use the elevations and can")
    return errors


def azimuth_only_errors(batch: ProblemBatch, name: str) -> dict[int, LocalizationError]:
    """Refusals of an azimuth-only method that needs a known target altitude.

    Returns
    -------
    dict of int to LocalizationError
        ``TooFewMeasurements`` without an altitude, ``InvalidInput`` naming the
        first measurement other than a bearing.
    """
    errors: dict[int, LocalizationError] = {}
    for b in np.flatnonzero(~batch.constrained).tolist():
        errors[b] = TooFewMeasurements(
            f"{name} locates from azimuths only, which do not determine the target's height: give the "
            "target altitude (constraints.altitude_m); with elevations use eove, taylor_wls or ml",
            ("altitude_m",))
    other = batch.valid & ((batch.kinds == RANGE) | (batch.kinds == TOA))
    for b in np.flatnonzero(batch.constrained & np.any(other, axis=-1)).tolist():
        m = int(np.flatnonzero(other[b])[0])
        source = int(batch.source_index[b, m])
        errors[b] = InvalidInput(
            f"{name} uses bearings only; measurement {source} is a {KIND_NAMES[batch.kinds[b, m]]}: "
            "use ml for a mix", ("measurements", source))
    return errors


def has_elevations(batch: ProblemBatch) -> np.ndarray:
    """``(B,)``: some bearing carries an elevation."""
    return batch.kind_counts[:, ELEVATION] > 0


@dataclass(frozen=True)
class TangentPlane:
    """Two coordinates on planes tangent to the targets' altitude surfaces, one per problem.

    Attributes
    ----------
    centre_enu_m : ndarray, shape (B, 3)
        Where ``q = 0`` lies: the foot of the stations' centroid on the plane.
    axes_enu : ndarray, shape (B, 2, 3)
        Local east and north unit vectors of the surface, common frame.
    """

    centre_enu_m: np.ndarray
    axes_enu: np.ndarray

    def point(self, plane_m) -> np.ndarray:
        """Common-frame points ``(B, 3)`` of plane coordinates ``(B, 2)`` (metres)."""
        return self.centre_enu_m + np.einsum("bi,bij->bj", plane_m, self.axes_enu)

    def coordinates(self, position_enu_m) -> np.ndarray:
        """Plane coordinates ``(B, ..., 2)`` of the feet of points ``(B, ..., 3)``."""
        extra = (slice(None),) + (None,) * (np.ndim(position_enu_m) - 2)
        relative = position_enu_m - self.centre_enu_m[extra]
        return np.einsum("bij,b...j->b...i", self.axes_enu, relative)

    def to_common(self, covariance_plane_m2) -> np.ndarray:
        """Plane covariances ``(B, 2, 2)`` as common-frame covariances ``(B, 3, 3)``."""
        return np.einsum("bki,bkl,blj->bij", self.axes_enu, covariance_plane_m2, self.axes_enu)


def plane_and_equations(lines: Lines, position_enu_m) -> tuple[TangentPlane, AzimuthEquations]:
    """The planes tangent to the altitude surfaces at points ``(B, 3)``, centred under the stations (the foot
    of the stations' centroid), and every azimuth line written as a linear equation in their coordinates
    (compiled, one problem at a time)."""
    origin_ecef_m, origin_rotation = frame_placements(lines.origin)
    centre, axes, rows, rhs, along_rows, along_rhs = _plane_equations_kernel(
        lines.count, np.ascontiguousarray(lines.origins_enu_m), np.ascontiguousarray(lines.rotations),
        np.ascontiguousarray(lines.azimuth_rad), np.ascontiguousarray(position_enu_m, dtype=float),
        np.ascontiguousarray(lines.geodetic), np.ascontiguousarray(origin_ecef_m),
        np.ascontiguousarray(origin_rotation))
    return TangentPlane(centre, axes), AzimuthEquations(rows, rhs, along_rows, along_rhs)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _plane_equations_kernel(count, origins, rotations, azimuth, position, geodetic, origin_ecef_m, origin_rotation):
    """Each problem's tangent plane (``centre`` ``(B, 3)``, ``axes`` ``(B, 2, 3)``) and its lines' equations
    (``rows``, ``rhs``, ``along_rows``, ``along_rhs``: :class:`AzimuthEquations`), see :func:`plane_and_equations`;
    the equations of padding lines are zero."""
    size, width = azimuth.shape
    centre, axes = np.empty((size, 3)), np.empty((size, 2, 3))
    rows, along_rows = np.zeros((size, width, 2)), np.zeros((size, width, 2))
    rhs, along_rhs = np.zeros((size, width)), np.zeros((size, width))
    local = np.empty((3, 3))
    normal, horizontal = np.empty(3), np.empty(3)
    for b in range(count.size):
        n = count[b]
        local_axes_point(position[b], geodetic[b], origin_ecef_m[b], origin_rotation[b], local)
        mean = np.zeros(3)
        for k in range(n):
            for j in range(3):
                mean[j] += origins[b, k, j]
        for j in range(3):
            mean[j] = mean[j] / max(n, 1) - position[b, j]
        along0 = local[0, 0] * mean[0] + local[0, 1] * mean[1] + local[0, 2] * mean[2]
        along1 = local[1, 0] * mean[0] + local[1, 1] * mean[1] + local[1, 2] * mean[2]
        for j in range(3):
            axes[b, 0, j], axes[b, 1, j] = local[0, j], local[1, j]
            centre[b, j] = position[b, j] + (along0 * local[0, j] + along1 * local[1, j])
        for k in range(n):
            azimuth_directions_point(azimuth[b, k], rotations[b, k], normal, horizontal)
            r0, r1 = rhs[b, k], along_rhs[b, k]
            for j in range(3):
                relative = origins[b, k, j] - centre[b, j]
                for i in range(2):
                    rows[b, k, i] += normal[j] * local[i, j]
                    along_rows[b, k, i] += horizontal[j] * local[i, j]
                r0 += normal[j] * relative
                r1 += horizontal[j] * relative
            rhs[b, k], along_rhs[b, k] = r0, r1
    return centre, axes, rows, rhs, along_rows, along_rhs


def plane_spread_m(lines: Lines, plane: TangentPlane) -> np.ndarray:
    """RMS distance ``(B,)`` of the stations from the plane's centre (at least 1 m)."""
    offsets = plane.coordinates(lines.origins_enu_m) * lines.mask[..., None]
    squares = (offsets**2).reshape(offsets.shape[0], offsets.shape[1] * offsets.shape[2])
    return np.maximum(np.sqrt(row_sums(squares) / np.maximum(lines.count, 1)), 1.0)


@dataclass(frozen=True)
class AzimuthEquations:
    """Azimuth lines as equations in tangent-plane coordinates (zero rows on padding).

    ``e_i(q) = A_i . q - b_i = n_i . (p(q) - r_i)`` is the signed distance of
    the plane point from line i's vertical plane, and
    ``rho_i(q) = D_i . q - d_i = h_i . (p(q) - r_i)`` its distance along the
    measured line of sight; ``e_i / rho_i = tan(az_i - azimuth of p)``.

    Attributes
    ----------
    rows, along_rows : ndarray, shape (B, K, 2)
        ``A`` and ``D``.
    rhs, along_rhs : ndarray, shape (B, K)
        ``b`` and ``d`` (metres).
    """

    rows: np.ndarray
    rhs: np.ndarray
    along_rows: np.ndarray
    along_rhs: np.ndarray
