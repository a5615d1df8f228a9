"""Write fix bodies from a solved core batch (:func:`fix_bodies`): the last step of the fix road.

Every body is JSON text made from the batch's arrays by compiled loops, read
as a mapping on demand (:class:`service.web.responses.JsonObject`).
"""

from __future__ import annotations

import functools
import math
import re
from dataclasses import dataclass

import numba
import numpy as np
import orjson

from core.estimators import FixBatch
from core.error_summary import radius50_tables
from core.fix_summary import summary_kernel
from core.measurements import KIND_NAMES, Kind
from service.web.problems import localization_problem
from service.renderings.points import fix_cot, fix_geojson
from service.web.responses import JsonObject

_AZ, _EL = int(Kind.AZIMUTH), int(Kind.ELEVATION)

#: A template's slot marker, written raw: the slot's number between NUL bytes, which orjson never writes
#: (it escapes control characters in strings, station ids included).
_SLOT = re.compile(rb"\x00(\d+)\x00")
_NUMPY = orjson.OPT_SERIALIZE_NUMPY
_MAX = np.finfo(np.float64).max
#: The value blocks of a fix body, in their order among its values in :func:`fix_bodies` (the first eleven are
#: numbers), and their widths (``None``: one per residual).
_BLOCKS = {"position": 3, "covariance": 9, "crlb": 9, "error": 8, "residual": None, "normalized": None, "fit": 3,
           "geodetic": 3, "ecef": 3, "covariance_ecef": 9, "coarse": 3, "warnings": 1, "bearing_errors": 1}


@dataclass(frozen=True)
class _Template:
    """The JSON text of the fix bodies of one structure: constant pieces around value slots.

    Attributes
    ----------
    pieces : ndarray of uint8
        The ``S + 1`` constant pieces (before, between and after the slots), joined.
    piece_starts, piece_lengths : ndarray of int, shape ``(S + 1,)``
        Where each piece is in ``pieces``.
    columns : ndarray of int, shape ``(S,)``
        The value that fills each slot: its column among a fix's values.
    """

    pieces: np.ndarray
    piece_starts: np.ndarray
    piece_lengths: np.ndarray
    columns: np.ndarray


def _fix_template(structure: bytes, station_ids: tuple, method: str, source: str) -> _Template:
    """The template of the fix bodies of one structure.

    The body is the FixResponse dict with the structure's own values in place and a marker for each
    value of the fix (positions, covariances, error figures, residual values, warnings...);
    orjson writes it and the text is cut at the markers.

    Parameters
    ----------
    structure : bytes
        A row of :func:`_fix_structures`; its width sets the residual columns among a fix's values (the
        batch's widest problem).
    station_ids : tuple of str
    method, source : str
        The ``method`` and ``covariance_source`` of the fixes.
    """
    row = np.frombuffer(structure, dtype=np.int64)
    width = (row.size - 7) // 5
    n, dof, converged, iterations, geodetic, coarse, bearing_errors = row[:7].tolist()
    stations, sources, kinds, used, excluded = row[7:].reshape(5, width)[:, :n].tolist()
    residuals = zip([station_ids[s] for s in stations], sources, [KIND_NAMES[k] for k in kinds], map(bool, used),
                    map(bool, excluded))
    names: list[tuple[str, int]] = []

    def slot(block: str, column: int = 0) -> orjson.Fragment:
        names.append((block, column))
        return orjson.Fragment(b"\x00%d\x00" % (len(names) - 1))

    def matrix(block: str) -> list:
        return [[slot(block, 3 * i + j) for j in range(3)] for i in range(3)]

    def enu(block: str) -> dict:
        return {"east_m": slot(block, 0), "north_m": slot(block, 1), "up_m": slot(block, 2)}

    body = {
        "method": method,
        "position_local": enu("position"),
        "covariance_enu_m2": matrix("covariance"),
        "covariance_source": source,
        "crlb_enu_m2": matrix("crlb"),
        "error": {
            "cep50_m": slot("error", 0), "sep50_m": slot("error", 1), "vertical_sigma_m": slot("error", 2),
            "gdop": slot("error", 3), "sqrt_trace_m": slot("error", 4),
            "ellipse95": {"semi_major_m": slot("error", 5), "semi_minor_m": slot("error", 6),
                          "orientation_deg": slot("error", 7)},
        },
        "residuals": [
            {"station_id": station, "measurement_index": index, "component": component,
             "residual": slot("residual", m), "normalized": slot("normalized", m), "used": used,
             "excluded": excluded}
            for m, (station, index, component, used, excluded) in enumerate(residuals)
        ],
        "fit": {"chi2": slot("fit", 0), "dof": dof, "p_value": slot("fit", 1), "sigma_scale": slot("fit", 2)},
        "converged": bool(converged),
        "iterations": iterations,
        "warnings": slot("warnings"),
    }
    if geodetic:
        body["position"] = {"lat_deg": slot("geodetic", 0), "lon_deg": slot("geodetic", 1),
                            "alt_m": slot("geodetic", 2)}
        body["position_ecef_m"] = [slot("ecef", i) for i in range(3)]
        body["covariance_ecef_m2"] = matrix("covariance_ecef")
    if coarse:
        body["stages"] = {"coarse": enu("coarse")}
    if bearing_errors:
        body["estimated_bearing_errors_deg"] = slot("bearing_errors")
    parts = _SLOT.split(orjson.dumps(body))
    slots = [names[int(i)] for i in parts[1::2]]
    widths = [width if w is None else w for w in _BLOCKS.values()]
    first = dict(zip(_BLOCKS, np.cumsum([0, *widths[:-1]]).tolist()))
    pieces, piece_starts, piece_lengths = _text_spans(parts[0::2])
    return _Template(np.frombuffer(pieces, dtype=np.uint8), piece_starts, piece_lengths,
                     np.array([first[block] + column for block, column in slots], dtype=np.intp))


