"""Output paths, checked before any work: torchtrack never deletes or mixes into what it did not write.

Every command that writes names its output's *kind* (a track folder, a synthetic sequence, a poses file, ...).
:func:`check_output` runs before the command reads anything:

* a path that does not exist (or an empty folder) is written;
* a path that holds torchtrack's own earlier output of the same kind is replaced only with ``--overwrite``;
* anything else (a user's files, a folder where a file goes, a file where a folder goes, a parent that is a file)
  is refused with an :class:`~torchtrack.checks.InputError` naming the path and what is there.

"Own output" is recognised by content, so outputs written before this check existed count too: a folder whose
entries are all ones that kind writes, each of the content that kind writes (a ``poses.npz`` that is a poses
file, a ``tb/`` of TensorBoard event files, a synthetic sequence with meta.toml's ``[synth]`` table and only
videos and frames in its camera folders), a file that parses as that kind. Hidden entries count as the user's
(a synthetic sequence is replaced whole), except the temporaries of this module and of atomic writes. Folder
outputs written in place (a track's TensorBoard logs grow during the run) are replaced through
:func:`replacing`: the old entries are moved aside and come back if the run fails or is interrupted. Single files
are written atomically by their writers (:mod:`torchtrack.io.atomic`).
"""

from __future__ import annotations

import contextlib
import json
import logging
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

log = logging.getLogger(__name__)

__all__ = ["OutputKind", "TRACK_DIR", "OBSERVE_DIR", "SEQUENCE_DIR", "MARKERS_DIR", "EASYMOCAP_FILE", "POSES_FILE",
           "JSON_REPORT", "CALIBRATION_FILE", "check_output", "replacing",
           "script_work_folder"]


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


#: Prefix of the folder :func:`replacing` moves an earlier output into.
ASIDE_PREFIX = ".replaced."


def _synth_sequence(folder: Path) -> bool:
    """Whether ``folder`` is a sequence `torchtrack synth` wrote: meta.toml with its ``[synth]`` table, and in
    ``video/``, ``frames/`` and ``background/`` only video files and folders of images."""
    from torchtrack.io.video import IMAGE_SUFFIXES, VIDEO_SUFFIXES

    try:
        if not isinstance(tomllib.loads((folder / "meta.toml").read_text(encoding="utf-8")).get("synth"), dict):
            return False
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return False
    for sub in ("video", "frames", "background"):
        if not (folder / sub).is_dir():
            continue
        for entry in (folder / sub).iterdir():
            if entry.is_dir():
                if any(not f.is_file() or f.suffix.lower() not in IMAGE_SUFFIXES for f in entry.iterdir()):
                    return False
            elif entry.suffix.lower() not in VIDEO_SUFFIXES:
                return False
    return True


def _event_files(tb: Path) -> bool:
    """Whether ``tb`` holds only TensorBoard event files, at its top and in ``body_refit_N/`` runs."""
    for entry in tb.iterdir():
        if entry.is_dir() and entry.name.startswith("body_refit_"):
            if not _event_files(entry) or any(e.is_dir() for e in entry.iterdir()):
                return False
        elif not (entry.is_file() and entry.name.startswith("events.out.tfevents.")):
            return False
    return True


def _run_folder(result: str, keys: set[str]) -> Callable[[Path], bool]:
    """A track's or observe's folder: its ``result`` npz holding ``keys``, its ``tb/`` only event files."""
    def test(folder: Path) -> bool:
        if (folder / result).exists() and not _npz_with(keys)(folder / result):
            return False
        return not (folder / "tb").exists() or ((folder / "tb").is_dir() and _event_files(folder / "tb"))
    return test


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
    """A native calibration TOML, as `calib convert` writes: camera tables with a matrix, a rotation and a
    translation each (and any ``[metadata]``)."""
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return False
    cameras = [v for k, v in doc.items() if k != "metadata"]
    return bool(cameras) and all(isinstance(v, dict) and {"matrix", "rotation", "translation"} <= set(v)
                                 for v in cameras)


def _opencv_yaml(path: Path) -> bool:
    """An OpenCV FileStorage YAML file with camera matrices (EasyMocap's intri.yml / extri.yml)."""
    try:
        text = path.read_bytes()
    except OSError:
        return False
    return text.startswith(b"%YAML") and (b"\nK_" in text or b"\nR_" in text or b"\nRot_" in text)


