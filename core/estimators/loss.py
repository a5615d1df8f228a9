"""Robust losses with scipy's names and meanings (``scipy.optimize.least_squares(loss=..., f_scale=...)``).

A loss ``rho`` replaces each squared whitened residual ``z = (r / sigma)^2``
in the cost: ``sum C^2 rho(z / C^2)`` with the scale ``C`` in sigmas (scipy's
``f_scale`` applied to whitened residuals). ``linear`` is plain least squares.
The cost here is scipy's times two, so that with ``linear`` it is chi-square.

The Levenberg-Marquardt iteration (:mod:`core.estimators.lm`) uses the loss as
scipy does: the gradient weights each measurement by ``rho'``, the Gauss-Newton
matrix by ``rho' + 2 rho'' z`` (floored at machine epsilon: a measurement past
the loss's bend adds no curvature). Its steps are Jacobi-scaled by the larger
of that matrix's diagonal and the one weighted by ``rho'``: when every
residual is past the bend the first vanishes, and the damping, relative to
it, no longer shortened the steps (the fit stopped short of its minimum).
"""

from __future__ import annotations

import math

import numba
import numpy as np

#: The losses, as ``options.loss`` and scipy name them.
LOSSES = ("linear", "huber", "soft_l1", "cauchy", "arctan")
#: The losses whose ``rho`` stops growing (a measurement far enough out loses all its weight): they have a minimum
#: for each subset of measurements they set aside.
REDESCENDING = ("cauchy", "arctan")
#: Floor of a measurement's Gauss-Newton weight factor (scipy's ``EPS``).
CURVATURE_FLOOR = np.finfo(float).eps


@numba.njit(cache=True, nogil=True, error_model="numpy")
def loss_point(z, code, c2):
    """One measurement's ``C^2 rho(z / C^2)`` and its first two derivatives by ``z`` (compiled).

    ``code`` is the loss's index in :data:`LOSSES`, ``c2`` the squared scale ``C^2``; the one coding of the
    losses, which :func:`loss_terms` and the ML iteration's kernel evaluate.
    """
    if code == 0:
        return z, 1.0, 0.0
    u = z / c2
    if code == 1:
        if u <= 1.0:
            rho, rho1, rho2 = u, 1.0, 0.0
        else:
            root = math.sqrt(u)
            rho, rho1, rho2 = 2.0 * root - 1.0, 1.0 / root, -0.5 / (root * root * root)
    elif code == 2:
        t = 1.0 + u
        root = math.sqrt(t)
        rho, rho1, rho2 = 2.0 * (root - 1.0), 1.0 / root, -0.5 / (t * root)
    elif code == 3:
        t = 1.0 + u
        rho, rho1, rho2 = math.log1p(u), 1.0 / t, -1.0 / (t * t)
    else:
        t = 1.0 + u * u
        rho, rho1, rho2 = math.atan(u), 1.0 / t, -2.0 * u / (t * t)
    return c2 * rho, rho1, rho2 / c2


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _loss_many(z, code, c2):
    rho, rho1, rho2 = np.empty_like(z), np.empty_like(z), np.empty_like(z)
    for i in range(z.size):
        rho[i], rho1[i], rho2[i] = loss_point(z[i], code, c2)
    return rho, rho1, rho2


def loss_code(loss: str) -> int:
    """The loss's index in :data:`LOSSES` (what the compiled functions take)."""
    if loss not in LOSSES:
        raise ValueError(f"unknown loss {loss!r}; known: {', '.join(LOSSES)}")
    return LOSSES.index(loss)


def loss_terms(z, loss: str, scale: float):
    """``C^2 rho(z / C^2)`` and its first two derivatives with respect to ``z`` (:func:`loss_point`).

    Parameters
    ----------
    z : ndarray, shape (...)
        Squared whitened residuals.
    loss : str
        One of :data:`LOSSES`.
    scale : float
        ``C``, in sigmas.

    Returns
    -------
    rho : ndarray, shape (...)
        The cost terms (``z`` itself for ``linear``).
    rho1 : ndarray, shape (...)
        ``d rho / d z``: the measurement's weight in the gradient (1 for ``linear``).
    rho2 : ndarray, shape (...)
        ``d^2 rho / d z^2``.
    """
    z = np.asarray(z, dtype=float)
    terms = _loss_many(np.ascontiguousarray(z).ravel(), loss_code(loss), float(scale) ** 2)
    return tuple(t.reshape(z.shape) for t in terms)


def loss_weights(z, loss: str, scale: float):
    """The cost terms and the gradient and Gauss-Newton weight factors of each measurement.

    Returns
    -------
    rho, gradient_factor, curvature_factor : ndarray, shape (...)
        ``rho``; ``rho'``; ``max(rho' + 2 rho'' z, CURVATURE_FLOOR)`` (all 1 for ``linear``).
    """
    rho, rho1, rho2 = loss_terms(z, loss, scale)
    if loss == "linear":
        return rho, rho1, rho1
    return rho, rho1, np.maximum(rho1 + 2.0 * rho2 * z, CURVATURE_FLOOR)
