"""The command line's help and usage errors: every option documented with its default, the commands listed,
bad input answered with the usage and the commands (exit status 2), the config defaults quoted right."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest
import yaml

from torchtrack.cli import build_parser, command_lines, main

COMMANDS = ("synth", "calib", "observe", "track", "init-pose", "eval")
CONFIG = Path(__file__).resolve().parents[1] / "configs" / "markerless.yaml"
#: track's options that override a setting of the tracking config, and that setting
CONFIG_OPTIONS = {
    "--model": "observation.model", "--voxel": "observation.voxel_m", "--scale": "observation.scale",
    "--workers": "observation.workers", "--fill-static-subject": "observation.fill_static_subject",
    "--refine-passes": "background_refinement.passes", "--refit-passes": "body_refit.passes",
    "--smooth-hz": "smoothing.cutoff_hz",
}
CONFIG_NOTE = re.compile(r"default from --config: (\w+)\.(\w+), (\S+) in markerless\.yaml")


def _parsers(parser: argparse.ArgumentParser):
    """``parser`` and all its sub-parsers, recursively, each once."""
    yield parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for child in dict.fromkeys(action.choices.values()):
                yield from _parsers(child)


def _rendered(parser: argparse.ArgumentParser, action: argparse.Action) -> str:
    """``action.help`` formatted with the action's attributes, as argparse formats it."""
    params = dict(vars(action), prog=parser.prog)
    params = {k: v for k, v in params.items() if v is not argparse.SUPPRESS}
    params = {k: getattr(v, "__name__", v) for k, v in params.items()}
    if params.get("choices") is not None:
        params["choices"] = ", ".join(str(c) for c in params["choices"])
    return action.help % params


def _mentions_default(text: str, default) -> bool:
    values = default if isinstance(default, (list, tuple)) else [default]
    return all(str(v) in text for v in values)


def _commands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """The sub-parsers of ``parser`` by command name."""
    return next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices


@pytest.fixture(scope="module")
def parser():
    return build_parser()


def test_every_option_has_help_that_states_its_default(parser):
    seen = 0
    for p in _parsers(parser):
        p.format_help()  # renders (no bad % in a help string)
        for action in p._actions:
            if isinstance(action, argparse._SubParsersAction):
                for choice in action._choices_actions:
                    assert choice.help and choice.help.strip(), f"{p.prog} {choice.dest}: no help line"
                continue
            where = f"{p.prog} {'/'.join(action.option_strings) or action.dest}"
            assert action.help and action.help is not argparse.SUPPRESS and action.help.strip(), f"{where}: no help"
            seen += 1
            default = action.default
            if default is None or default is False or default is argparse.SUPPRESS:
                continue
            text = _rendered(p, action)
            assert _mentions_default(text, default), f"{where}: help {text!r} does not state its default {default!r}"
    assert seen > 40


def test_root_help_lists_each_command_on_one_line(parser, capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "80")
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert "``" not in out
    names = list(_commands(parser))
    assert set(COMMANDS) <= set(names)
    listing = out.split("COMMAND\n", 1)[1].split("\n\n", 1)[0].splitlines()
    assert [line.split()[0] for line in listing] == names  # one line each, none wrapped
    for example in ("torchtrack synth --out", "torchtrack track", "torchtrack eval"):
        assert example in out


@pytest.mark.parametrize("argv, expect", [
    (["nosuchcommand"], "invalid choice: 'nosuchcommand'"),
    (["track", "--no-such-option", "x"], "unrecognized arguments: --no-such-option"),
    (["track", "seq", "--out", "o", "--no-such-option"], "unrecognized arguments: --no-such-option"),
    (["track", "seq"], "the following arguments are required: --out"),
    (["calib", "convert", "in.toml"], "the following arguments are required: OUT"),
    ([], "the following arguments are required: COMMAND"),
])
def test_bad_input_prints_the_usage_and_the_commands(parser, argv, expect, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    err = captured.err
    assert "usage:" in err and expect in err
    for name in COMMANDS:
        assert name in err
    for name, help_line in command_lines(parser):
        assert re.search(rf"^  {re.escape(name)}\s+{re.escape(help_line)}$", err, re.MULTILINE), name
    if argv[:1] == ["track"]:
        assert "usage: torchtrack track" in err  # the sub-command's usage, not the root's


def test_track_help_quotes_the_shipped_config(parser, capsys, monkeypatch):
    config = yaml.safe_load(CONFIG.read_text(encoding="utf-8"))
    track = _commands(parser)["track"]
    notes = {}
    for action in track._actions:
        found = CONFIG_NOTE.findall(_rendered(track, action)) if action.help else []
        if found:
            notes[[o for o in action.option_strings if o.startswith("--")][0]] = found  # --x of --x / --no-x
    assert set(notes) == set(CONFIG_OPTIONS)
    for option, found in notes.items():
        ((section, key, printed),) = found
        assert f"{section}.{key}" == CONFIG_OPTIONS[option]
        assert yaml.safe_load(printed) == config[section][key], option
    monkeypatch.setenv("COLUMNS", "100")
    with pytest.raises(SystemExit):
        main(["track", "--help"])
    out = " ".join(capsys.readouterr().out.split())  # the help as printed, unwrapped
    for option, setting in CONFIG_OPTIONS.items():
        section, key = setting.split(".")
        value = config[section][key]
        text = str(value).lower() if isinstance(value, bool) else f"{value:g}" if isinstance(value, float) \
            else str(value)
        assert f"default from --config: {setting}, {text} in markerless.yaml" in out, option


def test_version_and_verbose_after_the_command(capsys, tmp_path):
    from torchtrack import __version__
    from torchtrack.checks import InputError

    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0 and capsys.readouterr().out.strip() == f"torchtrack {__version__}"
    missing = str(tmp_path / "missing.toml")
    assert main(["calib", "show", missing]) == 2  # an input error: one line
    for argv in (["-v", "calib", "show", missing], ["calib", "show", missing, "-v"]):
        with pytest.raises(InputError, match="missing.toml"):  # -v: the traceback, before or after the command
            main(argv)


def test_configs_by_name_and_listed_in_the_help(parser):
    from torchtrack.checks import InputError
    from torchtrack.resources import CONFIG_DIR, builtin_configs
    from torchtrack.tracking.pipeline import load_config

    names = sorted(p.stem for p in CONFIG_DIR.glob("markerless*.yaml"))
    assert builtin_configs() == names and "markerless_fast" in names
    assert load_config("markerless_fast")["source"] == str(CONFIG_DIR / "markerless_fast.yaml")
    assert load_config("markerless_fast.yaml")["source"] == str(CONFIG_DIR / "markerless_fast.yaml")
    with pytest.raises(InputError, match="built-in tracking configs: " + ", ".join(names)):
        load_config("no_such_config")
    help_text = " ".join(_commands(parser)["track"].format_help().split())
    assert f"a built-in name ({', '.join(names)})" in help_text
