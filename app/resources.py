"""Memory checks before large allocations, so a too-fine grid is a clear error, not exit 1."""

from __future__ import annotations

import os
from typing import Optional

from .options import OptionError

#: share of the available memory one array may take
_SHARE = 0.5


def available_bytes() -> Optional[int]:
    """Memory available to this process now (bytes), None where it cannot be read."""
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):  # pragma: no cover - non-POSIX
        return None


def check_grid_memory(
    key: str, n_cells: float, *, bytes_per_cell: float, what: str = "grid"
) -> None:
    """Refuse a grid whose working arrays would not fit in memory.

    Parameters
    ----------
    key
        The option that sets the grid's resolution (named in the message).
    n_cells
        Number of cells of the grid.
    bytes_per_cell
        Working memory per cell of the job (all its arrays together), bytes.

    Raises
    ------
    OptionError
        When ``n_cells * bytes_per_cell`` exceeds half the memory available now.
    """
    need = float(n_cells) * float(bytes_per_cell)
    avail = available_bytes()
    if avail is None or need <= _SHARE * avail:
        return
    raise OptionError(
        key,
        f"the {what} would have {n_cells:.3g} cells and need {need / 2**30:.1f} GiB, more than "
        f"the {_SHARE * avail / 2**30:.1f} GiB this machine can give it; choose a coarser value "
        "or crop the input",
    )
