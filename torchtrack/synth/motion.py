"""Procedural motions for synthetic sequences, as state-vector trajectories ``(T, D)``.

Every sequence starts with ``starfish_s`` seconds in the starfish pose (arms and legs spread, as a subject
is asked to do for initialisation), then blends over ``blend_s`` seconds into the motion. Motions stay within
about 1 m of the origin so that a rig on a 3-4 m circle sees them. Angles are in radians, the body frame of
:mod:`torchtrack.conventions` (facing +X at yaw 0).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch

from torchtrack.checks import InputError
from torchtrack.skeleton import Skeleton

MOTIONS = ("walk", "turn", "arm_raise", "squat", "kick")


def _set(angles: torch.Tensor, skel: Skeleton, name: str, value: torch.Tensor | float) -> None:
    angles[:, skel.dof_names.index(name)] = value


def _gait(skel: Skeleton, a: torch.Tensor, phase: torch.Tensor, scale: float | torch.Tensor = 1.0) -> None:
    """The walk's legs, arms and bob at gait ``phase`` (rad, one cycle per stride); ``scale`` (per frame or one
    value) shrinks the swings from a walk at :data:`WALK_SPEED_M_S` (1) to standing (0)."""
    _set(a, skel, "root_tz", skel.standing_root_height() - 0.03 + (0.015 * scale) * torch.cos(2 * phase))
    for side in ("l", "r"):
        p = phase + (0.0 if side == "l" else math.pi)
        _set(a, skel, f"{side}_hip_flex", (0.35 * scale) * torch.sin(p))
        _set(a, skel, f"{side}_knee_flex", 0.15 + (0.5 * scale) * torch.clamp(torch.sin(p + 1.2), min=0))
        _set(a, skel, f"{side}_ankle_flex", (0.1 * scale) * torch.sin(p - 0.5))
        _set(a, skel, f"{side}_shoulder_flex", (-0.35 * scale) * torch.sin(p))
        _set(a, skel, f"{side}_shoulder_abd", 0.12)
        _set(a, skel, f"{side}_elbow_flex", 0.35 + (0.15 * scale) * torch.sin(p))
    _set(a, skel, "spine_twist", (0.08 * scale) * torch.sin(phase))


#: The procedural walk: its speed and gait cycle (the circle walk's; a path walk strides longer or shorter).
WALK_SPEED_M_S = 0.9
WALK_CYCLE_S = 1.1


def _walk(skel: Skeleton, t: torch.Tensor, a: torch.Tensor, radius_m: float = 0.8,
          speed_mps: float = WALK_SPEED_M_S) -> None:
    """Walk counter-clockwise on a circle of ``radius_m`` around the origin, facing the walking direction."""
    heading = speed_mps * t / radius_m
    _set(a, skel, "root_tx", radius_m * torch.sin(heading))
    _set(a, skel, "root_ty", -radius_m * torch.cos(heading))
    _set(a, skel, "root_rz", heading)
    _gait(skel, a, 2 * math.pi * t / WALK_CYCLE_S)


#: The path walk's swings grow with the speed up to this (the circle walk's 1.6x), then its cadence does.
PATH_WALK_MAX_SCALE = 1.6
#: Turning on the spot steps too: metres of stride a radian of turn (a turn of 4 rad/s strides as walking at 1 m/s),
#: in short steps: at most the stride of walking at PATH_WALK_TURN_MAX_M_S.
PATH_WALK_TURN_M = 0.25
PATH_WALK_TURN_MAX_M_S = 0.45


def path_position(path: Sequence[Sequence[float]], t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor,
                                                                              torch.Tensor]:
    """Where ``path`` (``(time_s, x, y)`` waypoints in increasing time) puts the subject at times ``t (T,)``:
    (T, 2) float64 positions eased between waypoints (smoothstep: no jump in speed at a waypoint), held before
    the first and after the last; (T,) each time's segment end (1 .. P - 1) and (T,) its eased fraction."""
    way = torch.tensor([list(p) for p in path], dtype=torch.float64)  # (P, 3)
    if way.ndim != 2 or way.shape[1] != 3 or not bool((way[1:, 0] > way[:-1, 0]).all()):
        raise InputError(f"path: (time_s, x, y) waypoints in increasing time, got {path}")
    t = t.to(torch.float64)
    if way.shape[0] == 1:  # one place, at all times
        return way[:1, 1:].expand(t.shape[0], 2).clone(), torch.ones_like(t, dtype=torch.long), torch.zeros_like(t)
    seg = torch.searchsorted(way[:, 0].contiguous(), t).clamp(1, way.shape[0] - 1)  # (T,) segment end
    t0, t1 = way[seg - 1, 0], way[seg, 0]
    u = ((t - t0) / (t1 - t0).clamp(min=1e-9)).clamp(0, 1)
    u = u * u * (3 - 2 * u)
    return (1 - u)[:, None] * way[seg - 1, 1:] + u[:, None] * way[seg, 1:], seg, u


def _moves(path: Sequence[Sequence[float]]) -> list[tuple[int, float]]:
    """The segments of ``path`` that move (k: from waypoint k to k + 1) and each one's direction (rad): a few
    waypoints, read on the host."""
    pts = [(float(p[1]), float(p[2])) for p in path]
    return [(k, math.atan2(b[1] - a[1], b[0] - a[0])) for k, (a, b) in enumerate(zip(pts, pts[1:]))
            if math.dist(a, b) > 1e-9]


