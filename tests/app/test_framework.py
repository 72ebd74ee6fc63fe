"""The application layer's own machinery: options declared once, output safety."""

from __future__ import annotations

import hashlib
import math
import os

import pytest
from hypothesis import given
from hypothesis import strategies as st

from slipmap.app.options import JobSpec, Option, OptionError
from slipmap.app.outputs import OutputPlan, refuse_same_inputs
from slipmap.app.resources import check_grid_memory

CELL = Option(
    "cell_m", "float", "cell size, metres", label="Cell size (m)", minimum=0, exclusive=True
)
SPEC = JobSpec(
    "toy",
    "Toy",
    "A job for tests.",
    (
        CELL,
        Option(
            "tile_size_m",
            "float",
            "tile size, metres",
            label="Tile size (m)",
            minimum=0,
            exclusive=True,
        ),
        Option(
            "combine", "choice", "how tiles combine", choices=("joint", "tiles"), default="joint"
        ),
        Option("classes", "ints", "classes", nargs="+"),
        Option("name", "str", "a name"),
        Option("input", "path", "input", required=True, role="input", cli="input"),
    ),
    check=lambda o: _check(o),
)


def _check(o):
    if o["combine"] == "tiles" and o["tile_size_m"] is None:
        raise OptionError("combine", "'tiles' needs {tile_size_m}; give it", also=("tile_size_m",))


# --------------------------------------------------------------------------- options


@pytest.mark.parametrize("bad", ["nan", "NaN", "inf", "-inf", float("nan"), float("inf"), "x"])
def test_non_finite_and_text_numbers_refused(bad):
    with pytest.raises(OptionError) as e:
        CELL.convert(bad)
    assert e.value.key == "cell_m"


@pytest.mark.parametrize("bad", [0, -1, "0", "-0.5"])
def test_bounds(bad):
    with pytest.raises(OptionError, match="must be > 0"):
        CELL.convert(bad)


def test_empty_strings_refused():
    with pytest.raises(OptionError, match="empty"):
        SPEC["name"].convert("  ")
    with pytest.raises(OptionError, match="empty"):
        SPEC["input"].convert("")


def test_lists_and_none():
    opt = SPEC["classes"]
    assert opt.convert("6 2") == (6, 2)
    assert opt.convert("6,2") == (6, 2)
    assert opt.convert([6]) == (6,)
    assert opt.convert("none") == ()
    with pytest.raises(OptionError):
        opt.convert("6 x")


def test_choice_case_insensitive():
    assert SPEC["combine"].convert("TILES") == "tiles"
    with pytest.raises(OptionError, match="one of joint, tiles"):
        SPEC["combine"].convert("both")


@given(st.floats(min_value=1e-9, max_value=1e9, allow_nan=False))
def test_number_roundtrip_through_text(x):
    """A float given as text converts to the same float (CLI, QGIS string, PDAL JSON)."""
    assert CELL.convert(repr(x)) == x == CELL.convert(x)


def test_parse_fills_defaults_and_requires():
    opts = SPEC.parse({"input": "a.laz"})
    assert opts["combine"] == "joint" and opts["cell_m"] is None
    with pytest.raises(OptionError, match="is required"):
        SPEC.parse({})


def test_cross_check_named_per_face():
    with pytest.raises(OptionError) as e:
        SPEC.parse({"input": "a.laz", "combine": "tiles"})
    assert SPEC.render_error(e.value, "cli") == "--combine: 'tiles' needs --tile-size; give it"
    assert SPEC.render_error(e.value, "qgis") == (
        '"Combine": \'tiles\' needs "Tile size (m)"; give it'
    )
    assert SPEC.render_error(e.value, "pdal") == ("combine: 'tiles' needs tile_size_m; give it")


def test_face_names():
    assert CELL.name_in("cli") == "--cell"
    assert CELL.name_in("qgis") == "CELL"
    assert CELL.name_in("pdal") == "cell_m"
    assert SPEC["input"].display_in("cli") == "INPUT"


# --------------------------------------------------------------------------- outputs


