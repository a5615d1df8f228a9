"""Summaries of solved fixes, each in the axes its reader uses: one pass over a :class:`~core.estimators.FixBatch`.

A geodetic fix's covariance and CRLB are turned into the east/north/up axes
at the fix (:func:`core.geodesy.covariance_to_point`), and its error figures
(:func:`core.error_summary.summaries_kernel`) are of that covariance, rather
than in the common frame's axes at the stations' centroid; a flat frame has
one set of axes. Every fix is also placed on the earth: its geodetic and
ECEF position and its covariance in ECEF axes.
"""

from __future__ import annotations

import typing

import numba
import numpy as np

from core import geodesy
from core.error_summary import ErrorSummary, radius50_tables, summaries_kernel


class FixSummary(typing.NamedTuple):
    """What a batch of fixes says, fix by fix (leading axis B); a failed fix's position and covariance are zeros.

    Attributes
    ----------
    position_enu_m : ndarray, shape (B, 3)
        In the common frame.
    covariance_enu_m2, crlb_enu_m2 : ndarray, shape (B, 3, 3)
        In the east/north/up axes at the fix (a geodetic frame), else the frame's own axes.
    position_geodetic : ndarray, shape (B, 3)
        ``(lat_rad, lon_rad, alt_m)`` on WGS84 (meaningful where the frame is geodetic).
    position_ecef_m : ndarray, shape (B, 3)
    covariance_ecef_m2 : ndarray, shape (B, 3, 3)
    error : ErrorSummary
        Of ``covariance_enu_m2``.
    """

    position_enu_m: np.ndarray
    covariance_enu_m2: np.ndarray
    crlb_enu_m2: np.ndarray
    position_geodetic: np.ndarray
    position_ecef_m: np.ndarray
    covariance_ecef_m2: np.ndarray
    error: ErrorSummary


@numba.njit(cache=True, nogil=True, error_model="numpy")
def summary_kernel(ok, position_enu_m, covariance_enu_m2, crlb_enu_m2, geodetic, origin_ecef_m, rotation, circle,
                   sphere):
    """:func:`summarise_fixes` on arrays, for compiled callers (which call it directly, without a dispatch).

    Parameters
    ----------
    ok, geodetic : ndarray of bool, shape (B,)
        Solved fixes (the others' position and covariance are zeros); frames that touch the earth.
    position_enu_m, covariance_enu_m2, crlb_enu_m2 : ndarray, shape (B, 3), (B, 3, 3), (B, 3, 3)
        In the common frame.
    origin_ecef_m, rotation : ndarray, shape (B, 3), (B, 3, 3)
        Each frame's placement (:meth:`core.problem.batch.ProblemBatch.frame_placements`).
    circle, sphere : ndarray
        :func:`core.error_summary.radius50_tables`.

    Returns
    -------
    tuple
        The first six fields of :class:`FixSummary`, then the error figures: CEP50, SEP50, vertical sigma,
        ``sqrt(trace)``, the 95 % ellipse's semi-axes and its orientation (rad), each ``(B,)``.
    """
    size = ok.size
    position, covariance, crlb = np.zeros((size, 3)), np.zeros((size, 3, 3)), crlb_enu_m2.copy()
    geodetic_position, ecef_position, covariance_ecef = np.empty((size, 3)), np.empty((size, 3)), np.empty((size, 3, 3))
    turn = np.empty((3, 3))
    for b in range(size):
        r = rotation[b]
        if ok[b]:
            position[b], covariance[b] = position_enu_m[b], covariance_enu_m2[b]
        x, y, z = geodesy.enu_to_ecef_point(position[b, 0], position[b, 1], position[b, 2], origin_ecef_m[b], r)
        lat, lon, alt = geodesy.ecef_to_geodetic_point(x, y, z)
        geodetic_position[b, 0], geodetic_position[b, 1], geodetic_position[b, 2] = lat, lon, alt
        ecef_position[b, 0], ecef_position[b, 1], ecef_position[b, 2] = x, y, z
        geodesy.covariance_enu_to_ecef_point(covariance[b], r, covariance_ecef[b])
        if ok[b] and geodetic[b]:
            geodesy.covariance_to_point(covariance_enu_m2[b], lat, lon, r, turn, covariance[b])
            geodesy.covariance_to_point(crlb_enu_m2[b], lat, lon, r, turn, crlb[b])
    _, _, orientation, cep, sep, vertical, root_trace, semi_major, semi_minor, _ = summaries_kernel(
        covariance, circle, sphere, True)
    return (position, covariance, crlb, geodetic_position, ecef_position, covariance_ecef, cep, sep, vertical,
            root_trace, semi_major, semi_minor, orientation)


def summarise_fixes(fixes) -> FixSummary:
    """Summarise a :class:`core.estimators.FixBatch` (see :class:`FixSummary`)."""
    c = np.ascontiguousarray
    batch = fixes.problems
    (position, covariance, crlb, geodetic_position, ecef_position, covariance_ecef, cep, sep, vertical, root_trace,
     semi_major, semi_minor, orientation) = summary_kernel(
        c(fixes.ok, dtype=bool), c(fixes.position_enu_m, dtype=float), c(fixes.covariance_enu_m2, dtype=float),
        c(fixes.crlb_enu_m2, dtype=float), c(batch.geodetic, dtype=bool), *batch.frame_placements(),
        *radius50_tables())
    error = ErrorSummary(cep50_m=cep, sep50_m=sep, vertical_sigma_m=vertical, gdop_m=root_trace,
                         ellipse_semi_major_m=semi_major, ellipse_semi_minor_m=semi_minor,
                         ellipse_orientation_rad=orientation)
    return FixSummary(position, covariance, crlb, geodetic_position, ecef_position, covariance_ecef, error)
