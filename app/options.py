"""The options of a job, declared once; the CLI, QGIS and PDAL faces are generated from them.

Each job module of :mod:`slipmap.app` holds one :class:`JobSpec`: its inputs, outputs and
settings as :class:`Option` rows (key, type, unit, default, range, help, label). From that one
table

* the CLI builds its ``argparse`` arguments (:mod:`slipmap.cli._args`),
* QGIS builds its Processing parameters (``qgis_plugin/algorithms/_base.py``),
* PDAL builds its ``pdalargs`` table (``pdal_filters/_stage.py``),

and every face converts what the user gave with the same :meth:`Option.convert`, so NaN,
infinities, empty strings and out-of-range numbers are refused the same way everywhere, at
parse time. An error about an option is an :class:`OptionError` that carries the option's
key; each face renders it with the option's name *as that face calls it* (``--grid``,
"Grid cell size (m)", ``grid_m``) through :meth:`JobSpec.render_error`.

Why not a third-party schema library (pydantic, attrs validators): the faces need per-face
names, QGIS parameter kinds and PDAL's typed JSON, none of which those model; the table stays
plain data that every face can read without importing anything heavy.
"""

from __future__ import annotations

import json
import math
from contextvars import ContextVar
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Dict, Iterable, Mapping, Optional, Sequence, Tuple

from ..core.errors import InvalidParameterError

#: option types; ``floats``/``ints``/``strs`` are lists (``nargs``), ``path``/``paths`` files
TYPES = (
    "float",
    "int",
    "bool",
    "str",
    "choice",
    "floats",
    "ints",
    "strs",
    "vector3",
    "keyvalues",
    "object",
    "path",
    "paths",
    "crs",
)
#: what an option is for: a setting, an input file, or an output file/folder
ROLES = ("setting", "input", "output")
FACES = ("cli", "qgis", "pdal")
_UNIT_SUFFIXES = ("_m", "_deg", "_s", "_mm", "_m2")


class OptionError(InvalidParameterError):
    """A value of one option (or a combination) cannot work.

    ``key`` is the option's key in its :class:`JobSpec`; ``text`` says what is wrong and what
    to do, without the option's name (the face puts its own name in front). ``str(exc)`` uses
    the key; :meth:`JobSpec.render_error` gives a face's wording.
    """

    def __init__(self, key: str, text: str, *, also: Sequence[str] = ()):
        self.key = key
        self.text = text
        self.also = tuple(also)
        super().__init__(f"{key}: {text}")


