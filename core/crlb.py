"""Fisher information and the Cramer-Rao bound for any measurement mix.

The information is ``J^T W J`` over the parameters ``(east, north, up, b)``
with ``b`` the TOA emission offset (a nuisance, marginalised by inverting the
full matrix). A known altitude removes the local ``up`` direction: the
position is parameterised by its local east/north offsets and the bound is
``L^T (F_en)^-1 L`` (rank 2). Every function carries a leading batch axis.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from core.linalg import row_sums, weighted_gram
from core.measurements import MeasurementModel
from core.problem import local_axes

#: Smallest eigenvalue of the unit-diagonal information matrix below which a
#: direction counts as unobserved (relative, so independent of units).
OBSERVABILITY_THRESHOLD = 1e-11


@dataclass(frozen=True)
class Information:
    """Inverted information of a batch of problems.

    Attributes
    ----------
    covariance_enu_m2 : ndarray, shape (B, 3, 3)
        Position block of the inverse information, in the common frame.
    covariance_params : ndarray, shape (B, 4, 4)
        Inverse information over the local parameters (zero for frozen ones).
    observable : ndarray of bool, shape (B,)
    min_eigenvalue : ndarray, shape (B,)
        Of the unit-diagonal information; small means nearly unobservable.
    reference_sigma_m : ndarray, shape (B,), or None
        The measurements' metres-equivalent sigma (:func:`reference_sigma_m`), where it was computed.
    """

    covariance_enu_m2: np.ndarray
    covariance_params: np.ndarray
    observable: np.ndarray
    min_eigenvalue: np.ndarray
    reference_sigma_m: np.ndarray | None = None


def normal_matrix(jacobian, weights, axes, free):
    """``J'^T W J'`` over the local parameters, and the local Jacobian.

    Parameters
    ----------
    jacobian : ndarray, shape (B, 4, M)
        Derivatives w.r.t. (east, north, up, b) in the common frame
        (component-first, as :meth:`core.measurements.MeasurementModel.predict` gives them).
    weights : ndarray, shape (B, M)
        ``1 / sigma^2``; zero for padding.
    axes : ndarray, shape (B, 3, 3), or None
        Rows: the local east/north/up unit vectors the position moves along;
        None for the common frame's own axes.
    free : ndarray of bool, shape (B, 4)
        Which local parameters are estimated.

    Returns
    -------
    information : ndarray, shape (B, 4, 4)
        With frozen rows/columns replaced by the identity.
    local_jacobian : ndarray, shape (B, 4, M)
        Zero rows for frozen parameters.
    """
    local = jacobian
    if axes is not None:
        local = jacobian.copy()
        local[:, :3] = axes @ jacobian[:, :3]
    local = local * free[:, :, None]
    information = weighted_gram(local, weights)
    information += np.eye(4) * ~free[:, None, :]
    return information, local


def reference_sigma_m(jacobian, weights):
    """The metres-equivalent sigma of each problem's measurements, the unit of :func:`gdop`.

    Measurement ``i`` (sigma ``s_i`` in its own unit, gradient ``g_i`` with
    respect to the position) moves by ``s_i`` when the position moves by
    ``s_i / |g_i|`` metres along the gradient: that is its metres-equivalent
    sigma ``r_i`` (a range: ``sigma_m``; a TOA: ``c sigma_s``; an azimuth:
    ``sigma_rad`` times the horizontal distance; an elevation: ``sigma_rad``
    times the slant range). The reference is their information mean,
    ``sigma_ref = (mean_i r_i^-2)^-1/2``: the one sigma that, given to every
    measurement, would carry the same total position information. With
    equal ``r_i`` it is that common value, and :func:`gdop` is then the
    classical ``sqrt(trace((H^T H)^-1))`` of unit line-of-sight rows.

    Parameters
    ----------
    jacobian : ndarray, shape (B, 4, M)
        As for :func:`normal_matrix` (rows east, north, up, b).
    weights : ndarray, shape (B, M)
        ``1 / sigma^2`` in model units; zero for padding (left out).

    Returns
    -------
    ndarray, shape (B,)
        NaN where no measurement has a finite, non-zero gradient.
    """
    with np.errstate(invalid="ignore", over="ignore"):
        information = weights * np.sum(jacobian[:, :3] ** 2, axis=1)
    usable = (weights > 0) & np.isfinite(information) & (information > 0)
    total = row_sums(np.where(usable, information, 0.0))
    count = np.count_nonzero(usable, axis=-1)
    return np.where(count > 0, np.sqrt(count / np.where(count > 0, total, 1.0)), np.nan)


def gdop(covariance_enu_m2, sigma_ref_m):
    """Dimensionless geometric dilution of precision ``sqrt(trace(C)) / sigma_ref``.

    Parameters
    ----------
    covariance_enu_m2 : ndarray, shape (B, 3, 3)
        A bound (the CRLB) on the position.
    sigma_ref_m : ndarray, shape (B,)
        From :func:`reference_sigma_m`.

    Returns
    -------
    ndarray, shape (B,)
        The position (not time) dilution; NaN where ``sigma_ref_m`` is.
    """
    trace = np.maximum(np.trace(covariance_enu_m2, axis1=-2, axis2=-1), 0.0)
    return np.sqrt(trace) / sigma_ref_m


def invert_information(information, axes, free) -> Information:
    """Invert information matrices with Jacobi scaling and an observability test.

    ``axes`` as in :func:`normal_matrix` (None: the common frame's axes).
    """
    diag = np.einsum("bii->bi", information)
    scale = 1.0 / np.sqrt(np.where(diag > 0, diag, 1.0))
    scaled = information * scale[:, :, None] * scale[:, None, :]
    finite = np.all(np.isfinite(scaled), axis=(-2, -1))
    scaled = np.where(finite[:, None, None], scaled, np.eye(4))
    eig = np.linalg.eigvalsh(scaled)
    min_eig = np.where(np.all(diag > 0, axis=-1) & finite, eig[:, 0], 0.0)
    observable = min_eig > OBSERVABILITY_THRESHOLD
    safe = np.where(observable[:, None, None], scaled, np.eye(4))
    inverse = np.linalg.inv(safe) * scale[:, :, None] * scale[:, None, :]
    inverse = inverse * (free[:, :, None] & free[:, None, :])
    inverse = 0.5 * (inverse + np.swapaxes(inverse, -1, -2))
    block = inverse[:, :3, :3]
    position = block if axes is None else np.swapaxes(axes, -1, -2) @ block @ axes
    return Information(position, inverse, observable, min_eig)


def sandwich_covariance(jacobian, bread_weights, meat_weights, axes, free):
    """``A^-1 B A^-1`` over the local parameters with ``A = J'^T W_a J'``, ``B = J'^T W_b J'``: the
    position covariance ``(B, 3, 3)`` of a weighted least-squares fit whose weights ``W_a`` are not the
    inverse variances (``W_b = W_a^2 Sigma``). Arguments as in :func:`normal_matrix`; ``A`` is inverted by
    :func:`invert_information`.
    """
    bread, local = normal_matrix(jacobian, bread_weights, axes, free)
    inverse = invert_information(bread, axes, free).covariance_params
    meat = weighted_gram(local, meat_weights)
    params = inverse @ meat @ inverse
    block = 0.5 * (params[:, :3, :3] + np.swapaxes(params[:, :3, :3], -1, -2))
    return block if axes is None else np.swapaxes(axes, -1, -2) @ block @ axes


def parameterisation(positions_enu_m, altitude_m, has_toa, origin, geodetic):
    """Axes and free parameters of the ``(east, north, up, b)`` parameterisation of B problems.

    With a known altitude the position moves along the local east and north
    at the current point and ``up`` is frozen; TOA adds the free bias ``b``.

    Parameters
    ----------
    positions_enu_m : ndarray, shape (B, 3)
    altitude_m : ndarray, shape (B,)
        NaN where unconstrained.
    has_toa : ndarray of bool, shape (B,)
    origin : ndarray, shape (B, 3)
        Each frame's ``(lat_rad, lon_rad, alt_m)``.
    geodetic : ndarray of bool, shape (B,)

    Returns
    -------
    axes : ndarray, shape (B, 3, 3), or None
        None when no problem is constrained (the common frame's axes).
    free : ndarray of bool, shape (B, 4)
    """
    constrained = ~np.isnan(altitude_m)
    free = np.empty((positions_enu_m.shape[0], 4), dtype=bool)
    free[:, :2] = True
    free[:, 2] = ~constrained
    free[:, 3] = has_toa
    if not np.any(constrained):
        return None, free
    axes = np.where(constrained[:, None, None], local_axes(positions_enu_m, origin, geodetic), np.eye(3))
    return axes, free


def batch_information(batch, positions_enu_m, sigmas=None) -> Information:
    """Inverse Fisher information of every problem of a batch at a position each.

    Parameters
    ----------
    batch : core.problem_batch.ProblemBatch
        Its kinds, stations and sigmas are used, not its values.
    positions_enu_m : ndarray, shape (B, 3)
    sigmas : ndarray, shape (B, M), optional
        Replacement sigmas in problem units (NaN: no weight).

    Returns
    -------
    Information
    """
    positions_enu_m = np.asarray(positions_enu_m, dtype=float).reshape(-1, 3)
    stations, rotations = batch.measurement_stations()
    model = MeasurementModel(stations, rotations, batch.kinds)
    _, jacobian = model.predict(positions_enu_m, np.zeros(batch.size))
    axes, free = parameterisation(positions_enu_m, batch.altitude_m, batch.has_toa, batch.origin, batch.geodetic)
    weights = batch.weights(sigmas)
    information, _ = normal_matrix(jacobian, weights, axes, free)
    return replace(invert_information(information, axes, free), reference_sigma_m=reference_sigma_m(jacobian, weights))


def information_at(problem, position_enu_m, sigmas=None) -> Information:
    """Inverse Fisher information of one problem at a position (a batch of one).

    Parameters
    ----------
    problem : core.problem.Problem
        Its kinds, stations and sigmas are used, not its values.
    position_enu_m : ndarray, shape (3,)
    sigmas : ndarray, shape (M,), optional
        Replacement sigmas in problem units.

    Returns
    -------
    Information
        ``covariance_enu_m2[0]`` is the CRLB ``(3, 3)``.
    """
    from core.problem_batch import ProblemBatch

    return batch_information(ProblemBatch.from_problems([problem]), np.reshape(position_enu_m, (1, 3)),
                             None if sigmas is None else np.reshape(sigmas, (1, -1)))
