"""The subject's body and pose from 3D landmarks: an initial pose for tracking from keypoints.

de Bem's tracker can start from a saved initialisation instead of the starfish pose: the subject's body and the
first frame's pose. Where 3D keypoints of the first frames are at hand (another tool's triangulated keypoints,
joint centres from markers, Pose2Sim's output), :func:`fit_to_landmarks` makes one:

1. the body model scaled to the subject's height, from the median ratio of :data:`SCALE_SEGMENTS` lengths (the
   limbs' segments, whose lengths do not depend on the pose, and pelvis to neck, which the spine's bend shortens a
   little) to the template's;
2. the pose by least squares: the root by weighted Kabsch on the trunk's points, the limbs by CCD;
3. with ``fit_bones``, alternated with 2: each bone group's length (:data:`FIT_BONE_GROUPS`) and the neck's and
   shoulders' height on the trunk (:data:`FIT_HEIGHT_JOINTS`) by linear least squares. At fixed joint angles
   every output point is affine in the bones' lengths and in those joints' offsets (forward kinematics is linear
   in the links' offsets), so each group's effect is one exact finite difference; a small ridge keeps groups no
   landmark constrains at their current length, and each frame's root may shift.

What the points do not pin, the template's proportions decide: without the ``spine`` and ``lumbar`` landmarks
(Pose2Sim gives neither) the torso's length is told by the shoulders' width as much as by their height (its
length scales the shoulders' offsets, left-right too, and the shoulders' height shift takes up the rest), and the
pelvis' by the hips' width.

The bone fit matters on real subjects: Pose2Sim's demo subject has a longer trunk and higher shoulders on it than
the template scaled to its height, and the fitted body brings both the landmark fit and the track closer to the
reference than the scaled template does (``scripts/eval_pose2sim_tracking.py --reference-fit`` and
``--init-from-reference``; docs/results.md, "The real Pose2Sim demo").

:func:`initial_pose` records the result for ``torchtrack track --init-pose`` (a poses.npz frame with the body's
URDF in its ``body_urdf`` key, as the tracker's own output carries the body it fitted).

The tracker's own bone fit (:meth:`MarkerlessTracker._fit_bone_lengths`) works from blobs fitted to voxels; this
one from landmarks, which pin joint centres directly, so it fits each limb's two bones apart.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from torchtrack.blobs import BlobModel
from torchtrack.checks import InputError, check_shape
from torchtrack.io.poses import Poses
from torchtrack.skeleton.ik import CCDConfig, CCDSolver
from torchtrack.skeleton.model import EXTRA_OUTPUT_FRAMES, JOINT_FRAMES, LANDMARK_FRAMES, Skeleton
from torchtrack.tracking.goals import TRUNK_JOINTS, GoalModel

#: Segments whose lengths give the subject's scale (they do not depend on the pose).
SCALE_SEGMENTS: tuple[tuple[str, str], ...] = (
    ("l_hip", "l_knee"), ("l_knee", "l_ankle"), ("r_hip", "r_knee"), ("r_knee", "r_ankle"),
    ("l_shoulder", "l_elbow"), ("l_elbow", "l_wrist"), ("r_shoulder", "r_elbow"), ("r_elbow", "r_wrist"),
    ("pelvis", "neck"))
#: Bones fitted together (left and right tied; the hands and feet, which landmarks rarely reach, keep the scale).
FIT_BONE_GROUPS: tuple[tuple[str, ...], ...] = (
    ("pelvis",), ("torso",), ("head",), ("l_upperarm", "r_upperarm"), ("l_forearm", "r_forearm"),
    ("l_thigh", "r_thigh"), ("l_shank", "r_shank"))
#: Joints whose height on the trunk is fitted on top of the torso's length, one shift per group.
FIT_HEIGHT_JOINTS: tuple[tuple[str, ...], ...] = (("neck_flex",), ("l_shoulder_flex", "r_shoulder_flex"))
#: Finite-difference step of those shifts (m; exact, as the points are affine in them).
HEIGHT_STEP_M = 0.1
#: Ridge on the groups' relative changes (against the squared metres of landmark residual).
RIDGE = 1e-3
#: Alternations of the pose fit and the bone fit.
ROUNDS = 6


def _goals(names: Sequence[str], points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(T, L, 3) landmarks named ``names`` -> (T, G, 3) joint goals and (T, G) weights (JOINT_FRAMES order; a
    NaN point gives no goal)."""
    frames = {**LANDMARK_FRAMES, **EXTRA_OUTPUT_FRAMES}
    T = points.shape[0]
    goals = points.new_zeros(T, len(JOINT_FRAMES), 3)
    weights = points.new_zeros(T, len(JOINT_FRAMES))
    for i, n in enumerate(names):
        j = JOINT_FRAMES.index(frames[n])
        ok = torch.isfinite(points[:, i]).all(-1)
        goals[:, j] = torch.where(ok[:, None], points[:, i], 0.0)
        weights[:, j] = ok.to(points.dtype)
    return goals, weights