@dataclass(frozen=True)
class Option:
    """One option of a job.

    Parameters
    ----------
    key
        Python name, with the unit in it (``grid_m``); the PDAL name unless ``pdal`` is given.
    type
        One of :data:`TYPES`.
    help
        One or two plain-text sentences (no HTML, no face's syntax); the unit in words.
    label
        The QGIS dialog label ("Grid cell size (m)"); defaults to a label made from the key.
    default
        The value when not given; ``None`` means "not set" (the job's automatic choice).
    choices
        For ``choice`` (and ``strs`` limited to a set).
    minimum, maximum, exclusive
        Bounds for numbers (``exclusive``: strict lower bound).
    required
        The user must give it (inputs and outputs usually are).
    nargs
        For list types: ``"+"`` or a fixed count.
    role
        ``setting``, ``input`` (a file read) or ``output`` (a file or folder written).
    advanced
        Shown under "Advanced parameters" in QGIS.
    group
        Heading of the CLI argument group (and the order in QGIS).
    cli, qgis, pdal
        The face's name when it is not derived from the key: CLI ``--key-without-unit`` (or
        a positional ``BEFORE``: give ``cli="before"`` without dashes), QGIS
        ``KEY_WITHOUT_UNIT`` upper case, PDAL the key. ``""`` derives; ``None`` leaves the
        option out of that face (the face supplies the value another way).
    metavar, unset_text, file_filter
        Presentation: CLI metavar, how "not set" reads in docs, the QGIS file filter.
    """

    key: str
    type: str
    help: str
    label: str = ""
    default: Any = None
    choices: Tuple[Any, ...] = ()
    minimum: Optional[float] = None
    maximum: Optional[float] = None
    exclusive: bool = False
    required: bool = False
    nargs: Any = None
    role: str = "setting"
    advanced: bool = False
    group: str = ""
    cli: Optional[str] = ""
    qgis: Optional[str] = ""
    pdal: Optional[str] = ""
    metavar: Optional[str] = None
    unset_text: str = "automatic"
    file_filter: str = ""

    def __post_init__(self):
        if self.type not in TYPES:  # programming errors: fail at import
            raise ValueError(f"option {self.key!r}: unknown type {self.type!r}")
        if self.role not in ROLES:
            raise ValueError(f"option {self.key!r}: unknown role {self.role!r}")
        if self.type == "choice" and not self.choices:
            raise ValueError(f"option {self.key!r}: a choice needs choices")

    # ------------------------------------------------------------------ names per face

    @property
    def stem(self) -> str:
        """The key without its unit suffix (``grid_m`` -> ``grid``)."""
        for sfx in _UNIT_SUFFIXES:
            if self.key.endswith(sfx) and len(self.key) > len(sfx):
                return self.key[: -len(sfx)]
        return self.key

    def name_in(self, face: str) -> Optional[str]:
        """The option's name in ``face`` (``cli``, ``qgis``, ``pdal``), None when absent."""
        if face == "cli":
            if self.cli is None:
                return None
            return self.cli or "--" + self.stem.replace("_", "-")
        if face == "qgis":
            if self.qgis is None:
                return None
            return self.qgis or self.stem.upper()
        if face == "pdal":
            if self.pdal is None:
                return None
            return self.pdal or self.key
        return self.key

    def display_in(self, face: str) -> str:
        """How messages name the option in ``face``: the flag, the dialog label, the key."""
        if face == "qgis":
            return f'"{self.dialog_label}"'
        name = self.name_in(face)
        if face == "cli" and name and not name.startswith("-"):
            return name.upper()
        return name or self.key

    @property
    def dialog_label(self) -> str:
        if self.label:
            return self.label
        words = self.stem.replace("_", " ")
        return words[:1].upper() + words[1:]

    @property
    def is_list(self) -> bool:
        return self.type in ("floats", "ints", "strs", "paths")

    # ------------------------------------------------------------------ conversion

    def convert(self, value: Any) -> Any:
        """``value`` as this option's type, checked; ``None`` stays "not set".

        Raises
        ------
        OptionError
            The value has the wrong type, is NaN/inf/empty, or is out of range.
        """
        if value is None:
            return None
        t = self.type
        if self.is_list:
            if isinstance(value, str) and value.strip().lower() == "none":
                return ()  # an explicit empty list ("drop no class")
            items = _as_list(value, self.key)
            if not items:
                raise OptionError(self.key, "needs at least one value")
            if isinstance(self.nargs, int) and len(items) != self.nargs:
                raise OptionError(self.key, f"needs {self.nargs} values, got {len(items)}")
            one = replace(self, type={"floats": "float", "ints": "int"}.get(t, "str"))
            if t == "paths":
                one = replace(self, type="path")
            return tuple(one._scalar(v) for v in items)
        return self._scalar(value)

    def _scalar(self, value: Any) -> Any:
        t = self.type
        if t == "bool":
            if isinstance(value, bool):
                return value
            text = str(value).strip().lower()
            if text in ("true", "1", "yes", "on"):
                return True
            if text in ("false", "0", "no", "off"):
                return False
            raise OptionError(self.key, f"must be true or false, got {value!r}")
        if t in ("float", "int"):
            return self._number(value)
        if t == "choice":
            v = str(value).strip()
            for c in self.choices:  # case-insensitive; the choice as the table spells it
                if v == str(c) or v.lower() == str(c).lower():
                    return c
            for c in self.choices:  # "gps-time" or "gps_time" for GpsTime
                if _squeezed(v) == _squeezed(str(c)):
                    return c
            raise OptionError(
                self.key, f"must be one of {', '.join(map(str, self.choices))}; got {value!r}"
            )
        if t in ("str", "path", "crs"):
            text = str(value) if not isinstance(value, str) else value
            if not text.strip():
                what = {"path": "a file or folder path", "crs": "a CRS such as EPSG:32611"}
                raise OptionError(self.key, f"is empty; give {what.get(t, 'a value')}")
            if self.choices and text not in self.choices:
                raise OptionError(
                    self.key, f"must be one of {', '.join(map(str, self.choices))}; got {text!r}"
                )
            if t == "crs":
                return _check_crs(self.key, text.strip())
            return text if t == "path" else text.strip()
        if t == "vector3":
            items = _as_list(value, self.key)
            nums = tuple(replace(self, type="float")._number(v) for v in items)
            if len(nums) != 3:
                raise OptionError(self.key, f"needs three numbers (x y z), got {len(nums)}")
            return nums
        if t in ("keyvalues", "object"):
            return _key_values(self.key, value, plain_text=t == "keyvalues")
        raise OptionError(self.key, f"has an unknown type {t!r}")  # pragma: no cover

    def _number(self, value: Any) -> Any:
        if isinstance(value, bool):
            raise OptionError(self.key, f"must be a number, got {value!r}")
        try:
            num = float(value)
        except (TypeError, ValueError):
            raise OptionError(self.key, f"must be a number, got {value!r}") from None
        if not math.isfinite(num):
            raise OptionError(self.key, f"must be a finite number, got {value!r}")
        if self.type == "int" or self.type == "ints":
            if num != int(num):
                raise OptionError(self.key, f"must be a whole number, got {value!r}")
            num = int(num)
        if self.minimum is not None:
            if num <= self.minimum if self.exclusive else num < self.minimum:
                op = ">" if self.exclusive else ">="
                raise OptionError(self.key, f"must be {op} {self.minimum:g}, got {value!r}")
        if self.maximum is not None and num > self.maximum:
            raise OptionError(self.key, f"must be <= {self.maximum:g}, got {value!r}")
        return num

    # ------------------------------------------------------------------ presentation

    def default_text(self) -> str:
        if self.required:
            return "(required)"
        if self.default is None:
            return self.unset_text
        if isinstance(self.default, bool):
            return "true" if self.default else "false"
        if isinstance(self.default, (list, tuple)):
            return " ".join(f"{v:g}" if isinstance(v, float) else str(v) for v in self.default)
        if isinstance(self.default, float):
            return f"{self.default:g}"
        return str(self.default)

    def type_text(self) -> str:
        if self.type == "choice":
            return " \\| ".join(map(str, self.choices))
        return {"vector3": "[x, y, z]", "keyvalues": "object or name=value,…"}.get(
            self.type, self.type
        )


