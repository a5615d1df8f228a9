"""Fisher information and the Cramer-Rao bound for any measurement mix.

The information is ``J^T W J`` over the parameters ``(east, north, up, b)``
with ``b`` the TOA emission offset (a nuisance, marginalised by inverting the
full matrix). A known altitude removes the local ``up`` direction: the
position is parameterised by its local east/north offsets and the bound is
``L^T (F_en)^-1 L`` (rank 2). Every function carries a leading batch axis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import NamedTuple

import numba
import numpy as np

from core.linalg import gram_point, symmetric_eigen_in_place
from core.measurements import MeasurementModel
from core.problem.frame import frame_placements, local_axes_point

#: Smallest eigenvalue of the unit-diagonal information matrix below which a
#: direction counts as unobserved (relative, so independent of units).
OBSERVABILITY_THRESHOLD = 1e-11


class SandwichScratch(NamedTuple):
    """The work arrays of one problem's :func:`sandwich_point` (``M`` measurements); what it leaves in them is
    of no use after.

    Attributes
    ----------
    local : ndarray, shape (4, M)
        The local Jacobian.
    bread, meat, params, work, vectors : ndarray, shape (4, 4)
        The bread's information, the meat, the bread's inverse and :func:`invert_point`'s scratch.
    """

    local: np.ndarray
    bread: np.ndarray
    meat: np.ndarray
    params: np.ndarray
    work: np.ndarray
    vectors: np.ndarray


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


@numba.njit(cache=True, nogil=True, error_model="numpy")
def parameters_point(position_enu_m, altitude_m, has_toa, geodetic, origin_ecef_m, origin_rotation, axes, free):
    """One problem's :func:`parameterisation` into ``axes`` ``(3, 3)`` and ``free`` ``(4,)``; returns whether
    the altitude is known (compiled)."""
    constrained = not math.isnan(altitude_m)
    if constrained:
        local_axes_point(position_enu_m, geodetic, origin_ecef_m, origin_rotation, axes)
    else:
        for i in range(3):
            for j in range(3):
                axes[i, j] = 1.0 if i == j else 0.0
    free[0] = free[1] = True
    free[2] = not constrained
    free[3] = has_toa
    return constrained


@numba.njit(cache=True, nogil=True, error_model="numpy")
def normal_point(jacobian, weights, axes, rotate, free, local, information):
    """One problem's :func:`normal_matrix`: ``local`` ``(4, M)`` and ``information`` ``(4, 4)`` from its
    ``jacobian`` ``(4, M)`` and ``weights`` ``(M,)``; ``rotate``: move the position along ``axes`` (compiled)."""
    width = weights.size
    for m in range(width):
        for i in range(3):
            if rotate:
                local[i, m] = axes[i, 0] * jacobian[0, m] + axes[i, 1] * jacobian[1, m] + axes[i, 2] * jacobian[2, m]
            else:
                local[i, m] = jacobian[i, m]
        local[3, m] = jacobian[3, m]
        for i in range(4):
            if not free[i]:
                local[i, m] = 0.0
    gram_point(local, weights, information)
    for i in range(4):
        if not free[i]:
            information[i, i] += 1.0


@numba.njit(cache=True, nogil=True, error_model="numpy")
def invert_point(information, axes, rotate, free, params, position, work, vectors):
    """One problem's :func:`invert_information`: ``params`` ``(4, 4)`` and ``position`` ``(3, 3)`` (the
    position block in the common frame); returns the unit-diagonal information's smallest eigenvalue (0
    where a diagonal is not positive or an entry not finite). ``work`` and ``vectors``: ``(4, 4)`` scratch.

    The Jacobi-scaled matrix is inverted through its eigen-decomposition
    (:func:`core.linalg.symmetric_eigen_in_place`), which also gives the
    eigenvalue; an unobservable one's inverse is taken as the identity's.
    """
    size = information.shape[0]
    positive, finite = True, True
    scale = np.empty(size)
    for i in range(size):
        d = information[i, i]
        positive &= d > 0
        scale[i] = 1.0 / math.sqrt(d if d > 0 else 1.0)
    for i in range(size):
        for j in range(size):
            work[i, j] = information[i, j] * scale[i] * scale[j]
            finite &= math.isfinite(work[i, j])
    if not finite:
        for i in range(size):
            for j in range(size):
                work[i, j] = 1.0 if i == j else 0.0
    symmetric_eigen_in_place(work, vectors)
    smallest = work[0, 0]
    for i in range(1, size):
        smallest = min(smallest, work[i, i])
    smallest = smallest if positive and finite else 0.0
    observable = smallest > OBSERVABILITY_THRESHOLD
    for i in range(size):
        for j in range(i + 1):
            if observable:
                total = 0.0
                for k in range(size):
                    total += vectors[i, k] * vectors[j, k] / work[k, k]
            else:
                total = 1.0 if i == j else 0.0
            value = total * scale[i] * scale[j] if free[i] and free[j] else 0.0
            params[i, j] = params[j, i] = value
    rotate_block(params, axes, rotate, position)
    return smallest


@numba.njit(cache=True, nogil=True, error_model="numpy")
def rotate_block(params, axes, rotate, position):
    """The position block of ``params`` ``(4, 4)`` in the common frame, ``axes^T P axes`` when ``rotate``,
    into ``position`` ``(3, 3)`` (symmetrised; compiled)."""
    for i in range(3):
        for j in range(3):
            if rotate:
                total = 0.0
                for k in range(3):
                    for m in range(3):
                        total += axes[k, i] * params[k, m] * axes[m, j]
                position[i, j] = total
            else:
                position[i, j] = params[i, j]
    for i in range(3):
        for j in range(i):
            position[i, j] = position[j, i] = 0.5 * (position[i, j] + position[j, i])


@numba.njit(cache=True, nogil=True, error_model="numpy")
def reference_sigma_point(jacobian, weights):
    """One problem's :func:`reference_sigma_m` from its ``jacobian`` ``(4, M)`` and ``weights`` ``(M,)``."""
    total, count = 0.0, 0
    for m in range(weights.size):
        w = weights[m]
        information = w * (jacobian[0, m] ** 2 + jacobian[1, m] ** 2 + jacobian[2, m] ** 2)
        if w > 0 and math.isfinite(information) and information > 0:
            total += information
            count += 1
    return math.sqrt(count / total) if count > 0 else math.nan


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _parameters_many(positions_enu_m, altitude_m, has_toa, geodetic, origin_ecef_m, origin_rotation):
    size = positions_enu_m.shape[0]
    axes, free = np.empty((size, 3, 3)), np.empty((size, 4), dtype=np.bool_)
    for b in range(size):
        parameters_point(positions_enu_m[b], altitude_m[b], has_toa[b], geodetic[b], origin_ecef_m[b],
                         origin_rotation[b], axes[b], free[b])
    return axes, free


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _normal_many(jacobian, weights, axes, rotate, free):
    size, _, width = jacobian.shape
    local, information = np.empty((size, 4, width)), np.empty((size, 4, 4))
    for b in range(size):
        normal_point(jacobian[b], weights[b], axes[b], rotate, free[b], local[b], information[b])
    return information, local


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _invert_many(information, axes, rotate, free):
    size = information.shape[0]
    params, position, smallest = np.empty((size, 4, 4)), np.empty((size, 3, 3)), np.empty(size)
    work, vectors = np.empty((4, 4)), np.empty((4, 4))
    for b in range(size):
        smallest[b] = invert_point(information[b], axes[b], rotate, free[b], params[b], position[b], work, vectors)
    return params, position, smallest


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _sandwich_many(jacobian, bread_weights, meat_weights, axes, rotate, free):
    size, _, width = jacobian.shape
    scratch = SandwichScratch(np.empty((4, width)), np.empty((4, 4)), np.empty((4, 4)), np.empty((4, 4)),
                              np.empty((4, 4)), np.empty((4, 4)))
    out = np.empty((size, 3, 3))
    for b in range(size):
        sandwich_point(jacobian[b], bread_weights[b], meat_weights[b], axes[b], rotate, free[b], scratch, out[b])
    return out


