"""Shared plumbing of SlipMap's PDAL ``filters.python`` stages.

PDAL loads one script, ``pdal_filters/slipmap_stages.py``: it finds the ``slipmap`` package
(the only place ``slipmap_path`` is handled) and hands each call to :func:`run_stage` with the
script's globals, where PDAL has put ``pdalargs``, ``spatialreference``, ``schema`` and
``metadata``. The stages themselves (``planes``, ``roughness``, ``accuracy``,
``displacement`` in this package) are ordinary modules with ``STAGE``, ``TABLE``,
``outputs(opts)`` and ``run(ins, outs, *, opts, inputs)``.

What lives here:

* :class:`Option` / :class:`OptionTable`: each stage's options (name, type, default, help) in
  one table; ``pdalargs`` (a dict, or the JSON text PDAL may pass) is parsed once against it
  and cached by its raw value; unknown or invalid options raise :class:`StageError` naming them.
* :class:`StageInputs` and :func:`srs_wkt`: what PDAL injects, read as PDAL 2.8 passes it
  (``spatialreference`` is a dict ``{"srs": {"wkt": ..., ...}}``, empty strings without an SRS).
* :func:`run_stage`: the one call path (options, core errors -> :class:`StageError`, output
  checks, ``out_metadata``).
* :func:`points_from`, :func:`set_output`, :func:`metadata_node`: input and output shaping.

No science here: the stages call ``slipmap.core``.
"""

from __future__ import annotations

import json
import logging
import math
import os
from dataclasses import dataclass, field
from typing import Any, Dict, Mapping, Optional, Sequence, Tuple

import numpy as np

from slipmap.app.options import OptionError
from slipmap.app.summaries import json_safe
from slipmap.core.errors import SlipMapError

log = logging.getLogger(__name__)

TYPES = ("float", "int", "bool", "str", "choice", "object", "vector3", "names", "keyvalues")


class StageError(SlipMapError, RuntimeError):
    """A SlipMap PDAL stage cannot run; the message names the option or dimension at fault."""


# --------------------------------------------------------------------------- options


