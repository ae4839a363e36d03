"""The ``torchtrack`` command line: one sub-command per stage, each registered by its own module.

Sub-command modules expose ``add_parser(subparsers)``, which adds a parser whose ``func(args) -> int``
runs it. They are imported only here, so heavy imports (OpenCV, TensorBoard) stay out of package import.
Every parser is a :class:`Parser`: an error (an unknown command or option, a missing argument) prints the
usage, the error and the list of commands to stderr and exits with status 2.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
import warnings

from torchtrack.checks import InputError

#: Modules that register sub-commands, in help order.
COMMAND_MODULES = (
    "torchtrack.synth.cli",
    "torchtrack.cameras.cli",
    "torchtrack.occupancy.cli",
    "torchtrack.tracking.cli",
    "torchtrack.tracking.init_cli",
    "torchtrack.markers.cli",
    "torchtrack.eval.cli",
)

DESCRIPTION = "Markerless 3D human motion tracking from calibrated multi-camera video."
EPILOG = """\
examples:
  torchtrack synth --out out/walk --motion walk --duration 3
  torchtrack track out/walk --out out/walk_track
  torchtrack eval out/walk_track/poses.npz out/walk/gt.npz

Run `torchtrack COMMAND --help` for a command's options and their defaults."""

VERBOSE_HELP = "log debug messages, and show the traceback of an input error"
_REQUIRED = "the following arguments are required"  # argparse's message for missing arguments


class Parser(argparse.ArgumentParser):
    """An :class:`argparse.ArgumentParser` whose errors also list torchtrack's commands (``commands``, set by
    :func:`build_parser` on every parser; ``add_subparsers`` makes the sub-parsers of this class too), and
    whose ``parse_args`` reports unrecognised arguments with the usage of the (sub-)command they were given to."""

    commands: str = ""
    _argv: list[str] = []

    def parse_known_args(self, args=None, namespace=None):
        self._argv = list(sys.argv[1:] if args is None else args)  # for error(): the unknown options
        return super().parse_known_args(args, namespace)

    def parse_args(self, args=None, namespace=None):
        ns, extras = self.parse_known_args(args, namespace)
        if extras:
            _chosen_parser(self, ns).error(f"unrecognized arguments: {' '.join(extras)}")
        return ns

    def error(self, message: str):
        """Print the usage, the error (with any unknown option, which argparse leaves out when an argument is
        missing) and the commands to stderr; exit with status 2."""
        lines = [message]
        if message.startswith(_REQUIRED):
            unknown = self._unknown_options(self._argv)
            if unknown:
                lines.insert(0, f"unrecognized arguments: {' '.join(unknown)}")
        self.print_usage(sys.stderr)
        text = "".join(f"{self.prog}: error: {line}\n" for line in lines)
        self.exit(2, text + (f"\n{self.commands}\n" if self.commands else ""))

    def _unknown_options(self, argv: list[str]) -> list[str]:
        """The tokens of ``argv`` that look like options this parser does not know (nor abbreviates)."""
        known = self._option_string_actions
        out = []
        for tok in argv:
            if tok == "--":
                break
            if not tok.startswith("-") or tok == "-" or _is_number(tok):
                continue
            name = tok.split("=", 1)[0]
            if name in known or (self.allow_abbrev and name.startswith("--")
                                 and any(o.startswith(name) for o in known)):
                continue
            out.append(tok)
        return out


def _is_number(tok: str) -> bool:
    try:
        float(tok)
    except ValueError:
        return False
    return True


def _subcommands(parser: argparse.ArgumentParser) -> argparse._SubParsersAction | None:
    return next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)


def _chosen_parser(parser: argparse.ArgumentParser, ns: argparse.Namespace) -> argparse.ArgumentParser:
    """The (sub-)parser of the command chosen in ``ns``: ``torchtrack calib convert`` -> the convert parser."""
    sub = _subcommands(parser)
    name = None if sub is None else getattr(ns, sub.dest, None)
    return parser if name not in getattr(sub, "choices", {}) else _chosen_parser(sub.choices[name], ns)


