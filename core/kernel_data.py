"""The named structures the compiled kernels take: a batch's measurements, its frames, and how to fit.

Numba passes a ``typing.NamedTuple`` of arrays as one argument and reads its
fields at no cost inside a kernel, so a kernel takes these few named
structures rather than a long row of positional arrays. A
:class:`~core.problem.batch.ProblemBatch` makes its :class:`Measurements` and
:class:`Frames` once (``kernel_measurements``, ``kernel_frames``).

From Python, a kernel is handed each structure as a plain tuple
(``tuple(measurements)``) and names it again in its first line
(``Measurements(*measurements)``, free in compiled code): numba types a
plain tuple's arrays in C but a named tuple's in Python, about 0.2 us an
array on every call, which a batch of one feels.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class Measurements(NamedTuple):
    """A batch's measurements as ``(B, M)`` planes (C-contiguous), padding included.

    Attributes
    ----------
    kinds : ndarray of int64, shape (B, M)
        Kind codes (:class:`core.measurements.Kind`).
    n_measurements : ndarray of int64, shape (B,)
        Real measurements of each problem; the rest of its row is padding.
    valid : ndarray of bool, shape (B, M)
        The measurements an estimator uses.
    values : ndarray, shape (B, M)
        Problem units (rad, m, s after the problem's TOA reference).
    sigmas : ndarray, shape (B, M)
        Problem units; NaN where not given and on padding.
    model_values : ndarray, shape (B, M)
        Model units (a TOA as pseudo-range metres).
    weights : ndarray, shape (B, M)
        ``1 / sigma^2`` in model units; 0 on padding, unused rows and unknown sigmas.
    stations_enu_m : ndarray, shape (B, M, 3)
        The station of each measurement, in its problem's common frame.
    rotations : ndarray, shape (B, M, 3, 3)
        That station's ENU <- common ENU rotation.
    is_line : ndarray of bool, shape (B, M)
        True on the azimuth row of each used bearing (a line of sight).
    elevation_rad, sigma_elevation_rad : ndarray, shape (B, M)
        A line of sight's elevation and its sigma on its azimuth row; NaN elsewhere.
    source_index : ndarray of int64, shape (B, M)
        The request measurement each row comes from; -1 on padding.
    """

    kinds: np.ndarray
    n_measurements: np.ndarray
    valid: np.ndarray
    values: np.ndarray
    sigmas: np.ndarray
    model_values: np.ndarray
    weights: np.ndarray
    stations_enu_m: np.ndarray
    rotations: np.ndarray
    is_line: np.ndarray
    elevation_rad: np.ndarray
    sigma_elevation_rad: np.ndarray
    source_index: np.ndarray


class Frames(NamedTuple):
    """Each problem's common frame and what constrains its fit.

    Attributes
    ----------
    altitude_m : ndarray, shape (B,)
        Known target altitude; NaN where unconstrained.
    has_toa : ndarray of bool, shape (B,)
        Some measurement is a TOA (the emission offset is a free parameter).
    geodetic : ndarray of bool, shape (B,)
        The frame touches the earth.
    origin_ecef_m : ndarray, shape (B, 3)
        The frame's origin in ECEF.
    origin_rotation : ndarray, shape (B, 3, 3)
        Its ECEF -> ENU rotation.
    """

    altitude_m: np.ndarray
    has_toa: np.ndarray
    geodetic: np.ndarray
    origin_ecef_m: np.ndarray
    origin_rotation: np.ndarray


class Fitting(NamedTuple):
    """How the ML iteration fits: its loss and its limits.

    Attributes
    ----------
    loss_code : int
        :func:`core.estimators.loss.loss_code` of the loss (0: linear).
    c2 : float
        The loss's scale squared (sigmas^2).
    max_iterations : int
    tolerance_m : float
        Converged when a step moves the position less than this.
    """

    loss_code: int
    c2: float
    max_iterations: int
    tolerance_m: float