#: Templates of fixes with at most this many residuals are kept, the last 1024 used: about 20 KB each at most
#: (128-character station ids), where one of 2048 residuals takes about 0.5 MB (kept, a client could make the
#: cache hold half a gigabyte).
_KEPT_RESIDUALS = 64
_kept_template = functools.lru_cache(maxsize=1024)(_fix_template)


def _template(structure: bytes, station_ids: tuple, method: str, source: str, residuals: int) -> _Template:
    """:func:`_fix_template`, from the cache when its ``residuals`` (the fix's measurement rows) are few enough to
    keep."""
    build = _kept_template if residuals <= _KEPT_RESIDUALS else _fix_template
    return build(structure, station_ids, method, source)


@numba.njit(cache=True, nogil=True)
def _value_spans(values, text_lengths, starts, lengths):
    """Where each value of each fix is in the values' text, and the bytes they take in all.

    Parameters
    ----------
    values : ndarray of uint8
        orjson's text of the B fixes' numbers, ``K`` each, as one flat array (``[a,b,...]``), then ``2 B``
        texts: each fix's warnings, then each fix's bearing errors.
    text_lengths : ndarray of int, shape (2 B,)
        The texts' lengths.
    starts, lengths : ndarray of int, shape ``(B, K + 2)``
        Filled with each value's first byte in ``values`` and its length: a fix's numbers, its warnings and its
        bearing errors.

    Returns
    -------
    int
    """
    size, columns = starts.shape
    total = 0
    at = 1
    for b in range(size):
        for j in range(columns - 2):
            end = at
            while values[end] != 44 and values[end] != 93:  # the comma after a number, or the closing bracket
                end += 1
            starts[b, j], lengths[b, j] = at, end - at
            total += end - at
            at = end + 1
    for j in range(2):
        for b in range(size):
            starts[b, columns - 2 + j], lengths[b, columns - 2 + j] = at, text_lengths[j * size + b]
            total += text_lengths[j * size + b]
            at += text_lengths[j * size + b]
    return total


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _fix_structures(n_measurements, dof, converged, iterations, geodetic, coarse_enu_m, bearing_error_lengths,
                    station_index, source_index, kinds, used, excluded):
    """Each fix body's structure, what its template (:func:`_fix_template`) is made of, as a row of integers.

    Parameters
    ----------
    n_measurements, dof, iterations : ndarray of int64, shape (B,)
    converged, geodetic : ndarray of bool, shape (B,)
    coarse_enu_m : ndarray, shape (B, 3)
        NaN where no coarse stage ran.
    bearing_error_lengths : ndarray of int64, shape (B,)
        The length of each fix's estimated bearing errors text (0: none).
    station_index, source_index : ndarray of int64, shape (B, M)
    kinds : ndarray of int8, shape (B, M)
    used, excluded : ndarray of bool, shape (B, M)

    Returns
    -------
    ndarray of int64, shape (B, 7 + 5 M)
        Per fix: measurement rows, dof, converged, iterations, geodetic, a coarse stage, bearing errors, then
        ``M`` each of station indices, source indices, kind codes, used and excluded flags (padding included).
    """
    size, width = kinds.shape
    out = np.empty((size, 7 + 5 * width), dtype=np.int64)
    for b in range(size):
        row, columns = out[b, :7], out[b, 7:].reshape(5, width)
        row[0], row[1], row[2], row[3] = n_measurements[b], dof[b], converged[b], iterations[b]
        row[4], row[5], row[6] = geodetic[b], not math.isnan(coarse_enu_m[b, 0]), bearing_error_lengths[b] > 0
        for m in range(width):
            columns[0, m], columns[1, m], columns[2, m] = station_index[b, m], source_index[b, m], kinds[b, m]
            columns[3, m], columns[4, m] = used[b, m], excluded[b, m]
    return out


