"""Readers (and one writer) for other rigs' calibration files; all return a :class:`CameraRig`.

* caliscope ``camera_array.toml``: ``[cameras.N]`` tables with ``size``, ``matrix``, ``distortions``,
  ``rotation`` (3x3 MATRIX, world -> camera: caliscope projects with ``matrix @ [rotation | translation]``)
  and ``translation`` (m); other fields ignored. Cameras are named ``port_N`` (caliscope's recordings are
  ``port_N.mp4``); cameras with ``ignore = true`` are skipped. ``rotation_count`` (display rotation) is ignored.
* Qualisys QTM ``.qca`` XML export (also ``.qca.txt``): per ``<camera serial=...>``: ``<transform>`` holds the
  camera centre C (x, y, z in mm) and a 3x3 matrix M (r11..r33); world -> OpenCV camera is
  ``R = diag(1, -1, -1) @ M``, ``t = -R @ C`` with C in metres. ``<intrinsic>`` focal lengths and principal
  point are in 1/64 px; distortion ``(k1, k2, p1, p2, k3)`` = (radialDistortion1, radialDistortion2,
  tangentalDistortion1, tangentalDistortion2, radialDistortion3), used as written. Image size from
  ``<fov_video>``: ``(right - left + 1, bottom - top + 1)``; the principal point is shifted by (left, top).
  (Pose2Sim's converter also divides the distortion coefficients by 64 and names the cameras ``cam_01``
  where the serials say ``cam01``.)
* EasyMocap / OpenCV YAML: ``intri.yml`` (``names``, ``K_<cam>``, ``dist_<cam>`` or ``D_<cam>``, optional
  ``H_<cam>``/``W_<cam>``) and ``extri.yml`` (``R_<cam>`` Rodrigues or ``Rot_<cam>`` 3x3, ``T_<cam>``), read
  with ``cv2.FileStorage``. Without ``W_``/``H_`` the image size is estimated as ``2 c + 1`` (a warning says
  so). :func:`write_easymocap_yaml` writes both files.

OpenCV is imported inside the functions that need it.
"""

from __future__ import annotations

import logging
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import torch

from torchtrack.cameras import _fields as F
from torchtrack.cameras.rig import CameraRig
from torchtrack.checks import InputError, check_file
from torchtrack.io.atomic import atomic_path

log = logging.getLogger(__name__)

_QCA_TO_OPENCV = np.diag([1.0, -1.0, -1.0])  # Qualisys camera axes -> OpenCV (x right, y down, z forward)
_QCA_UNITS_PER_PX = 64.0
_MM_PER_M = 1000.0
_YAML_KEY = re.compile(r"^[A-Za-z0-9_-]+$")


# ------------------------------------------------------------------------------------------------ caliscope
def read_caliscope_toml(path: str | Path, dtype: torch.dtype = torch.float32) -> CameraRig:
    """Read a caliscope ``camera_array.toml`` (layout in the module docstring)."""
    data = F.read_toml_file(path)
    cameras = data.get("cameras")
    if not isinstance(cameras, dict):
        raise F.Where(path).error("cameras", "missing: expected [cameras.N] tables")
    records = []
    for port, table in cameras.items():
        name = f"port_{port}"
        where = F.Where(path, name)
        if not isinstance(table, dict):
            raise where.error(None, f"expected a table, got {table!r}")
        if table.get("ignore", False) is True:
            log.warning("%s: camera %s is marked ignore = true: skipped", path, name)
            continue
        for key in ("matrix", "distortions", "rotation", "translation", "size"):
            if key not in table:
                raise where.error(key, "missing" + (" (extrinsics not calibrated?)"
                                                    if key in ("rotation", "translation") else ""))
        records.append(F.CameraRecord(
            name=name,
            K=F.intrinsics(table["matrix"], where, "matrix"),
            dist=F.distortions(table["distortions"], False, where, "distortions"),
            R_cam_world=F.rotation_matrix(table["rotation"], where, "rotation"),
            t_cam_world=F.numbers(table["translation"], ((3,), (3, 1), (1, 3)), where, "translation").reshape(3),
            size_wh=F.image_size(table["size"], where, "size"),
        ))
    return F.build_rig(records, path, dtype)


# ------------------------------------------------------------------------------------------------- Qualisys
def _attr_floats(element: ET.Element | None, keys: list[str], where: F.Where, tag: str) -> list[float]:
    if element is None:
        raise where.error(tag, f"missing <{tag}> element")
    values = []
    for key in keys:
        text = element.get(key)
        if text is None:
            raise where.error(f"{tag}.{key}", "missing attribute")
        try:
            values.append(float(text))
        except ValueError:
            raise where.error(f"{tag}.{key}", f"not a number: {text!r}") from None
    return values


