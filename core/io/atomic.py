"""Atomic output files: write to a temporary file beside the target, then rename.

A run that fails half-way leaves no partial output, and an existing file is replaced only
when the new one is complete.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import Iterable, Iterator, Optional, Union

from ..errors import InvalidParameterError, SlipMapFileError

PathLike = Union[str, "os.PathLike[str]"]


def check_not_input(output: PathLike, inputs: Iterable[Optional[PathLike]]) -> None:
    """Refuse to write ``output`` when it is one of ``inputs`` (same file on disk).

    Raises
    ------
    InvalidParameterError
        If ``output`` resolves to an input file.
    """
    out = Path(output)
    for inp in inputs:
        if inp is None:
            continue
        p = Path(inp)
        same = False
        if out.exists() and p.exists():
            same = os.path.samefile(out, p)
        else:
            same = out.resolve() == p.resolve()
        if same:
            raise InvalidParameterError(
                f"output {str(out)!r} is the input file; SlipMap never overwrites an input — "
                "choose another output path"
            )


def ensure_output_dir(directory: PathLike) -> Path:
    """Create ``directory`` (and parents) and check that it is writable.

    Raises
    ------
    SlipMapFileError
        If the directory cannot be created or written to.
    """
    d = Path(directory)
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SlipMapFileError(
            f"cannot create output directory {str(d)!r}: {exc.strerror}"
        ) from exc
    if not d.is_dir():
        raise SlipMapFileError(f"output path {str(d)!r} exists and is not a directory")
    if not os.access(d, os.W_OK | os.X_OK):
        raise SlipMapFileError(
            f"output directory {str(d)!r} is not writable; choose another --out directory"
        )
    return d


@contextlib.contextmanager
def atomic_path(path: PathLike, *, suffix: Optional[str] = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` if the block succeeds.

    The temporary file keeps the target's suffix (or ``suffix``), so format-sniffing writers
    (laspy's LAZ by extension, GDAL drivers) behave as for the final name.
    """
    target = Path(path)
    directory = target.parent if str(target.parent) else Path(".")
    sfx = suffix if suffix is not None else "".join(target.suffixes[-1:])
    try:
        fd, tmp_name = tempfile.mkstemp(
            prefix=f".{target.stem}.", suffix=f".tmp{sfx}", dir=directory
        )
    except OSError as exc:
        raise SlipMapFileError(
            f"cannot write in {str(directory)!r}: {exc.strerror}; choose a writable output path"
        ) from exc
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        if tmp.exists():
            # mkstemp creates 0600 files; give outputs the usual permissions (umask applies)
            umask = os.umask(0)
            os.umask(umask)
            os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def write_text_atomic(path: PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically and return the path."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)
