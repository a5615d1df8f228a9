"""The covariance of an ML fix whose model is far from linear over its own uncertainty.

The inverse information at the fix is the covariance of a fix whose
measurement model is linear over its uncertainty. A line of sight nearly
tangent to a TDOA hyperbola breaks that: the bearing's noise slides the
crossing kilometres along the (precise) hyperbola, which curves away from the
straight, metres-thin ellipse the bound draws, and the truth falls outside
it (NEES in the hundreds). The spread of the fixes the ML estimator gives
for measurements moved by their sigmas is the honest figure: the unscented
transform of the estimator, with ``2 k`` sigma points at ``+-sqrt(k)`` whitened
sigmas along the ``k`` directions of measurement space that move the fit (the
column space of the whitened Jacobian), each re-fitted from the fix, and
their second moment about the fix. For a linear model it is exactly the
inverse information; over a curved one it holds the curvature's offset too
(the fourth moment of the noise along each direction, matched by ``sqrt(k)``
where ``k = 3``). It is never reported below the bound (:func:`never_below`).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from core.crlb import batch_information, normal_matrix, parameterisation
from core.estimators.region import holding, normal_draws
from core.measurements import SPEED_OF_LIGHT_MPS, TOA, MeasurementModel
from core.problem.batch import ProblemBatch

#: A fix warns ``curved_uncertainty`` where its unscented covariance exceeds the bound by more than this factor
#: (variance) along some direction: the inverse information then understates the fix's error.
CURVED_VARIANCE_RATIO = 2.0
#: Fixes whose error-model draws are held at once (:func:`curved_covariance`).
HELD_ROWS = 64


def sigma_point_values(batch: ProblemBatch, positions_enu_m, bias_m):
    """The measured values moved by the sigma points of each problem.

    Parameters
    ----------
    batch : ProblemBatch
    positions_enu_m : ndarray, shape (B, 3)
        The fixes.
    bias_m : ndarray, shape (B,)

    Returns
    -------
    owners : ndarray of int, shape (S,)
        The problem of each sigma point.
    values : ndarray, shape (S, M)
        Problem units.
    """
    stations, rotations = batch.measurement_stations()
    _, jacobian = MeasurementModel(stations, rotations, batch.kinds).predict(positions_enu_m, bias_m)
    axes, free = parameterisation(positions_enu_m, batch.altitude_m, batch.has_toa, batch.origin, batch.geodetic,
                                  batch.frame_placements())
    weights = batch.weights()
    _, local = normal_matrix(jacobian, weights, axes, free)  # (B, 4, M), zero rows for frozen parameters
    root = np.sqrt(weights)
    whitened = local.swapaxes(-1, -2) * root[..., None]  # (B, M, 4)
    basis, singular, _ = np.linalg.svd(whitened, full_matrices=False)  # (B, M, 4), (B, 4)
    rank = np.sum(singular > 1e-12 * np.maximum(singular[:, :1], 1e-300), axis=-1)  # (B,)
    unit = np.where(batch.kinds == TOA, SPEED_OF_LIGHT_MPS, 1.0)  # model units (TOA as metres) per problem unit
    owners, values = [], []
    for b in range(batch.size):
        k = int(rank[b])
        used = root[b] > 0.0
        for i in range(k):
            step = np.zeros(batch.values.shape[1])
            step[used] = np.sqrt(k) * basis[b, used, i] / root[b, used] / unit[b, used]
            for sign in (1.0, -1.0):
                owners.append(b)
                values.append(batch.values[b] + sign * step)
    return np.asarray(owners, dtype=np.intp), np.asarray(values, dtype=float).reshape(-1, batch.values.shape[1])


def sigma_point_offsets(batch: ProblemBatch, positions_enu_m, bias_m, refit):
    """The ML fixes of each problem's sigma-point measurements (:func:`sigma_point_values`), less its fix.

    Parameters
    ----------
    batch : ProblemBatch
    positions_enu_m : ndarray, shape (B, 3)
        The ML fixes.
    bias_m : ndarray, shape (B,)
    refit : callable
        ``refit(problems, starts_enu_m)``: the ML positions ``(S, 3)`` of a batch from starts ``(S, 3)``.

    Returns
    -------
    owners : ndarray of int, shape (S,)
        The problem of each sigma point: per problem ``2 k`` rows, pairs ``(+, -)`` along each of its ``k``
        directions, at ``sqrt(k)`` whitened sigmas.
    offsets_enu_m : ndarray, shape (S, 3)
        Zero where a refit gave no finite position.
    """
    positions = np.asarray(positions_enu_m, dtype=float)
    owners, values = sigma_point_values(batch, positions, np.asarray(bias_m, dtype=float))
    if not owners.size:
        return owners, np.zeros((0, 3))
    moved = replace(batch.take(owners), values=values)
    return owners, np.nan_to_num(refit(moved, positions[owners]) - positions[owners])


def unscented_covariance(batch: ProblemBatch, positions_enu_m, bias_m, refit) -> np.ndarray:
    """The second moment ``(B, 3, 3)`` about each fix of the ML fixes of its sigma-point measurements
    (:func:`sigma_point_offsets`, same parameters)."""
    return second_moment(batch.size, *sigma_point_offsets(batch, positions_enu_m, bias_m, refit))


def second_moment(size: int, owners, offsets_enu_m) -> np.ndarray:
    """The second moment ``(size, 3, 3)`` of each problem's sigma-point offsets ``(S, 3)`` (owners ``(S,)``)."""
    out = np.zeros((size, 3, 3))
    if not owners.size:
        return out
    counts = np.bincount(owners, minlength=size)
    np.add.at(out, owners, np.einsum("si,sj->sij", offsets_enu_m, offsets_enu_m) / counts[owners, None, None])
    return out