def fit_pose(skeleton: Skeleton, names: Sequence[str], points: torch.Tensor, start: torch.Tensor | None = None,
             root_passes: int = 5, sweeps: int = 40) -> torch.Tensor:
    """(T, D) states that put ``skeleton``'s output points named ``names`` on ``points (T, L, 3)``: the root by
    weighted Kabsch on the trunk's points (``root_passes`` times, any rotation), then the limbs by CCD. ``start``:
    (T, D) states to start from (default: the rest pose). Every frame needs 3 trunk points
    (:func:`check_trunk_points`)."""
    points = points.to(skeleton.lower)
    check_trunk_points(names, points)
    goals, weights = _goals(names, points)
    gm = GoalModel(skeleton, BlobModel.from_config(skeleton))
    T = points.shape[0]
    angles = skeleton.rest_angles()[None].repeat(T, 1).to(points) if start is None else start.to(points).clone()
    for _ in range(root_passes):
        angles = gm.fit_root(angles, skeleton.forward(angles).joints, goals, weights, max_rotation=3.2)
    ccd = CCDSolver(skeleton, JOINT_FRAMES[1:], CCDConfig(damping=0.5, sweeps=sweeps))
    return ccd(angles, goals[:, 1:], weights[:, 1:])


def check_trunk_points(names: Sequence[str], points: torch.Tensor) -> None:
    """Raise InputError naming the frames of ``points (T, L, 3)`` with fewer than 3 finite trunk points (the
    root's fit needs them: the pelvis, hips, lumbar, spine or shoulders, ``goals.TRUNK_JOINTS``)."""
    frames = {**LANDMARK_FRAMES, **EXTRA_OUTPUT_FRAMES}
    trunk = [i for i, n in enumerate(names) if frames[n] in TRUNK_JOINTS]
    count = torch.isfinite(points[:, trunk]).all(-1).sum(-1) if trunk else points.new_zeros(points.shape[0])
    bad = (count < 3).nonzero()[:, 0].tolist()
    if bad:
        trunk_names = [n for n, f in frames.items() if f in TRUNK_JOINTS]
        raise InputError(f"fit_to_landmarks: frame{'s' if len(bad) > 1 else ''} {bad[:10]}"
                         f"{' ...' if len(bad) > 10 else ''} of {points.shape[0]} ha{'ve' if len(bad) > 1 else 's'} "
                         f"fewer than 3 trunk points ({trunk_names}) to place the root; leave such frames out")


def scale_to_landmarks(generic: Skeleton, names: Sequence[str], points: torch.Tensor) -> Skeleton:
    """``generic`` scaled to the subject's height: the median ratio of the :data:`SCALE_SEGMENTS` both have."""
    points = points.to(generic.lower)
    rest = generic.forward(generic.rest_angles()[None]).output_points[0]
    out = list(generic.output_names)
    ratios = []
    for a, b in SCALE_SEGMENTS:
        if a in names and b in names:
            seg = (points[:, names.index(a)] - points[:, names.index(b)]).norm(dim=-1)
            ratios.append(seg[torch.isfinite(seg)] / (rest[out.index(a)] - rest[out.index(b)]).norm())
    ratios = torch.cat(ratios) if ratios else points.new_zeros(0)
    if ratios.numel() == 0:
        raise InputError(f"fit_to_landmarks: no segment to scale the body from: give both ends, finite in some "
                         f"frame, of at least one of {[f'{a}-{b}' for a, b in SCALE_SEGMENTS]} (got {list(names)})")
    return generic.scaled_to_height(generic.height() * float(ratios.median()))


