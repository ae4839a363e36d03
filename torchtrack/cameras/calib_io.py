"""Calibration files: torchtrack's native TOML, and auto-detected imports of other rigs' formats.

Native TOML (the anipose / Pose2Sim layout, see docs/formats.md): one table per camera with
``name``, ``size = [W, H]``, ``matrix`` (3x3 px), ``distortions`` (4 or 5 OpenCV coefficients; fisheye: 4),
``rotation`` (Rodrigues vector, world -> camera), ``translation`` and an optional ``fisheye``. A top-level
table is a camera when it has any of ``matrix``, ``distortions``, ``rotation``, ``translation``; other tables
(``[metadata]``, ...) are ignored. A missing ``name`` defaults to the table's key.

What "exact" means for ``read_native_toml(write_native_toml(rig))``:

* names, sizes, fisheye flags and every value of ``K``, ``dist`` and ``t_cam_world`` come back bit-identical
  in the rig's dtype (float64 rigs are written with Python's shortest round-trip ``repr``, float32 rigs with
  the shortest string that reads back as the same float32);
* ``R_cam_world`` is stored as a Rodrigues vector (that is the format), written with full float64 precision;
  both conversions (kornia, via quaternions) are accurate to ~1e-16, so R comes back within 1e-15 for
  float64 rigs. A float32 R is the rounding of a rotation, not a rotation itself, so it comes back within one
  float32 ulp (6e-8), not always bit-identical: load in float64 (``dtype=torch.float64``) for exact work.

Other formats are read by :mod:`torchtrack.cameras.calib_formats`; :func:`load_calibration` picks the reader.
Bad input raises :class:`~torchtrack.checks.InputError` naming the file, the camera and the field.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np
import torch

from torchtrack.cameras import _fields as F
from torchtrack.cameras import calib_formats
from torchtrack.cameras.rig import CameraRig
from torchtrack.checks import InputError, check_file
from torchtrack.io.atomic import write_text_atomic

log = logging.getLogger(__name__)

#: Keys that make a top-level TOML table a camera table.
_CAMERA_KEYS = frozenset({"matrix", "distortions", "rotation", "translation"})
_BARE_KEY = re.compile(r"^[A-Za-z0-9_-]+$")


# ------------------------------------------------------------------------------------------------- reading
def _native_camera(key: str, table: dict, path: Path) -> F.CameraRecord:
    name = table.get("name", key)
    if isinstance(name, int) and not isinstance(name, bool):
        name = str(name)
    if not isinstance(name, str) or not name:
        raise F.Where(path, key).error("name", f"expected a non-empty string, got {name!r}")
    where = F.Where(path, name)
    fisheye = table.get("fisheye", False)
    if not isinstance(fisheye, bool):
        raise where.error("fisheye", f"expected true or false, got {fisheye!r}")
    size = F.image_size(table.get("size"), where, "size")  # fields checked in the order files list them
    K = F.intrinsics(table.get("matrix"), where, "matrix")
    dist = F.distortions(table.get("distortions"), fisheye, where, "distortions")
    rotvec = F.numbers(table.get("rotation"), ((3,), (3, 1), (1, 3)), where, "rotation").reshape(3)
    t = F.numbers(table.get("translation"), ((3,), (3, 1), (1, 3)), where, "translation").reshape(3)
    return F.CameraRecord(name=name, K=K, dist=dist, R_cam_world=F.rotvec_to_matrix(rotvec), t_cam_world=t,
                          size_wh=size, fisheye=fisheye)


def native_records(data: dict, path: str | Path) -> list[F.CameraRecord]:
    """Camera records of a parsed native TOML document, in file order."""
    path = Path(path)
    return [_native_camera(key, table, path) for key, table in data.items()
            if isinstance(table, dict) and key != "metadata" and _CAMERA_KEYS & table.keys()]


def read_native_toml(path: str | Path, dtype: torch.dtype = torch.float32) -> CameraRig:
    """Read a native (anipose / Pose2Sim) calibration TOML. Units are kept as in the file.

    Args:
        path: the ``.toml`` file.
        dtype: float dtype of the rig's buffers (values are parsed in float64, then cast).

    Raises:
        InputError: unreadable file, invalid TOML, no cameras, or a bad field (naming file, camera, field).
    """
    return F.build_rig(native_records(F.read_toml_file(path), path), path, dtype)


# ------------------------------------------------------------------------------------------------- writing
def toml_string(s: str) -> str:
    """A TOML basic string (quotes, backslashes and control characters escaped)."""
    out = []
    for ch in s:
        if ch in '"\\':
            out.append("\\" + ch)
        elif ord(ch) < 0x20 or ord(ch) == 0x7F:
            out.append(f"\\u{ord(ch):04X}")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def _float_formatter(dtype: torch.dtype):
    """Shortest text that reads back (as float64, then cast) to the same value in ``dtype``."""
    if dtype == torch.float64:
        return lambda x: repr(float(x))
    # float32 (and narrower): numpy's shortest float32 repr, re-spelled by Python (valid TOML either way).
    return lambda x: repr(float(str(np.float32(x))))


def native_toml_text(rig: CameraRig) -> str:
    """The native TOML document of ``rig`` (see the module docstring for the layout and exactness)."""
    fmt = _float_formatter(rig.K.dtype)
    full = _float_formatter(torch.float64)

    def arr(values, f=fmt) -> str:
        values = np.asarray(values)
        if values.ndim > 1:
            return "[" + ", ".join(arr(v, f) for v in values) + "]"
        return "[" + ", ".join(f(v) for v in values) + "]"

    used: set[str] = set()
    blocks = []
    for i, cam in enumerate(F.rig_records(rig)):
        key = cam.name if _BARE_KEY.match(cam.name) and cam.name != "metadata" else f"cam_{i}"
        while key in used:
            key = f"{key}_"
        used.add(key)
        dist = cam.dist[:4] if cam.fisheye else cam.dist
        blocks.append("\n".join([
            f"[{key}]",
            f"name = {toml_string(cam.name)}",
            f"size = [{cam.size_wh[0]}, {cam.size_wh[1]}]",
            f"matrix = {arr(cam.K)}",
            f"distortions = {arr(dist)}",
            f"rotation = {arr(F.matrix_to_rotvec(cam.R_cam_world), full)}",
            f"translation = {arr(cam.t_cam_world)}",
            f"fisheye = {'true' if cam.fisheye else 'false'}",
        ]))
    return "\n\n".join(blocks) + "\n"


def write_native_toml(rig: CameraRig, path: str | Path) -> None:
    """Write ``rig`` as native calibration TOML, atomically (a reader sees the old file or the new one)."""
    write_text_atomic(path, native_toml_text(rig))


# ------------------------------------------------------------------------------------------------ dispatch

#: The formats :func:`detect_format` recognises, for messages.
KNOWN_FORMATS = ("native / anipose / Pose2Sim TOML (calibration.toml), caliscope camera_array.toml, Qualisys QTM "
                 ".qca XML (.qca, .qca.txt, .xml), EasyMocap / OpenCV YAML (intri.yml + extri.yml)")


def detect_format(path: str | Path) -> str:
    """``"native"``, ``"caliscope"``, ``"qualisys"`` or ``"easymocap"`` for a calibration path.

    Folders: EasyMocap when they hold ``intri.yml``, native when they hold ``calibration.toml``.
    Files: by extension (``.qca``, ``.qca.txt``, ``.xml``; ``.yml``/``.yaml``; ``.toml``: caliscope when it
    has a ``[cameras.N]`` table, else native), otherwise by the first characters of the content.
    """
    p = Path(path)
    if p.is_dir():
        if (p / "intri.yml").is_file() or (p / "intri.yaml").is_file():
            return "easymocap"
        if (p / "calibration.toml").is_file():
            return "native"
        raise InputError(f"{p}: folder holds no calibration (intri.yml + extri.yml, or calibration.toml)")
    check_file(p, "calibration file")
    name = p.name.lower()
    if name.endswith((".qca", ".qca.txt", ".xml")):
        return "qualisys"
    if name.endswith((".yml", ".yaml")):
        return "easymocap"
    if not name.endswith(".toml"):
        head = p.read_bytes()[:64].lstrip()
        if head.startswith(b"<"):
            return "qualisys"
        if head.startswith(b"%YAML"):
            return "easymocap"
        try:
            doc = F.read_toml_file(p)
        except InputError:
            raise InputError(f"{p}: not a calibration format torchtrack reads; it knows {KNOWN_FORMATS}") from None
        if not doc or not all(isinstance(v, dict) for v in doc.values()):
            raise InputError(f"{p}: not a calibration format torchtrack reads; it knows {KNOWN_FORMATS}")
    cameras = F.read_toml_file(p).get("cameras")
    if isinstance(cameras, dict) and cameras and all(isinstance(v, dict) for v in cameras.values()):
        return "caliscope"
    return "native"


#: Camera centres farther than this from the world origin (m) mean translations in another unit (mm, cm): no
#: capture room is that large, and millimetres read as metres put a 3 m ring 3 km away.
MAX_CAMERA_DISTANCE_M = 100.0


def check_translation_units(rig: CameraRig, where: str) -> None:
    """Refuse a rig whose camera centres lie farther than :data:`MAX_CAMERA_DISTANCE_M` from the origin (its
    translations are likely in millimetres), naming ``where``, the farthest camera and the conversion."""
    dist = rig.centers().detach().double().norm(dim=-1)
    far = int(dist.argmax())
    d = float(dist[far])
    if d > MAX_CAMERA_DISTANCE_M:
        raise InputError(
            f"{where}: camera '{rig.names[far]}' is {d:,.0f} units from the world origin, farther than "
            f"{MAX_CAMERA_DISTANCE_M:g} m if they were metres: the translations look like millimetres (or "
            f"centimetres); "
            f"convert with `torchtrack calib convert IN OUT.toml --translation-scale 0.001` (0.01 for cm)")


def load_calibration(path: str | Path, dtype: torch.dtype = torch.float32, warn_units: bool = True) -> CameraRig:
    """Load a calibration in any supported format (:func:`detect_format`) as a CameraRig.

    Args:
        path: native / anipose / Pose2Sim TOML, caliscope ``camera_array.toml``, Qualisys ``.qca`` XML (also
            ``.qca.txt``), EasyMocap ``intri.yml`` / ``extri.yml`` (either file, or their folder), or a
            sequence folder holding ``calibration.toml``.
        dtype: float dtype of the rig's buffers.
        warn_units: warn when the translations look like millimetres (:func:`check_translation_units`; they are
            kept as they are: a rig of mouse cameras may be calibrated in mm on purpose; a sequence folder refuses
            them).

    Raises:
        InputError: naming the file (and camera and field) for anything unreadable or invalid.
    """
    fmt = detect_format(path)
    p = Path(path)
    log.debug("%s: reading %s calibration", p, fmt)
    if fmt == "native":
        rig = read_native_toml(p / "calibration.toml" if p.is_dir() else p, dtype)
    elif fmt == "caliscope":
        rig = calib_formats.read_caliscope_toml(p, dtype)
    elif fmt == "qualisys":
        rig = calib_formats.read_qualisys_qca(p, dtype)
    else:
        rig = calib_formats.read_easymocap_yaml(p, dtype)
    if warn_units:
        try:
            check_translation_units(rig, str(p))
        except InputError as exc:
            log.warning("%s", exc)
    return rig


def save_calibration(rig: CameraRig, path: str | Path) -> None:
    """Save ``rig`` as native calibration TOML (atomically)."""
    write_native_toml(rig, path)
