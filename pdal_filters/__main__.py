"""``python -m slipmap.pdal_filters``: where the stage script and example pipelines are."""

import argparse
import sys

from slipmap.pdal_filters import JOBS, PIPELINES, SCRIPT


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m slipmap.pdal_filters",
        description="Print the path of SlipMap's PDAL stage script (the filters.python "
        f"'script' option; functions: {', '.join(JOBS)}) and of the example pipelines.",
    )
    parser.add_argument(
        "what", nargs="?", choices=("script", "pipelines"), help="print only this path"
    )
    args = parser.parse_args(argv)
    if args.what == "script":
        sys.stdout.write(f"{SCRIPT}\n")
    elif args.what == "pipelines":
        sys.stdout.write(f"{PIPELINES}\n")
    else:
        sys.stdout.write(f"script     {SCRIPT}\npipelines  {PIPELINES}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
