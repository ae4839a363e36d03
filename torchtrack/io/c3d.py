"""C3D motion-capture files (ezc3d): 3D marker trajectories in metres, in our world axes (Z up).

The point labels lose any subject prefix (``Male:LFWT`` -> ``LFWT``); a sample that the file marks missing (a
negative residual, or NaN as ezc3d gives it) is NaN. A file's own axes are its lab's: a Y-up capture
(e.g. Motion Analysis) is turned to Z up, the up axis found as the one along which the labelled head and shoulder
markers lie above the ankle, heel and toe markers, or, without those labels, the one along which each frame's
points spread most (a standing body's height), taken as pointing up.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from torchtrack.checks import InputError, check_file

_UNIT_TO_M = {"m": 1.0, "mm": 1e-3, "cm": 1e-2}
#: Markers that lie above (head) and below (ankles, toes, heels) on a standing body, in common marker sets
#: (CMU, Vicon Plug-in-Gait, Motion Analysis): they tell the file's up axis.
_HIGH = ("LFHD", "RFHD", "LBHD", "RBHD", "C7", "CLAV", "LSHO", "RSHO")
_LOW = ("LANK", "RANK", "LTOE", "RTOE", "LHEE", "RHEE")


@dataclass
class C3D:
    """A C3D file's points. T frames, M points.

    Attributes:
        labels: (M,) point labels, subject prefixes stripped.
        positions: (T, M, 3) float64 metres in our world axes (Z up, right-handed); NaN where missing.
        rate_hz: the point rate. source: the file.
    """

    labels: list[str]
    positions: np.ndarray
    rate_hz: float
    source: str
    outputs: frozenset[str] = frozenset()

    def markers(self) -> list[int]:
        """The points that are skin markers: not a model's outputs (listed in the POINT group's ANGLES, FORCES,
        MOMENTS, POWERS, SCALARS or REACTIONS, or named as Plug-in-Gait's segment axes and centre of mass)."""
        return [i for i, n in enumerate(self.labels) if n not in self.outputs and not _modelled(n)]

    def index(self, label: str) -> int:
        try:
            return self.labels.index(label)
        except ValueError:
            raise InputError(f"{self.source}: no point {label!r}; it has {self.labels}") from None


#: The POINT parameters that list a model's outputs stored as points (Vicon's and others' writers).
_OUTPUT_GROUPS = ("ANGLES", "FORCES", "MOMENTS", "POWERS", "SCALARS", "REACTIONS")
#: Plug-in-Gait's segments, whose axes it writes as points named segment + O (origin), A, L or P (its axes' ends).
_PIG_SEGMENTS = ("HED", "TRX", "PEL", "LCL", "RCL", "LHU", "RHU", "LRA", "RRA", "LHN", "RHN", "LFE", "RFE", "LTI",
                 "RTI", "LFO", "RFO", "LTO", "RTO")


def _modelled(label: str) -> bool:
    return (len(label) == 4 and label[:3] in _PIG_SEGMENTS and label[3] in "OALP") or label.startswith("CentreOfMass")


def strip_prefix(label: str) -> str:
    """``Male:LFWT`` -> ``LFWT`` (a subject name before the last colon), whitespace trimmed."""
    return label.rsplit(":", 1)[-1].strip()


def _up_axis(labels: list[str], pos: np.ndarray) -> tuple[int, float]:
    """(axis, sign) of the file's up direction."""
    high = [i for i, n in enumerate(labels) if n in _HIGH]
    low = [i for i, n in enumerate(labels) if n in _LOW]
    if high and low:
        d = np.nanmean(pos[:, high], axis=(0, 1)) - np.nanmean(pos[:, low], axis=(0, 1))  # (3,)
        if np.isfinite(d).all():
            axis = int(np.argmax(np.abs(d)))
            return axis, float(np.sign(d[axis]))
    # no labelled head or feet: the axis along which each frame's points spread most, its sign unknown: kept
    spread = np.nanmedian(np.nanmax(pos, 1) - np.nanmin(pos, 1), axis=0)
    return int(np.argmax(spread)), 1.0


def read_c3d(path: str | Path) -> C3D:
    """Read a C3D file's points (module docstring).

    Raises:
        InputError: the file is missing, unreadable or malformed (naming it), or has no points.
    """
    path = check_file(path, "C3D file")
    try:
        import ezc3d
    except ImportError:  # pragma: no cover - a declared dependency
        raise InputError("reading C3D files needs ezc3d (pip install ezc3d)") from None
    try:
        c = ezc3d.c3d(str(path))
        point = c["parameters"]["POINT"]
        labels = [strip_prefix(str(n)) for n in point["LABELS"]["value"]]
        rate = float(np.asarray(point["RATE"]["value"]).ravel()[0])
        units = str(np.asarray(point["UNITS"]["value"]).ravel()[0]).strip().lower() if "UNITS" in point else "mm"
        data = np.asarray(c["data"]["points"], dtype=np.float64)  # (4, M, T)
        residual = np.asarray(c["data"]["meta_points"]["residuals"], dtype=np.float64)  # (1, M, T)
        outputs = frozenset(strip_prefix(str(n)) for g in _OUTPUT_GROUPS if g in point
                            for n in np.asarray(point[g]["value"]).ravel())
    except InputError:
        raise
    except Exception as exc:  # ezc3d raises plain exceptions (RuntimeError, IndexError, ...) on bad headers
        raise InputError(f"{path}: not a readable C3D file ({type(exc).__name__}: {exc})") from None
    if data.ndim != 3 or data.shape[1] == 0 or data.shape[2] == 0:
        raise InputError(f"{path}: the C3D file holds no 3D points")
    if units not in _UNIT_TO_M:
        raise InputError(f"{path}: POINT:UNITS {units!r} is not one of {sorted(_UNIT_TO_M)}")
    if not rate > 0:
        raise InputError(f"{path}: POINT:RATE {rate} is not a frame rate")
    labels = labels[:data.shape[1]] + [f"point{i}" for i in range(len(labels), data.shape[1])]
    pos = data[:3].transpose(2, 1, 0) * _UNIT_TO_M[units]  # (T, M, 3)
    missing = (residual[0].T < 0) if residual.size else np.zeros(pos.shape[:2], bool)
    pos[missing | (np.abs(pos) < 1e-12).all(-1)] = np.nan  # a (0, 0, 0) sample is a gap in many writers' files
    axis, sign = _up_axis(labels, pos)
    if axis != 2 or sign < 0:  # turn the up axis to +Z, a proper rotation (the other two follow cyclically)
        a, b = (axis + 1) % 3, (axis + 2) % 3
        pos = np.stack([pos[..., a], pos[..., b], pos[..., axis]], -1)
        if sign < 0:
            pos[..., 1:] *= -1.0
    return C3D(labels, pos, rate, str(path), outputs)
