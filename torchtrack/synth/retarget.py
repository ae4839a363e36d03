"""Retarget motion-capture joint positions (e.g. a BVH file's) onto the body skeleton.

The source gives world positions of its own joints per frame. We (1) scale our skeleton to the source
subject (height, then limb lengths measured from the source), (2) initialise the root from the hips and
shoulders, and (3) fit all state vectors at once by minimising the squared distance between our joints and
the corresponding source points, batched over frames, with Adam on the differentiable forward kinematics of
pytorch-kinematics and projection onto the joint limits after every step (plus a weak pull to the rest
pose for the twists the points do not determine). This is a one-off data conversion, not the tracker's IK.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch

from torchtrack.checks import InputError, check_shape
from torchtrack.skeleton import Skeleton, fit_states

log = logging.getLogger(__name__)

#: Raised when a change here changes the bodies and motions retargeted from a capture: sequences rendered from
#: captures record it (meta.toml), and scripts that keep rendered sequences re-render the older ones.
RETARGET_REVISION = 2

#: Our joint (``Skeleton.joint_names``) -> source joint names whose mean is its position. For CMU BVH files
#: (bvh11 conversions, as in ../shared/data/mocap/cmu); an ``_end`` suffix names a joint's End Site. CMU's
#: ``lowerneck`` sits at the collar bones, some 9 cm below the shoulder joints, and its head's End Site near the
#: skull's middle, not its crown: our neck (a few cm above the shoulders) is taken between CMU's ``Neck`` (at the
#: shoulders' height) and ``Head`` (the skull's base), and the End Site as our ``head_center``.
CMU_BVH_MAP: dict[str, tuple[str, ...]] = {
    "pelvis": ("LeftHip", "RightHip"),
    "l_thigh": ("LeftHip",), "l_shank": ("LeftKnee",), "l_foot": ("LeftAnkle",), "l_toe": ("LeftToe",),
    "r_thigh": ("RightHip",), "r_shank": ("RightKnee",), "r_foot": ("RightAnkle",), "r_toe": ("RightToe",),
    "head": ("Neck", "Head"), "head_center": ("Head_end",),
    "l_upperarm": ("LeftShoulder",), "l_forearm": ("LeftElbow",), "l_hand": ("LeftWrist",),
    "l_hand_tip": ("LFingers",),
    "r_upperarm": ("RightShoulder",), "r_forearm": ("RightElbow",), "r_hand": ("RightWrist",),
    "r_hand_tip": ("RFingers",),
}

#: Limb bones whose length is measured from the source: bone -> (proximal, distal) of our joints.
_LIMBS = {
    "upperarm": ("upperarm", "forearm"), "forearm": ("forearm", "hand"),
    "thigh": ("thigh", "shank"), "shank": ("shank", "foot"),
}


@dataclass(frozen=True)
class RetargetResult:
    """Retargeted motion: our skeleton scaled to the subject, the state vectors and the fit residuals."""

    skeleton: Skeleton
    angles: torch.Tensor  # (T, D)
    joint_names: tuple[str, ...]  # the matched joints, in the order of residual_m's last axis
    residual_m: torch.Tensor  # (T, len(joint_names)) distance between our joint and the source point


def _targets(positions: torch.Tensor, names: Sequence[str], mapping: Mapping[str, Sequence[str]]
             ) -> tuple[list[str], torch.Tensor]:
    index = {n: i for i, n in enumerate(names)}
    ours, pts = [], []
    for joint, sources in mapping.items():
        missing = [s for s in sources if s not in index]
        if missing:
            raise InputError(f"retargeting: source joints {missing} (for our {joint!r}) are not in the motion; "
                             f"it has {list(names)}")
        ours.append(joint)
        pts.append(positions[:, [index[s] for s in sources]].mean(dim=1))
    return ours, torch.stack(pts, dim=1)  # (T, n, 3)


def _body_frame_offsets(at: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Median over frames of the shoulders relative to the neck, hips relative to the pelvis and the
    pelvis-neck distance, in a body frame (x forward, y left, z from the pelvis to the neck)."""
    up = at["head"] - at["pelvis"]
    trunk = up.norm(dim=-1)  # (T,)
    up = up / trunk[:, None]
    left = at["l_thigh"] - at["r_thigh"]
    left = left - (left * up).sum(-1, keepdim=True) * up
    left = left / left.norm(dim=-1, keepdim=True)
    fwd = torch.cross(left, up, dim=-1)
    R = torch.stack([fwd, left, up], dim=1)  # (T, 3, 3) rows: body axes in world

    def local(p: torch.Tensor, o: torch.Tensor) -> torch.Tensor:
        return (R @ (p - o)[..., None])[..., 0].median(dim=0).values

    out = {"trunk": trunk.median(), "l_thigh": local(at["l_thigh"], at["pelvis"]),
           "r_thigh": local(at["r_thigh"], at["pelvis"])}
    for s in "lr":
        if f"{s}_upperarm" in at:
            out[f"{s}_upperarm"] = local(at[f"{s}_upperarm"], at["head"])
    return out


