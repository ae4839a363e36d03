"""The ``poses.npz`` schema (tracker output, and ``gt.npz`` of synthetic sequences); see docs/formats.md.

| key | shape / type | meaning |
|---|---|---|
| fps | scalar float | frame rate |
| frame_index | (T,) int | source frame numbers |
| joint_names | (J,) str | includes the 16 landmarks |
| joints3d | (T, J, 3) float32 | world positions, metres |
| dof_names, angles | (D,) str, (T, D) float32 | root translation (m), root rotation and joint angles (rad) |
| valid | (T,) bool | False where there is no estimate |
| confidence | (T, J) float32 | 0..1 |
| marker_names, markers3d | (M,) str, (T, M, 3) | optional, marker mode |

Readers ignore keys they do not know, so writers may add keys (extending, never changing, the contract).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from torchtrack.checks import InputError
from torchtrack.conventions import LANDMARKS
from torchtrack.io.atomic import atomic_path

REQUIRED = ("fps", "frame_index", "joint_names", "joints3d", "dof_names", "angles", "valid", "confidence")


@dataclass
class Poses:
    """A pose sequence in the poses.npz schema (numpy arrays, shapes as in the module docstring)."""

    fps: float
    frame_index: np.ndarray  # (T,)
    joint_names: list[str]
    joints3d: np.ndarray  # (T, J, 3)
    dof_names: list[str]
    angles: np.ndarray  # (T, D)
    valid: np.ndarray  # (T,) bool
    confidence: np.ndarray  # (T, J)
    marker_names: list[str] | None = None
    markers3d: np.ndarray | None = None  # (T, M, 3)
    extra: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def num_frames(self) -> int:
        return int(self.frame_index.shape[0])

    def landmarks(self) -> np.ndarray:
        """(T, 16, 3) the 16 landmarks in ``conventions.LANDMARKS`` order."""
        idx = [self.joint_names.index(n) for n in LANDMARKS]
        return self.joints3d[:, idx]

    def validate(self, source: str) -> None:
        T = self.frame_index.shape[0]
        J, D = len(self.joint_names), len(self.dof_names)

        def need(name: str, arr: np.ndarray, shape: tuple) -> None:
            if tuple(arr.shape) != shape:
                raise InputError(f"{source}: field '{name}' has shape {tuple(arr.shape)}, expected {shape}")

        need("frame_index", self.frame_index, (T,))
        need("joints3d", self.joints3d, (T, J, 3))
        need("angles", self.angles, (T, D))
        need("valid", self.valid, (T,))
        need("confidence", self.confidence, (T, J))
        missing = [n for n in LANDMARKS if n not in self.joint_names]
        if missing:
            raise InputError(f"{source}: field 'joint_names' lacks the landmarks {missing}")
        if self.markers3d is not None:
            need("markers3d", self.markers3d, (T, len(self.marker_names or []), 3))
        if not np.isfinite(self.joints3d[self.valid]).all():
            raise InputError(f"{source}: field 'joints3d' has NaN/inf in frames marked valid")


def save_poses(poses: Poses, path: str | Path) -> None:
    """Write ``poses`` to ``path`` (.npz) atomically."""
    poses.validate(str(path))
    arrays = {
        "fps": np.float64(poses.fps),
        "frame_index": np.asarray(poses.frame_index, dtype=np.int64),
        "joint_names": np.asarray(poses.joint_names, dtype=str),
        "joints3d": np.asarray(poses.joints3d, dtype=np.float32),
        "dof_names": np.asarray(poses.dof_names, dtype=str),
        "angles": np.asarray(poses.angles, dtype=np.float32),
        "valid": np.asarray(poses.valid, dtype=bool),
        "confidence": np.asarray(poses.confidence, dtype=np.float32),
        **poses.extra,
    }
    if poses.markers3d is not None:
        arrays["marker_names"] = np.asarray(poses.marker_names, dtype=str)
        arrays["markers3d"] = np.asarray(poses.markers3d, dtype=np.float32)
    with atomic_path(path, suffix=".npz") as tmp:
        np.savez_compressed(tmp, **arrays)


def load_poses(path: str | Path) -> Poses:
    """Read a poses.npz (or gt.npz); errors name the file and the field."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"poses file not found: {path}")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except Exception as exc:  # zipfile / numpy raise many types on corrupt files
        raise InputError(f"{path}: not a readable .npz file ({exc})") from None
    missing = [k for k in REQUIRED if k not in data]
    if missing:
        raise InputError(f"{path}: missing fields {missing}")
    known = set(REQUIRED) | {"marker_names", "markers3d"}
    poses = Poses(
        fps=float(data["fps"]), frame_index=data["frame_index"], joint_names=[str(s) for s in data["joint_names"]],
        joints3d=data["joints3d"], dof_names=[str(s) for s in data["dof_names"]], angles=data["angles"],
        valid=data["valid"].astype(bool), confidence=data["confidence"],
        marker_names=[str(s) for s in data["marker_names"]] if "marker_names" in data else None,
        markers3d=data.get("markers3d"), extra={k: v for k, v in data.items() if k not in known})
    poses.validate(str(path))
    return poses
