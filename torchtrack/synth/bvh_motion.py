"""Motions from BVH files (e.g. the CMU captures), retargeted onto our skeleton for synthetic sequences."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch

from torchtrack.checks import InputError
from torchtrack.io.bvh import CMU_UNIT_M, bvh_forward_kinematics, bvh_to_world, read_bvh
from torchtrack.skeleton import Skeleton
from torchtrack.synth.motion import on_the_floor, with_starfish_start
from torchtrack.synth.retarget import RetargetResult, retarget_positions

log = logging.getLogger(__name__)


def bvh_world_positions(path: str | Path, fps: float, duration_s: float | None = None,
                        unit_to_m: float = CMU_UNIT_M) -> tuple[list[str], torch.Tensor]:
    """Joint positions of a BVH file resampled to ``fps`` (nearest frames), in our world (Z up, metres),
    centred so the pelvis path's mid-range is at the origin.

    Returns:
        names (J,), positions (T, J, 3) float64.
    """
    bvh = read_bvh(path)
    step = bvh.fps / fps
    if step < 1 - 1e-6:
        raise InputError(f"{path}: recorded at {bvh.fps:.1f} fps; cannot resample up to {fps} fps")
    n = int(np.floor((bvh.num_frames - 1) / step)) + 1
    if duration_s is not None:
        n = min(n, max(1, round(duration_s * fps)))
    frames = np.round(np.arange(n) * step).astype(np.int64)
    pos = torch.from_numpy(bvh_to_world(bvh_forward_kinematics(bvh, frames), unit_to_m=unit_to_m))
    hips = pos[:, [bvh.index("LeftHip"), bvh.index("RightHip")]].mean(1) if "LeftHip" in bvh.joint_names \
        else pos[:, 0]
    mid = 0.5 * (hips[:, :2].min(0).values + hips[:, :2].max(0).values)  # (2,)
    pos[..., :2] -= mid
    return list(bvh.joint_names), pos


def bvh_motion(path: str | Path, skel: Skeleton, fps: float, duration_s: float | None, starfish_s: float,
               **starfish: float) -> tuple[Skeleton, torch.Tensor]:
    """A BVH file as our skeleton's motion: retargeted, starfish start prepended (``starfish``: its style, see
    :func:`~torchtrack.synth.motion.with_starfish_start`), soles on the floor.

    Returns:
        the skeleton scaled to the BVH subject, (T, D) state vectors.
    """
    result = retarget_bvh(path, skel, fps, duration_s)
    angles = with_starfish_start(result.skeleton, result.angles, fps, starfish_s, **starfish)
    return result.skeleton, on_the_floor(result.skeleton, angles)


def retarget_bvh(path: str | Path, skel: Skeleton, fps: float, duration_s: float | None = None
                 ) -> RetargetResult:
    """Retarget a CMU BVH file to ``skel`` (see :func:`torchtrack.synth.retarget.retarget_positions`)."""
    names, pos = bvh_world_positions(path, fps, duration_s)
    result = retarget_positions(skel, pos, names)
    log.info("%s: %d frames retargeted, mean landmark distance %.1f mm", Path(path).name,
             result.angles.shape[0], 1e3 * float(result.residual_m.mean()))
    return result