@numba.njit(cache=True, nogil=True)
def _write_bodies(pieces, piece_starts, piece_lengths, columns, rows, values, value_starts, value_lengths, out, at,
                  ends):
    """Write the bodies of ``rows`` from one template into ``out`` from ``at`` on; return where they end.

    Parameters
    ----------
    pieces : ndarray of uint8
        The template's ``S + 1`` constant pieces, joined; ``piece_starts``, ``piece_lengths`` ``(S + 1,)`` say
        where each is.
    columns : ndarray of int, shape ``(S,)``
        The value column that fills each slot.
    rows : ndarray of int, shape ``(G,)``
    values : ndarray of uint8
        The values' text; ``value_starts``, ``value_lengths`` ``(B, W)`` say where each row's values are.
    out : ndarray of uint8
    at : int
    ends : ndarray of int, shape ``(B,)``
        Set at ``rows``: where each body ends in ``out``.
    """
    k = numba.uint64(at)  # unsigned offsets: no negative-index wraparound per byte (twice as fast)
    for b in rows:
        for j in range(columns.size + 1):
            start, length = numba.uint64(piece_starts[j]), numba.uint64(piece_lengths[j])
            for i in range(length):
                out[k + i] = pieces[start + i]
            k += length
            if j < columns.size:
                start, length = numba.uint64(value_starts[b, columns[j]]), numba.uint64(value_lengths[b, columns[j]])
                for i in range(length):
                    out[k + i] = values[start + i]
                k += length
        ends[b] = k
    return k


def _text_spans(texts: list) -> tuple[bytes, np.ndarray, np.ndarray]:
    """``texts`` joined, and where each one is in the join: ``(joined, starts (N,), lengths (N,))``."""
    lengths = np.fromiter(map(len, texts), dtype=np.int64, count=len(texts))
    return b"".join(texts), lengths.cumsum() - lengths, lengths


def _warning_texts(warnings_per_fix) -> list[bytes]:
    """Each fix's warnings as JSON text, written once for the fixes that hold the same warning objects (the
    finisher shares one object among the fixes a warning says the same of)."""
    written: dict[tuple, bytes] = {}
    texts = []
    for warnings in warnings_per_fix:
        if not warnings:
            texts.append(b"[]")
            continue
        key = tuple(map(id, warnings))  # the objects are alive for the whole call: an id names one
        text = written.get(key)
        if text is None:
            text = written[key] = orjson.dumps([{"code": w.code, "message": w.message} for w in warnings])
        texts.append(text)
    return texts


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _fix_numbers(ok, position_enu_m, covariance_enu_m2, crlb_enu_m2, gdop, residuals, normalized, kinds, chi2,
                 p_value, sigma_scale, coarse_enu_m, geodetic, origin_ecef_m, rotation, circle, sphere):
    """Every number of each fix body, in :data:`_BLOCKS` order (the first eleven blocks) and API units: the
    fixes summarised by the core (:func:`core.fix_summary.summary_kernel`: positions on the earth, covariances
    in the axes at each fix, error figures) and laid out, in one compiled call.

    Parameters
    ----------
    ok : ndarray of bool, shape (B,)
        Fixes whose position and covariance are written (zeros for the others).
    position_enu_m, covariance_enu_m2, crlb_enu_m2 : ndarray, shape (B, 3), (B, 3, 3), (B, 3, 3)
        In the common frame.
    gdop, chi2, p_value, sigma_scale : ndarray, shape (B,)
    residuals, normalized : ndarray, shape (B, M)
        Residuals in model units (angles in radians: written in degrees).
    kinds : ndarray of int8, shape (B, M)
    coarse_enu_m : ndarray, shape (B, 3)
        NaN where no coarse stage ran (written as 0).
    geodetic, origin_ecef_m, rotation, circle, sphere
        As :func:`core.fix_summary.summary_kernel` takes them.

    Returns
    -------
    ndarray, shape (B, 50 + 2 M)
    """
    (position, covariance, crlb, position_geodetic, position_ecef_m, covariance_ecef, cep, sep, vertical,
     root_trace, semi_major, semi_minor, orientation) = summary_kernel(
        ok, position_enu_m, covariance_enu_m2, crlb_enu_m2, geodetic, origin_ecef_m, rotation, circle, sphere)
    size, width = residuals.shape
    out = np.empty((size, 50 + 2 * width))
    to_degrees = 180.0 / math.pi
    for b in range(size):
        row = out[b]
        row[0:3] = position[b]
        row[3:12] = covariance[b].ravel()
        row[12:21] = crlb[b].ravel()
        row[21], row[22], row[23], row[24] = cep[b], sep[b], vertical[b], gdop[b]
        row[25], row[26], row[27] = root_trace[b], semi_major[b], semi_minor[b]
        row[28] = orientation[b] * to_degrees
        k = 29
        for m in range(width):
            angle = kinds[b, m] == _AZ or kinds[b, m] == _EL
            row[k + m] = residuals[b, m] * to_degrees if angle else residuals[b, m]
            row[k + width + m] = normalized[b, m]
        k += 2 * width
        row[k], row[k + 1], row[k + 2] = chi2[b], p_value[b], sigma_scale[b]
        row[k + 3], row[k + 4] = position_geodetic[b, 0] * to_degrees, position_geodetic[b, 1] * to_degrees
        row[k + 5] = position_geodetic[b, 2]
        row[k + 6], row[k + 7], row[k + 8] = position_ecef_m[b, 0], position_ecef_m[b, 1], position_ecef_m[b, 2]
        row[k + 9:k + 18] = covariance_ecef[b].ravel()
        for i in range(3):
            coarse = coarse_enu_m[b, i]
            row[k + 18 + i] = 0.0 if math.isnan(coarse) else min(max(coarse, -_MAX), _MAX)
    return out


