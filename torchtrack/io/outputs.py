"""Output paths, checked before any work: torchtrack never deletes or mixes into what it did not write.

Every command that writes names its output's *kind* (a track folder, a synthetic sequence, a poses file, ...).
:func:`check_output` runs before the command reads anything:

* a path that does not exist (or an empty folder) is written;
* a path that holds torchtrack's own earlier output of the same kind is replaced only with ``--overwrite``;
* anything else (a user's files, a folder where a file goes, a file where a folder goes, a parent that is a file)
  is refused with an :class:`~torchtrack.checks.InputError` naming the path and what is there.

"Own output" is recognised by content, so outputs written before this check existed count too: a folder whose
visible entries are all ones that kind writes (a synthetic sequence also needs meta.toml's ``[synth]`` table), a
file that parses as that kind. Folder outputs written in place (a track's TensorBoard logs grow during the run)
are replaced through :func:`replacing`: the old entries are moved aside and come back if the run fails or is
interrupted. Single files are written atomically by their writers (:mod:`torchtrack.io.atomic`).
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
import zipfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

from torchtrack.checks import InputError

try:  # Python >= 3.11
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    import tomli as tomllib

__all__ = ["OutputKind", "TRACK_DIR", "OBSERVE_DIR", "SEQUENCE_DIR", "EASYMOCAP_FILE", "POSES_FILE", "JSON_REPORT",
           "CALIBRATION_FILE", "check_output", "replacing"]


@dataclass(frozen=True)
class OutputKind:
    """What one command writes at its output path.

    Attributes:
        name: how messages call it ("track output", "synthetic sequence", ...).
        folder: True for a folder output, False for a single file.
        entries: a folder's own entries (files and sub-folders), each one optional.
        is_own: for a folder, a further test of its content; for a file, the test that it is this kind.
    """

    name: str
    folder: bool
    entries: frozenset[str] = frozenset()
    is_own: Callable[[Path], bool] | None = None


def _synth_meta(folder: Path) -> bool:
    """Whether ``folder/meta.toml`` has the ``[synth]`` table that `torchtrack synth` writes."""
    try:
        return isinstance(tomllib.loads((folder / "meta.toml").read_text(encoding="utf-8")).get("synth"), dict)
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return False


def _npz_with(keys: set[str]) -> Callable[[Path], bool]:
    def test(path: Path) -> bool:
        try:
            with zipfile.ZipFile(path) as z:
                return keys <= {n.removesuffix(".npy") for n in z.namelist()}
        except (OSError, zipfile.BadZipFile):
            return False
    return test


def _json_with(keys: set[str]) -> Callable[[Path], bool]:
    def test(path: Path) -> bool:
        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, ValueError):
            return False
        return isinstance(doc, dict) and keys <= set(doc)
    return test


def _calibration(path: Path) -> bool:
    """A TOML file of camera tables, as `calib convert` writes (any readable calibration TOML)."""
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return False
    return bool(doc) and all(isinstance(v, dict) for k, v in doc.items() if k != "metadata")


def _opencv_yaml(path: Path) -> bool:
    """An OpenCV FileStorage YAML file (EasyMocap's intri.yml / extri.yml)."""
    try:
        with path.open("rb") as f:
            return f.read(5) == b"%YAML"
    except OSError:
        return False


TRACK_DIR = OutputKind("track output", True, frozenset({"poses.npz", "tb"}))
OBSERVE_DIR = OutputKind("occupancy output", True, frozenset({"occupancy.npz", "tb"}))
SEQUENCE_DIR = OutputKind("synthetic sequence", True,
                          frozenset({"calibration.toml", "video", "frames", "background", "gt.npz", "meta.toml",
                                     "body.urdf"}),
                          _synth_meta)
EASYMOCAP_FILE = OutputKind("EasyMocap calibration file", False, is_own=_opencv_yaml)
POSES_FILE = OutputKind("poses file", False, is_own=_npz_with({"joint_names", "joints3d", "valid"}))
JSON_REPORT = OutputKind("evaluation report", False, is_own=_json_with({"pred", "gt"}))
CALIBRATION_FILE = OutputKind("calibration file", False, is_own=_calibration)


def _visible(folder: Path) -> list[str]:
    """The folder's entries, hidden ones (temporaries of atomic writes, .DS_Store) left out."""
    return sorted(p.name for p in folder.iterdir() if not p.name.startswith("."))


def _listing(names: list[str], limit: int = 5) -> str:
    shown = ", ".join(names[:limit])
    return shown + (f" and {len(names) - limit} more" if len(names) > limit else "")


def _a(name: str) -> str:
    return ("an " if name[0] in "aeiou" else "a ") + name


def _check_parent(path: Path, option: str) -> None:
    """The nearest existing ancestor of ``path`` must be a writable folder."""
    parent = path.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise InputError(f"{option} {path}: {parent} is a file, not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(f"{option} {path}: {parent} is not writable")


def check_output(path: str | Path, kind: OutputKind, overwrite: bool, option: str = "--out") -> bool:
    """Check an output path before any work (module docstring).

    Args:
        path: the output path. kind: what will be written there. overwrite: the user's ``--overwrite``.
        option: the option that named the path, for messages.

    Returns:
        True when ``path`` holds an earlier output of this kind that will be replaced, False when it is new
        (or an empty folder).

    Raises:
        InputError: the path holds something else, or an earlier output and ``overwrite`` is False.
    """
    path = Path(path)
    _check_parent(path, option)
    if not path.exists() and not path.is_symlink():
        return False
    where = f"{option} {path}"
    if kind.folder:
        if not path.is_dir():
            raise InputError(f"{where}: is a file; the {kind.name} is a folder: give a new or empty folder")
        names = _visible(path)
        if not names:
            return False
        foreign = [n for n in names if n not in kind.entries]
        if foreign or (kind.is_own is not None and not kind.is_own(path)):
            what = f"files torchtrack did not write there ({_listing(foreign)})" if foreign else (
                f"something other than {_a(kind.name)} ({_listing(names)})")
            raise InputError(f"{where}: holds {what}; refused so that nothing is lost: give a new or empty folder")
    else:
        if path.is_dir():
            raise InputError(f"{where}: is a folder; the {kind.name} is a file: give a file path")
        if kind.is_own is not None and not kind.is_own(path):
            raise InputError(f"{where}: exists and is not {_a(kind.name)} torchtrack wrote; refused so that nothing "
                             "is lost: give another path")
    if not overwrite:
        raise InputError(f"{where}: already holds {_a(kind.name)}; pass --overwrite to replace it")
    return True


@contextlib.contextmanager
def replacing(folder: str | Path, kind: OutputKind) -> Iterator[Path]:
    """Write a folder output in place over an earlier one of ``kind`` (checked with :func:`check_output`).

    The earlier output's entries are moved aside into a hidden folder inside ``folder`` before the body runs.
    If it completes, they are deleted; if it raises (an error, Ctrl-C), what it wrote of ``kind``'s entries is
    removed and the earlier ones come back, so ``folder`` is as it was. Without an earlier output, what the body
    wrote is kept either way (a failed run's logs show how far it got).
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    old = [folder / e for e in sorted(kind.entries) if (folder / e).exists()]
    aside = Path(tempfile.mkdtemp(prefix=".replaced.", dir=folder)) if old else None
    for p in old:
        os.replace(p, aside / p.name)
    try:
        yield folder
    except BaseException:
        if aside is not None:
            for e in kind.entries:
                new = folder / e
                if new.is_dir() and not new.is_symlink():
                    shutil.rmtree(new, ignore_errors=True)
                elif new.exists() or new.is_symlink():
                    new.unlink()
            for p in aside.iterdir():
                os.replace(p, folder / p.name)
            aside.rmdir()
        raise
    if aside is not None:
        shutil.rmtree(aside, ignore_errors=True)
