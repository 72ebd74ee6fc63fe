"""Output safety, in one place for every job and face.

:class:`OutputPlan` is how a job writes files:

1. Before anything runs, every output path is compared with every input path (the same file
   on disk, or an input inside the output folder under the name of an output) and every
   output's folder is checked writable: :meth:`OutputPlan.check`.
2. While the job runs, it writes into a temporary folder beside each target
   (:meth:`OutputPlan.path`), never into the target itself.
3. At the end, :meth:`OutputPlan.commit` checks the staged names against the inputs once
   more and moves every file into place; a failed or cancelled run removes the temporary
   folder and leaves the output folder as it was. A commit that fails half-way (a full disk,
   a file that cannot be replaced) puts back what it had replaced, removes what it had moved
   in and removes its temporary folder: no ``.slipmap-partial-*`` folder and no partial
   output remain, whatever raised.

An output is never written into a folder of tiles given as an input, nor anywhere inside it
(issue #31): the next run would read the outputs back as tiles. A folder given as an input,
and the folder of the files of an input given as several files, count as such folders.

Use it as a context manager::

    with OutputPlan(inputs={"before": path_a, "fault": trace}, out_dir=("out_m", out)) as plan:
        plan.expect("displacement.json", "displacement.gpkg")
        plan.check()
        ... write to plan.path("displacement.json") ...
    # committed here when the block succeeded, removed when it raised
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import tempfile
from pathlib import Path
from typing import Dict, Iterable, List, Mapping, Optional, Sequence, Tuple, Union

from ..core.errors import SlipMapFileError
from .options import OptionError

log = logging.getLogger("slipmap.app")

PathLike = Union[str, "os.PathLike[str]"]

#: free space an output folder must have before a run starts (the outputs of one job are
#: rarely smaller; a full disk is then said before the work, not after it)
MIN_FREE_BYTES = 16 * 2**20


def _existing_ancestor(p: Path) -> Path:
    p = p.absolute()
    while not p.exists() and p.parent != p:
        p = p.parent
    return p


def _inside(path: Path, folder: Path) -> bool:
    """Whether ``path`` is ``folder`` or lies somewhere under it (links resolved)."""
    try:
        p, f = path.resolve(), folder.resolve()
    except OSError:  # pragma: no cover - a loop of links
        return False
    return p == f or f in p.parents


def _same_file(a: Path, b: Path) -> bool:
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
    except OSError:
        pass
    return os.path.normcase(str(a.resolve())) == os.path.normcase(str(b.resolve()))


class OutputPlan:
    """Stage a run's outputs in a temporary folder and move them in at the end.

    Parameters
    ----------
    inputs
        ``{option key: path or list of paths}`` of every file the run reads (``None`` values
        ignored). In-memory inputs (arrays, QGIS layers) are simply not listed.
    out_dir
        ``(option key, folder)`` when the run writes named files into one folder (the CLI's
        ``--out``), or ``None``.
    files
        ``{option key: path}`` of single output files (QGIS file destinations,
        ``accuracy --out``).
    """

    def __init__(
        self,
        *,
        inputs: Mapping[str, object] = (),
        out_dir: Optional[Tuple[str, PathLike]] = None,
        files: Mapping[str, Optional[PathLike]] = (),
    ):
        self._inputs: List[Tuple[str, Path]] = []
        self._input_folders: List[Tuple[str, Path]] = []  # folders of tiles, see check()
        for key, value in dict(inputs).items():
            paths = [
                Path(v)
                for v in (value if isinstance(value, (list, tuple)) else [value])
                if isinstance(v, (str, os.PathLike)) and str(v)
            ]
            self._inputs.extend((key, p) for p in paths)
            plain = [p for p in paths if not p.is_dir()]
            folders = [p for p in paths if p.is_dir()]
            if len(plain) > 1:  # several files: a tile set, their folders hold tiles
                folders += [p.parent for p in plain]
            for f in folders:
                if not any(_same_file(f, g) for _, g in self._input_folders):
                    self._input_folders.append((key, f))
        self.out_key: Optional[str] = None
        self.out_dir: Optional[Path] = None
        if out_dir is not None:
            self.out_key, d = out_dir[0], Path(out_dir[1])
            if not str(out_dir[1]).strip():
                raise OptionError(self.out_key, "is empty; give an output folder")
            self.out_dir = d
        self._files: Dict[str, Path] = {}
        for key, p in dict(files).items():
            if p is None:
                continue
            if not str(p).strip():
                raise OptionError(key, "is empty; give an output file path")
            self._files[key] = Path(p)
        self._expected: List[str] = []
        self._names: Dict[str, str] = {}
        self._staging: Dict[Path, Path] = {}  # target folder -> its temporary folder
        self._staged: Dict[Path, Path] = {}  # final path -> staged path
        self.written: List[Path] = []

    @classmethod
    def for_outputs(
        cls,
        *,
        inputs: Mapping[str, object],
        outputs: Mapping[str, Optional[PathLike]],
        default_names: Mapping[str, str],
    ) -> OutputPlan:
        """The plan of a job's outputs given either as ``{"out": folder}`` (every output under
        its default name in that folder: the CLI) or as ``{output key: path or None}`` (QGIS
        destinations; None: not wanted). Use :meth:`wants` and :meth:`file` with the keys."""
        outputs = dict(outputs)
        out_dir = outputs.pop("out", None)
        if out_dir is not None:
            plan = cls(inputs=inputs, out_dir=("out", out_dir))
            plan._names = dict(default_names)
            plan.expect(*default_names.values())
        else:
            plan = cls(inputs=inputs, files=outputs)
            plan._names = {k: k for k, v in outputs.items() if v is not None}
        return plan

    def wants(self, key: str) -> bool:
        """Whether the output ``key`` is to be written."""
        return key in self._names

    def file(self, key: str) -> Path:
        """The temporary path of output ``key`` (see :meth:`for_outputs`)."""
        return self.path(self._names[key])

    def final(self, key: str) -> Path:
        """Where output ``key`` ends up (``key``: an output of :meth:`for_outputs`, or the
        key of a single-file output the plan was made with, as :meth:`path` takes it)."""
        if key not in self._names and key in self._files:
            return self._files[key]
        name = self._names[key]
        return self._files[name] if name in self._files else self.out_dir / name

    def written_names(self, keys: Iterable[str]) -> List[str]:
        """The final file names of those outputs of ``keys`` that are wanted and already
        written (for a summary's list of files)."""
        return [self.final(k).name for k in keys if self.wants(k) and self.file(k).exists()]

    # ------------------------------------------------------------------ planning

    def expect(self, *names: str) -> None:
        """Declare file names the run will write into ``out_dir`` (checked by :meth:`check`)."""
        self._expected.extend(names)

    def targets(self) -> List[Tuple[str, Path]]:
        """``(option key, final path)`` of every declared output."""
        out = [(k, p) for k, p in self._files.items()]
        if self.out_dir is not None:
            out += [(self.out_key, self.out_dir / n) for n in self._expected]
        return out

    def check(self) -> None:
        """Refuse the run before anything is computed when an output would overwrite an input
        or could not be written.

        Raises
        ------
        OptionError
            Naming the output option (and the input option in the text).
        """
        if self.out_dir is not None:
            d = self.out_dir
            if d.exists() and not d.is_dir():
                raise OptionError(
                    self.out_key, f"{str(d)!r} exists and is not a folder; give a folder"
                )
            self._refuse_tile_folder(self.out_key, d)
            for key, inp in self._inputs:
                if _same_file(inp, d):
                    raise OptionError(
                        self.out_key,
                        f"{str(d)!r} is the input given as {{{key}}}; choose another folder",
                        also=(key,),
                    )
            self._check_writable(self.out_key, d)
        for key, path in self._files.items():
            if path.exists() and path.is_dir():
                raise OptionError(key, f"{str(path)!r} is a folder; give a file name")
            self._check_writable(key, path.parent)
        for key, path in self._files.items():
            self._refuse_tile_folder(key, path.parent)
        for out_key, target in self.targets():
            self._refuse_input(out_key, target)

    def _refuse_tile_folder(self, out_key: str, folder: Path) -> None:
        for key, tiles in self._input_folders:
            if _inside(folder, tiles):
                where = "is" if _same_file(folder, tiles) else "is inside"
                raise OptionError(
                    out_key,
                    f"{str(folder)!r} {where} the folder of the tiles given as {{{key}}} "
                    f"({str(tiles)!r}); outputs there would be read as tiles by the next run: "
                    "choose a folder outside it",
                    also=(key,),
                )

    def _refuse_input(self, out_key: str, target: Path) -> None:
        for key, inp in self._inputs:
            if _same_file(inp, target):
                raise OptionError(
                    out_key,
                    f"would write {str(target)!r}, which is the input given as {{{key}}}; "
                    "SlipMap never overwrites an input: choose another output or move the input",
                    also=(key,),
                )

    @staticmethod
    def _check_writable(key: str, folder: Path) -> None:
        probe = _existing_ancestor(folder)
        if not probe.is_dir():
            raise OptionError(
                key,
                f"{str(probe)!r} is a file, not a folder: nothing can be written under it; "
                "choose a folder",
            )
        if not os.access(probe, os.W_OK | os.X_OK):
            raise OptionError(key, f"cannot write in {str(probe)!r}; choose a writable place")
        # os.access does not see everything (a read-only mount or an ACL for root, a full
        # disk): a file is made and removed there, and the free space compared with a stated
        # minimum, before any work rather than at the first write after it
        try:
            with tempfile.TemporaryFile(prefix=".slipmap-probe-", dir=probe):
                pass
        except OSError as exc:
            raise OptionError(
                key, f"cannot write in {str(probe)!r} ({exc.strerror}); choose a writable place"
            ) from exc
        free = shutil.disk_usage(probe).free
        if free < MIN_FREE_BYTES:
            raise OptionError(
                key,
                f"only {free / 2**20:.1f} MiB free in {str(probe)!r} (at least "
                f"{MIN_FREE_BYTES / 2**20:.0f} MiB needed); free some space or choose another "
                "place",
            )

    # ------------------------------------------------------------------ staging

    def path(self, name_or_key: str) -> Path:
        """The temporary path to write an output to.

        ``name_or_key`` is a file name inside ``out_dir`` or the key of a single-file output.
        The temporary file keeps the final suffix, so writers that pick a format by
        extension (laspy's LAZ, GDAL) behave as for the final name.
        """
        if name_or_key in self._files:
            final = self._files[name_or_key]
        elif self.out_dir is not None:
            final = self.out_dir / name_or_key
        else:
            raise KeyError(f"no output {name_or_key!r} in this plan")  # programming error
        return self._stage(final)

    def beside(self, key: str, suffix: str) -> Path:
        """The temporary path of a file that belongs to output ``key`` (e.g. the ``.qml``
        style QGIS reads beside a GeoTIFF): ``final(key)`` with ``suffix``, staged and moved
        in with the outputs (and checked against the inputs as they are)."""
        return self._stage(self.final(key).with_suffix(suffix))

    def _stage(self, final: Path) -> Path:
        staged = self._staged.get(final)
        if staged is None:
            folder = final.parent
            tmp = self._staging.get(folder)
            if tmp is None:
                base = _existing_ancestor(folder)
                try:
                    tmp = Path(tempfile.mkdtemp(prefix=".slipmap-partial-", dir=base))
                except OSError as exc:
                    raise SlipMapFileError(
                        f"cannot write in {str(base)!r}: {exc.strerror}; choose a writable place"
                    ) from exc
                self._staging[folder] = tmp
            rel = final.relative_to(folder)
            staged = tmp / rel
            staged.parent.mkdir(parents=True, exist_ok=True)
            self._staged[final] = staged
        return staged

    def commit(self) -> List[Path]:
        """Move every staged file into place; returns the final paths written.

        All or nothing: when a move fails (or the last check refuses), the files already
        moved in are removed, the files they replaced are put back, and the temporary
        folders are removed before the error propagates.
        """
        moved: List[Tuple[Path, Optional[Path]]] = []  # (final, backup of what it replaced)
        try:
            finals = [f for f, s in self._staged.items() if s.exists()]
            for final in finals:  # the last check, on what was really written
                key = next((k for k, p in self._files.items() if p == final), self.out_key or "out")
                self._refuse_input(key, final)
            for n, final in enumerate(finals):
                final.parent.mkdir(parents=True, exist_ok=True)
                staged = self._staged[final]
                if final.is_dir() and not staged.is_dir():
                    raise SlipMapFileError(
                        f"{str(final)!r} is a folder; cannot replace it by a file"
                    )
                if staged.is_file():
                    _usual_permissions(staged)
                backup = None
                if final.is_file() or final.is_symlink():  # kept until every move succeeded
                    backup = self._staging_for(final).joinpath(f".slipmap-replaced-{n}")
                    os.replace(final, backup)
                moved.append((final, backup))
                os.replace(staged, final)
            self.written.extend(final for final, _ in moved)
        except BaseException:
            self._roll_back(moved)
            raise
        finally:
            self._cleanup()
        return list(self.written)

    def _staging_for(self, final: Path) -> Path:
        tmp = self._staging.get(final.parent)
        if tmp is None:  # a file staged in a subfolder: its top staging folder
            tmp = next(t for f, t in self._staging.items() if _inside(final, f))
        return tmp

    @staticmethod
    def _roll_back(moved: List[Tuple[Path, Optional[Path]]]) -> None:
        """Undo a commit's moves, last first (best effort: each step on its own)."""
        for final, backup in reversed(moved):
            try:
                if final.is_dir() and not final.is_symlink():
                    shutil.rmtree(final)
                elif final.exists() or final.is_symlink():
                    final.unlink()
                if backup is not None:
                    os.replace(backup, final)
            except OSError as exc:  # pragma: no cover - a second failure while undoing
                log.error("could not restore %s after a failed write: %s", final, exc)

    def abort(self) -> None:
        """Remove everything staged; the targets stay as they were."""
        self._staged.clear()
        self._cleanup()

    def _cleanup(self) -> None:
        for tmp in self._staging.values():
            shutil.rmtree(tmp, ignore_errors=True)
        self._staging.clear()

    def __enter__(self) -> OutputPlan:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.commit()
        else:
            self.abort()


def _usual_permissions(path: Path) -> None:
    """mkstemp-made files are 0600; give outputs the usual permissions (umask applies)."""
    umask = os.umask(0)
    os.umask(umask)
    with contextlib.suppress(OSError):
        os.chmod(path, 0o666 & ~umask)


def input_paths(values: Mapping[str, object], keys: Iterable[str]) -> Dict[str, object]:
    """``{key: values[key]}`` for the input keys that hold paths (helper for jobs)."""
    return {k: values.get(k) for k in keys if values.get(k) is not None}


def refuse_same_inputs(pairs: Sequence[Tuple[str, object]]) -> None:
    """Refuse two inputs that are the same file (e.g. the same file as both epochs)."""
    seen: List[Tuple[str, Path]] = []
    for key, value in pairs:
        if not isinstance(value, (str, os.PathLike)) or not str(value):
            continue
        p = Path(value)
        for k0, p0 in seen:
            if _same_file(p, p0):
                raise OptionError(
                    key,
                    f"{str(p)!r} is the same file as {{{k0}}}; give two different surveys",
                    also=(k0,),
                )
        seen.append((key, p))
