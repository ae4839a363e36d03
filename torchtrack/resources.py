"""Where the built-in configuration files live (the repository's ``configs/`` folder)."""

from __future__ import annotations

from pathlib import Path

from torchtrack.checks import InputError

CONFIG_DIR = Path(__file__).resolve().parents[1] / "configs"
_INSTALL_HINT = ("torchtrack is meant to be installed with `pip install -e .` from its repository so that configs/ "
                 "is found")


def builtin_config(name: str) -> Path:
    """The built-in ``configs/NAME`` itself, whatever the working directory holds (a sequence folder has its
    subject's own ``body.urdf``, which :func:`config_path` would take for a bare ``body.urdf``)."""
    p = CONFIG_DIR / name
    if not p.is_file():
        raise InputError(f"built-in config not found: {p} ({_INSTALL_HINT})")
    return p


def config_path(name: str | Path) -> Path:
    """Resolve a config: an existing path as given, else (for a bare file name) the built-in ``configs/NAME``."""
    p = Path(name)
    if p.is_file():
        return p
    if p.parent != Path("."):
        raise InputError(f"config file not found: {p}")
    if not (CONFIG_DIR / p.name).is_file():
        raise InputError(f"config file not found: {p} (nor {CONFIG_DIR / p.name}; {_INSTALL_HINT})")
    return builtin_config(p.name)