def quadratic_offsets(size: int, owners, offsets_enu_m):
    """Draws of each fix's error under the second-order expansion its sigma points give, for
    :func:`core.estimators.region.holding`.

    Along each sigma direction ``i`` (whitened noise ``n_i``, refits ``x+`` and ``x-`` at ``+-a``,
    ``a = sqrt(k)``) the fix moves by ``g_i n_i + h_i n_i^2``, ``g_i = (x+ - x-) / 2a`` (the bound's
    linear term), ``h_i = (x+ + x-) / 2a^2`` (the curvature's, which a straight ellipse cannot follow);
    the error is their sum over ``k`` independent standard normal ``n_i``.

    Parameters
    ----------
    size : int
        Problems ``B``.
    owners, offsets_enu_m : ndarray, shapes (S,), (S, 3)
        :func:`sigma_point_offsets`.

    Returns
    -------
    offsets_enu_m : ndarray, shape (B, N, 3)
    weights : ndarray, shape (B, N)
    curvature_enu_m2 : ndarray, shape (B, 3, 3)
        ``sum_i h_i h_i^T``: where the error departs from the bound's Gaussian.
    """
    draws = normal_draws(4)  # (N, 4): at most four parameters (a position and a TOA bias) move a fix
    linear, curved = np.zeros((size, 4, 3)), np.zeros((size, 4, 3))
    counts = np.bincount(owners, minlength=size)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    for b in np.flatnonzero(counts).tolist():
        pairs = offsets_enu_m[starts[b]:starts[b] + counts[b]].reshape(-1, 2, 3)
        k = pairs.shape[0]
        linear[b, :k] = (pairs[:, 0] - pairs[:, 1]) / (2.0 * np.sqrt(k))
        curved[b, :k] = (pairs[:, 0] + pairs[:, 1]) / (2.0 * k)
    out = np.matmul(draws, linear) + np.matmul(draws**2, curved)
    weights = np.full(out.shape[:2], 1.0 / draws.shape[0])
    return out, weights, np.einsum("bki,bkj->bij", curved, curved)


def curved_covariance(batch: ProblemBatch, positions_enu_m, bias_m, refit):
    """Each fix's covariance where the model may be far from linear over its uncertainty: the unscented spread
    (:func:`unscented_covariance`), never below the bound (:func:`never_below`), widened where its 99 % region
    would not hold the curved error its sigma points describe (:func:`quadratic_offsets`,
    :func:`core.estimators.region.holding`).

    Parameters
    ----------
    batch : ProblemBatch
    positions_enu_m : ndarray, shape (B, 3)
    bias_m : ndarray, shape (B,)
    refit : callable
        As for :func:`sigma_point_offsets`.

    Returns
    -------
    covariance_enu_m2 : ndarray, shape (B, 3, 3)
    ratio : ndarray, shape (B,)
        Its largest ratio to the bound (variance) over the bound's directions.
    widened : ndarray of bool, shape (B,)
        Where the region needed widening beyond the spread.
    """
    positions = np.asarray(positions_enu_m, dtype=float)
    owners, offsets = sigma_point_offsets(batch, positions, bias_m, refit)
    bound = batch_information(batch, positions).covariance_enu_m2
    raised, _ = never_below(second_moment(batch.size, owners, offsets), bound)
    held, widened = raised.copy(), np.zeros(batch.size, dtype=bool)
    counts = np.bincount(owners, minlength=batch.size)
    first = np.concatenate([[0], np.cumsum(counts)])
    for start in range(0, batch.size, HELD_ROWS):  # the draws of a block take megabytes, not gigabytes
        rows = slice(start, min(start + HELD_ROWS, batch.size))
        points = slice(first[rows.start], first[rows.stop])
        held[rows], widened[rows] = holding(raised[rows], *quadratic_offsets(
            rows.stop - rows.start, owners[points] - rows.start, offsets[points]))
    return held, never_below(held, bound)[1], widened


def never_below(covariance_enu_m2, bound_enu_m2):
    """``covariance`` raised to the bound along every direction where it falls below it, and the largest ratio of
    the two (variance) over the bound's directions: both ``(B, 3, 3)``, the ratio ``(B,)``. Computed in the
    bound's whitened coordinates over its range (a known altitude leaves it rank 2)."""
    bound = 0.5 * (bound_enu_m2 + bound_enu_m2.swapaxes(-1, -2))
    values, vectors = np.linalg.eigh(bound)
    keep = values > 1e-12 * np.maximum(values[:, -1:], 1e-300)
    scale = np.where(keep, np.sqrt(np.clip(values, 0.0, None)), 0.0)
    inverse = np.where(keep, 1.0 / np.where(keep, scale, 1.0), 0.0)
    root = vectors * scale[:, None, :]  # (B, 3, 3): columns sqrt(lambda) v
    whiten = vectors * inverse[:, None, :]
    inner = np.einsum("bji,bjk,bkl->bil", whiten, covariance_enu_m2, whiten)
    inner = 0.5 * (inner + inner.swapaxes(-1, -2))
    ratios, axes = np.linalg.eigh(inner)  # outside the bound's range inner is 0, and root drops it
    raised = np.maximum(ratios, 1.0)
    inner = np.einsum("bij,bj,bkj->bik", axes, raised, axes)
    out = np.einsum("bij,bjk,blk->bil", root, inner, root)
    return 0.5 * (out + out.swapaxes(-1, -2)), np.max(ratios, axis=-1)
