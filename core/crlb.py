"""Fisher information and the Cramer-Rao bound for any measurement mix.

The information is ``J^T W J`` over the parameters ``(east, north, up, b)``
with ``b`` the TOA emission offset (a nuisance, marginalised by inverting the
full matrix). A known altitude removes the local ``up`` direction: the
position is parameterised by its local east/north offsets and the bound is
``L^T (F_en)^-1 L`` (rank 2). Every function carries a leading batch axis.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.measurements import predict

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
    """

    covariance_enu_m2: np.ndarray
    covariance_params: np.ndarray
    observable: np.ndarray
    min_eigenvalue: np.ndarray


def normal_matrix(jacobian, weights, axes, free):
    """``J'^T W J'`` and the map to local parameters.

    Parameters
    ----------
    jacobian : ndarray, shape (B, M, 4)
        Derivatives w.r.t. (east, north, up, b) in the common frame.
    weights : ndarray, shape (B, M)
        ``1 / sigma^2``; zero for padding.
    axes : ndarray, shape (B, 3, 3)
        Rows: the local east/north/up unit vectors the position moves along.
    free : ndarray of bool, shape (B, 4)
        Which local parameters are estimated.

    Returns
    -------
    information : ndarray, shape (B, 4, 4)
        With frozen rows/columns replaced by the identity.
    local_jacobian : ndarray, shape (B, M, 4)
    """
    local = np.concatenate([jacobian[..., :3] @ np.swapaxes(axes, -1, -2), jacobian[..., 3:]], axis=-1)
    local = local * free[:, None, :]
    information = np.einsum("bmi,bm,bmj->bij", local, weights, local)
    information = information + np.eye(4) * (~free)[:, None, :]
    return information, local


def invert_information(information, axes, free) -> Information:
    """Invert information matrices with Jacobi scaling and an observability test."""
    diag = np.einsum("bii->bi", information)
    scale = 1.0 / np.sqrt(np.where(diag > 0, diag, 1.0))
    scaled = information * scale[:, :, None] * scale[:, None, :]
    eig = np.linalg.eigvalsh(scaled)
    min_eig = np.where(np.all(diag > 0, axis=-1), eig[:, 0], 0.0)
    observable = min_eig > OBSERVABILITY_THRESHOLD
    safe = np.where(observable[:, None, None], scaled, np.eye(4))
    inverse = np.linalg.inv(safe) * scale[:, :, None] * scale[:, None, :]
    inverse = inverse * (free[:, :, None] & free[:, None, :])
    inverse = 0.5 * (inverse + np.swapaxes(inverse, -1, -2))
    position = np.swapaxes(axes, -1, -2) @ inverse[:, :3, :3] @ axes
    return Information(position, inverse, observable, min_eig)


def local_parameterisation(problem, positions_enu_m):
    """Axes and free parameters of the ``(east, north, up, b)`` parameterisation.

    With a known altitude the position moves along the local east and north
    at the current point and ``up`` is frozen; TOA adds the free bias ``b``.

    Parameters
    ----------
    problem : core.problem.Problem
    positions_enu_m : ndarray, shape (B, 3)

    Returns
    -------
    axes : ndarray, shape (B, 3, 3)
    free : ndarray of bool, shape (B, 4)
    """
    positions_enu_m = np.asarray(positions_enu_m, dtype=float).reshape(-1, 3)
    batch = positions_enu_m.shape[0]
    free = np.ones((batch, 4), dtype=bool)
    free[:, 3] = problem.has_toa
    if problem.altitude_m is None:
        return np.broadcast_to(np.eye(3), (batch, 3, 3)), free
    free[:, 2] = False
    return problem.frame.local_axes(positions_enu_m).reshape(batch, 3, 3), free


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
    p = np.asarray(position_enu_m, dtype=float).reshape(1, 3)
    s = problem.station_index
    sig = problem.model_sigmas() if sigmas is None else sigmas * problem.unit_scale()
    _, jac = predict(p, np.zeros(1), problem.stations_enu_m[s][None], problem.station_rotations[s][None],
                     problem.kinds[None])
    axes, free = local_parameterisation(problem, p)
    information, _ = normal_matrix(jac, (1.0 / sig**2)[None], axes, free)
    return invert_information(information, axes, free)