@dataclass(frozen=True)
class Option:
    """One stage option.

    ``type`` is one of :data:`TYPES`; ``choices`` for "choice"; ``minimum`` (with
    ``exclusive`` for a strict bound) for numbers; ``default=None`` means "not set" (the core
    function's own default or automatic estimate is used); ``required`` options have no default.
    """

    name: str
    type: str
    default: Any
    help: str
    choices: Tuple[str, ...] = ()
    minimum: Optional[float] = None
    exclusive: bool = False
    required: bool = False
    unset_text: str = "automatic"  # how docs show a numeric default of None

    def convert(self, stage: str, value: Any) -> Any:
        where = f"{stage}: option {self.name!r}"
        if value is None:
            if self.required:
                raise StageError(f"{where} is required")
            return None
        t = self.type
        if t == "bool":
            if isinstance(value, bool):
                return value
            if isinstance(value, str) and value.strip().lower() in ("true", "false", "1", "0"):
                return value.strip().lower() in ("true", "1")
            if isinstance(value, int) and value in (0, 1):
                return bool(value)
            raise StageError(f"{where} must be true or false, got {value!r}")
        if t in ("float", "int"):
            if isinstance(value, bool):
                raise StageError(f"{where} must be a number, got {value!r}")
            try:
                num = float(value)
            except (TypeError, ValueError):
                raise StageError(f"{where} must be a number, got {value!r}") from None
            if not math.isfinite(num):
                raise StageError(f"{where} must be finite, got {value!r}")
            if t == "int":
                if num != int(num):
                    raise StageError(f"{where} must be an integer, got {value!r}")
                num = int(num)
            if self.minimum is not None:
                bad = num <= self.minimum if self.exclusive else num < self.minimum
                if bad:
                    op = ">" if self.exclusive else ">="
                    raise StageError(f"{where} must be {op} {self.minimum:g}, got {value!r}")
            return num
        if t == "choice":
            v = str(value).strip().lower() if isinstance(value, str) else value
            for c in self.choices:  # case-insensitive; the choice as the table spells it
                if v == c or (isinstance(v, str) and v == c.lower()):
                    return c
            raise StageError(f"{where} must be one of {list(self.choices)}, got {value!r}")
        if t == "str":
            if not isinstance(value, str) or not value.strip():
                raise StageError(f"{where} must be a non-empty string, got {value!r}")
            return value.strip()
        if t == "object":
            if isinstance(value, str):
                try:
                    value = json.loads(value)
                except ValueError:
                    raise StageError(f"{where} must be a JSON object, got {value!r}") from None
            if not isinstance(value, dict):
                raise StageError(f"{where} must be a JSON object, got {value!r}")
            return dict(value)
        if t == "keyvalues":
            if isinstance(value, str):
                text = value.strip()
                if text.startswith("{"):
                    try:
                        value = json.loads(text)
                    except ValueError:
                        raise StageError(f"{where} must be a JSON object, got {value!r}") from None
                else:
                    pairs = {}
                    for part in (p.strip() for p in text.split(",")):
                        if not part:
                            continue
                        key, sep, val = part.partition("=")
                        if not sep or not key.strip() or not val.strip():
                            raise StageError(
                                f"{where} must be a JSON object or name=value,… text, got {value!r}"
                            )
                        pairs[key.strip()] = val.strip()
                    value = pairs
            if not isinstance(value, dict):
                raise StageError(
                    f"{where} must be a JSON object or name=value,… text, got {value!r}"
                )
            return dict(value)
        if t == "vector3":
            if isinstance(value, str):
                text = value.strip()
                try:
                    value = json.loads(text) if text.startswith("[") else text.split(",")
                except ValueError:
                    raise StageError(f"{where} must be [x, y, z] numbers, got {value!r}") from None
            try:
                vec = [float(v) for v in value]
            except (TypeError, ValueError):
                raise StageError(f"{where} must be [x, y, z] numbers, got {value!r}") from None
            if len(vec) != 3 or not all(math.isfinite(v) for v in vec):
                raise StageError(f"{where} must be three finite numbers, got {value!r}")
            if self.minimum is not None and min(vec) <= self.minimum:
                raise StageError(f"{where} must all be > {self.minimum:g}, got {value!r}")
            return vec
        if t == "names":
            items = value.split(",") if isinstance(value, str) else value
            if not isinstance(items, (list, tuple)):
                raise StageError(f"{where} must be a list of dimension names, got {value!r}")
            names = [str(v).strip() for v in items]
            if len(names) != 3 or not all(names):
                raise StageError(f"{where} must name three dimensions, got {value!r}")
            return names
        raise StageError(f"{where} has an unknown type {t!r}")  # pragma: no cover

    def default_text(self) -> str:
        if self.required:
            return "(required)"
        if self.default is None:
            return self.unset_text if self.type in ("float", "int") else "none"
        if isinstance(self.default, bool):
            return "true" if self.default else "false"
        if isinstance(self.default, dict):
            return json.dumps(self.default)
        if isinstance(self.default, (list, tuple)):
            return ", ".join(str(v) for v in self.default)
        return str(self.default)

    def type_text(self) -> str:
        if self.type == "choice":
            return " \\| ".join(self.choices)
        if self.type == "vector3":
            return "[x, y, z]"
        if self.type == "names":
            return "3 names"
        if self.type == "keyvalues":
            return "object or name=value,…"
        return self.type


