"""Rewrite the option tables of docs/pdal.md from the jobs' one declaration.

Each ``### <stage> (`function: <stage>`)`` section's Markdown table is replaced by
``slipmap.pdal_filters.<stage>.options_table().markdown()``. Run with the project's venv:
``.venv/bin/python scripts/docs_options.py``; ``--check`` exits 1 when a table is stale.
"""

from __future__ import annotations

import importlib
import re
import sys
from pathlib import Path

DOC = Path(__file__).resolve().parents[1] / "docs" / "pdal.md"


def main(argv) -> int:
    text = DOC.read_text(encoding="utf-8")
    out = text
    for m in re.finditer(r"^### (\w+) \(`function: \w+`\)\n", text, re.M):
        stage = m.group(1)
        table = importlib.import_module(f"slipmap.pdal_filters.{stage}").options_table()
        start = out.index("| Option | Type |", out.index(m.group(0)))
        end = start
        lines = out[start:].split("\n")
        n = 0
        while n < len(lines) and lines[n].startswith("|"):
            n += 1
        end = start + len("\n".join(lines[:n]))
        out = out[:start] + table.markdown() + out[end:]
    if "--check" in argv:
        return int(out != text)
    if out != text:
        DOC.write_text(out, encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