@numba.njit(cache=True, nogil=True, error_model="numpy")
def sandwich_point(jacobian, bread_weights, meat_weights, axes, rotate, free, scratch, position):
    """One problem's :func:`sandwich_covariance` into ``position`` ``(3, 3)``, with the work arrays ``scratch``
    (:class:`SandwichScratch`; compiled)."""
    local, bread, meat, params = scratch.local, scratch.bread, scratch.meat, scratch.params
    work, vectors = scratch.work, scratch.vectors
    normal_point(jacobian, bread_weights, axes, rotate, free, local, bread)
    invert_point(bread, axes, False, free, params, position, work, vectors)
    gram_point(local, meat_weights, meat)
    for i in range(4):
        for j in range(4):
            total = 0.0
            for k in range(4):
                for m in range(4):
                    total += params[i, k] * meat[k, m] * params[m, j]
            bread[i, j] = total
    rotate_block(bread, axes, rotate, position)


def _axes(axes, size):
    """``(axes, rotate)`` for the kernels: the identity (and no rotation) where ``axes`` is None."""
    if axes is None:
        return np.tile(np.eye(3), (size, 1, 1)), False
    return np.ascontiguousarray(axes, dtype=float), True


def normal_matrix(jacobian, weights, axes, free):
    """``J'^T W J'`` over the local parameters, and the local Jacobian (:func:`normal_point` per problem).

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
    jacobian = np.ascontiguousarray(jacobian, dtype=float)
    axes, rotate = _axes(axes, jacobian.shape[0])
    return _normal_many(jacobian, np.ascontiguousarray(weights, dtype=float), axes, rotate,
                        np.ascontiguousarray(free, dtype=np.bool_))


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
    :func:`reference_sigma_point` per problem.

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
    return _reference_sigmas(np.ascontiguousarray(jacobian, dtype=float), np.ascontiguousarray(weights, dtype=float))


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _reference_sigmas(jacobian, weights):
    out = np.empty(jacobian.shape[0])
    for b in range(out.size):
        out[b] = reference_sigma_point(jacobian[b], weights[b])
    return out


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
    covariance = np.ascontiguousarray(covariance_enu_m2, dtype=float)
    shape = covariance.shape[:-2]
    sigma = np.ascontiguousarray(np.broadcast_to(sigma_ref_m, shape), dtype=float).reshape(-1)
    return _gdop_many(covariance.reshape(-1, 3, 3), sigma).reshape(shape)[()]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def gdop_point(covariance_enu_m2, sigma_ref_m):
    """One :func:`gdop`: ``covariance_enu_m2`` ``(3, 3)``, ``sigma_ref_m`` a float."""
    trace = covariance_enu_m2[0, 0] + covariance_enu_m2[1, 1] + covariance_enu_m2[2, 2]
    return math.sqrt(0.0 if trace < 0.0 else trace) / sigma_ref_m


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _gdop_many(covariance_enu_m2, sigma_ref_m):
    out = np.empty(sigma_ref_m.size)
    for b in range(out.size):
        out[b] = gdop_point(covariance_enu_m2[b], sigma_ref_m[b])
    return out


def invert_information(information, axes, free) -> Information:
    """Invert information matrices with Jacobi scaling and an observability test (:func:`invert_point`).

    ``axes`` as in :func:`normal_matrix` (None: the common frame's axes).
    """
    information = np.ascontiguousarray(information, dtype=float)
    axes, rotate = _axes(axes, information.shape[0])
    params, position, smallest = _invert_many(information, axes, rotate, np.ascontiguousarray(free, dtype=np.bool_))
    return Information(position, params, smallest > OBSERVABILITY_THRESHOLD, smallest)


def sandwich_covariance(jacobian, bread_weights, meat_weights, axes, free):
    """``A^-1 B A^-1`` over the local parameters with ``A = J'^T W_a J'``, ``B = J'^T W_b J'``: the
    position covariance ``(B, 3, 3)`` of a weighted least-squares fit whose weights ``W_a`` are not the
    inverse variances (``W_b = W_a^2 Sigma``). Arguments as in :func:`normal_matrix`; ``A`` is inverted by
    :func:`invert_point` (:func:`sandwich_point` per problem).
    """
    jacobian = np.ascontiguousarray(jacobian, dtype=float)
    axes, rotate = _axes(axes, jacobian.shape[0])
    return _sandwich_many(jacobian, np.ascontiguousarray(bread_weights, dtype=float),
                          np.ascontiguousarray(meat_weights, dtype=float), axes, rotate,
                          np.ascontiguousarray(free, dtype=np.bool_))


def parameterisation(positions_enu_m, altitude_m, has_toa, origin, geodetic, placements=None):
    """Axes and free parameters of the ``(east, north, up, b)`` parameterisation of B problems
    (:func:`parameters_point` per problem).

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
    placements : tuple of ndarray, optional
        :func:`core.problem.frame.frame_placements` of ``origin``, when known.

    Returns
    -------
    axes : ndarray, shape (B, 3, 3), or None
        None when no problem is constrained (the common frame's axes).
    free : ndarray of bool, shape (B, 4)
    """
    positions = np.ascontiguousarray(positions_enu_m, dtype=float).reshape(-1, 3)
    altitude = np.ascontiguousarray(altitude_m, dtype=float)
    origin_ecef, origin_rotation = frame_placements(origin) if placements is None else placements
    axes, free = _parameters_many(positions, altitude, np.ascontiguousarray(has_toa, dtype=np.bool_),
                                  np.ascontiguousarray(geodetic, dtype=np.bool_), origin_ecef, origin_rotation)
    return (axes if np.any(~np.isnan(altitude)) else None), free


def batch_information(batch, positions_enu_m, sigmas=None) -> Information:
    """Inverse Fisher information of every problem of a batch at a position each.

    Parameters
    ----------
    batch : core.problem.batch.ProblemBatch
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
    axes, free = parameterisation(positions_enu_m, batch.altitude_m, batch.has_toa, batch.origin, batch.geodetic,
                                  batch.frame_placements())
    weights = batch.weights(sigmas)
    information, _ = normal_matrix(jacobian, weights, axes, free)
    return replace(invert_information(information, axes, free), reference_sigma_m=reference_sigma_m(jacobian, weights))


def information_at(problem, position_enu_m, sigmas=None) -> Information:
    """Inverse Fisher information of one problem at a position (a batch of one).

    Parameters
    ----------
    problem : core.problem.frame.Problem
        Its kinds, stations and sigmas are used, not its values.
    position_enu_m : ndarray, shape (3,)
    sigmas : ndarray, shape (M,), optional
        Replacement sigmas in problem units.

    Returns
    -------
    Information
        ``covariance_enu_m2[0]`` is the CRLB ``(3, 3)``.
    """
    from core.problem.batch import ProblemBatch

    return batch_information(ProblemBatch.from_problems([problem]), np.reshape(position_enu_m, (1, 3)),
                             None if sigmas is None else np.reshape(sigmas, (1, -1)))
