"""Robust losses with scipy's names and meanings (``scipy.optimize.least_squares(loss=..., f_scale=...)``).

A loss ``rho`` replaces each squared whitened residual ``z = (r / sigma)^2``
in the cost: ``sum C^2 rho(z / C^2)`` with the scale ``C`` in sigmas (scipy's
``f_scale`` applied to whitened residuals). ``linear`` is plain least squares.
The cost here is scipy's times two, so that with ``linear`` it is chi-square.

The Levenberg-Marquardt iteration (:mod:`core.estimators.ml`) uses the loss as
scipy does: the gradient weights each measurement by ``rho'``, the Gauss-Newton
matrix by ``rho' + 2 rho'' z`` (floored at machine epsilon: a measurement past
the loss's bend adds no curvature).
"""

from __future__ import annotations

import numpy as np

#: The losses, as ``options.loss`` and scipy name them.
LOSSES = ("linear", "huber", "soft_l1", "cauchy", "arctan")
#: Floor of a measurement's Gauss-Newton weight factor (scipy's ``EPS``).
CURVATURE_FLOOR = np.finfo(float).eps


def loss_terms(z, loss: str, scale: float):
    """``C^2 rho(z / C^2)`` and its first two derivatives with respect to ``z``.

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
    if loss == "linear":
        return z, np.ones_like(z), np.zeros_like(z)
    c2 = float(scale) ** 2
    u = z / c2
    if loss == "huber":
        inside = u <= 1.0
        root = np.sqrt(np.where(inside, 1.0, u))
        rho = np.where(inside, u, 2.0 * root - 1.0)
        rho1 = np.where(inside, 1.0, 1.0 / root)
        rho2 = np.where(inside, 0.0, -0.5 / (root * root * root))
    elif loss == "soft_l1":
        t = 1.0 + u
        root = np.sqrt(t)
        rho, rho1, rho2 = 2.0 * (root - 1.0), 1.0 / root, -0.5 / (t * root)
    elif loss == "cauchy":
        t = 1.0 + u
        rho, rho1, rho2 = np.log1p(u), 1.0 / t, -1.0 / (t * t)
    elif loss == "arctan":
        t = 1.0 + u * u
        rho, rho1, rho2 = np.arctan(u), 1.0 / t, -2.0 * u / (t * t)
    else:
        raise ValueError(f"unknown loss {loss!r}; known: {', '.join(LOSSES)}")
    return c2 * rho, rho1, rho2 / c2


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