TRACK_DIR = OutputKind("track output", True, frozenset({"poses.npz", "tb"}),
                       _run_folder("poses.npz", {"joint_names", "joints3d", "valid"}))
OBSERVE_DIR = OutputKind("occupancy output", True, frozenset({"occupancy.npz", "tb"}),
                         _run_folder("occupancy.npz", {"frame_index", "frame_offsets", "centres"}))
SEQUENCE_DIR = OutputKind("synthetic sequence", True,
                          frozenset({"calibration.toml", "video", "frames", "background", "gt.npz", "meta.toml",
                                     "body.urdf", "marker_labels.csv", "markers2d.npz"}),
                          _synth_sequence)
MARKERS_DIR = OutputKind("simulated marker capture", True, frozenset({"calibration.toml", "markers2d.npz", "gt.npz"}),
                         lambda folder: _npz_with({"uv", "marker_names"})(folder / "markers2d.npz"))
EASYMOCAP_FILE = OutputKind("EasyMocap calibration file", False, is_own=_opencv_yaml)
POSES_FILE = OutputKind("poses file", False, is_own=_npz_with({"joint_names", "joints3d", "valid"}))
JSON_REPORT = OutputKind("evaluation report", False, is_own=_json_with({"pred", "gt"}))
CALIBRATION_FILE = OutputKind("calibration file", False, is_own=_calibration)


def _entries(folder: Path, kind: OutputKind) -> list[str]:
    """The folder's entries but the temporaries of an atomic write of one of ``kind``'s entries (``.NAME.*``)
    and macOS's ``.DS_Store``: what decides whose the folder is."""
    def temporary(name: str) -> bool:
        return name == ".DS_Store" or any(name.startswith(f".{e}.") for e in kind.entries)
    return sorted(p.name for p in folder.iterdir() if not temporary(p.name))


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
    where = f"{option} {path}"
    if path.is_symlink() and not path.exists():
        raise InputError(f"{where}: is a link to {os.readlink(path)}, which does not exist")
    if not path.exists():
        return False
    if kind.folder:
        if not path.is_dir():
            raise InputError(f"{where}: is a file; the {kind.name} is a folder: give a new or empty folder")
        names = _entries(path, kind)
        aside = [n for n in names if n.startswith(ASIDE_PREFIX)]
        if aside:
            raise InputError(f"{where}: holds {path / aside[0]}, an earlier output an interrupted run set aside; "
                             f"move its contents back into {path} (or delete it) and run again")
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
    aside = Path(tempfile.mkdtemp(prefix=ASIDE_PREFIX, dir=folder)) if old else None
    for p in old:
        os.replace(p, aside / p.name)
    try:
        yield folder
    except BaseException:
        if aside is not None:
            try:
                for e in kind.entries:
                    new = folder / e
                    if new.is_dir() and not new.is_symlink():
                        shutil.rmtree(new)
                    elif new.exists() or new.is_symlink():
                        new.unlink()
                for p in aside.iterdir():
                    os.replace(p, folder / p.name)
                aside.rmdir()
            except OSError as exc:  # the run's own error goes on; say where the earlier output is
                log.error("%s: could not put the earlier output back (%s); it is in %s", folder, exc, aside)
        raise
    if aside is not None:
        shutil.rmtree(aside, ignore_errors=True)


def script_work_folder(path: str | Path, script: str, empty: bool = True) -> Path:
    """A measurement script's work folder: a new or empty folder, or one this ``script`` wrote before (marked by a
    ``.<script>`` file), whose contents are deleted first unless ``empty`` is False (a cache of rendered sequences
    that the script checks itself); anything else is refused (a typo in ``--out`` must not delete a user's
    folder)."""
    path, mark = Path(path), f".{script}"
    if path.exists() and any(path.iterdir()):
        if not (path / mark).is_file():
            raise InputError(f"--out {path}: not empty and not the work folder of {script}; give another")
        if not empty:
            return path
        shutil.rmtree(path)
    path.mkdir(parents=True, exist_ok=True)
    (path / mark).write_text(f"work folder of scripts/{script}.py\n")
    return path
