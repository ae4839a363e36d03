"""The finished track low-pass filtered in time: a zero-phase Butterworth filter over its joint angles.

The tracker is a filter: each frame's pose comes from that frame's blobs and the frames before it, so it carries
the frame's noise (a limb's blob pulled by a shadow for a frame, the EM settling differently) as jitter a body
does not make. Biomechanics filters such data with a low-pass Butterworth filter run forward and backward (zero
phase lag), commonly at 6 Hz (Winter, *Biomechanics and Motor Control of Human Movement*, §2.2-2.3), as Pose2Sim
does with its own triangulated keypoints. :func:`smooth_track` does that on the track's degrees of freedom, not on
its points, so the smoothed landmarks stay a pose of the subject's skeleton (bone lengths kept, joint limits
kept, ``joints3d`` the forward kinematics of ``angles``):

* the root translation and the joint angles are filtered as they are; the root's three Euler angles are first
  unwrapped along time (the tracker keeps the heading continuous, a turning subject's past +-180 deg; a track
  that wraps it has no jump either) and stay on the branch of each run's first frame; the joint angles are
  clamped to their limits after (the filter's ringing can overshoot them). Near ``root_ry`` = +-90 deg (a
  subject lying down) the Euler angles themselves jump, which unwrapping does not mend;
* each run of consecutive valid frames with finite angles is filtered on its own (frame numbers are taken as
  consecutive), and a re-initialisation starts a new run (the pose jumps there on purpose); runs shorter than
  :data:`MIN_RUN_FRAMES` are left as they are;
* invalid frames are left as they are: NaN before the tracker's start, the held last pose after it (which the
  smoothed frame before them no longer quite matches).

The confidences and the per-frame diagnostics (``extra['ik_residual_m']``, ``extra['explained']``) stay those of
the tracked poses. It is off-line: it needs the frames after each one, so it runs on the finished track
(``torchtrack track``, the ``smoothing`` section of the config, ``--smooth-hz``), not in the tracker
(:class:`~torchtrack.tracking.markerless.MarkerlessTracker`), whose next frame starts from the unfiltered pose.
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
    first = valid & (~np.r_[False, valid[:-1]] | cut)  # (T,) a run starts here
    last = valid & (~np.r_[valid[1:], False] | np.r_[cut[1:], False])  # (T,) a run ends here
    return list(zip(np.flatnonzero(first).tolist(), (np.flatnonzero(last) + 1).tolist()))


def smooth_track(poses: Poses, skeleton: Skeleton, config: SmoothingConfig) -> Poses:
    """``poses`` with its angles low-pass filtered in time and its points re-stated from them.

    Args:
        poses: a track of ``skeleton``: ``angles (T, D)`` in its ``dof_names``, ``joints3d (T, J, 3)`` in its
            ``output_names``; ``extra['reinitialised'] (T,)`` bool, where present, starts a new run at each True
            frame.
        skeleton: the subject's body the track was made with (``joints3d`` of the filtered frames is re-computed
            as its forward kinematics, on its device).
        config: the filter.

    Returns:
        a new :class:`Poses`: ``angles (T, D)`` and ``joints3d (T, J, 3)`` filtered (their dtypes kept), the
        rest as in ``poses``, and ``extra['smoothing_cutoff_hz']`` the cut-off, 0 where no frame was filtered
        (``cutoff_hz`` 0 or at or over half ``poses.fps``, or no run of :data:`MIN_RUN_FRAMES` valid frames).

    Raises:
        InputError: the skeleton's degrees of freedom or outputs are not the track's; a frame rate that is not a
            positive number.
    """
    from scipy.signal import butter, sosfiltfilt

    if list(skeleton.dof_names) != list(poses.dof_names):
        raise InputError(f"smoothing: the track's degrees of freedom {list(poses.dof_names)} are not the "
                         f"skeleton's {list(skeleton.dof_names)}")
    if list(skeleton.output_names) != list(poses.joint_names):
        raise InputError("smoothing: the track's joints are not the skeleton's outputs")
    if not (math.isfinite(poses.fps) and poses.fps > 0):
        raise InputError(f"smoothing: the track's frame rate must be a positive number, got {poses.fps!r}")
    unfiltered = replace(poses, extra={**poses.extra, "smoothing_cutoff_hz": np.float64(0.0)})
    nyquist = poses.fps / 2
    if config.cutoff_hz == 0:
        return unfiltered
    if config.cutoff_hz >= nyquist:
        log.warning("smoothing: the cut-off %.1f Hz is at or over half the frame rate (%.1f fps): not filtered",
                    config.cutoff_hz, poses.fps)
        return unfiltered
    sos = butter(config.order, config.cutoff_hz / nyquist, output="sos")
    names = list(poses.dof_names)
    rot = [names.index(n) for n in ROOT_ROTATION_DOFS]
    lower = skeleton.lower.detach().cpu().double().numpy()  # (D,) (the root's are wide bounds: +-50 m, +-100 rad)
    upper = skeleton.upper.detach().cpu().double().numpy()
    limited = np.isfinite(lower) & np.isfinite(upper)
    limited[rot] = False  # the root's Euler angles are unwrapped, not bounded

    angles = poses.angles.astype(np.float64)  # (T, D) a copy
    usable = np.asarray(poses.valid, bool) & np.isfinite(angles).all(1)  # (T,)
    done = np.zeros(poses.num_frames, bool)  # (T,) the frames filtered
    for a, b in valid_runs(usable, poses.extra.get("reinitialised")):
        if b - a < MIN_RUN_FRAMES:
            continue
        run = angles[a:b]  # (n, D)
        run[:, rot] = np.unwrap(run[:, rot], axis=0)  # on the branch of the run's first frame
        run = sosfiltfilt(sos, run, axis=0, padlen=min(3 * (2 * sos.shape[0] + 1), b - a - 1))
        run[:, limited] = np.clip(run[:, limited], lower[limited], upper[limited])
        angles[a:b] = run
        done[a:b] = True
    if not done.any():
        return unfiltered
    p = skeleton.lower
    with torch.no_grad():
        fk = skeleton.forward(torch.as_tensor(angles[done], dtype=p.dtype, device=p.device))  # (n, J, 3) points
    joints3d = poses.joints3d.copy()  # (T, J, 3)
    joints3d[done] = fk.output_points.cpu().numpy()
    out_angles = poses.angles.copy()  # (T, D)
    out_angles[done] = angles[done]
    return replace(poses, angles=out_angles, joints3d=joints3d,
                   extra={**poses.extra, "smoothing_cutoff_hz": np.float64(config.cutoff_hz)})
