"""The ``markers2d.npz`` schema: 2D detections of distinguishable markers (docs/formats.md).

| key | shape / type | meaning |
|---|---|---|
| fps | scalar float | frame rate |
| frame_index | (T,) int | frame numbers |
| camera_names | (C,) str | as in the calibration |
| marker_names | (M,) str | marker labels, subject prefixes stripped |
| uv | (T, C, M, K, 2) float32 | up to K candidate detections per marker and view (pixels), NaN where none |

The candidates of one marker in one view are in no particular order: at most one is the marker, the others are
false detections. Readers ignore keys they do not know (a simulator adds its truth, ``true_index``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from torchtrack.checks import InputError
from torchtrack.io.atomic import atomic_path

REQUIRED = ("fps", "frame_index", "camera_names", "marker_names", "uv")


@dataclass
class Markers2D:
    """Marker detections in the ``markers2d.npz`` schema (shapes as in the module docstring).

    Attributes:
        extra: further arrays written and read as they are (e.g. a simulator's ``true_index (T, C, M)``: the
            candidate that is the marker, -1 where none is).
    """

    fps: float
    frame_index: np.ndarray  # (T,)
    camera_names: list[str]
    marker_names: list[str]
    uv: np.ndarray  # (T, C, M, K, 2)
    extra: dict[str, np.ndarray] = field(default_factory=dict)

    def validate(self, source: str) -> None:
        """Raises InputError naming ``source`` and the field that does not fit the schema."""
        T, C, M = len(self.frame_index), len(self.camera_names), len(self.marker_names)
        if not (np.isfinite(self.fps) and self.fps > 0):
            raise InputError(f"{source}: fps must be a positive number, got {self.fps}")
        if self.uv.ndim != 5 or self.uv.shape[:3] != (T, C, M) or self.uv.shape[4] != 2:
            raise InputError(f"{source}: uv has shape {self.uv.shape}, expected (T, C, M, K, 2) = ({T}, {C}, {M}, "
                             "K, 2) from frame_index, camera_names and marker_names")
        if len(set(self.marker_names)) != M:
            raise InputError(f"{source}: marker_names has repeated labels")
        if np.isinf(self.uv).any():
            raise InputError(f"{source}: uv holds infinite values (NaN marks a missing candidate)")


def save_markers2d(data: Markers2D, path: str | Path) -> Path:
    """Write ``data`` to ``path`` atomically (a reader never sees a half-written file)."""
    path = Path(path)
    data.validate(str(path))
    arrays = {"fps": np.asarray(data.fps, dtype=np.float64), "frame_index": np.asarray(data.frame_index, np.int64),
              "camera_names": np.asarray(data.camera_names, dtype=str),
              "marker_names": np.asarray(data.marker_names, dtype=str),
              "uv": np.asarray(data.uv, dtype=np.float32), **data.extra}
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)
    return path


def load_markers2d(path: str | Path) -> Markers2D:
    """Read and check a ``markers2d.npz``; InputError names the file and the missing or malformed key."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such markers2d file")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: not a readable .npz file ({exc})") from None
    missing = [k for k in REQUIRED if k not in data]
    if missing:
        raise InputError(f"{path}: missing keys {missing} of the markers2d schema (docs/formats.md)")
    out = Markers2D(float(data.pop("fps")), data.pop("frame_index"), [str(s) for s in data.pop("camera_names")],
                    [str(s) for s in data.pop("marker_names")], data.pop("uv").astype(np.float32), extra=data)
    out.validate(str(path))
    return out
