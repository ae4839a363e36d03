"""Shared parsing helpers of the calibration readers: every error names the file, the camera and the field.

Readers parse into :class:`CameraRecord` (float64 numpy values, exactly as in the file) and build the rig
once with :func:`build_rig`, which casts to the requested dtype.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix, rotation_matrix_to_axis_angle

from torchtrack.cameras.rig import ROTATION_TOL, CameraRig, rotation_error
from torchtrack.checks import InputError, ShapeError, check_file


@dataclass
class CameraRecord:
    """One camera as read from a file (float64)."""

    name: str
    K: np.ndarray  # (3, 3) px
    dist: np.ndarray  # (5,) pinhole (k1, k2, p1, p2, k3) or fisheye (k1, k2, k3, k4, 0)
    R_cam_world: np.ndarray  # (3, 3)
    t_cam_world: np.ndarray  # (3,)
    size_wh: tuple[int, int]
    fisheye: bool = False


class Where:
    """Names the place of a value for error messages: file, camera, field."""

    def __init__(self, path: str | Path, camera: str | None = None) -> None:
        self.path = Path(path)
        self.camera = camera

    def error(self, field: str | None, message: str) -> InputError:
        parts = [str(self.path)]
        if self.camera is not None:
            parts.append(f"camera {self.camera!r}")
        if field is not None:
            parts.append(f"field {field!r}")
        return InputError(": ".join(parts) + ": " + message)


def read_toml_file(path: str | Path) -> dict:
    """Parse a TOML file; unreadable or invalid files raise InputError naming the file."""
    p = check_file(path, "calibration file")
    try:
        return tomllib.loads(p.read_bytes().decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise InputError(f"{p}: not a UTF-8 text file ({exc.reason} at byte {exc.start})") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{p}: not valid TOML: {exc}") from None
    except OSError as exc:
        raise InputError(f"{p}: cannot read: {exc}") from None


def _is_number(x: object) -> bool:
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, (bool, np.bool_))


def numbers(value: object, shapes: tuple[tuple[int, ...], ...], where: Where, field: str) -> np.ndarray:
    """A nested list (or array) of finite numbers with one of ``shapes`` -> float64 array of that shape."""
    if value is None:
        raise where.error(field, "missing")
    if isinstance(value, np.ndarray):
        arr = value
    else:
        def walk(v: object) -> object:
            if isinstance(v, (list, tuple)):
                return [walk(e) for e in v]
            if not _is_number(v):
                raise where.error(field, f"expected numbers, found {v!r}")
            return v
        nested = walk(value)
        try:
            arr = np.asarray(nested, dtype=np.float64)
        except ValueError:  # ragged nesting
            raise where.error(field, f"expected an array of shape {_shapes(shapes)}, got {value!r}") from None
    if arr.shape not in shapes:
        raise where.error(field, f"expected shape {_shapes(shapes)}, got {arr.shape}")
    arr = arr.astype(np.float64)
    if not np.isfinite(arr).all():
        raise where.error(field, f"values must be finite, got {arr.tolist()}")
    return arr


def _shapes(shapes: tuple[tuple[int, ...], ...]) -> str:
    return " or ".join(str(s) for s in shapes)


def intrinsics(value: object, where: Where, field: str = "matrix") -> np.ndarray:
    """3x3 pinhole intrinsics with positive focal lengths and no skew."""
    K = numbers(value, ((3, 3),), where, field)
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise where.error(field, f"focal lengths must be positive, got fx={K[0, 0]}, fy={K[1, 1]}")
    if K[0, 1] != 0 or K[1, 0] != 0 or K[2].tolist() != [0.0, 0.0, 1.0]:
        raise where.error(field, f"expected [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew), got {K.tolist()}")
    return K


def rotation_matrix(value: object, where: Where, field: str) -> np.ndarray:
    """3x3 rotation matrix (orthonormal, det +1 within ROTATION_TOL)."""
    R = numbers(value, ((3, 3),), where, field)
    err = float(rotation_error(torch.from_numpy(R)))
    if not err <= ROTATION_TOL:
        detail = "det <= 0" if err == math.inf else f"max |R R^T - I| = {err:.3g}"
        raise where.error(field, f"not a rotation matrix ({detail}; tolerance {ROTATION_TOL:g}): {R.tolist()}")
    return R


def rotvec_to_matrix(rotvec: np.ndarray) -> np.ndarray:
    """Rodrigues vector ``(3,)`` -> rotation matrix ``(3, 3)``, float64 (kornia; exact to ~1e-16)."""
    return axis_angle_to_rotation_matrix(torch.from_numpy(np.asarray(rotvec, np.float64))[None])[0].numpy()


def matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation matrix ``(3, 3)`` -> Rodrigues vector ``(3,)``, float64.

    kornia (via quaternions) keeps ~1e-16 everywhere; ``cv2.Rodrigues`` loses ~1e-9 near pi.
    """
    return rotation_matrix_to_axis_angle(torch.from_numpy(np.asarray(R, np.float64))[None])[0].numpy()


def image_size(value: object, where: Where, field: str = "size") -> tuple[int, int]:
    """``[W, H]``: two positive whole numbers (``1088.0`` is accepted, ``1088.5`` is not)."""
    wh = numbers(value, ((2,),), where, field)
    if (wh != np.round(wh)).any() or (wh <= 0).any():
        raise where.error(field, f"expected two positive whole numbers [W, H], got {wh.tolist()}")
    return int(wh[0]), int(wh[1])


def distortions(value: object, fisheye: bool, where: Where, field: str = "distortions") -> np.ndarray:
    """4 or 5 OpenCV coefficients -> ``(5,)``; fisheye (k1..k4) takes 4 (a 5th must be 0)."""
    d = numbers(value, ((4,), (5,), (1, 4), (1, 5), (4, 1), (5, 1)), where, field).reshape(-1)
    if fisheye and d.size == 5 and d[4] != 0:
        raise where.error(field, f"fisheye cameras take 4 coefficients (k1..k4), got {d.tolist()}")
    return np.pad(d, (0, 5 - d.size))


def build_rig(records: list[CameraRecord], path: str | Path, dtype: torch.dtype) -> CameraRig:
    """One CameraRig from the parsed records, in ``dtype``; errors name the file."""
    if not records:
        from torchtrack.cameras.calib_io import KNOWN_FORMATS

        raise InputError(f"{path}: no cameras found; the calibration formats torchtrack reads: {KNOWN_FORMATS}")
    names = [r.name for r in records]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise InputError(f"{path}: camera names must be unique, repeated: {dupes}")

    def stack(key: str) -> torch.Tensor:
        return torch.from_numpy(np.stack([getattr(r, key) for r in records])).to(dtype)

    try:
        return CameraRig(names, stack("K"), stack("R_cam_world"), stack("t_cam_world"),
                         torch.tensor([r.size_wh for r in records], dtype=torch.int64), stack("dist"),
                         [r.fisheye for r in records])
    except (InputError, ShapeError) as exc:
        raise InputError(f"{path}: {exc}") from exc


def rig_records(rig: CameraRig) -> list[CameraRecord]:
    """The rig's cameras as float64 records (for writers)."""
    K, R, t, d = (x.detach().to("cpu", torch.float64).numpy() for x in
                  (rig.K, rig.R_cam_world, rig.t_cam_world, rig.dist))
    sizes = rig.image_size_wh.tolist()
    return [CameraRecord(n, K[i], d[i], R[i], t[i], (sizes[i][0], sizes[i][1]), rig.fisheye[i])
            for i, n in enumerate(rig.names)]