def _sha(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _listing(folder):
    return sorted((str(p.relative_to(folder)), p.stat().st_size) for p in folder.rglob("*"))


def test_input_under_an_output_name_is_refused_before_anything(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    fault = out / "result.gpkg"
    fault.write_bytes(b"the user's fault trace")
    before = _listing(out)
    plan = OutputPlan.for_outputs(
        inputs={"fault": fault},
        outputs={"out": out},
        default_names={"vectors": "result.gpkg", "summary": "result.json"},
    )
    with pytest.raises(OptionError) as e:
        plan.check()
    assert e.value.key == "out" and "{fault}" in e.value.text
    assert (
        _listing(out) == before
        and _sha(fault) == hashlib.sha256(b"the user's fault trace").hexdigest()
    )


def test_failed_run_leaves_nothing(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "old.txt").write_text("keep")
    before = _listing(out)
    with pytest.raises(RuntimeError):
        with OutputPlan(out_dir=("out", out)) as plan:
            plan.path("a.json").write_text("{}")
            plan.path("sub/b.tif").write_bytes(b"x")
            raise RuntimeError("the computation failed")
    assert _listing(out) == before


def test_success_moves_everything_in(tmp_path):
    out = tmp_path / "new" / "out"
    with OutputPlan(out_dir=("out", out)) as plan:
        plan.path("a.json").write_text("{}")
        plan.path("sub/b.tif").write_bytes(b"x")
        assert not out.exists()
    assert (out / "a.json").read_text() == "{}" and (out / "sub" / "b.tif").is_file()
    assert not [p for p in tmp_path.rglob(".slipmap-partial-*")]


def test_file_outputs_and_folder_refused(tmp_path):
    plan = OutputPlan(files={"out": tmp_path})
    with pytest.raises(OptionError, match="is a folder"):
        plan.check()
    with pytest.raises(OptionError, match="empty"):
        OutputPlan(out_dir=("out", ""))


def test_output_is_the_input(tmp_path):
    src = tmp_path / "a.laz"
    src.write_bytes(b"points")
    plan = OutputPlan(inputs={"input": src}, files={"output": tmp_path / "." / "a.laz"})
    with pytest.raises(OptionError, match="never overwrites an input"):
        plan.check()


@pytest.mark.skipif(os.geteuid() == 0, reason="root ignores file permissions")
def test_unwritable_refused_before_running(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        with pytest.raises(OptionError, match="cannot write"):
            OutputPlan(out_dir=("out", ro / "x")).check()
    finally:
        ro.chmod(0o700)


def test_same_file_twice(tmp_path):
    a = tmp_path / "a.laz"
    a.write_bytes(b"x")
    with pytest.raises(OptionError, match="same file"):
        refuse_same_inputs([("before", a), ("after", tmp_path / "." / "a.laz")])


def test_grid_memory():
    check_grid_memory("grid_m", 1e3, bytes_per_cell=8)
    with pytest.raises(OptionError, match="coarser") as e:
        check_grid_memory("grid_m", 1e15, bytes_per_cell=64)
    assert e.value.key == "grid_m" and not math.isnan(len(e.value.text))


# --------------------------------------------------------------------------- every job


def _job_specs():
    import importlib
    import pkgutil

    import slipmap.app

    specs = []
    for m in pkgutil.iter_modules(slipmap.app.__path__):
        mod = importlib.import_module(f"slipmap.app.{m.name}")
        for value in vars(mod).values():
            if isinstance(value, JobSpec) and value not in specs:
                specs.append(value)
    return specs


JOB_SPECS = _job_specs()


@pytest.mark.parametrize("spec", JOB_SPECS, ids=lambda s: s.name)
def test_each_face_names_each_option_once(spec):
    for face in ("cli", "qgis", "pdal"):
        names = [o.name_in(face) for o in spec.for_face(face)]
        assert len(names) == len(set(names)), (face, names)
    for o in spec.options:
        assert o.help and not o.help.startswith(" "), o.key
        assert "<" not in o.help, f"{o.key}: plain text help, no HTML"


@pytest.mark.parametrize("spec", JOB_SPECS, ids=lambda s: s.name)
def test_cli_arguments_come_from_the_spec(spec):
    """Every CLI-facing option of the job is an argument of its command."""
    from slipmap.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    commands = [p for p in sub.choices.values() if p.get_default("_spec") is spec]
    assert commands, f"no CLI command runs the {spec.name} job"
    dests = {a.dest for a in commands[0]._actions}
    for o in spec.for_face("cli"):
        assert o.key in dests, o.key
