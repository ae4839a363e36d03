"""The ``torchtrack`` command line: one sub-command per stage, each registered by its own module.

Sub-command modules expose ``add_parser(subparsers)``, which adds a parser whose ``func(args) -> int``
runs it. They are imported only here, so heavy imports (OpenCV, TensorBoard) stay out of package import.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from torchtrack.checks import InputError

#: Modules that register sub-commands, in help order.
COMMAND_MODULES = (
    "torchtrack.synth.cli",
    "torchtrack.cameras.cli",
    "torchtrack.occupancy.cli",
    "torchtrack.tracking.cli",
    "torchtrack.eval.cli",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="torchtrack", description=__doc__.splitlines()[0])
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(levelname)s %(name)s: %(message)s")
    logging.captureWarnings(True)
    try:
        return int(args.func(args) or 0)
    except (InputError, FileNotFoundError, ValueError) as exc:
        # Bad input: one clear line, no traceback (use -v for the traceback).
        if args.verbose:
            raise
        print(f"torchtrack {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
