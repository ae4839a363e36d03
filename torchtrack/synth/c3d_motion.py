"""Motions from C3D marker captures, as joint centres retargeted onto our skeleton for synthetic sequences.

Joint centres come from the file's own model outputs where it has them (Vicon Plug-in-Gait's segment origins,
each at the segment's distal joint: ``LFEO`` knee, ``LTIO`` ankle, ``LCLO`` shoulder, ``LHUO`` elbow, ``LRAO``
wrist; a ``LeftHipCenter``), else from the skin markers of the common sets (CMU's 41, Plug-in-Gait, Motion Analysis):
the hips by Bell et al.'s (1990) regression from the four pelvis markers (ASIS/PSIS, or CMU's front and back
waist), knees, ankles, elbows and wrists at their markers (the mean of a medial and a lateral one where both
exist), the shoulders at the acromion markers, the neck between C7 and the clavicle, the head top above the
four head markers. A few centimetres off the true centres is fine here: the motion is re-posed on our skeleton,
which is what gets rendered and is the ground truth.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from torchtrack.checks import InputError
from torchtrack.io.c3d import C3D, read_c3d
from torchtrack.skeleton import Skeleton
from torchtrack.synth.motion import on_the_floor, with_starfish_start
from torchtrack.synth.retarget import RetargetResult, retarget_positions

__all__ = ["C3D_JOINT_MAP", "c3d_motion", "c3d_resampled", "c3d_world_positions", "joint_centres", "retarget_c3d"]

log = logging.getLogger(__name__)

#: The head top lies about this far above the mean of the four head markers (forehead and back of the head),
#: along the neck-to-head direction (m).
HEAD_TOP_ABOVE_MARKERS_M = 0.09
#: A joint centre is usable when the file gives it in at least this share of the frames (gaps are interpolated).
MIN_PRESENT = 0.5

#: Our joint (retarget names) -> the derived centre it takes.
C3D_JOINT_MAP: dict[str, tuple[str, ...]] = {
    "pelvis": ("LHIP", "RHIP"), "l_thigh": ("LHIP",), "r_thigh": ("RHIP",), "l_shank": ("LKNEE",),
    "r_shank": ("RKNEE",), "l_foot": ("LANKLE",), "r_foot": ("RANKLE",), "l_toe": ("LTOE",), "r_toe": ("RTOE",),
    "head": ("NECK",), "head_top": ("HEADTOP",), "l_upperarm": ("LSHOULDER",), "r_upperarm": ("RSHOULDER",),
    "l_forearm": ("LELBOW",), "r_forearm": ("RELBOW",), "l_hand": ("LWRIST",), "r_hand": ("RWRIST",),
    "l_hand_tip": ("LHANDTIP",), "r_hand_tip": ("RHANDTIP",),
}
#: Centres no file can do without (the hand tips are optional).
_REQUIRED = ("LHIP", "RHIP", "LKNEE", "RKNEE", "LANKLE", "RANKLE", "LTOE", "RTOE", "NECK", "HEADTOP", "LSHOULDER",
             "RSHOULDER", "LELBOW", "RELBOW", "LWRIST", "RWRIST")


def _filled(x: np.ndarray) -> np.ndarray:
    """(T, 3) with NaN gaps linearly interpolated (held before the first and after the last sample)."""
    ok = np.isfinite(x).all(-1)
    if ok.all() or not ok.any():
        return x
    t = np.arange(len(x))
    return np.stack([np.interp(t, t[ok], x[ok, k]) for k in range(3)], -1)


def _bell_hips(asis_l: np.ndarray, asis_r: np.ndarray, psis_l: np.ndarray, psis_r: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """Hip joint centres (T, 3) each, from the pelvis markers: Bell, Pedersen & Brand (1990), in the pelvis frame
    at the ASIS midpoint, as shares of the ASIS distance: 19 % back, 30 % down, 36 % out from the midline."""
    mid = 0.5 * (asis_l + asis_r)
    y = asis_l - asis_r
    d = np.linalg.norm(y, axis=-1, keepdims=True)
    y = y / d
    x = mid - 0.5 * (psis_l + psis_r)
    x = x - (x * y).sum(-1, keepdims=True) * y
    x = x / np.linalg.norm(x, axis=-1, keepdims=True)
    z = np.cross(x, y)
    base = mid + d * (-0.19 * x - 0.30 * z)
    return base + 0.36 * d * y, base - 0.36 * d * y


def joint_centres(c3d: C3D, min_present: float = MIN_PRESENT) -> dict[str, np.ndarray]:
    """The derived joint centres (``C3D_JOINT_MAP``'s source names) of a capture, each (T, 3), gaps filled; a
    point counts where the capture has it in at least ``min_present`` of the frames.

    Raises:
        InputError: a centre cannot be had from the file's labels, naming it and what was looked for.
    """
    have = {n: i for i, n in enumerate(c3d.labels)}

    def point(name: str) -> np.ndarray | None:
        i = have.get(name)
        if i is None:
            return None
        p = c3d.positions[:, i]
        return p if np.isfinite(p).all(-1).mean() >= min_present else None

    def mean_of(*names: str) -> Callable[[], np.ndarray | None]:
        def get() -> np.ndarray | None:
            pts = [point(n) for n in names]
            if any(p is None for p in pts):
                return None
            return np.mean([_filled(p) for p in pts], axis=0)
        return get

    def first(*options: Callable[[], np.ndarray | None]) -> np.ndarray | None:
        for get in options:
            p = get()
            if p is not None:
                return _filled(p)
        return None

    out: dict[str, np.ndarray] = {}
    for side in ("L", "R"):
        hip = first(mean_of("LeftHipCenter" if side == "L" else "RightHipCenter"),
                    mean_of(f"{side}HJC"))
        if hip is None:  # from the pelvis markers: Plug-in-Gait's ASIS/PSIS, or CMU's front and back waist
            for front, back in (("ASI", "PSI"), ("FWT", "BWT")):
                pel = [first(mean_of(f"{s}{m}")) for m in (front, back) for s in ("L", "R")]
                if all(p is not None for p in pel):
                    hip = _bell_hips(*pel)[0 if side == "L" else 1]
                    break
        out[f"{side}HIP"] = hip
        out[f"{side}KNEE"] = first(mean_of(f"{side}FEO"), mean_of(f"{side}KNE", f"{side}KNEin"), mean_of(f"{side}KNE"))
        out[f"{side}ANKLE"] = first(mean_of(f"{side}TIO"), mean_of(f"{side}ANK", f"{side}ANKin"),
                                    mean_of(f"{side}ANK"))
        out[f"{side}TOE"] = first(mean_of(f"{side}TOE"))
        out[f"{side}SHOULDER"] = first(mean_of(f"{side}CLO"), mean_of(f"{side}SHO"))
        out[f"{side}ELBOW"] = first(mean_of(f"{side}HUO"), mean_of(f"{side}ELB"))
        out[f"{side}WRIST"] = first(mean_of(f"{side}RAO"), mean_of(f"{side}WRA", f"{side}WRB"),
                                    mean_of(f"{side}WRI"))
        out[f"{side}HANDTIP"] = first(mean_of(f"{side}FIN"))
    out["NECK"] = first(mean_of("C7", "CLAV"))
    head = first(mean_of("LFHD", "RFHD", "LBHD", "RBHD"))
    if head is not None and out["NECK"] is not None:
        up = head - out["NECK"]
        out["HEADTOP"] = head + HEAD_TOP_ABOVE_MARKERS_M * up / np.linalg.norm(up, axis=-1, keepdims=True)
    else:
        out["HEADTOP"] = None
    missing = [n for n in _REQUIRED if out.get(n) is None]
    if missing:
        raise InputError(f"{c3d.source}: cannot place the joint centres {missing} from its points (present in at "
                         f"least {min_present:.0%} of the frames: none of the Plug-in-Gait origins, the CMU or "
                         f"Plug-in-Gait markers they are taken from); it has {c3d.labels}")
    return {n: p for n, p in out.items() if p is not None}


def c3d_world_positions(path: str | Path, fps: float, duration_s: float | None = None
                        ) -> tuple[list[str], torch.Tensor]:
    """Joint centres of a C3D capture resampled to ``fps`` (nearest frames), centred so that the hips' path
    mid-range is over the origin. Returns names (J,) and positions (T, J, 3) float64."""
    names, pos, _, _ = c3d_resampled(read_c3d(path), fps, duration_s)
    return names, pos


def c3d_resampled(c3d: C3D, fps: float, duration_s: float | None = None
                  ) -> tuple[list[str], torch.Tensor, np.ndarray, np.ndarray]:
    """:func:`c3d_world_positions` of a read file, with the file's frames it took ``(T,)`` and the horizontal
    shift ``(2,)`` it applied (m), so that the file's markers can be placed with the joint centres."""
    step = c3d.rate_hz / fps
    if step < 1 - 1e-6:
        raise InputError(f"{c3d.source}: recorded at {c3d.rate_hz:.1f} fps; cannot resample up to {fps} fps")
    centres = joint_centres(c3d)
    T = c3d.positions.shape[0]
    n = int(np.floor((T - 1) / step)) + 1
    if duration_s is not None:
        n = min(n, max(1, round(duration_s * fps)))
    frames = np.round(np.arange(n) * step).astype(np.int64)
    names = sorted(centres)
    pos = torch.from_numpy(np.stack([centres[k][frames] for k in names], 1))
    hips = pos[:, [names.index("LHIP"), names.index("RHIP")]].mean(1)
    shift = 0.5 * (hips[:, :2].min(0).values + hips[:, :2].max(0).values)
    pos[..., :2] -= shift
    return names, pos, frames, shift.numpy()


def retarget_c3d(path: str | Path, skel: Skeleton, fps: float, duration_s: float | None = None,
                 positions: tuple[list[str], torch.Tensor] | None = None) -> RetargetResult:
    """A C3D capture's joint centres retargeted to ``skel`` (:func:`~torchtrack.synth.retarget.retarget_positions`);
    ``positions``: its :func:`c3d_world_positions` where the caller has them already."""
    names, pos = c3d_world_positions(path, fps, duration_s) if positions is None else positions
    mapping = {ours: src for ours, src in C3D_JOINT_MAP.items() if all(s in names for s in src)}
    result = retarget_positions(skel, pos, names, mapping)
    log.info("%s: %d frames retargeted, mean joint-centre distance %.1f mm", Path(path).name,
             result.angles.shape[0], 1e3 * float(result.residual_m.mean()))
    return result


def c3d_motion(path: str | Path, skel: Skeleton, fps: float, duration_s: float | None, starfish_s: float,
               **starfish: float) -> tuple[Skeleton, torch.Tensor]:
    """A C3D capture as our skeleton's motion (as :func:`~torchtrack.synth.bvh_motion.bvh_motion` for BVH):
    retargeted, starfish start prepended, soles on the floor. Returns the scaled skeleton and (T, D) states."""
    result = retarget_c3d(path, skel, fps, duration_s)
    angles = with_starfish_start(result.skeleton, result.angles, fps, starfish_s, **starfish)
    return result.skeleton, on_the_floor(result.skeleton, angles)
