"""Plain CSV tables of numbers: vector fields (PIV, ICP) and control points.

One header row of column names, then one row per record; numbers as text with enough digits
to round-trip metres at UTM size. Writing is atomic. Reading names the file, the row and the
column of anything that is not a number, and the columns that are missing.
"""

from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import Dict, Mapping, Sequence, Tuple

import numpy as np

from ..errors import InputDataError, InvalidParameterError, SlipMapFileError
from .atomic import PathLike, write_text_atomic

__all__ = ["read_control_points", "read_csv_columns", "write_csv_columns"]


def _text(value) -> str:
    if isinstance(value, (bool, np.bool_)):
        return "1" if value else "0"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    v = float(value) + 0.0  # no '-0.0'
    if v != v:
        return "nan"
    return repr(v) if abs(v) < 1e16 else f"{v:.17g}"


def write_csv_columns(path: PathLike, columns: Mapping[str, np.ndarray]) -> Path:
    """Write equal-length 1-D arrays as CSV columns (header = the mapping's keys), atomically.

    Floats are written with ``repr`` (shortest round-trip text), NaN as ``nan``, booleans as
    0/1, integers as integers.
    """
    if not columns:
        raise InvalidParameterError("write_csv_columns: give at least one column")
    arrays = {str(k): np.asarray(v).ravel() for k, v in columns.items()}
    sizes = {a.size for a in arrays.values()}
    if len(sizes) != 1:
        raise InvalidParameterError(
            "write_csv_columns: columns differ in length: "
            + ", ".join(f"{k}={a.size}" for k, a in arrays.items())
        )
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(list(arrays))
    cols = [a.tolist() for a in arrays.values()]
    for row in zip(*cols):
        w.writerow([_text(v) for v in row])
    return write_text_atomic(path, buf.getvalue())


def read_csv_columns(
    path: PathLike,
    *,
    required: Sequence[str] = (),
    optional: Sequence[str] = (),
) -> Dict[str, np.ndarray]:
    """Numeric columns of a CSV file with a header row (comma, semicolon or tab separated).

    Column names are matched case-insensitively and without surrounding spaces. Returns the
    ``required`` and the present ``optional`` columns as float64 arrays (empty cells and
    ``nan`` are NaN).

    Raises
    ------
    SlipMapFileError
        The file is missing or unreadable.
    InputDataError
        No header, missing required columns, or a cell that is not a number.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise SlipMapFileError(f"{p}: cannot read the CSV file ({exc})") from None
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise InputDataError(f"{p}: the CSV file is empty (a header row is needed)")
    try:
        dialect = csv.Sniffer().sniff(lines[0], delimiters=",;\t")
        delim = dialect.delimiter
    except csv.Error:
        delim = ","
    rows = list(csv.reader(lines, delimiter=delim))
    header = [h.strip().lower() for h in rows[0]]
    where = {h: i for i, h in enumerate(header)}
    missing = [c for c in required if c.lower() not in where]
    if missing:
        raise InputDataError(
            f"{p}: missing column(s) {missing}; the header has {rows[0]} (needed: {list(required)})"
        )
    out: Dict[str, np.ndarray] = {}
    for name in list(required) + [c for c in optional if c.lower() in where]:
        j = where[name.lower()]
        vals = np.empty(len(rows) - 1)
        for i, r in enumerate(rows[1:]):
            cell = r[j].strip() if j < len(r) else ""
            try:
                vals[i] = float(cell) if cell else np.nan
            except ValueError:
                raise InputDataError(
                    f"{p}: row {i + 2}, column {name!r}: {cell!r} is not a number"
                ) from None
        out[name] = vals
    return out


def read_control_points(path: PathLike) -> Tuple[np.ndarray, np.ndarray]:
    """Control points (the study's GPS / feature tracking) from a CSV ``x,y,dx,dy[,dz]``.

    Returns
    -------
    xy : (M, 2) float64
        Map coordinates of the control points (the estimate's CRS, metres).
    d : (M, 3) float64
        Their displacement dx, dy, dz (metres; dz NaN when the file has no dz column).
    """
    cols = read_csv_columns(path, required=("x", "y", "dx", "dy"), optional=("dz",))
    xy = np.column_stack([cols["x"], cols["y"]])
    if xy.shape[0] == 0:
        raise InputDataError(f"{path}: no control points (only a header)")
    bad = np.flatnonzero(~np.isfinite(xy).all(axis=1))
    if bad.size:
        rows = ", ".join(str(int(i) + 2) for i in bad[:10]) + (", ..." if bad.size > 10 else "")
        raise InputDataError(
            f"{path}: {bad.size} of {xy.shape[0]} control point(s) have no finite x, y (row(s) "
            f"{rows}); give every row its position in metres"
        )
    dz = cols.get("dz", np.full(xy.shape[0], np.nan))
    return xy, np.column_stack([cols["dx"], cols["dy"], dz])