def fix_bodies(fixes: FixBatch, formats) -> list[dict]:
    """Response bodies of a :class:`core.estimators.FixBatch`: a fix body, or the problem body of its error.

    The fixes are summarised by the core once, over the batch
    (:func:`core.fix_summary.summary_kernel`: error summaries, geodetic
    positions, ECEF covariances), their numbers laid out in API units, and so does writing their numbers as
    JSON text (one orjson call). Fixes of one structure (the residuals'
    stations, components and flags, the frame, stages...) share a template
    (:func:`_fix_template`); every body is then its template's pieces and
    its values' text in turn, written by one compiled loop per template: no
    Python object per value. A fix's renderings are made from the same
    numbers (:func:`_rendered_fields`) and appended to its text.

    Parameters
    ----------
    fixes : FixBatch
    formats : sequence of tuple of str, length B

    Returns
    -------
    list of dict
        ``{"ok": True, "fix": JsonObject}`` or ``{"ok": False, "error": problem body}`` per problem.
    """
    batch = fixes.problems
    size = batch.size
    ok = fixes.ok
    coarse = fixes.coarse_position_enu_m
    bearing_errors = [b"" if e is None else orjson.dumps(np.degrees(e).tolist())
                      for e in fixes.estimated_bearing_errors_rad]

    # The text of every value and where it is, columns by block in _BLOCKS' order: the numbers, then the
    # warnings and the bearing errors (one text each per fix).
    numbers = _fix_numbers(ok, *(np.ascontiguousarray(a, dtype=float) for a in (
        fixes.position_enu_m, fixes.covariance_enu_m2, fixes.crlb_enu_m2, fixes.gdop, fixes.residuals,
        fixes.normalized_residuals)), np.ascontiguousarray(batch.kinds, dtype=np.int8),
        *(np.ascontiguousarray(a, dtype=float) for a in (fixes.chi2, fixes.p_value, fixes.sigma_scale, coarse)),
        np.ascontiguousarray(batch.geodetic, dtype=bool), *batch.frame_placements(), *radius50_tables())
    value_texts = _warning_texts(fixes.warnings) + bearing_errors
    values = np.frombuffer(orjson.dumps(numbers.ravel(), option=_NUMPY) + b"".join(value_texts), dtype=np.uint8)
    text_lengths = np.fromiter(map(len, value_texts), dtype=np.int64, count=len(value_texts))
    value_starts = np.empty((size, numbers.shape[1] + 2), dtype=np.int64)
    value_lengths = np.empty_like(value_starts)
    value_bytes = _value_spans(values, text_lengths, value_starts, value_lengths)

    # Fixes of one structure share a template. The structure as a row of integers groups them (padding
    # columns included: rows that differ only there make two groups of one template).
    c = np.ascontiguousarray
    structures = _fix_structures(
        c(batch.n_measurements, dtype=np.int64), c(fixes.dof, dtype=np.int64), c(fixes.converged, dtype=bool),
        c(fixes.iterations, dtype=np.int64), c(batch.geodetic, dtype=bool), c(coarse, dtype=float),
        text_lengths[size:], c(batch.station_index, dtype=np.int64), c(batch.source_index, dtype=np.int64),
        c(batch.kinds, dtype=np.int8), c(fixes.used, dtype=bool), c(fixes.excluded, dtype=bool))
    blob, step = structures.tobytes(), structures.shape[1] * 8
    groups: dict[tuple, list[int]] = {}
    for b in ok.nonzero()[0].tolist():
        groups.setdefault((blob[b * step:(b + 1) * step], batch.station_ids[b]), []).append(b)

    # Each body: its template's pieces and its values in turn, all written into one buffer.
    work = [(_template(structure, ids, fixes.method, fixes.covariance_source, int(batch.n_measurements[members[0]])),
             members) for (structure, ids), members in groups.items()]
    texts: list[bytes | None] = [None] * size
    if work:
        written = np.empty(sum(len(members) * template.pieces.size for template, members in work) + value_bytes,
                           dtype=np.uint8)
        ends = np.empty(size, dtype=np.int64)
        end = 0
        for template, members in work:
            end = _write_bodies(template.pieces, template.piece_starts, template.piece_lengths, template.columns,
                                np.array(members), values, value_starts, value_lengths, written, end, ends)
        ends = ends.tolist()
        view = memoryview(written)  # each body copied out once (no whole-buffer bytes to slice again)
        start = 0
        for _, members in work:
            for b in members:
                texts[b] = bytes(view[start:ends[b]])
                start = ends[b]

    known = {"method": fixes.method}
    out: list[dict] = []
    for b, text in enumerate(texts):
        if text is None:
            out.append({"ok": False, "error": localization_problem(fixes.errors[b])})
            continue
        wanted = formats[b]
        if wanted:
            text = _with_renderings(text, _rendered_fields(numbers[b], fixes.method, fixes.covariance_source,
                                                           bool(batch.geodetic[b])), wanted)
        out.append({"ok": True, "fix": JsonObject(text, known)})
    return out


