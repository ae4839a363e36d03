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


def builtin_configs(prefix: str = "markerless") -> list[str]:
    """Names (without ``.yaml``) of the built-in YAML configs starting with ``prefix``: the tracking configs."""
    return sorted(p.stem for p in CONFIG_DIR.glob(f"{prefix}*.yaml"))


def config_path(name: str | Path) -> Path:
    """Resolve a config: an existing path as given, else (for a bare name) the built-in ``configs/NAME``, with
    ``.yaml`` added where the name has no suffix (``markerless_fast`` -> ``configs/markerless_fast.yaml``)."""
    p = Path(name)
    if p.is_file():
        return p
    if p.parent != Path("."):
        raise InputError(f"config file not found: {p}")
    for candidate in (p.name, p.name + ".yaml") if not p.suffix else (p.name,):
        if (CONFIG_DIR / candidate).is_file():
            return builtin_config(candidate)
    known = ", ".join(builtin_configs()) or "none"
    raise InputError(f"config file not found: {p} (nor {CONFIG_DIR / p.name}; built-in tracking configs: {known}; "
                     f"{_INSTALL_HINT})")