def command_lines(parser: argparse.ArgumentParser, prefix: str = "") -> list[tuple[str, str]]:
    """``(command, one-line help)`` of every runnable command under ``parser``, nested ones spelt out
    (``calib convert``), in help order."""
    sub = _subcommands(parser)
    if sub is None:
        return []
    out = []
    for choice in sub._choices_actions:  # the help of each choice, in the order they were added
        name = f"{prefix}{choice.dest}"
        nested = command_lines(sub.choices[choice.dest], name + " ")
        out += nested or [(name, choice.help or "")]
    return out


def _leaf_parsers(parser: argparse.ArgumentParser) -> list[argparse.ArgumentParser]:
    """The parsers of the runnable commands under ``parser`` (``calib convert``, not ``calib``)."""
    sub = _subcommands(parser)
    if sub is None:
        return [parser]
    return [leaf for child in dict.fromkeys(sub.choices.values()) for leaf in _leaf_parsers(child)]


def _set_commands(parser: argparse.ArgumentParser, text: str) -> None:
    parser.commands = text
    sub = _subcommands(parser)
    for child in ([] if sub is None else set(sub.choices.values())):
        _set_commands(child, text)


def build_parser() -> Parser:
    from torchtrack import __version__

    parser = Parser(prog="torchtrack", description=DESCRIPTION, epilog=EPILOG,
                    formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("-v", "--verbose", action="store_true", help=VERBOSE_HELP)
    parser.add_argument("--version", action="version", version=f"torchtrack {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).add_parser(sub)
    for leaf in _leaf_parsers(parser):  # -v also after the command; SUPPRESS keeps one given before it
        leaf.add_argument("-v", "--verbose", action="store_true", default=argparse.SUPPRESS, help=VERBOSE_HELP)
    lines = command_lines(parser)
    width = max((len(n) for n, _ in lines), default=0)
    text = "commands (`torchtrack COMMAND --help` for its options):\n" + "\n".join(
        f"  {n:<{width}}  {h}" for n, h in lines)
    _set_commands(parser, text)
    return parser


class _Once(logging.Filter):
    """Lets each info or warning text through once: a worker process and this one, or a run's several passes over
    the same frames, report the same damaged file, camera or volume once."""

    def __init__(self) -> None:
        super().__init__()
        self.seen: set[str] = set()

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno not in (logging.INFO, logging.WARNING):
            return True
        text = record.getMessage()
        if text in self.seen:
            return False
        self.seen.add(text)
        return True


def _short_warning(message, category, filename, lineno, line=None) -> str:
    """A warning as one line, without the source line Python's default format adds (``-v`` keeps that)."""
    return str(message)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(levelname)s %(name)s: %(message)s" if args.verbose else "%(levelname)s: %(message)s")
    logging.captureWarnings(True)
    from tqdm.contrib.logging import logging_redirect_tqdm

    format_warning = warnings.formatwarning
    if not args.verbose:
        warnings.formatwarning = _short_warning
    try:
        with logging_redirect_tqdm():  # log lines above the progress bars, not through them
            once = [(handler, _Once()) for handler in logging.getLogger().handlers]  # one per handler: each sees all
            for handler, f in once:
                handler.addFilter(f)
            try:
                return _run(args)
            finally:
                for handler, f in once:
                    handler.removeFilter(f)
    finally:
        warnings.formatwarning = format_warning


def _run(args: argparse.Namespace) -> int:
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:  # a command that keeps partial work says so itself; outputs are written atomically
        print(f"torchtrack {args.command}: interrupted; no output was half-written", file=sys.stderr)
        return 130
    except (InputError, FileNotFoundError, ValueError) as exc:
        # Bad input: one clear line, no traceback (use -v for the traceback).
        if args.verbose:
            raise
        print(f"torchtrack {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
