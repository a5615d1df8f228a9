"""Coverage maps: the Cramer-Rao bound of one sensor geometry over a grid of target positions.

A grid is square in the scene's common ENU frame: cells ``step_m`` apart
along east and north, as many as fit within ``half_width_m`` of the centre
on each side (the centre is a cell), all at one target altitude (geodetic
height in a geodetic scene, the ``up`` coordinate in a flat one). Every
cell is a copy of one template problem (its stations, kinds and sigmas),
and the bound of a chunk of cells is one batch through
:func:`core.crlb.batch_information`. The chunks have a fixed size and no
randomness, so :func:`coverage_map` gives the same arrays, bit for bit,
in this process or on any number of Dask workers (:mod:`core.parallel`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.crlb import batch_information, gdop
from core.error_summary import error_summary
from core.parallel import chunk_slices, run_chunks
from core.problem.batch import ProblemBatch
from core.problem.frame import Problem

#: Cells per chunk: one batch through the information code (a few milliseconds each with ten measurements).
CHUNK_CELLS = 1024


@dataclass(frozen=True)
class Grid:
    """Cell centres of a coverage map.

    Attributes
    ----------
    east_m : ndarray, shape (NE,)
        East coordinate of each column of cells, ascending.
    north_m : ndarray, shape (NN,)
        North coordinate of each row of cells, ascending.
    cells_enu_m : ndarray, shape (NN * NE, 3)
        Row-major (north index first): cell ``k`` is row ``k // NE``, column ``k % NE``.
    step_m : float
    """

    east_m: np.ndarray
    north_m: np.ndarray
    cells_enu_m: np.ndarray
    step_m: float

    @property
    def shape(self) -> tuple[int, int]:
        """``(NN, NE)``: rows (south to north) and columns (west to east)."""
        return self.north_m.size, self.east_m.size


def cells_per_side(half_width_m: float, step_m: float) -> int:
    """Cells along one side: the centre and ``floor(half_width / step)`` on either side of it."""
    return 2 * int(np.floor(half_width_m / step_m * (1.0 + 1e-12))) + 1


def grid(template: Problem, centre_enu_m, half_width_m: float, step_m: float, altitude_m: float) -> Grid:
    """The cells of a square grid around ``centre_enu_m`` in ``template``'s frame.

    Parameters
    ----------
    template : core.problem.frame.Problem
        Only its frame is used.
    centre_enu_m : array_like, shape (2,) or (3,)
        East and north of the centre cell (an up coordinate is ignored).
    half_width_m, step_m : float
        Positive.
    altitude_m : float
        Height of every cell above the ellipsoid (geodetic frame) or its ``up`` (flat frame).

    Returns
    -------
    Grid
    """
    if not (step_m > 0 and half_width_m > 0):
        raise ValueError("half_width_m and step_m must be positive")
    half = (cells_per_side(half_width_m, step_m) - 1) // 2
    offsets = step_m * np.arange(-half, half + 1, dtype=float)
    east = float(centre_enu_m[0]) + offsets
    north = float(centre_enu_m[1]) + offsets
    ee, nn = np.meshgrid(east, north)
    flat = np.stack([ee.ravel(), nn.ravel(), np.zeros(ee.size)], axis=-1)
    return Grid(east, north, template.frame.onto_altitude(flat, altitude_m), float(step_m))


@dataclass(frozen=True)
class Coverage:
    """The bound at each cell (arrays of shape (N,); NaN where unobservable).

    Attributes
    ----------
    cep50_m : ndarray
        Horizontal CEP50 of the CRLB.
    sqrt_trace_crlb_m : ndarray
        ``sqrt(trace(CRLB))`` over east, north and up.
    gdop : ndarray
        Dimensionless: :func:`core.crlb.gdop`.
    reference_sigma_m : ndarray
        Its unit, :func:`core.crlb.reference_sigma_m`.
    observable : ndarray of bool
        False where the sensors do not determine the position (singular information).
    """

    cep50_m: np.ndarray
    sqrt_trace_crlb_m: np.ndarray
    gdop: np.ndarray
    reference_sigma_m: np.ndarray
    observable: np.ndarray

    @classmethod
    def concatenate(cls, parts) -> "Coverage":
        return cls(*(np.concatenate([getattr(p, name) for p in parts]) for name in cls.__dataclass_fields__))


def _template_batch(template) -> ProblemBatch:
    batch = template if isinstance(template, ProblemBatch) else ProblemBatch.from_problems([template])
    if batch.size != 1:
        raise ValueError("the template is one problem")
    return batch


def coverage_grid(template, cells_enu_m) -> Coverage:
    """The bound of one problem's sensors at each of a chunk of cells, as one batch.

    Parameters
    ----------
    template : core.problem.frame.Problem or ProblemBatch of one problem
        Its stations, kinds and sigmas (and known altitude, if any) are used, not its values.
    cells_enu_m : ndarray, shape (N, 3)
        Target positions in the template's frame.

    Returns
    -------
    Coverage
    """
    cells = np.asarray(cells_enu_m, dtype=float).reshape(-1, 3)
    batch = _template_batch(template).take(np.zeros(cells.shape[0], dtype=np.intp))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        info = batch_information(batch, cells)
    observable = info.observable & np.all(np.isfinite(info.covariance_enu_m2), axis=(-2, -1))
    covariance = np.where(observable[:, None, None], info.covariance_enu_m2, 0.0)
    summary = error_summary(covariance)
    sigma_ref = info.reference_sigma_m
    observable &= np.isfinite(sigma_ref)

    def masked(values):
        return np.where(observable, values, np.nan)

    return Coverage(
        cep50_m=masked(summary.cep50_m),
        sqrt_trace_crlb_m=masked(summary.gdop_m),
        gdop=masked(gdop(covariance, np.where(observable, sigma_ref, 1.0))),
        reference_sigma_m=sigma_ref,
        observable=observable,
    )


def coverage_map(template, cells_enu_m, *, scheduler=None, should_stop=None, progress=None,
                 chunk_cells: int = CHUNK_CELLS) -> Coverage:
    """:func:`coverage_grid` over every cell, in chunks of ``chunk_cells``, here or on a Dask cluster.

    Parameters
    ----------
    template : core.problem.frame.Problem or ProblemBatch of one problem
    cells_enu_m : ndarray, shape (N, 3)
        E.g. :attr:`Grid.cells_enu_m`.
    scheduler, should_stop, progress
        As for :func:`core.parallel.run_chunks` (raises :class:`core.parallel.Stopped`).
    chunk_cells : int
        The result does not depend on it, nor on the number of workers.

    Returns
    -------
    Coverage
        In the order of ``cells_enu_m``.
    """
    batch = _template_batch(template)
    cells = np.asarray(cells_enu_m, dtype=float).reshape(-1, 3)
    chunks = [(batch, cells[part]) for part in chunk_slices(cells.shape[0], chunk_cells)]
    return Coverage.concatenate(run_chunks(coverage_grid, chunks, scheduler=scheduler, should_stop=should_stop,
                                           progress=progress))