def _as_list(value: Any, key: str) -> list:
    if isinstance(value, str):
        text = value.strip()
        if text.startswith("["):
            try:
                loaded = json.loads(text)
            except ValueError:
                loaded = None
            if isinstance(loaded, list):
                return loaded
        return [v for v in text.replace(",", " ").split() if v]
    if isinstance(value, Mapping):
        raise OptionError(key, "must be a list, not an object")
    try:
        return list(value)
    except TypeError:
        return [value]


def _squeezed(text: str) -> str:
    """``text`` lower case without ``-`` and ``_`` (choices spelled as a face spells them)."""
    return text.lower().replace("-", "").replace("_", "")


def _check_crs(key: str, text: str) -> str:
    """``text`` if pyproj reads it as a CRS (the text is kept: faces store it as given)."""
    try:
        import pyproj
    except ImportError:  # pragma: no cover - pyproj is a dependency
        return text
    try:
        pyproj.CRS.from_user_input(text)
    except pyproj.exceptions.CRSError:
        raise OptionError(
            key, f"{text!r} is not a CRS pyproj knows; give e.g. EPSG:32611 or a WKT"
        ) from None
    return text


def _key_values(key: str, value: Any, *, plain_text: bool) -> Dict[str, Any]:
    if isinstance(value, (list, tuple)) and plain_text:
        value = ",".join(map(str, value))
    if isinstance(value, str):
        text = value.strip()
        if text.startswith("{") or not plain_text:
            try:
                value = json.loads(text)
            except ValueError:
                raise OptionError(key, f"must be a JSON object, got {value!r}") from None
        else:
            pairs = {}
            for part in (p.strip() for p in text.split(",")):
                if not part:
                    continue
                name, sep, val = part.partition("=")
                if not sep or not name.strip() or not val.strip():
                    raise OptionError(key, f"must be name=value pairs, got {value!r}")
                if name.strip() in pairs:
                    raise OptionError(key, f"{name.strip()} is given twice")
                pairs[name.strip()] = val.strip()
            value = pairs
    if not isinstance(value, Mapping):
        raise OptionError(key, f"must be an object (name=value pairs), got {value!r}")
    return dict(value)