@dataclass(frozen=True)
class _SpecOption(Option):
    """A PDAL option backed by a job option of the application layer (same conversion)."""

    spec_option: Any = None

    @classmethod
    def of(cls, o) -> _SpecOption:
        return cls(
            o.name_in("pdal"),
            "str",
            o.default,
            o.help,
            choices=tuple(map(str, o.choices)),
            required=o.required,
            unset_text=o.unset_text,
            spec_option=o,
        )

    def convert(self, stage: str, value: Any) -> Any:
        from slipmap.app.options import OptionError

        if value is None:
            if self.required:
                raise StageError(f"{stage}: option {self.name!r} is required")
            return None
        try:
            return self.spec_option.convert(value)
        except OptionError as exc:
            raise StageError(f"{stage}: option {self.name!r} {exc.text}") from None

    def default_text(self) -> str:
        return self.spec_option.default_text()

    def type_text(self) -> str:
        return self.spec_option.type_text()


SLIPMAP_PATH = Option(
    "slipmap_path",
    "str",
    None,
    "Where `slipmap` is when it is not installed in PDAL's Python: the folder holding the "
    "`slipmap` package, or the package root itself (a checkout, whatever its folder name).",
)


class OptionTable:
    """A stage's options; :meth:`parse` checks ``pdalargs`` against them (cached by raw value)."""

    def __init__(self, stage: str, options: Sequence[Option]):
        self.stage = stage
        self.options: Tuple[Option, ...] = tuple(options) + (SLIPMAP_PATH,)
        self.by_name: Dict[str, Option] = {o.name: o for o in self.options}
        if len(self.by_name) != len(self.options):
            raise ValueError(f"{stage}: duplicate option names")  # programming error
        self._cache: Dict[str, Dict[str, Any]] = {}

    def defaults(self) -> Dict[str, Any]:
        return {o.name: o.default for o in self.options}

    def parse(self, raw: Any) -> Dict[str, Any]:
        """Options from ``pdalargs`` (dict, JSON text, or None), defaults filled in.

        Raises :class:`StageError` naming unknown options and invalid values.
        """
        key = raw if isinstance(raw, str) else _canonical(raw)
        hit = self._cache.get(key)
        if hit is not None:
            return dict(hit)
        args = load_pdalargs(raw, self.stage)
        unknown = sorted(set(args) - set(self.by_name))
        if unknown:
            raise StageError(
                f"{self.stage}: unknown option(s) {', '.join(repr(u) for u in unknown)} in "
                f"pdalargs; known options: {', '.join(sorted(self.by_name))}"
            )
        out = {}
        for o in self.options:
            out[o.name] = o.convert(self.stage, args.get(o.name, o.default))
        self._cache[key] = out
        return dict(out)

    @classmethod
    def from_spec(cls, stage: str, spec, *, extra: Sequence[Option] = (), skip=()) -> OptionTable:
        """The table of a job's options that PDAL shows (``pdal`` not None), plus ``extra``
        PDAL-only options; values are converted by the job's own rules
        (:meth:`slipmap.app.options.Option.convert`), errors as :class:`StageError`."""
        rows = [_SpecOption.of(o) for o in spec.for_face("pdal") if o.key not in set(skip)]
        return cls(stage, rows + list(extra))

    def markdown(self) -> str:
        """The option table as Markdown (the tables of docs/pdal.md)."""
        rows = ["| Option | Type | Default | Description |", "|---|---|---|---|"]
        for o in self.options:
            rows.append(f"| `{o.name}` | {o.type_text()} | {o.default_text()} | {o.help} |")
        return "\n".join(rows)


def _canonical(raw: Any) -> str:
    try:
        return "\0" + json.dumps(raw, sort_keys=True, default=repr)
    except (TypeError, ValueError):  # pragma: no cover - exotic keys
        return "\0" + repr(raw)


