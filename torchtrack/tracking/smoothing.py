"""The finished track low-pass filtered in time: a zero-phase Butterworth filter over its joint angles.

The tracker is a filter: each frame's pose comes from that frame's blobs and the frames before it, so it carries
the frame's noise (a limb's blob pulled by a shadow for a frame, the EM settling differently) as jitter a body
does not make. Biomechanics filters such data with a low-pass Butterworth filter run forward and backward (zero
phase lag), commonly at 6 Hz (Winter, *Biomechanics and Motor Control of Human Movement*, §2.2-2.3), as Pose2Sim
does with its own triangulated keypoints. :func:`smooth_track` does that on the track's degrees of freedom, not on
its points, so the smoothed landmarks stay a pose of the subject's skeleton (bone lengths kept, joint limits
kept, ``joints3d`` the forward kinematics of ``angles``):

* the root translation and the joint angles are filtered as they are; the root's three Euler angles are first
  unwrapped along time (a subject turning past +-180 deg has no jump), the heading wrapped back to (-pi, pi]
  after; the joint angles are clamped to their limits after (the filter's ringing can overshoot them);
* each run of consecutive valid frames is filtered on its own, and a re-initialisation starts a new run (the
  pose jumps there on purpose); runs shorter than :data:`MIN_RUN_FRAMES` are left as they are;
* invalid frames are left as they are (NaN).

It is off-line: it needs the frames after each one, so it runs on the finished track (``torchtrack track``, the
``smoothing`` section of the config, ``--smooth-hz``), not in :class:`~torchtrack.tracking.markerless.
MarkerlessTracker`, whose own next frame starts from the unfiltered pose.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import torch

from torchtrack.checks import InputError, config_section
from torchtrack.io.poses import Poses
from torchtrack.skeleton import Skeleton

__all__ = ["MIN_RUN_FRAMES", "SmoothingConfig", "smooth_track", "valid_runs"]

log = logging.getLogger(__name__)

#: Runs of fewer valid frames are not filtered: the filter's padding (odd extension of the ends) would be most of
#: such a run.
MIN_RUN_FRAMES = 8

#: The root's Euler angles among the track's degrees of freedom (unwrapped along time before filtering).
ROOT_ROTATION_DOFS = ("root_rz", "root_ry", "root_rx")


@dataclass(frozen=True)
class SmoothingConfig:
    """Smoothing settings (the ``smoothing`` section of a tracking config).

    Attributes:
        cutoff_hz: the low-pass filter's cut-off frequency in Hz (0: off). A cut-off at or over half the frame
            rate (nothing to remove) leaves the track as it is.
        order: the Butterworth filter's order (run twice, forward and backward: twice this in effect).
    """

    cutoff_hz: float = 6.0
    order: int = 4

    def __post_init__(self) -> None:
        c = self.cutoff_hz
        if isinstance(c, bool) or not isinstance(c, (int, float)) or not math.isfinite(c) or c < 0:
            raise InputError(f"smoothing.cutoff_hz must be a number >= 0 (0: off), got {c!r}")
        o = self.order
        if isinstance(o, bool) or not isinstance(o, int) or not 1 <= o <= 8:
            raise InputError(f"smoothing.order must be a whole number in [1, 8], got {o!r}")

    @classmethod
    def from_dict(cls, doc: dict[str, Any] | None, source: str = "<config>") -> SmoothingConfig:
        """Build from the YAML section (None: the defaults), naming unknown keys."""
        return cls(**config_section(cls, doc, source, "smoothing", " (cutoff_hz: 0 turns it off)"))


def valid_runs(valid: np.ndarray, breaks: np.ndarray | None = None) -> list[tuple[int, int]]:
    """The ``[start, stop)`` ranges of consecutive True in ``valid (T,)``, each also cut before every frame where
    ``breaks (T,)`` is True (a run starts there)."""
    valid = np.asarray(valid, bool)
    cut = np.zeros_like(valid) if breaks is None else np.asarray(breaks, bool)
    runs: list[tuple[int, int]] = []
    start = None
    for t, ok in enumerate(valid.tolist()):
        if start is not None and (not ok or cut[t]):
            runs.append((start, t))
            start = None
        if ok and start is None:
            start = t
    if start is not None:
        runs.append((start, valid.size))
    return runs


def smooth_track(poses: Poses, skeleton: Skeleton, config: SmoothingConfig) -> Poses:
    """``poses`` with its angles low-pass filtered in time and its points re-stated from them.

    Args:
        poses: a track of ``skeleton`` (``dof_names`` its degrees of freedom; ``extra['reinitialised'] (T,)``,
            where present, starts a new run at each True frame).
        skeleton: the subject's body the track was made with (``joints3d`` is re-computed as its forward
            kinematics: its ``output_names`` must be the track's ``joint_names``).
        config: the filter; ``cutoff_hz`` 0, or at or over half ``poses.fps``, returns ``poses`` itself.

    Returns:
        a new :class:`Poses` (the same frames, validity and confidences) whose ``extra['smoothing_cutoff_hz']``
        records the cut-off (0: not filtered).

    Raises:
        InputError: the skeleton's degrees of freedom or outputs are not the track's.
    """
    from scipy.signal import butter, sosfiltfilt

    if list(skeleton.dof_names) != list(poses.dof_names):
        raise InputError(f"smoothing: the track's degrees of freedom {list(poses.dof_names)} are not the "
                         f"skeleton's {list(skeleton.dof_names)}")
    if list(skeleton.output_names) != list(poses.joint_names):
        raise InputError("smoothing: the track's joints are not the skeleton's outputs")
    nyquist = poses.fps / 2
    if config.cutoff_hz == 0 or config.cutoff_hz >= nyquist:
        if config.cutoff_hz:
            log.info("smoothing: cut-off %.1f Hz at or over half the frame rate (%.1f fps): not filtered",
                     config.cutoff_hz, poses.fps)
        return replace(poses, extra={**poses.extra, "smoothing_cutoff_hz": np.float64(0.0)})
    sos = butter(config.order, config.cutoff_hz / nyquist, output="sos")
    names = list(poses.dof_names)
    rot = [names.index(n) for n in ROOT_ROTATION_DOFS]
    heading = names.index("root_rz")
    lower = skeleton.lower.detach().cpu().double().numpy()  # (D,) limits (-inf/inf for the root)
    upper = skeleton.upper.detach().cpu().double().numpy()
    limited = np.isfinite(lower) & np.isfinite(upper)
    limited[rot] = False

    angles = poses.angles.astype(np.float64).copy()  # (T, D)
    reinit = poses.extra.get("reinitialised")
    done = np.zeros(poses.num_frames, bool)
    for a, b in valid_runs(poses.valid, reinit):
        if b - a < MIN_RUN_FRAMES:
            continue
        run = angles[a:b].copy()  # (n, D)
        run[:, rot] = np.unwrap(run[:, rot], axis=0)
        run = sosfiltfilt(sos, run, axis=0, padlen=min(3 * (2 * sos.shape[0] + 1), b - a - 1))
        run[:, heading] = np.angle(np.exp(1j * run[:, heading]))  # back to (-pi, pi]
        run[:, limited] = np.clip(run[:, limited], lower[limited], upper[limited])
        angles[a:b] = run
        done[a:b] = True
    joints3d = poses.joints3d.copy()
    if done.any():
        p = skeleton.lower
        with torch.no_grad():
            fk = skeleton.forward(torch.as_tensor(angles[done], dtype=p.dtype, device=p.device))
        joints3d[done] = fk.output_points.cpu().numpy()
    out_angles = poses.angles.copy()
    out_angles[done] = angles[done]
    return replace(poses, angles=out_angles.astype(poses.angles.dtype), joints3d=joints3d.astype(poses.joints3d.dtype),
                   extra={**poses.extra, "smoothing_cutoff_hz": np.float64(config.cutoff_hz)})
