"""Constant-velocity motion of the session states: transition, process noise and the closed-form prediction.

The motion model is linear, so the prediction is done in closed form; the unscented transform of a linear
map is exactly that.
"""

from __future__ import annotations

import numpy as np


def transition(n: int, velocity_blocks: tuple[int, ...], moves_position: bool, dt_s: float, accel_psd: float,
               separate_block: int | None = None):
    """Transition matrix and process noise of a constant-velocity state, memoised.

    ``[0:3]`` (if ``moves_position``) is a position advanced by the velocity
    ``[3:6]``; every 3-component velocity block starting at an index in
    ``velocity_blocks`` takes the same white acceleration (so their noises are
    fully correlated); the block at ``separate_block``, if any, takes an
    acceleration of the same intensity but modelled as independent; other
    components are constant. The noise is the exact discretisation
    ``q [[dt^3/3, dt^2/2], [dt^2/2, dt]]`` per axis.

    Parameters
    ----------
    n : int
        State size.
    velocity_blocks : tuple of int
    moves_position : bool
    dt_s : float
    accel_psd : float
        Power spectral density of the acceleration noise (m^2/s^3).
    separate_block : int, optional

    Returns
    -------
    transition : ndarray, shape (n, n)
    noise : ndarray, shape (n, n)
        Read-only; shared between calls with equal arguments.
    """
    key = (n, velocity_blocks, moves_position, dt_s, accel_psd, separate_block)
    found = _TRANSITIONS.get(key)
    if found is None:
        phi = np.eye(n)
        if moves_position:
            phi[(0, 1, 2), (3, 4, 5)] = dt_s
        noise = np.zeros((n, n))
        for i in range(3):
            for first in velocity_blocks:
                for second in velocity_blocks:
                    noise[first + i, second + i] = accel_psd * dt_s
                if moves_position:
                    noise[i, first + i] = noise[first + i, i] = accel_psd * dt_s * dt_s / 2.0
            if moves_position:
                noise[i, i] = accel_psd * dt_s**3 / 3.0
            if separate_block is not None:
                noise[separate_block + i, separate_block + i] = accel_psd * dt_s
        phi.flags.writeable = False
        noise.flags.writeable = False
        if len(_TRANSITIONS) >= 256:
            _TRANSITIONS.clear()
        found = _TRANSITIONS[key] = (phi, noise)
    return found


_TRANSITIONS: dict = {}


def transitions(n: int, velocity_blocks: tuple[int, ...], moves_position: bool, dt_s: float,
                accel_psds: tuple[float, ...]):
    """:func:`transition` for several acceleration intensities at once (the components of a mixture or the
    modes of an IMM), memoised.

    Returns
    -------
    transition : ndarray, shape (n, n)
    noises : ndarray, shape (M, n, n)
        One per intensity of ``accel_psds``; read-only.
    """
    key = (n, velocity_blocks, moves_position, dt_s, accel_psds)
    found = _STACKED.get(key)
    if found is None:
        pairs = [transition(n, velocity_blocks, moves_position, dt_s, q) for q in accel_psds]
        noises = np.array([noise for _, noise in pairs])
        noises.flags.writeable = False
        if len(_STACKED) >= 256:
            _STACKED.clear()
        found = _STACKED[key] = (pairs[0][0], noises)
    return found


_STACKED: dict = {}


def constant_velocity_predict(mean, cov, dt_s: float, accel_psd: float, velocity_blocks: tuple[int, ...],
                              moves_position: bool, separate_block: int | None = None):
    """Propagate a state and covariance over ``dt_s`` (see :func:`transition`).

    Parameters
    ----------
    mean : list of n floats
    cov : ndarray, shape (n, n)
    dt_s, accel_psd : float
    velocity_blocks : tuple of int
    moves_position : bool
    separate_block : int, optional

    Returns
    -------
    mean : list of n floats
    cov : ndarray, shape (n, n)
        New; symmetric to rounding.
    """
    phi, noise = transition(len(mean), velocity_blocks, moves_position, dt_s, accel_psd, separate_block)
    predicted = phi.dot(cov).dot(phi.T)
    predicted += noise
    mean = list(mean)
    if moves_position:
        mean[0] += dt_s * mean[3]
        mean[1] += dt_s * mean[4]
        mean[2] += dt_s * mean[5]
    return mean, predicted