def load_pdalargs(raw: Any, stage: str = "stage") -> Dict[str, Any]:
    """``pdalargs`` as a dict: None/"" -> {}, JSON text -> its object, a mapping as is."""
    if raw is None or (isinstance(raw, str) and not raw.strip()):
        return {}
    if isinstance(raw, str):
        try:
            raw = json.loads(raw)
        except ValueError as e:
            raise StageError(f"{stage}: pdalargs is not valid JSON ({e}): {raw!r}") from None
    if not isinstance(raw, Mapping):
        raise StageError(f"{stage}: pdalargs must be a JSON object, got {type(raw).__name__}")
    return dict(raw)


# --------------------------------------------------------------------------- arrays


def n_points(ins: Mapping[str, np.ndarray]) -> int:
    """Number of points of the view (0 for an empty view or no dimensions)."""
    for v in ins.values():
        return int(np.asarray(v).shape[0])
    return 0


def points_from(ins: Mapping[str, np.ndarray], stage: str) -> np.ndarray:
    """``(N, 3)`` float64 X, Y, Z of the view."""
    missing = [d for d in ("X", "Y", "Z") if d not in ins]
    if missing:
        raise StageError(
            f"{stage}: the point view has no {', '.join(missing)} dimension(s); "
            f"it has {', '.join(sorted(ins)) or 'none'}"
        )
    return np.column_stack([np.asarray(ins[d], dtype=np.float64) for d in ("X", "Y", "Z")])


def set_output(
    outs: Dict[str, np.ndarray], name: str, values: Any, dtype: Any, n: int, stage: str
) -> None:
    """Put ``values`` into ``outs[name]`` as a contiguous ``(n,)`` array of ``dtype``."""
    arr = np.ascontiguousarray(np.asarray(values).astype(dtype, copy=False))
    if arr.shape != (n,):
        raise StageError(f"{stage}: output {name!r} has shape {arr.shape}, expected ({n},)")
    outs[name] = arr


def metadata_node(name: str, value: Any, description: str = "", children=()) -> Dict[str, Any]:
    """One node of ``out_metadata`` in the form filters.python reads back.

    PDAL reads ``name``, ``value`` (through ``str()``), ``type`` and ``description`` of each
    node and a ``children`` list. Values are written as text of the type PDAL is told:
    booleans as ``true``/``false``, floats at full precision (``repr``), a non-finite float
    and any dict/list as ``type: "json"`` (JSON text, NaN as null), which ``pdal pipeline
    --metadata`` and ``pipeline.metadata`` show as JSON values, not as strings.
    """
    if isinstance(value, (bool, np.bool_)):
        typ, val = "boolean", "true" if value else "false"
    elif isinstance(value, (int, np.integer)):
        typ, val = "integer", str(int(value))
    elif isinstance(value, (float, np.floating)):
        if math.isfinite(float(value)):
            typ, val = "double", repr(float(value))
        else:
            typ, val = "json", "null"
    elif isinstance(value, str):
        typ, val = "string", value
    else:
        typ, val = "json", json.dumps(json_safe(value), allow_nan=False, default=_listed)
    return {
        "name": name,
        "value": val,
        "type": typ,
        "description": description,
        "children": list(children),
    }


def _listed(o: Any) -> Any:
    """json.dumps fallback: arrays as lists, anything else as its text."""
    if isinstance(o, np.ndarray):
        return json_safe(o.tolist())
    return str(o)


# --------------------------------------------------------------------------- PDAL's globals


def srs_wkt(spatialreference: Any) -> Optional[str]:
    """The view's SRS as WKT, or None when the view has none.

    PDAL 2.8's filters.python passes ``spatialreference`` as the SRS metadata dict
    ``{"srs": {"wkt": ..., "compoundwkt": ..., "horizontal": ..., "proj4": ..., ...}}`` with
    empty strings when the view has no SRS; older bindings passed the WKT text. Both are read;
    the compound WKT (horizontal + vertical) is preferred.
    """
    if spatialreference is None:
        return None
    if isinstance(spatialreference, str):
        return spatialreference.strip() or None
    if isinstance(spatialreference, Mapping):
        srs = spatialreference.get("srs", spatialreference)
        if isinstance(srs, Mapping):
            for key in ("compoundwkt", "wkt", "horizontal"):
                text = srs.get(key)
                if isinstance(text, str) and text.strip():
                    return text.strip()
        return None
    raise StageError(
        f"spatialreference from PDAL has an unknown form ({type(spatialreference).__name__}); "
        "please report the PDAL and pdal-plugins versions"
    )