def _scaled_skeleton(skel: Skeleton, ours: list[str], target: torch.Tensor) -> Skeleton:
    """Fit our proportions to the source subject: overall height, trunk length, hip and shoulder placement,
    then limb lengths (left/right mean), all as medians over the motion."""
    at = {n: target[:, i] for i, n in enumerate(ours)}
    # The height from the highest head point the source gives (the crown, else the head's centre).
    head_point = next((k for k in ("head_top", "head_center") if k in at), None)
    if head_point is not None and "pelvis" in at:
        top = (at[head_point][:, 2] - at["pelvis"][:, 2]).median()
        z = skel.rest_frames[skel.frame_index([head_point, "pelvis"])][:, 2, 3]
        skel = skel.scaled_to_height(skel.height() * float(top) / float(z[0] - z[1]))
    if {"head", "pelvis", "l_thigh", "r_thigh"} <= at.keys():
        rel = _body_frame_offsets(at)
        spine = skel.joint_origin("spine_flex")[2]  # pelvis -> lumbar, kept
        torso = float(rel["trunk"]) - spine  # lumbar -> neck
        origins = {"neck_flex": (0.0, 0.0, torso)}
        for s in "lr":
            origins[f"{s}_hip_flex"] = tuple(float(v) for v in rel[f"{s}_thigh"])
            if f"{s}_upperarm" in rel:
                x, y, z = (float(v) for v in rel[f"{s}_upperarm"])
                if f"{s}_shoulder_elev" in skel.dof_names:  # a shoulder girdle: its pivot medial, the shoulder out
                    medial = skel.joint_origin(f"{s}_shoulder_elev")[1]
                    share = medial / (medial + skel.joint_origin(f"{s}_shoulder_flex")[1])
                    origins[f"{s}_shoulder_elev"] = (x, share * y, torso + z)
                    origins[f"{s}_shoulder_flex"] = (0.0, (1 - share) * y, 0.0)
                else:
                    origins[f"{s}_shoulder_flex"] = (x, y, torso + z)
        skel = skel.with_joint_origins(origins)
    lengths = {}
    for bone, (a, b) in _LIMBS.items():
        sides = [(at[f"{s}_{a}"] - at[f"{s}_{b}"]).norm(dim=-1).median() for s in "lr"
                 if f"{s}_{a}" in at and f"{s}_{b}" in at]
        if sides:
            mean = float(torch.stack(sides).mean())
            lengths.update({f"l_{bone}": mean, f"r_{bone}": mean})
    if head_point is not None and "head" in at:
        # the head bone runs from the neck to the crown; a point along it scales with it
        p = skel.rest_frames[skel.frame_index([head_point, "head"])][:, :3, 3]
        share = float((p[0] - p[1]).norm()) / float(skel.bone_lengths[skel.bone_names.index("head")])
        lengths["head"] = float((at[head_point] - at["head"]).norm(dim=-1).median()) / share
    return skel.with_bone_lengths(lengths) if lengths else skel