def _path_heading(path: Sequence[Sequence[float]], seg: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """(T,) float64 the heading (rad, unwrapped) of a walker on ``path`` (:func:`path_position`'s ``seg`` and
    ``u``): along each segment that moves; over a pause (the segments that stay between two moves, as one), turning
    from the way they came to the way they go next, the shorter way round (left on a half turn), as each segment's
    eased fraction ``u`` of its share of the pause's time; before the first move and after the last, the nearest
    move's. A path that never moves faces +X. (:func:`walks_path` refuses a turn without a pause.)"""
    way = [(float(p[0]), float(p[1]), float(p[2])) for p in path]
    moves = _moves(path)
    moving = [k for k, _ in moves]
    if not moving:
        return torch.zeros_like(u)
    unwrapped: dict[int, float] = {}
    for i, (k, along) in enumerate(moves):  # each move's direction, continued from the one before
        if i == 0:
            unwrapped[k] = along
            continue
        before = unwrapped[moving[i - 1]]
        turn = math.remainder(along - before, 2 * math.pi)
        unwrapped[k] = before + (math.pi if turn <= -math.pi + 1e-9 else turn)
    enter, leave = [], []  # (P - 1,) each segment's heading at its start and end
    for k in range(len(way) - 1):
        came = max((m for m in moving if m <= k), default=moving[0])
        goes = min((m for m in moving if m >= k), default=moving[-1])
        if came == goes:  # a move, or a pause before the first or after the last
            enter.append(unwrapped[came])
            leave.append(unwrapped[came])
            continue
        start, end = way[came + 1][0], way[goes][0]  # the pause's time, all its segments
        f0, f1 = (way[k][0] - start) / (end - start), (way[k + 1][0] - start) / (end - start)
        turn = unwrapped[goes] - unwrapped[came]
        enter.append(unwrapped[came] if k == came + 1 else unwrapped[came] + f0 * turn)
        leave.append(unwrapped[goes] if k + 1 == goes else unwrapped[came] + f1 * turn)
    enter_t, leave_t = (torch.tensor(v, dtype=torch.float64) for v in (enter, leave))
    k = seg - 1
    return enter_t[k] + u * (leave_t[k] - enter_t[k])


def _walk_path(skel: Skeleton, t: torch.Tensor, a: torch.Tensor, path: Sequence[Sequence[float]]) -> None:
    """Walk ``path`` (times ``t`` from the sequence's start): facing the way they go, turning on the spot where the
    path pauses, the gait's swings and stride as long as the speed asks (the circle walk's at its speed, up to
    :data:`PATH_WALK_MAX_SCALE` of them, faster by cadence), so the feet step as the body goes rather than slide."""
    pos, seg, u = path_position(path, t)
    heading = _path_heading(path, seg, u)
    dt = float(t[1] - t[0]) if t.shape[0] > 1 else 1.0
    speed = torch.gradient(pos, spacing=dt, dim=0)[0].norm(dim=-1) if t.shape[0] > 1 else torch.zeros_like(u)
    omega = torch.gradient(heading, spacing=dt)[0].abs() if t.shape[0] > 1 else torch.zeros_like(u)
    pace = speed + (PATH_WALK_TURN_M * omega).clamp(max=PATH_WALK_TURN_MAX_M_S)  # (T,) m/s the legs stride at
    scale = (pace / WALK_SPEED_M_S).clamp(max=PATH_WALK_MAX_SCALE)
    # the circle walk strides WALK_SPEED_M_S * WALK_CYCLE_S a cycle at scale 1, proportionally at other scales
    rate = 2 * math.pi / WALK_CYCLE_S * torch.where(scale > 1e-6, pace / (WALK_SPEED_M_S * scale.clamp(min=1e-6)),
                                                    torch.ones_like(scale))
    phase = torch.cumsum(rate * dt, 0) - rate[0] * dt
    _set(a, skel, "root_tx", pos[:, 0].float())
    _set(a, skel, "root_ty", pos[:, 1].float())
    _set(a, skel, "root_rz", heading.float())
    _gait(skel, a, phase.float(), scale.float())


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


def walks_path(kind: str, path: Sequence[Sequence[float]]) -> bool:
    """Whether motion ``kind`` on ``path`` walks it (the walk: facing the way it goes, stepping as it goes) rather
    than being carried along it by an offset (every other motion).

    Raises:
        InputError: a walk's path that changes direction at a waypoint without a pause there (the walker stops at
            every waypoint and turns on the spot where it stays: repeat the corner at a later time).
    """
    if kind != "walk" or not path:
        return False
    moves = _moves(path)
    for (k, a), (m, b) in zip(moves, moves[1:]):
        if m == k + 1 and abs(math.remainder(b - a, 2 * math.pi)) > 1e-6:
            raise InputError(f"path: the walk turns at waypoint {m} {tuple(path[m])} without a pause there; repeat "
                             f"that waypoint at a later time for the walker to turn in")
    return True


def procedural_motion(skel: Skeleton, kind: str, duration_s: float, fps: float, starfish_s: float = 1.0,
                      path: Sequence[Sequence[float]] = (), **starfish: float) -> torch.Tensor:
    """A procedural motion with the starfish start.

    Args:
        kind: one of :data:`MOTIONS`.
        duration_s: length of the motion itself (the starfish second comes on top).
        path: for the walk, ``(time_s, x, y)`` waypoints (times from the sequence's start, starfish included)
            that it walks instead of its circle (:func:`walks_path`); other motions ignore it (the caller carries
            them along it).
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
    if walks_path(kind, path):
        _walk_path(skel, t + starfish_s, a, path)
    else:
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