@dataclass(frozen=True)
class StageInputs:
    """What filters.python puts into the script's globals before each call.

    ``pdalargs``: the stage's ``pdalargs`` (dict, JSON text or None); ``spatialreference``:
    as PDAL passes it (see :func:`srs_wkt`); ``schema``: ``{"schema": {"dimensions": [...]}}``;
    ``metadata``: the pipeline's metadata tree (dict).
    """

    pdalargs: Any = None
    spatialreference: Any = None
    schema: Mapping[str, Any] = field(default_factory=dict)
    metadata: Mapping[str, Any] = field(default_factory=dict)

    @classmethod
    def from_globals(cls, g: Mapping[str, Any]) -> StageInputs:
        return cls(
            pdalargs=g.get("pdalargs"),
            spatialreference=g.get("spatialreference"),
            schema=g.get("schema") or {},
            metadata=g.get("metadata") or {},
        )

    @property
    def wkt(self) -> Optional[str]:
        """The view's SRS as WKT, None without one."""
        return srs_wkt(self.spatialreference)

    def crs(self, stage: str):
        """The view's SRS as a ``pyproj.CRS`` (None without one)."""
        text = self.wkt
        if text is None:
            return None
        import pyproj

        try:
            return pyproj.CRS.from_user_input(text)
        except pyproj.exceptions.CRSError as e:
            raise StageError(
                f"{stage}: the point view's spatial reference cannot be read ({e}); set or "
                "override it with the reader's spatialreference / override_srs option"
            ) from None


def run_stage(stage: Any, ins: Dict[str, np.ndarray], outs: Dict[str, np.ndarray], g) -> dict:
    """Run one stage module on one point view; returns its ``out_metadata`` node.

    ``stage`` is one of this package's stage modules, ``g`` the globals PDAL filled. Options are
    parsed against ``stage.TABLE``; errors of ``slipmap.core`` become :class:`StageError`
    prefixed with the stage name; every written output is checked against ``stage.outputs``.
    """
    inputs = StageInputs.from_globals(g)
    opts = stage.TABLE.parse(inputs.pdalargs)
    n = n_points(ins)
    try:
        node = stage.run(ins, outs, opts=opts, inputs=inputs)
    except StageError:
        raise
    except OptionError as e:
        spec = getattr(stage, "SPEC", None)
        text = spec.render_error(e, "pdal") if spec is not None else str(e)
        raise StageError(f"{stage.STAGE}: option {text}") from e
    except SlipMapError as e:
        raise StageError(f"{stage.STAGE}: {e}") from e
    declared = {k: np.dtype(v) for k, v in stage.outputs(opts).items()}
    for name, arr in outs.items():
        if name not in declared or arr.dtype != declared[name] or arr.shape != (n,):
            raise StageError(  # pragma: no cover - programming error
                f"{stage.STAGE}: internal: output {name!r} {arr.dtype}{arr.shape} does not "
                f"match the declared {declared.get(name)} ({n},)"
            )
    return node


def job_options(spec, opts: Mapping[str, Any]) -> Dict[str, Any]:
    """The job's options by key from a stage's parsed ``opts`` (PDAL names), the options PDAL
    does not show at their defaults, and the job's cross-option checks run."""
    raw = {}
    for o in spec.options:
        name = o.name_in("pdal")
        raw[o.key] = opts.get(name) if name is not None else None
    return spec.parse(raw, face="pdal")


