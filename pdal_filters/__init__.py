"""SlipMap's PDAL ``filters.python`` stages.

PDAL loads the script :data:`SCRIPT` (``slipmap_stages.py``, one function per job:
``planes``, ``roughness``, ``accuracy``, ``displacement``, ``icp``, ``piv``); the jobs live
in this package's modules of the same names, their shared plumbing in
:mod:`slipmap.pdal_filters._stage`.
Example pipelines are in :data:`PIPELINES`. ``python -m slipmap.pdal_filters`` prints both
paths, for pipelines that use an installed SlipMap. See docs/pdal.md.
"""

from pathlib import Path

SCRIPT = Path(__file__).resolve().with_name("slipmap_stages.py")
PIPELINES = SCRIPT.with_name("pipelines")
JOBS = ("planes", "roughness", "accuracy", "displacement", "icp", "piv")