def _qca_camera(cam: ET.Element, index: int, path: Path, distortion_scale: float) -> F.CameraRecord:
    name = cam.get("serial") or f"camera_{index}"
    where = F.Where(path, name)
    view_rotation = cam.get("viewrotation", "0")
    if view_rotation.strip() not in ("0", ""):
        raise where.error("viewrotation", f"rotated camera views are not supported (got {view_rotation})")
    tr = _attr_floats(cam.find("transform"), ["x", "y", "z"] + [f"r{i}{j}" for i in (1, 2, 3) for j in (1, 2, 3)],
                      where, "transform")
    centre_m = F.numbers(np.array(tr[:3]), ((3,),), where, "transform.xyz") / _MM_PER_M
    M = F.rotation_matrix(np.array(tr[3:]).reshape(3, 3), where, "transform.r11..r33")
    fu, fv, cu, cv = _attr_floats(cam.find("intrinsic"), ["focalLengthU", "focalLengthV", "centerPointU",
                                                           "centerPointV"], where, "intrinsic")
    dist_keys = ["radialDistortion1", "radialDistortion2", "tangentalDistortion1", "tangentalDistortion2",
                 "radialDistortion3"]
    dist = _attr_floats(cam.find("intrinsic"), dist_keys, where, "intrinsic")
    left, top, right, bottom = _attr_floats(cam.find("fov_video"), ["left", "top", "right", "bottom"], where,
                                            "fov_video")
    K = np.array([[fu / _QCA_UNITS_PER_PX, 0.0, cu / _QCA_UNITS_PER_PX - left],
                  [0.0, fv / _QCA_UNITS_PER_PX, cv / _QCA_UNITS_PER_PX - top],
                  [0.0, 0.0, 1.0]])
    R = _QCA_TO_OPENCV @ M
    return F.CameraRecord(
        name=name,
        K=F.intrinsics(K, where, "intrinsic"),
        dist=F.distortions(np.array(dist) * distortion_scale, False, where, "intrinsic.distortion"),
        R_cam_world=R,
        t_cam_world=-R @ centre_m,
        size_wh=F.image_size(np.array([right - left + 1, bottom - top + 1]), where, "fov_video"),
    )


def read_qualisys_qca(path: str | Path, dtype: torch.dtype = torch.float32,
                     distortion_scale: float = 1.0) -> CameraRig:
    """Read a Qualisys QTM ``.qca`` calibration export (conventions in the module docstring).

    Translations come out in metres. ``distortion_scale`` multiplies the distortion coefficients: 1 (the
    default) uses them as written; ``1 / 64`` reproduces Pose2Sim's ``calib_qca`` conversion. On the Pose2Sim
    demo rig the two differ by up to ~2.6 px on the subject and ~7 px towards the image corners.
    """
    p = check_file(path, "calibration file")
    try:
        root = ET.parse(p).getroot()
    except ET.ParseError as exc:
        raise InputError(f"{p}: not valid XML: {exc}") from None
    except OSError as exc:
        raise InputError(f"{p}: cannot read: {exc}") from None
    cameras = root.findall(".//cameras/camera")
    return F.build_rig([_qca_camera(c, i, p, distortion_scale) for i, c in enumerate(cameras)], p, dtype)


# ------------------------------------------------------------------------------------------------ EasyMocap
def _easymocap_paths(path: str | Path) -> tuple[Path, Path]:
    p = Path(path)
    folder = p if p.is_dir() else p.parent
    if not p.is_dir() and not p.is_file():
        raise InputError(f"calibration file not found: {p}")
    ext = p.suffix if p.is_file() else ".yml"
    pair = []
    for stem in ("intri", "extri"):
        candidates = [folder / f"{stem}{ext}", folder / f"{stem}.yml", folder / f"{stem}.yaml"]
        found = next((c for c in candidates if c.is_file()), None)
        if found is None:
            raise InputError(f"{folder}: missing {stem}.yml (EasyMocap calibration needs intri.yml and extri.yml)")
        pair.append(found)
    return pair[0], pair[1]


def _open_storage(path: Path):
    import cv2

    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except Exception as exc:  # cv2.error, or SystemError wrapping it (OpenCV 5 Python bindings)
        cause = exc.__cause__ or exc
        raise InputError(f"{path}: not a readable OpenCV YAML file: {str(cause).strip().splitlines()[-1]}") from None
    if not fs.isOpened():
        raise InputError(f"{path}: cannot open as OpenCV YAML")
    return fs


def _read_names(fs, path: Path) -> list[str] | None:
    node = fs.getNode("names")
    if node.empty():
        return None
    if not node.isSeq():
        raise F.Where(path).error("names", "expected a list of camera names")
    names = []
    for i in range(node.size()):
        item = node.at(i)
        names.append(item.string() if item.isString() else str(int(item.real())))
    return names