def stage_node(value: Any, description: str, children=()) -> Dict[str, Any]:
    """The root ``out_metadata`` node of a stage.

    PDAL 2.8 + pdal-plugins 1.6 file the root as ``"<name>": value`` in the stage's metadata
    and its children under a sibling key ``"children"``; the root is named ``slipmap`` with the
    stage's job as value, so ``metadata["filters.python"]["slipmap"] == "displacement"``.
    """
    return metadata_node("slipmap", value, description, children)


# --------------------------------------------------------------------------- fault trace


_WKT_KINDS = ("LINESTRING", "MULTILINESTRING")


def is_wkt_line(text: str) -> bool:
    """Whether ``text`` looks like a WKT (MULTI)LINESTRING."""
    head = text.lstrip().upper()
    return any(head.startswith(k) for k in _WKT_KINDS)


def parse_wkt_lines(text: str, option: str = "trace") -> list:
    """Vertex arrays ``[(M, 2|3) float64, ...]`` of a WKT LINESTRING or MULTILINESTRING.

    Z / M variants (``LINESTRING Z (...)``) are accepted; only x and y are kept downstream.
    """
    s = text.strip()
    upper = s.upper()
    kind = "MULTILINESTRING" if upper.startswith("MULTILINESTRING") else "LINESTRING"
    body = s[len(kind) :].strip()
    while body[:1].isalpha():  # Z, M or ZM tag
        body = body[1:].lstrip()
    where = f"option {option!r}"
    if not (body.startswith("(") and body.endswith(")")):
        raise StageError(f"{where}: not a WKT {kind}: {text!r}")
    inner = body[1:-1].strip()
    if kind == "MULTILINESTRING":
        if not (inner.startswith("(") and inner.endswith(")")):
            raise StageError(f"{where}: not a WKT MULTILINESTRING: {text!r}")
        groups = [g.strip(" ()") for g in inner[1:-1].split("),")]
    else:
        groups = [inner]
    parts = []
    for g in groups:
        try:
            rows = [[float(v) for v in pt.split()] for pt in g.split(",")]
            arr = np.array(rows, dtype=np.float64)
        except ValueError:
            raise StageError(f"{where}: bad coordinates in WKT: {g!r}") from None
        if arr.ndim != 2 or arr.shape[1] < 2:
            raise StageError(f"{where}: each WKT vertex needs x and y: {g!r}")
        parts.append(arr[:, :2])
    return parts


# --------------------------------------------------------------------------- two epochs

#: the options of a stage that takes two merged epochs (displacement, icp)
EPOCH_OPTIONS = (
    Option("epoch_dimension", "str", "Epoch", "Dimension tagging each point's epoch."),
    Option("before", "int", 1, "Epoch value of the first (before) epoch."),
    Option("after", "int", 2, "Epoch value of the second (after) epoch."),
)


def epochs(ins: Mapping[str, np.ndarray], opts: Mapping[str, Any], stage: str):
    """Indices of each epoch's points in the view, ``{"before": (N1,), "after": (N2,)}``,
    from the epoch dimension (:data:`EPOCH_OPTIONS`)."""
    if opts["before"] == opts["after"]:
        raise StageError(f"{stage}: options 'before' and 'after' must differ")
    dim = opts["epoch_dimension"]
    if dim not in ins:
        raise StageError(
            f"{stage}: option 'epoch_dimension': the view has no {dim!r} dimension (tag the "
            f"epochs with filters.assign before filters.merge); it has {', '.join(sorted(ins))}"
        )
    epoch = np.asarray(ins[dim])
    idx = {key: np.flatnonzero(epoch == opts[key]) for key in ("before", "after")}
    for key, ix in idx.items():
        if ix.size == 0:
            raise StageError(
                f"{stage}: no point has {dim} == {opts[key]} (option {key!r}); "
                f"values present: {np.unique(epoch)[:10].tolist()}"
            )
    return idx


