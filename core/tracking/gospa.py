"""GOSPA: the generalised optimal sub-pattern assignment metric between estimated and true emitter sets.

With ``alpha = 2`` (Rahmathullah, Garcia-Fernandez and Svensson 2017), for estimates ``X`` and truths ``Y``,
cut-off ``c`` and order ``p``::

    GOSPA^p = min over assignments gamma of  sum_{(i, j) in gamma} d(x_i, y_j)^p  +  c^p / 2 (|X| + |Y| - 2 |gamma|)

over partial assignments whose pairs are closer than ``c``. It splits into a localisation part (the sum over
the assigned pairs), a missed part (``c^p / 2`` per unassigned truth) and a false part (``c^p / 2`` per
unassigned estimate). The minimum is the linear assignment of the cost ``min(d, c)^p``: a pair at ``c`` or
beyond costs exactly what leaving both unassigned does, so such pairs are counted missed and false.

The parts are in the metric's ``p``-th power units (m^p), as Stone Soup's ``GOSPAMetric`` reports them;
``distance`` is the ``p``-th root of their sum (m).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.optimize import linear_sum_assignment

from core.errors import InvalidInput


class Gospa(NamedTuple):
    """GOSPA between one set of estimates and one set of truths.

    Attributes
    ----------
    distance : float
        ``(localisation + missed + false) ** (1 / p)`` (the units of the positions).
    localisation, missed, false : float
        The three parts, in the ``p``-th power of those units.
    missed_count, false_count : int
        Truths and estimates left unassigned (or assigned at ``c`` or beyond).
    assignment : ndarray of int, shape (N,)
        For each truth, the index of its estimate, -1 when missed.
    """

    distance: float
    localisation: float
    missed: float
    false: float
    missed_count: int
    false_count: int
    assignment: np.ndarray


def gospa(estimates, truths, cutoff: float, p: float = 2.0) -> Gospa:
    """GOSPA with ``alpha = 2`` (module docstring).

    Parameters
    ----------
    estimates : ndarray, shape (M, D)
    truths : ndarray, shape (N, D)
        Points in one frame (a horizontal position: ``D = 2``; a position: 3).
    cutoff : float
        ``c > 0``: the largest distance counted as a localisation error.
    p : float
        ``1 <= p``.

    Returns
    -------
    Gospa
    """
    if not cutoff > 0.0:
        raise InvalidInput("the GOSPA cut-off must be > 0", ("cutoff",))
    if not p >= 1.0:
        raise InvalidInput("the GOSPA order p must be >= 1", ("p",))
    estimates = np.asarray(estimates, dtype=float)
    truths = np.asarray(truths, dtype=float)
    m = estimates.shape[0] if estimates.size else 0
    n = truths.shape[0] if truths.size else 0
    half = cutoff ** p / 2.0
    assignment = np.full(n, -1, dtype=np.int64)
    localisation = 0.0
    if m and n:
        distances = np.linalg.norm(estimates[None, :, :] - truths[:, None, :], axis=-1)
        cost = np.minimum(distances, cutoff) ** p
        rows, cols = linear_sum_assignment(cost)
        close = distances[rows, cols] < cutoff
        assignment[rows[close]] = cols[close]
        localisation = float(np.sum(distances[rows[close], cols[close]] ** p))
    assigned = int(np.count_nonzero(assignment >= 0))
    missed_count, false_count = n - assigned, m - assigned
    missed, false = half * missed_count, half * false_count
    return Gospa(float((localisation + missed + false) ** (1.0 / p)), localisation, missed, false, missed_count,
                 false_count, assignment)


__all__ = ["Gospa", "gospa"]