def _fit_bones_once(skeleton: Skeleton, angles: torch.Tensor, idx: list[int], points: torch.Tensor
                    ) -> Skeleton:
    """One linear least-squares step of the bone groups and joint heights at the poses ``angles``."""
    ok = torch.isfinite(points).all(-1)  # (T, L)
    P0 = skeleton.forward(angles).output_points[:, idx].double()  # (T, L, 3)
    lengths = dict(zip(skeleton.bone_names, skeleton.bone_lengths.tolist()))
    edited = [skeleton.with_bone_lengths({b: 2.0 * lengths[b] for b in group}) for group in FIT_BONE_GROUPS] + [
        skeleton.with_joints_raised({j: HEIGHT_STEP_M for j in group}) for group in FIT_HEIGHT_JOINTS]
    cols = torch.stack([e.to(angles.device).forward(angles).output_points[:, idx].double() - P0 for e in edited],
                       -1)  # (T, L, 3, G): each group's step
    G, NB = cols.shape[-1], len(FIT_BONE_GROUPS)
    r = torch.where(ok[..., None], points.double() - P0, 0.0)  # (T, L, 3)
    # each frame's root may shift: the best shift is the frame's mean misfit, so the problem without it is the
    # one of the columns and residuals centred on each frame's mean over its finite points (per axis)
    m = ok.to(r.dtype)[..., None]  # (T, L, 1)
    n = m.sum(1, keepdim=True).clamp(min=1.0)  # (T, 1, 1)
    r = r - (m * r).sum(1, keepdim=True) / n
    cols = cols - (m[..., None] * cols).sum(1, keepdim=True) / n[..., None]
    A, r = cols[ok].reshape(-1, G), r[ok].reshape(-1)  # (3 n, G), (3 n,) over the n finite points
    reg = RIDGE * torch.eye(G, dtype=A.dtype, device=A.device)
    x = torch.linalg.solve(A.T @ A + reg, A.T @ r)
    scale = (1.0 + x[:NB]).clamp(0.6, 1.6)
    fitted = skeleton.with_bone_lengths({b: lengths[b] * float(s) for group, s in zip(FIT_BONE_GROUPS, scale)
                                         for b in group})
    shifts = x[NB:G].clamp(-1.0, 1.0) * HEIGHT_STEP_M
    # each group's shift on top of where the torso's length moved its joints
    return fitted.with_joints_raised({j: float(dz) for group, dz in zip(FIT_HEIGHT_JOINTS, shifts)
                                      for j in group}).to(angles.device)


def fit_to_landmarks(generic: Skeleton, names: Sequence[str], points: torch.Tensor | np.ndarray,
                     fit_bones: bool = True, rounds: int = ROUNDS) -> tuple[torch.Tensor, Skeleton]:
    """The subject's body and poses from landmarks (see the module docstring).

    Args:
        generic: the body model (its proportions are the start).
        names: (L,) output point names of ``points`` (``Skeleton.output_names``: the 16 landmarks, ``head_top``,
            ...).
        points: (L, 3) or (T, L, 3) world positions (m), an array or a tensor on any device (the fit runs on
            ``generic``'s); NaN where a landmark is missing, but every frame needs 3 trunk points (pelvis, hips,
            lumbar, spine, shoulders) for its root. The T frames share one body.
        fit_bones: fit the bone groups' lengths (else one scale for the body).
        rounds: alternations of the pose fit and the bone fit.

    Returns:
        (D,) or (T, D) states and the fitted skeleton.
    """
    points = torch.as_tensor(points.detach() if isinstance(points, torch.Tensor) else np.asarray(points),
                             dtype=torch.float32, device=generic.lower.device)
    single = points.ndim == 2
    points = points[None] if single else points
    if points.ndim != 3 or points.shape[1:] != (len(names), 3):
        raise InputError(f"fit_to_landmarks: points must be (L, 3) or (T, L, 3) with L = {len(names)} names, "
                         f"got {tuple(points.shape)}")
    out = list(generic.output_names)
    unknown = [n for n in names if n not in out]
    if unknown:
        raise InputError(f"fit_to_landmarks: unknown landmarks {unknown}; known: {out}")
    if not bool(torch.isfinite(points).all(-1).any()):
        raise InputError("fit_to_landmarks: every landmark is NaN")
    skel = scale_to_landmarks(generic, names, points).to(points.device)
    idx = [out.index(n) for n in names]
    angles = fit_pose(skel, names, points)
    for _ in range(rounds if fit_bones else 0):
        skel = _fit_bones_once(skel, angles, idx, points)
        angles = fit_pose(skel, names, points, start=angles)
    return (angles[0] if single else angles), skel


def initial_pose(skeleton: Skeleton, angles: torch.Tensor, fps: float = 30.0) -> Poses:
    """A one-frame poses.npz record of the state ``angles (D,)`` with its body (``body_urdf``) and height: what
    ``torchtrack track --init-pose`` starts from (write it with :func:`~torchtrack.io.poses.save_poses`)."""
    check_shape(angles, (skeleton.num_dofs,), "angles")
    if not bool(torch.isfinite(angles).all()):
        raise InputError("initial_pose: the state has NaN/inf entries")
    points = skeleton.forward(angles[None]).output_points.cpu().numpy().astype(np.float32)  # (1, J, 3)
    J = points.shape[1]
    return Poses(fps=float(fps), frame_index=np.zeros(1, np.int64), joint_names=list(skeleton.output_names),
                 joints3d=points, dof_names=list(skeleton.dof_names),
                 angles=angles[None].cpu().numpy().astype(np.float32), valid=np.ones(1, bool),
                 confidence=np.ones((1, J), np.float32),
                 extra={"subject_height_m": np.float64(skeleton.height()), "body_urdf": np.asarray(skeleton.urdf_text)})