def lines_file(text: str, option: str, stage: str, inputs: StageInputs) -> Tuple[str, Any]:
    """The path and the view's CRS (pyproj, None without one) of a line option given as a
    file rather than WKT; refused naming ``option`` when no such file exists."""
    path = os.path.expanduser(text)
    if not os.path.isfile(path):
        raise StageError(
            f"{stage}: option {option!r} is neither a WKT LINESTRING nor an existing file: {text!r}"
        )
    crs = inputs.crs(stage)
    if crs is None:
        log.warning(
            "%s: the point view has no spatial reference; the %s file %s is read in its own "
            "CRS, not reprojected (set the readers' spatialreference if the two differ)",
            stage, option, path,
        )  # fmt: skip
    return path, crs


def raster_index(xy: np.ndarray, origin_xy, spacing_m: float, shape) -> np.ndarray:
    """(N,) int64: the row-major index of the pixel each point ``xy`` (N, 2) lies in, of a
    raster of ``shape`` (rows, cols) whose upper-left corner is ``origin_xy`` and pixels
    ``spacing_m`` square (rows north to south); -1 outside it."""
    n_rows, n_cols = (int(v) for v in shape)
    x0, y0 = (float(v) for v in origin_xy)
    col = np.floor((xy[:, 0] - x0) / spacing_m).astype(np.int64)
    row = np.floor((y0 - xy[:, 1]) / spacing_m).astype(np.int64)
    inside = (row >= 0) & (row < n_rows) & (col >= 0) & (col < n_cols)
    return np.where(inside, row * n_cols + col, -1)


def lines_option(text: Any, option: str, stage: str, inputs: StageInputs):
    """The Breaklines of a line option (None when unset): WKT ``LINESTRING`` /
    ``MULTILINESTRING`` in the points' CRS, or an OGR line file reprojected to the view's
    SRS; errors name ``option``."""
    if text is None or not str(text).strip():
        return None
    from slipmap.core.breaklines import breaklines

    if is_wkt_line(text):
        return breaklines(parse_wkt_lines(text, option))
    from slipmap.app.fields import read_breaklines

    path, crs = lines_file(text, option, stage, inputs)
    return read_breaklines(path, crs, key=option)


def lines_file_name(text: Any) -> Optional[str]:
    """A line option's file for a summary (None when given as WKT or unset)."""
    return None if text is None or is_wkt_line(str(text)) else str(text)


# --------------------------------------------------------------------------- field stages

#: what a field stage (icp, piv) writes for each point, besides its index dimension
DISPLACEMENT_DIMS = ("DisplacementX", "DisplacementY", "DisplacementZ")


def field_outputs(index_dim: str) -> Dict[str, str]:
    """{dimension: dtype} of a field stage: the motion and ``index_dim`` (int32)."""
    return {**{d: "float64" for d in DISPLACEMENT_DIMS}, index_dim: "int32"}


def field_options(breaklines_help: str) -> Tuple[Option, ...]:
    """The options a field stage adds to its job's: ``breaklines`` and the epoch tagging."""
    return (Option("breaklines", "str", None, breaklines_help), *EPOCH_OPTIONS)


def set_field_outputs(outs, index, motion, *, index_dim: str, stage: str) -> None:
    """Each point's row ``index`` (N,) of the field's ``motion`` (K, 3), metres, into
    ``outs``: ``DisplacementX/Y/Z`` (NaN where ``index`` is -1) and ``index_dim``."""
    index = np.asarray(index, dtype=np.int32)
    n = len(index)
    per_point = np.full((n, 3), np.nan)
    has = index >= 0
    per_point[has] = np.asarray(motion, dtype=np.float64).reshape(-1, 3)[index[has]]
    for j, name in enumerate(DISPLACEMENT_DIMS):
        set_output(outs, name, per_point[:, j], np.float64, n, stage)
    set_output(outs, index_dim, index, np.int32, n, stage)
