"""Poses of the body, apart from any frame: the prior the start search draws its hypotheses from (a structured
one of per-limb poses, and the real captures' poses), and the body's symmetries (its left-right mirror, the same
silhouette turned round) that the search, the start race and the prior's builder use."""

from __future__ import annotations

import functools
import math

import numpy as np
import torch

from torchtrack.skeleton.model import Skeleton

__all__ = ["ARM_POSES", "LEG_POSES", "MIRROR_NEGATED", "POSE_PRIOR", "mirrored", "pose_prior", "real_pose_prior",
           "turned_round"]

#: Arm poses of the prior, per side: (shoulder flexion, shoulder abduction, elbow flexion) in radians.
ARM_POSES = ((0.0, 0.1, 0.15), (0.3, 0.15, 1.5), (1.5, 0.1, 0.1), (0.0, 0.75, 0.1), (0.0, 1.5, 0.1),
             (2.7, 0.3, 0.2))
#: Leg poses of the prior: {dof: value} on top of the rest pose (both legs named).
LEG_POSES = (
    {},
    {"l_hip_abd": 0.3, "r_hip_abd": 0.3},
    {"l_hip_flex": 0.45, "r_hip_flex": -0.3, "l_knee_flex": 0.2, "r_knee_flex": 0.3},
    {"r_hip_flex": 0.45, "l_hip_flex": -0.3, "r_knee_flex": 0.2, "l_knee_flex": 0.3},
    {"l_hip_flex": 1.3, "r_hip_flex": 1.3, "l_knee_flex": 2.0, "r_knee_flex": 2.0, "l_ankle_flex": 0.4,
     "r_ankle_flex": 0.4, "spine_flex": 0.4},
    {"l_hip_flex": 1.3, "l_knee_flex": 1.6},
    {"r_hip_flex": 1.3, "r_knee_flex": 1.6},
    {"l_hip_flex": 1.2, "l_knee_flex": 0.2, "spine_flex": -0.1},
)


def pose_prior(skel: Skeleton, symmetric_arms: bool = False) -> torch.Tensor:
    """(P, D) the prior's poses: every arm pose on each side (or the same on both: ``symmetric_arms``) with every
    leg pose, root at the origin facing +X (root translation and rotation zero)."""
    names = list(skel.dof_names)
    rest = torch.zeros(skel.num_dofs, dtype=skel.lower.dtype, device=skel.lower.device)
    out = []
    arm_pairs = ([(a, a) for a in ARM_POSES] if symmetric_arms else
                 [(a, b) for a in ARM_POSES for b in ARM_POSES])
    for legs in LEG_POSES:
        for left, right in arm_pairs:
            a = rest.clone()
            for side, (flex, abd, elbow) in (("l", left), ("r", right)):
                a[names.index(f"{side}_shoulder_flex")] = flex
                a[names.index(f"{side}_shoulder_abd")] = abd
                a[names.index(f"{side}_elbow_flex")] = elbow
            for dof, v in legs.items():
                a[names.index(dof)] = v
            out.append(a)
    return skel.clamp(torch.stack(out))


#: The real captures' poses (``scripts/build_pose_prior.py``): angles (P, D), dof_names (D,), source (P,).
POSE_PRIOR = "pose_prior.npz"


@functools.lru_cache(maxsize=2)
def _prior_file(path: str) -> dict[str, np.ndarray]:
    with np.load(path) as f:
        return {k: f[k] for k in ("angles", "dof_names", "source")}


def real_pose_prior(skel: Skeleton, exclude: tuple[str, ...] = ()) -> torch.Tensor:
    """(P, D) the real captures' poses (built-in ``configs/pose_prior.npz``: poses of the captures in
    ``../shared/data/mocap``, each with its left-right mirror, thinned by farthest-point sampling) on ``skel``'s
    DOFs (a DOF the file lacks at 0), root translation and heading zero, within the joint limits; the poses of the
    captures whose name contains a string of ``exclude`` left out."""
    from torchtrack.resources import builtin_config

    data = _prior_file(str(builtin_config(POSE_PRIOR)))
    keep = np.asarray([not any(e in str(src) for e in exclude) for src in data["source"]], dtype=bool)
    names = [str(n) for n in data["dof_names"]]
    src = torch.from_numpy(data["angles"][keep])
    out = torch.zeros(src.shape[0], skel.num_dofs, dtype=skel.lower.dtype, device=skel.lower.device)
    for d, name in enumerate(skel.dof_names):
        if name in names:
            out[:, d] = src[:, names.index(name)].to(out)
    return skel.clamp(out)


#: The DOFs that the body's left-right mirror negates (sideways bends, twists and the root's roll); the limbs'
#: DOFs are named per side with mirror-symmetric signs, so the mirror swaps them as they are.
MIRROR_NEGATED = ("root_rx", "spine_abd", "spine_twist", "neck_abd", "neck_twist")


def _sides_swapped(skel: Skeleton, angles: torch.Tensor) -> torch.Tensor:
    """``angles (..., D)`` with the left and right limbs' DOFs swapped and :data:`MIRROR_NEGATED` negated."""
    names = list(skel.dof_names)
    other = {"l_": "r_", "r_": "l_"}
    swap = [names.index(other[n[:2]] + n[2:]) if n[:2] in other else i for i, n in enumerate(names)]
    sign = torch.tensor([-1.0 if n in MIRROR_NEGATED else 1.0 for n in names], dtype=angles.dtype,
                        device=angles.device)
    return angles[..., swap] * sign  # one gather: each side takes the other's values


def mirrored(skel: Skeleton, angles: torch.Tensor) -> torch.Tensor:
    """``angles (..., D)`` mirrored left to right through the world's XZ plane (y -> -y): the same pose done by
    the other side (for a body facing +X at the origin, its own sagittal plane)."""
    out = _sides_swapped(skel, angles)
    for name in ("root_ty", "root_rz"):
        out[..., skel.dof_names.index(name)] *= -1.0
    return out


def turned_round(skel: Skeleton, angles: torch.Tensor) -> torch.Tensor:
    """``angles (..., D)`` reflected through the body's frontal plane (the vertical plane through the root across
    its heading) and re-expressed as a body facing the other way: heading + pi, left and right limbs swapped, the
    sideways bends, twists and roll negated. For a pose without flexion it fills the same space facing the other
    way (the front/back ambiguity of a silhouette, e.g. a starfish); a flexed joint then bends the other way in the
    world."""
    out = _sides_swapped(skel, angles)
    out[..., skel.dof_names.index("root_rz")] += math.pi
    return out