def _initial_root(skel: Skeleton, ours: list[str], target: torch.Tensor) -> torch.Tensor:
    """(T, D) rest pose placed at the source pelvis, yawed so the hips' left-right axis matches."""
    at = {n: target[:, i] for i, n in enumerate(ours)}
    T = target.shape[0]
    angles = skel.rest_angles().to(target).expand(T, -1).clone()
    angles[:, 0:3] = at["pelvis"]
    left = at["l_thigh"] - at["r_thigh"]  # (T, 3) the body's +Y
    angles[:, 3] = torch.atan2(-left[:, 0], left[:, 1])  # yaw that maps +Y onto `left`
    return angles


def _fit(skel: Skeleton, theta0: torch.Tensor, target: torch.Tensor, joint_idx: torch.Tensor, iterations: int,
         lr: float, rest_weight: float) -> torch.Tensor:
    """(T, D) states whose joints ``joint_idx`` meet ``target (T, n, 3)``, with a small pull to the rest pose
    (:func:`~torchtrack.skeleton.model.fit_states`)."""
    rest = skel.rest_angles().double()

    def loss(fk, theta):
        return (((fk.joints[:, joint_idx] - target) ** 2).sum(-1).mean()
                + rest_weight * ((theta[:, 6:] - rest[6:]) ** 2).mean())

    return fit_states(skel, theta0, loss, iterations, lr)


def retarget_positions(skel: Skeleton, positions: torch.Tensor, names: Sequence[str],
                       mapping: Mapping[str, Sequence[str]] = CMU_BVH_MAP, iterations: int = 400,
                       lr: float = 0.03, rest_weight: float = 1e-3, refit_threshold_m: float = 0.08
                       ) -> RetargetResult:
    """Fit our skeleton to source joint positions, all frames at once.

    Args:
        skel: our skeleton (it is scaled to the subject first).
        positions: (T, J, 3) source joint positions in our world frame (Z up, metres).
        names: (J,) source joint names.
        mapping: our joint name -> source names (their mean is the target).
        refit_threshold_m: frames whose worst joint is farther than this (and 3x the median frame's) are
            fitted again from their nearest well-fitted frame.

    Returns:
        RetargetResult; ``residual_m`` is the landmark distance after retargeting.
    """
    check_shape(positions, ("T", len(names), 3), "positions")
    if not torch.isfinite(positions).all():
        raise InputError("retargeting: the source positions contain NaN or inf")
    positions = positions.double()
    ours, target = _targets(positions, names, mapping)
    skel = _scaled_skeleton(skel, ours, target)
    joint_idx = torch.tensor([skel.joint_names.index(n) for n in ours])
    theta = _fit(skel, _initial_root(skel, ours, target), target, joint_idx, iterations, lr, rest_weight)
    with torch.no_grad():
        residual = (skel(theta).joints[:, joint_idx] - target).norm(dim=-1)  # (T, n)
    # Frames caught in a local minimum (typically a wrong initial facing): restart them from the nearest
    # well-fitted frame, moved to their own pelvis, and fit again.
    worst = residual.max(dim=1).values
    bad = worst > max(refit_threshold_m, 3 * float(worst.median()))
    good = (~bad).nonzero().flatten()
    if bool(bad.any()) and good.numel():
        idx = bad.nonzero().flatten()
        nearest = good[(idx[:, None] - good[None, :]).abs().argmin(dim=1)]
        start = theta[nearest].clone()
        start[:, 0:3] += target[idx, ours.index("pelvis")] - target[nearest, ours.index("pelvis")]
        theta[idx] = _fit(skel, start, target[idx], joint_idx, iterations, lr, rest_weight)
        with torch.no_grad():
            residual = (skel(theta).joints[:, joint_idx] - target).norm(dim=-1)
        log.info("retargeting: %d frames re-fitted from a neighbour", idx.numel())
    log.info("retargeted %d frames: mean joint distance %.1f mm, max %.1f mm", target.shape[0],
             1e3 * float(residual.mean()), 1e3 * float(residual.max()))
    return RetargetResult(skel, theta.detach().float(), tuple(ours), residual.float())
