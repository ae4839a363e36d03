"""Where the built-in configuration files live (the repository's ``configs/`` folder)."""

from __future__ import annotations

from pathlib import Path

from torchtrack.checks import InputError

CONFIG_DIR = Path(__file__).resolve().parents[1] / "configs"


def config_path(name: str | Path) -> Path:
    """Resolve a config: an existing path as given, else (for a bare file name) the built-in ``configs/NAME``."""
    p = Path(name)
    if p.is_file():
        return p
    q = CONFIG_DIR / p.name
    if p.parent == Path(".") and q.is_file():
        return q
    hint = "" if p.parent != Path(".") else (f" (nor {q}; torchtrack is meant to be installed with "
                                             "`pip install -e .` from its repository so that configs/ is found)")
    raise InputError(f"config file not found: {p}{hint}")