#: Where each block of a fix's numbers (:func:`_fix_numbers`) starts, before the residuals' two blocks.
_POSITION, _COVARIANCE, _ERROR = 0, 3, 21
#: The ``error`` block's fields, in the body's order (the last three are its ``ellipse95``).
_ERROR_FIELDS = ("cep50_m", "sep50_m", "vertical_sigma_m", "gdop", "sqrt_trace_m")
_ELLIPSE_FIELDS = ("semi_major_m", "semi_minor_m", "orientation_deg")


def _rendered_fields(numbers: np.ndarray, method: str, source: str, geodetic: bool) -> dict:
    """The fields of a fix body its renderings read (:func:`service.renderings.points.fix_geojson`,
    :func:`service.renderings.points.fix_cot`), from the fix's row of :func:`_fix_numbers`: the very numbers its text
    holds (and, as there, a number that is not finite is null).

    Parameters
    ----------
    numbers : ndarray, shape (50 + 2 M,)
    method, source : str
        The fix's ``method`` and ``covariance_source``.
    geodetic : bool
        Whether the fix has a ``position`` on the earth.
    """
    width = (numbers.size - 50) // 2
    values = [v if math.isfinite(v) else None for v in numbers.tolist()]
    error = dict(zip(_ERROR_FIELDS, values[_ERROR:_ERROR + 5]))
    error["ellipse95"] = dict(zip(_ELLIPSE_FIELDS, values[_ERROR + 5:_ERROR + 8]))
    covariance = values[_COVARIANCE:_COVARIANCE + 9]
    fields = {"method": method, "covariance_source": source, "error": error,
              "covariance_enu_m2": [covariance[0:3], covariance[3:6], covariance[6:9]]}
    if geodetic:
        at = _ERROR + 8 + 2 * width + 3  # after the residuals and the fit: the geodetic position
        fields["position"] = dict(zip(("lat_deg", "lon_deg", "alt_m"), values[at:at + 3]))
    return fields


def _with_renderings(text: bytes, fields: dict, wanted) -> bytes:
    """A fix body's text with the renderings ``wanted`` asks for (a :class:`service.renderings.points.Renderings`)
    appended as its last members, ``geojson`` then ``cot``."""
    members = b""
    if "geojson" in wanted:
        members += b',"geojson":' + orjson.dumps(fix_geojson(fields, wanted))
    if "cot" in wanted:
        members += b',"cot":' + orjson.dumps(fix_cot(fields, wanted))
    return text[:-1] + members + b"}"
