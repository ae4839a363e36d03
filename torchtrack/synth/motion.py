"""Procedural motions for synthetic sequences, as state-vector trajectories ``(T, D)``.

Every sequence starts with ``starfish_s`` seconds in the starfish pose (arms and legs spread, as a subject
is asked to do for initialisation), then blends over ``blend_s`` seconds into the motion. Motions stay within
about 1 m of the origin so that a rig on a 3-4 m circle sees them. Angles are in radians, the body frame of
:mod:`torchtrack.conventions` (facing +X at yaw 0).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

from torchtrack.checks import InputError
from torchtrack.skeleton import Skeleton

MOTIONS = ("walk", "turn", "arm_raise", "squat", "kick")


def _set(angles: torch.Tensor, skel: Skeleton, name: str, value: torch.Tensor | float) -> None:
    angles[:, skel.dof_names.index(name)] = value


def _walk(skel: Skeleton, t: torch.Tensor, a: torch.Tensor, radius_m: float = 0.8, speed_mps: float = 0.9) -> None:
    """Walk counter-clockwise on a circle of ``radius_m`` around the origin, facing the walking direction."""
    phase = 2 * math.pi * t / 1.1  # one gait cycle per 1.1 s
    heading = speed_mps * t / radius_m
    _set(a, skel, "root_tx", radius_m * torch.sin(heading))
    _set(a, skel, "root_ty", -radius_m * torch.cos(heading))
    _set(a, skel, "root_rz", heading)
    _set(a, skel, "root_tz", skel.standing_root_height() - 0.03 + 0.015 * torch.cos(2 * phase))
    for side, sgn in (("l", 1.0), ("r", -1.0)):
        p = phase + (0.0 if side == "l" else math.pi)
        _set(a, skel, f"{side}_hip_flex", 0.35 * torch.sin(p))
        _set(a, skel, f"{side}_knee_flex", 0.15 + 0.5 * torch.clamp(torch.sin(p + 1.2), min=0))
        _set(a, skel, f"{side}_ankle_flex", 0.1 * torch.sin(p - 0.5))
        _set(a, skel, f"{side}_shoulder_flex", -0.35 * torch.sin(p))
        _set(a, skel, f"{side}_shoulder_abd", 0.12)
        _set(a, skel, f"{side}_elbow_flex", 0.35 + 0.15 * torch.sin(p))
    _set(a, skel, "spine_twist", 0.08 * torch.sin(phase))


def _turn(skel: Skeleton, t: torch.Tensor, a: torch.Tensor) -> None:
    """Turn on the spot, one full turn per 4 s, with small stepping and arms half raised."""
    phase = 2 * math.pi * t / 0.8
    _set(a, skel, "root_rz", 2 * math.pi * t / 4.0)
    _set(a, skel, "root_tz", skel.standing_root_height() - 0.01)
    for side in ("l", "r"):
        p = phase + (0.0 if side == "l" else math.pi)
        step = torch.clamp(torch.sin(p), min=0)
        _set(a, skel, f"{side}_hip_flex", 0.3 * step)
        _set(a, skel, f"{side}_knee_flex", 0.6 * step)
        _set(a, skel, f"{side}_shoulder_abd", 0.6)
        _set(a, skel, f"{side}_elbow_flex", 0.8)


def _arm_raise(skel: Skeleton, t: torch.Tensor, a: torch.Tensor) -> None:
    """Raise the arms sideways over the head and forwards, alternating, every 2.5 s."""
    s = 0.5 - 0.5 * torch.cos(2 * math.pi * t / 2.5)  # 0 -> 1 -> 0
    cycle = torch.floor(t / 2.5) % 2
    sideways, forwards = s * (1 - cycle), s * cycle
    for side in ("l", "r"):
        _set(a, skel, f"{side}_shoulder_abd", 0.1 + 2.4 * sideways)
        _set(a, skel, f"{side}_shoulder_flex", 2.2 * forwards)
        _set(a, skel, f"{side}_elbow_flex", 0.2 + 0.6 * forwards)
    _set(a, skel, "root_rz", 0.4)


def _squat(skel: Skeleton, t: torch.Tensor, a: torch.Tensor) -> None:
    """Squat down and up every 2.5 s, arms forward for balance; the soles stay on the floor."""
    s = 0.5 - 0.5 * torch.cos(2 * math.pi * t / 2.5)
    hip, knee = 1.3 * s, 2.0 * s
    ankle = knee - hip  # keep the shank's tilt compensated so the foot stays flat
    thigh, shank = (float(skel.bone_lengths[skel.bone_names.index(n)]) for n in ("l_thigh", "l_shank"))
    drop = thigh * (1 - torch.cos(hip)) + shank * (1 - torch.cos(knee - hip))
    _set(a, skel, "root_tz", skel.standing_root_height() - drop)
    _set(a, skel, "root_rz", -0.6)
    _set(a, skel, "spine_flex", 0.4 * s)
    for side in ("l", "r"):
        _set(a, skel, f"{side}_hip_flex", hip)
        _set(a, skel, f"{side}_knee_flex", knee)
        _set(a, skel, f"{side}_ankle_flex", ankle.clamp(max=0.5))
        _set(a, skel, f"{side}_shoulder_flex", 1.4 * s)
        _set(a, skel, f"{side}_hip_abd", 0.15)


def _kick(skel: Skeleton, t: torch.Tensor, a: torch.Tensor) -> None:
    """Kick forwards with the left and right leg in turn, every 2 s."""
    s = torch.clamp(torch.sin(2 * math.pi * t / 2.0), min=0) ** 2
    left = (torch.floor(t / 2.0) % 2) == 0
    _set(a, skel, "root_rz", 1.2)
    _set(a, skel, "root_tz", skel.standing_root_height() - 0.02)
    for side, on in (("l", left), ("r", ~left)):
        k = s * on
        _set(a, skel, f"{side}_hip_flex", 1.3 * k)
        _set(a, skel, f"{side}_knee_flex", 0.9 * k * (1 - k) * 4 * 0.5 + 0.05)
        _set(a, skel, f"{side}_shoulder_abd", 0.5)
        _set(a, skel, f"{side}_shoulder_flex", -0.5 * k)
        _set(a, skel, f"{side}_elbow_flex", 0.5)
    _set(a, skel, "spine_flex", -0.15 * s)


_GENERATORS: dict[str, Callable[[Skeleton, torch.Tensor, torch.Tensor], None]] = {
    "walk": _walk, "turn": _turn, "arm_raise": _arm_raise, "squat": _squat, "kick": _kick}


def with_starfish_start(skel: Skeleton, motion: torch.Tensor, fps: float, starfish_s: float = 1.0,
                        blend_s: float = 0.5, arm_abduction: float = 1.25, leg_abduction: float = 0.3
                        ) -> torch.Tensor:
    """Prepend ``starfish_s`` seconds of the starfish pose, placed where the motion starts, then blend into it.

    Args:
        motion: (T, D) trajectory.
        arm_abduction, leg_abduction: the starfish's style (:meth:`Skeleton.starfish_angles`, radians).

    Returns:
        (T + round(starfish_s * fps), D); the first ``round(blend_s * fps)`` frames of ``motion`` are blended.
    """
    n_star, n_blend = round(starfish_s * fps), min(round(blend_s * fps), motion.shape[0])
    star = skel.starfish_angles(arm_abduction, leg_abduction).to(motion).expand(n_star, -1).clone()  # (n_star, D)
    star[:, :2] = motion[0, :2]  # stand where the motion begins, facing the same way
    star[:, 3] = motion[0, 3]
    if n_star == 0:
        return motion.clone()
    out = torch.cat([star, motion.clone()])
    w = torch.linspace(0, 1, n_blend + 2, dtype=motion.dtype, device=motion.device)[1:-1, None]  # (n_blend, 1)
    w = 0.5 - 0.5 * torch.cos(math.pi * w)
    out[n_star:n_star + n_blend] = (1 - w) * star[-1] + w * motion[:n_blend]
    return out


def procedural_motion(skel: Skeleton, kind: str, duration_s: float, fps: float, starfish_s: float = 1.0,
                      **starfish: float) -> torch.Tensor:
    """A procedural motion with the starfish start.

    Args:
        kind: one of :data:`MOTIONS`.
        duration_s: length of the motion itself (the starfish second comes on top).
        starfish: ``arm_abduction`` and ``leg_abduction`` of the starfish (:func:`with_starfish_start`).

    Returns:
        (T, D) float32 state vectors within the skeleton's joint limits.
    """
    if kind not in _GENERATORS:
        raise InputError(f"unknown motion {kind!r}; choose one of {', '.join(MOTIONS)}, a .bvh or a .c3d file")
    if duration_s <= 0 or fps <= 0:
        raise InputError(f"duration_s and fps must be positive, got {duration_s}, {fps}")
    t = torch.arange(round(duration_s * fps), dtype=torch.float32) / fps  # (T,)
    a = skel.rest_angles().float().expand(t.shape[0], -1).clone()  # (T, D)
    _GENERATORS[kind](skel, t, a)
    return on_the_floor(skel, with_starfish_start(skel, skel.clamp(a), fps, starfish_s, **starfish))


def on_the_floor(skel: Skeleton, angles: torch.Tensor) -> torch.Tensor:
    """Shift ``root_tz`` per frame so that the lowest sole point (toe tips, heels) touches z = 0.

    Args:
        angles: (T, D).

    Returns:
        (T, D) a copy with ``root_tz`` adjusted (no jumping: some foot is always on the floor).
    """
    fk = skel(angles)
    names = list(skel.joint_names)
    toes = fk.joints[:, [names.index("l_toe"), names.index("r_toe")], 2]  # (T, 2)
    ankle_height = float(skel.rest_frames[skel.frame_index(["l_foot"])][0, 2, 3]
                         - skel.rest_frames[skel.frame_index(["l_toe"])][0, 2, 3])
    heels = fk.joints[:, [names.index("l_foot"), names.index("r_foot")], 2] - ankle_height  # (T, 2)
    lowest = torch.cat([toes, heels], dim=1).min(dim=1).values  # (T,)
    out = angles.clone()
    out[:, skel.dof_names.index("root_tz")] -= lowest
    return out