@dataclass(frozen=True)
class JobSpec:
    """A job's options in one table, and its cross-option checks.

    ``check`` (optional) takes the converted options and raises :class:`OptionError` for a
    combination that cannot work; every face calls it before running (QGIS in
    ``checkParameterValues``).
    """

    name: str
    title: str
    description: str
    options: Tuple[Option, ...]
    check: Optional[Callable[[Dict[str, Any]], None]] = None
    citation: str = ""
    _by_key: Dict[str, Option] = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self):
        by = {o.key: o for o in self.options}
        if len(by) != len(self.options):
            raise ValueError(f"job {self.name}: duplicate option keys")  # programming error
        object.__setattr__(self, "_by_key", by)

    def __getitem__(self, key: str) -> Option:
        return self._by_key[key]

    def __contains__(self, key: str) -> bool:
        return key in self._by_key

    def for_face(self, face: str, *, roles: Iterable[str] = ROLES) -> Tuple[Option, ...]:
        roles = tuple(roles)
        return tuple(o for o in self.options if o.role in roles and o.name_in(face) is not None)

    def parse(
        self, values: Mapping[str, Any], *, face: str = "", run_check: bool = True
    ) -> Dict[str, Any]:
        """All options converted, defaults filled in, cross-option checks run.

        ``values`` maps keys to raw values (``None`` or absent: not given). Options that
        ``face`` leaves out keep their defaults unless given. Unknown keys are a programming
        error of the face (``KeyError``).

        Raises
        ------
        OptionError
            A bad value, a missing required option, or a combination ``check`` refuses.
        """
        unknown = set(values) - set(self._by_key)
        if unknown:
            raise KeyError(f"job {self.name}: unknown option key(s) {sorted(unknown)}")
        out: Dict[str, Any] = {}
        for o in self.options:
            raw = values.get(o.key)
            value = o.convert(raw) if raw is not None else None
            if value is None:
                if o.required and (not face or o.name_in(face) is not None):
                    raise OptionError(o.key, "is required")
                value = o.convert(o.default) if o.default is not None else None
            out[o.key] = value
        if face:  # warnings of the run name options as this face does (in_face_words)
            _FACE_WORDS.set((self, face))
        if run_check and self.check is not None:
            self.check(out)
        return out

    def help_in(self, opt: Option | str, face: str) -> str:
        """``opt``'s help with the other options it names (``{key}``) as ``face`` calls them
        (``--workers``, "Dask scheduler address (tcp://host:port)", ``scheduler``).

        A named option that ``face`` does not have is left out with its separator, and a
        parenthesis left empty goes with it, so no face shows another face's names.
        """
        import re

        o = self._by_key[opt] if isinstance(opt, str) else opt

        def name(key: str) -> Optional[str]:
            other = self._by_key.get(key)
            if other is None or other.name_in(face) is None:
                return None
            return other.display_in(face)

        def clause(match: re.Match) -> str:
            inner = match.group(1)
            head, sep, tail = inner.rpartition(":")
            names = [n for n in (name(k) for k in re.findall(r"\{(\w+)\}", tail)) if n]
            if not names:
                return ""
            return f" ({head}{sep} {', '.join(names)})" if sep else f" ({', '.join(names)})"

        text = re.sub(r"\s?\(([^()]*\{\w+\}[^()]*)\)", clause, o.help)
        return re.sub(r"\{(\w+)\}", lambda m: name(m.group(1)) or m.group(1), text)

    def render_error(self, exc: OptionError, face: str) -> str:
        """``exc``'s message with the option named as ``face`` calls it."""
        opt = self._by_key.get(exc.key)
        head = opt.display_in(face) if opt is not None else exc.key
        text = exc.text
        for k in exc.also:  # other options named in the text as {key}
            o = self._by_key.get(k)
            if o is not None:
                text = text.replace("{" + k + "}", o.display_in(face))
        return f"{head}: {text}"

    def markdown(self, face: str = "pdal") -> str:
        """The options as a Markdown table (docs)."""
        rows = ["| Option | Type | Default | Description |", "|---|---|---|---|"]
        for o in self.for_face(face):
            rows.append(
                f"| `{o.name_in(face)}` | {o.type_text()} | {o.default_text()} | "
                f"{self.help_in(o, face)} |"
            )
        return "\n".join(rows)


#: Tile sets as delivered (issue #31): every job that reads tiles declares this one option
#: (through :func:`slipmap.app.tiled.scale_options`), so every face gets it. PDAL hands its
#: stages a view, not tiles: no PDAL key.
KEEP_DUPLICATE_POINTS = Option(
    "keep_duplicate_points",
    "bool",
    "tiled inputs: read every file and every point as given. By default a file that is a "
    "copy of another (the same header and point records) is read once, with a warning, and "
    "where tiles overlap a point found in several files (the same GpsTime and coordinates) "
    "counts once; set this for data that really is distinct",
    label="Keep duplicate points of overlapping tiles",
    default=False,
    advanced=True,
    group="scale: tiled inputs and Dask",
    pdal=None,
)


# --------------------------------------------------------------------------- face words

#: the job's spec and the face of the run in this thread (set by :meth:`JobSpec.parse`
#: with a face: every face parses its options before it runs a job)
_FACE_WORDS: ContextVar[Optional[Tuple[JobSpec, str]]] = ContextVar(
    "slipmap_face_words", default=None
)


def in_face_words(text: str) -> str:
    """``text`` with the options it names as ``{key}`` as the running face calls them
    (``--units``, "Acquisition units", ``units``); the bare key outside a face's run or for
    an option that face does not have."""
    import re

    current = _FACE_WORDS.get()

    def name(match: re.Match) -> str:
        key = match.group(1)
        if current is not None:
            spec, face = current
            o = spec._by_key.get(key)
            if o is not None and o.name_in(face) is not None:
                return o.display_in(face)
        return key

    return re.sub(r"\{(\w+)\}", name, text)


def warn_option(text: str, *args: Any) -> None:
    """Log a warning whose ``{key}`` placeholders name options as the running face does;
    ``args`` fill the text's ``%s`` (file names: their braces are not placeholders)."""
    import logging

    logging.getLogger("slipmap.app").warning(in_face_words(text), *args)