def _read_mat(fs, key: str, where: F.Where) -> np.ndarray | None:
    node = fs.getNode(key)
    if node.empty():
        return None
    if node.isReal() or node.isInt():
        return np.array([node.real()])
    mat = node.mat() if node.isMap() else None
    if mat is None:
        raise where.error(key, "expected an OpenCV matrix (!!opencv-matrix) or a number")
    return np.asarray(mat, dtype=np.float64)


def _easymocap_camera(name: str, intri, extri, paths: tuple[Path, Path]) -> F.CameraRecord:
    wi, we = F.Where(paths[0], name), F.Where(paths[1], name)
    K = F.intrinsics(_read_mat(intri, f"K_{name}", wi), wi, f"K_{name}")
    dist_key = f"dist_{name}" if not intri.getNode(f"dist_{name}").empty() else f"D_{name}"
    dist = _read_mat(intri, dist_key, wi)
    dist = np.zeros(5) if dist is None else F.distortions(dist, False, wi, dist_key)
    rvec, rot = _read_mat(extri, f"R_{name}", we), _read_mat(extri, f"Rot_{name}", we)
    if rvec is not None and rvec.size == 3:
        R = F.rotvec_to_matrix(F.numbers(rvec.reshape(3), ((3,),), we, f"R_{name}"))
    elif rvec is not None and rvec.size == 9:
        R = F.rotation_matrix(rvec.reshape(3, 3), we, f"R_{name}")
    elif rvec is None and rot is not None:
        R = F.rotation_matrix(rot, we, f"Rot_{name}")
    else:
        raise we.error(f"R_{name}", "missing (or not a 3-vector / 3x3 matrix), and no Rot_ matrix either")
    t = F.numbers(_read_mat(extri, f"T_{name}", we), ((3, 1), (1, 3), (3,)), we, f"T_{name}").reshape(3)
    w, h = _read_mat(intri, f"W_{name}", wi), _read_mat(intri, f"H_{name}", wi)
    if w is None or h is None:
        size = (int(round(2 * K[0, 2] + 1)), int(round(2 * K[1, 2] + 1)))
        log.warning("%s: camera %r has no W_/H_: image size estimated from the principal point as %dx%d",
                    paths[0], name, *size)
    else:
        size = F.image_size(np.concatenate([w.reshape(-1), h.reshape(-1)]), wi, f"W_{name}/H_{name}")
    return F.CameraRecord(name, K, dist, R, t, size)


def read_easymocap_yaml(path: str | Path, dtype: torch.dtype = torch.float32) -> CameraRig:
    """Read an EasyMocap ``intri.yml`` + ``extri.yml`` pair; ``path`` is either file or their folder."""
    paths = _easymocap_paths(path)
    intri, extri = _open_storage(paths[0]), _open_storage(paths[1])
    try:
        names = _read_names(intri, paths[0]) or _read_names(extri, paths[1])
        if not names:
            raise InputError(f"{paths[0]}: no cameras found (no 'names' list)")
        records = [_easymocap_camera(n, intri, extri, paths) for n in names]
    finally:
        intri.release()
        extri.release()
    return F.build_rig(records, paths[0], dtype)


def write_easymocap_yaml(rig: CameraRig, folder: str | Path) -> tuple[Path, Path]:
    """Write ``rig`` as EasyMocap ``intri.yml`` + ``extri.yml`` in ``folder`` (each file atomically).

    Values are written by OpenCV with 17 significant digits (exact for float64). Fisheye cameras cannot be
    written (the format has no fisheye model).

    Returns:
        The paths of ``intri.yml`` and ``extri.yml``.
    """
    import cv2

    folder = Path(folder)
    records = F.rig_records(rig)
    fish = [r.name for r in records if r.fisheye]
    if fish:
        raise InputError(f"{folder}: EasyMocap YAML has no fisheye model; fisheye cameras: {fish}")
    bad = [r.name for r in records if not _YAML_KEY.match(r.name)]
    if bad:
        raise InputError(f"{folder}: camera names must be letters, digits, '_' or '-' to be YAML keys: {bad}")
    out = []
    for stem in ("intri", "extri"):
        target = folder / f"{stem}.yml"
        with atomic_path(target, suffix=".yml") as tmp:
            fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE)
            fs.startWriteStruct("names", cv2.FileNode_SEQ)
            for r in records:
                fs.write("", r.name)
            fs.endWriteStruct()
            for r in records:
                if stem == "intri":
                    fs.write(f"K_{r.name}", r.K)
                    fs.write(f"dist_{r.name}", r.dist.reshape(1, 5))
                    fs.write(f"W_{r.name}", int(r.size_wh[0]))
                    fs.write(f"H_{r.name}", int(r.size_wh[1]))
                else:
                    fs.write(f"R_{r.name}", F.matrix_to_rotvec(r.R_cam_world).reshape(3, 1))
                    fs.write(f"Rot_{r.name}", r.R_cam_world)
                    fs.write(f"T_{r.name}", r.t_cam_world.reshape(3, 1))
            fs.release()
        out.append(target)
    return out[0], out[1]
