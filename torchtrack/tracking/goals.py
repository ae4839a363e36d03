"""Joint goals from fitted blobs (de Bem Algorithm 2, Caillette §4.2) and the root fit.

Every blob rides on a bone. Given the bone's predicted world placement (R_b, P_b) and the blob's fitted mean mu
and covariance, the blob says where its bone should be:

* orientation: the predicted main axis a of the blob (its longest: along a limb, across the pelvis) is turned
  onto the fitted main axis u by the least rotation R_min (u from a few power iterations of the covariance
  started at a, so it stays on a's side: no flips). A bone with two blobs turns the predicted line between
  their centres onto the fitted one instead. Round blobs keep the predicted orientation;
* position: the bone's origin goes where the blob's centre lands on mu, ``P = mu - R_min R_b offset``.

Each kinematic joint rigidly attached to a bone (its proximal joint, distal joint and any joint whose position is
fixed in the bone's frame, such as the hips in the pelvis or the shoulders in the torso) gets a goal from every
blob of that bone; a joint's goal merges the goals of its own bone and its parent's, weighted by the blobs' fill.
The root is then the weighted least-squares rigid fit (Kabsch) of the trunk joints onto their goals, with the
change of orientation from the prediction bounded, and CCD moves the limbs onto the remaining goals.
"""

from __future__ import annotations

import copy
import math

import torch
from kornia.geometry.epipolar import cross_product_matrix
from torch import nn

from torchtrack.blobs.model import BlobModel
from torchtrack.checks import InputError, check_shape
from torchtrack.skeleton.model import (JOINT_FRAMES, Skeleton, root_rotation_angles, root_rotation_matrix,
                                       run_slice)

#: Joints whose goals fit the root (hips, trunk and shoulders).
TRUNK_JOINTS: tuple[str, ...] = ("pelvis", "l_thigh", "r_thigh", "torso", "thorax", "l_upperarm", "r_upperarm")


def axis_rotation(axis: torch.Tensor, sin: torch.Tensor, cos: torch.Tensor) -> torch.Tensor:
    """(..., 3) unit axes and the (...) sine and cosine of the angles -> (..., 3, 3) rotations,
    ``I + sin K + (1 - cos) K^2`` with K the axis's cross-product matrix (Rodrigues; a zero axis gives I).

    Hand-written rather than kornia's ``axis_angle_to_rotation_matrix``, which takes a rotation vector and
    evaluates both its branches (small and large angles) at every call: about a hundred tensor operations, where
    the tracker's step, bound by kernel launches on a GPU, needs a dozen."""
    K = cross_product_matrix(axis)
    eye = torch.eye(3, dtype=axis.dtype, device=axis.device)
    return torch.addcmul(eye, sin[..., None, None], K).addcmul_((1 - cos)[..., None, None], K @ K)


def least_rotation(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(..., 3) unit vectors a, b -> (..., 3, 3) the rotation of least angle taking a onto b (the identity where
    their cross product is under 1e-12: equal, or opposite, where no axis is least)."""
    v = torch.linalg.cross(a, b, dim=-1)
    sin = v.norm(dim=-1, keepdim=True)
    angle = torch.atan2(sin[..., 0], (a * b).sum(-1))  # (...,) in [0, pi]
    axis = torch.where(sin > 1e-12, v / sin.clamp(min=1e-30), 0.0)
    return axis_rotation(axis, angle.sin(), angle.cos())


def main_axis(cov: torch.Tensor, start: torch.Tensor, iterations: int = 4) -> torch.Tensor:
    """Main eigenvector of (..., 3, 3) covariances by power iteration from (..., 3) ``start`` (same side as it)."""
    u = start
    for _ in range(iterations):
        u = torch.einsum("...ij,...j->...i", cov, u)
        u = u / u.norm(dim=-1, keepdim=True).clamp(min=1e-30)
    return u


def weighted_kabsch(src: torch.Tensor, dst: torch.Tensor, w: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """Rigid transform (R, t) minimising sum_i w_i |R src_i + t - dst_i|^2.

    Args:
        src, dst: (B, N, 3). w: (B, N) non-negative weights (at least three non-collinear points weighted).

    Returns:
        R (B, 3, 3) proper rotations and t (B, 3).
    """
    wn = w / w.sum(-1, keepdim=True).clamp(min=1e-30)
    cs = (wn[..., None] * src).sum(1)  # (B, 3)
    cd = (wn[..., None] * dst).sum(1)
    H = torch.einsum("bn,bni,bnj->bij", wn, src - cs[:, None], dst - cd[:, None])  # (B, 3, 3)
    U, _, Vh = torch.linalg.svd(H)
    d = torch.sign(torch.linalg.det(Vh.transpose(-1, -2) @ U.transpose(-1, -2)))
    D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], dim=-1))
    R = Vh.transpose(-1, -2) @ D @ U.transpose(-1, -2)
    return R, cd - torch.einsum("bij,bj->bi", R, cs)


def bound_rotation(R: torch.Tensor, max_angle: float) -> torch.Tensor:
    """(B, 3, 3) rotations with their angle clipped to ``max_angle`` (rad) about the same axis.

    In closed form (a few dozen operations; kornia's matrix to axis-angle conversion takes two hundred): the angle
    from the trace and the skew part, ``(R - R^T) / 2 = sin K``; where it is clipped, the axis from the skew part
    under a quarter turn, else from the symmetric part, ``(R + R^T) / 2 - cos I = (1 - cos) a a^T``, its largest
    column turned to the skew part's side (the skew part vanishes at a half turn, the symmetric part at none)."""
    skew = (R - R.mT)[..., [2, 0, 1], [1, 2, 0]]  # (B, 3): 2 sin(angle) a
    cos = 0.5 * (R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1)
    sin2 = skew.norm(dim=-1, keepdim=True)
    angle = torch.atan2(0.5 * sin2[:, 0], cos)
    sym = 0.5 * (R + R.mT) - cos[..., None, None] * torch.eye(3, dtype=R.dtype, device=R.device)
    col = sym.diagonal(dim1=-2, dim2=-1).argmax(-1)  # (B,)
    wide = torch.take_along_dim(sym, col[:, None, None], dim=-1)[..., 0]  # (B, 3), along a
    wide = torch.where(((wide * skew).sum(-1) < 0)[:, None], -wide, wide)
    axis = torch.where((cos > 0)[:, None], skew / sin2.clamp(min=1e-30),
                       wide / wide.norm(dim=-1, keepdim=True).clamp(min=1e-30))
    bound = torch.full_like(angle, max_angle)
    return torch.where((angle > max_angle)[:, None, None], axis_rotation(axis, bound.sin(), bound.cos()), R)


def _dof_slice(skeleton, names: tuple[str, ...]) -> slice | list[int]:  # noqa: ANN001 (a Skeleton or stack)
    """The state-vector positions of ``names`` as a slice where they run one by one (:func:`run_slice`: indexing a
    device tensor with a host list would copy it there, a host synchronisation per call), else as a list."""
    i = [skeleton.dof_names.index(n) for n in names]
    run = run_slice(i)
    return i if run is None else run


class GoalModel(nn.Module):
    """Which joints ride on which bone, and where, for turning fitted blobs into joint goals.

    Buffers:
        attached: (nb, G) bool, joint g (``JOINT_FRAMES`` order) is fixed in bone b's frame.
        local: (nb, G, 3) its position in the bone's frame (m).
        elongated: (K,) bool, the blob has a main axis (largest semi-axis 1.25x the next); principal: (K,) which.
    """

    def __init__(self, skeleton: Skeleton, blobs: BlobModel) -> None:
        super().__init__()
        self.skeleton, self.blob_model = skeleton, blobs
        gen = torch.Generator().manual_seed(0)
        poses = [skeleton.rest_angles().double()]
        for _ in range(3):
            r = torch.rand(skeleton.num_dofs, generator=gen, dtype=torch.float64).to(skeleton.lower.device)
            poses.append(skeleton.lower.double() + r * (skeleton.upper.double() - skeleton.lower.double()))
        poses[1:] = [torch.nan_to_num(p, posinf=0.0, neginf=0.0) for p in poses[1:]]
        fk = skeleton.forward(torch.stack(poses))
        T = fk.bone_frames  # (P, nb, 4, 4)
        R, t = T[..., :3, :3], T[..., :3, 3]
        local = torch.einsum("pbji,pbgj->pbgi", R, fk.joints[:, None] - t[:, :, None])  # (P, nb, G, 3)
        attached = (local - local[:1]).norm(dim=-1).amax(0) < 1e-6  # (nb, G)
        self.register_buffer("attached", attached, persistent=False)
        self.register_buffer("local", local[0].float(), persistent=False)
        semi = blobs.semi_axes
        top2 = semi.topk(2, dim=-1).values
        # a blob whose largest semi-axis is 1.25x the next has a main axis (the along axis of a limb, the
        # left-right width of the pelvis, which gives the heading)
        self.register_buffer("elongated", top2[:, 0] > 1.25 * top2[:, 1], persistent=False)
        self.register_buffer("principal", semi.argmax(-1), persistent=False)
        # a bone with two blobs (torso: abdomen and chest; head: neck and head) is oriented by the line through
        # their centres, which is better defined than either blob's own axis
        bone = blobs.bone_of_blob.tolist()
        partner = [next((j for j in range(len(bone)) if j != k and bone[j] == bone[k]), -1) for k in range(len(bone))]
        if any(bone.count(b) > 2 for b in bone):
            raise InputError("GoalModel: at most two blobs per bone")
        self.register_buffer("partner", torch.tensor(partner), persistent=False)
        self.has_pairs = any(p >= 0 for p in partner)
        self.register_buffer("trunk_index", torch.tensor([JOINT_FRAMES.index(j) for j in TRUNK_JOINTS]),
                             persistent=False)

    @classmethod
    def stack(cls, models: list[GoalModel], blobs: BlobModel) -> GoalModel:
        """B subjects' goal models as one whose per-subject buffers (``local``, ``elongated``, ``principal``) have
        a leading B, on ``blobs`` (:meth:`BlobModel.stack` of theirs): its :meth:`joint_goals` of B bodies gives
        body b's goals from its own geometry. Which joints ride on which bone must agree."""
        first = models[0]
        for m in models[1:]:
            if not (torch.equal(m.attached, first.attached) and torch.equal(m.partner, first.partner)):
                raise InputError("GoalModel.stack: the bodies' joints do not ride on the same bones")
        out = copy.copy(first)
        nn.Module.__init__(out)
        out.skeleton, out.blob_model = first.skeleton, blobs
        for name, buf in first._buffers.items():
            out.register_buffer(name, torch.stack([m._buffers[name] for m in models]) if name in (
                "local", "elongated", "principal") else buf, persistent=False)
        return out

    def joint_goals(self, bone_frames: torch.Tensor, mean: torch.Tensor, cov: torch.Tensor, weight: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Merged goals of the 22 kinematic joints.

        Args:
            bone_frames: (B, nb, 4, 4) predicted bone placements.
            mean, cov: (B, K, 3), (B, K, 3, 3) fitted blobs. weight: (B, K) blob confidence (0 = no goals).

        Returns:
            goals (B, G, 3) and their weights (B, G) (0 where no blob informs the joint).
        """
        B = bone_frames.shape[0]
        K = self.blob_model.num_blobs
        check_shape(mean, (B, K, 3), "mean")
        bm = self.blob_model
        dt = mean.dtype
        bone = bm.bone_of_blob
        Rb = bone_frames[:, bone, :3, :3]  # (B, K, 3, 3)
        principal = self.principal[..., None, None].expand(*self.principal.shape, 3, 1)
        axes_blob = bm.R_bone_blob.to(dt).gather(-1, principal)  # ([B,] K, 3, 1)
        a = (Rb @ axes_blob)[..., 0]  # (B, K, 3) predicted main axis
        u = main_axis(cov, a)
        Rmin = least_rotation(a, u)
        Rmin = torch.where(self.elongated[..., None, None], Rmin, torch.eye(3, dtype=dt, device=mean.device))
        if self.has_pairs:
            paired = self.partner >= 0  # (K,)
            other = self.partner.clamp(min=0)
            c_pred = torch.einsum("...kij,...kj->...ki", Rb, bm.offset_local.to(dt))  # blob centre - bone origin
            v_pred = c_pred[:, other] - c_pred  # (B, K, 3) towards the partner, predicted
            v_fit = mean[:, other] - mean
            # a fitted line pointing against the predicted one is a mismatch, not a half turn of the bone
            pair_ok = paired & (weight[:, other] > 0) & (weight > 0) & ((v_pred * v_fit).sum(-1) > 0)  # (B, K)
            Rpair = least_rotation(v_pred / v_pred.norm(dim=-1, keepdim=True).clamp(min=1e-9),
                                   v_fit / v_fit.norm(dim=-1, keepdim=True).clamp(min=1e-9))
            Rmin = torch.where(pair_ok[..., None, None], Rpair, Rmin)
        Rnew = Rmin @ Rb  # (B, K, 3, 3)
        Pnew = mean - torch.einsum("...kij,...kj->...ki", Rnew, bm.offset_local.to(dt))  # bone origin
        local = self.local.to(dt)[..., bone, :, :]  # ([B,] K, G, 3)
        goals_k = torch.einsum("...kij,...kgj->...kgi", Rnew, local) + Pnew[:, :, None]  # (B, K, G, 3)
        w = weight[:, :, None] * self.attached[bone].to(dt)[None]  # (B, K, G)
        total = w.sum(1)  # (B, G)
        goals = (w[..., None] * goals_k).sum(1) / total.clamp(min=1e-12)[..., None]
        return goals, total

    def fit_root(self, angles: torch.Tensor, joints: torch.Tensor, goals: torch.Tensor, weights: torch.Tensor,
                 max_rotation: float = math.radians(20)) -> torch.Tensor:
        """Move the root so the trunk joints best fit their goals (bounded rotation change).

        Args:
            angles: (B, D) current states. joints: (B, G, 3) their joint positions. goals, weights: (B, G, 3),
            (B, G) from :meth:`joint_goals`.

        Returns:
            (B, D) with the root translation and rotation updated (unchanged where too few trunk goals).
        """
        skel = self.skeleton
        idx = self.trunk_index
        src, dst, w = joints[:, idx], goals[:, idx], weights[:, idx]
        R, t = weighted_kabsch(src, dst, w)
        R = bound_rotation(R, max_rotation)
        cs = (w[..., None] * src).sum(1) / w.sum(-1, keepdim=True).clamp(min=1e-12)
        cd = (w[..., None] * dst).sum(1) / w.sum(-1, keepdim=True).clamp(min=1e-12)
        t = cd - torch.einsum("bij,bj->bi", R, cs)
        root_t = _dof_slice(skel, ("root_tx", "root_ty", "root_tz"))
        root_r = _dof_slice(skel, ("root_rz", "root_ry", "root_rx"))
        R_root = root_rotation_matrix(angles[:, root_r])
        out = angles.clone()
        out[:, root_t] = torch.einsum("bij,bj->bi", R, angles[:, root_t]) + t
        out[:, root_r] = root_rotation_angles(R @ R_root)
        ok = (w > 0).sum(-1) >= 3
        return torch.where(ok[:, None], out, angles)


#: The feet's (ankle, sole) joints, for floor contact: the ankle and the toe site, which is on the sole.
FEET: tuple[tuple[str, str], ...] = (("l_foot", "l_toe"), ("r_foot", "r_toe"))


def feet_index() -> torch.Tensor:
    """(F, 2) long: the ``JOINT_FRAMES`` indices of each foot's ankle and toe site (``FEET``)."""
    return torch.tensor([[JOINT_FRAMES.index(a), JOINT_FRAMES.index(t)] for a, t in FEET])


def sole_heights(feet_points: torch.Tensor, ankle_height: torch.Tensor) -> torch.Tensor:
    """(..., F, 2, 3) each foot's ankle and toe-site positions, (F,) the ankles' rest heights above the sole ->
    (..., F) each sole's height: the lower of the toe site and the ankle less its rest height (the heel)."""
    return torch.minimum(feet_points[..., 1, 2], feet_points[..., 0, 2] - ankle_height.to(feet_points))


def floor_contact(goals: torch.Tensor, weights: torch.Tensor, joints: torch.Tensor, floor_z: float | torch.Tensor,
                  feet: torch.Tensor, ankle_height: torch.Tensor, min_weight: float = 1.0
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """Goals with the lowest foot standing on the floor (Caillette §4.2: at least one part of the body touches
    the floor).

    Each foot's sole height (:func:`sole_heights`) is read from the foot's goals, or from the current joints
    where a goal has no weight. The foot with the lowest sole is the support: its ankle goal, and its toe goal
    where the blobs gave one, move vertically, together, until its sole is at ``floor_z``, and weigh at least
    ``min_weight``. A lifted stance foot is pulled down; one sunk below the floor is lifted. Motions with both
    feet off the ground (jumps, running) break the assumption, which is why the contact is optional.

    Args:
        goals, weights: (B, G, 3), (B, G) from :meth:`GoalModel.joint_goals`.
        joints: (B, G, 3) the current joint positions (for feet without goals).
        floor_z: the floor's height (m), or (B,) each state's.
        feet: (F, 2) long, each foot's ankle and toe indices into G (:func:`feet_index`).
        ankle_height: (F,) each ankle's height above its sole in the rest pose (m), or (B, F) each state's.

    Returns:
        the goals and weights with the support foot's replaced (new tensors; the inputs are not modified).
    """
    B, G, _ = goals.shape
    check_shape(weights, (B, G), "weights")
    check_shape(joints, (B, G, 3), "joints")
    F = feet.shape[0]
    if ankle_height.dim() == 2:
        check_shape(ankle_height, (B, F), "ankle_height")
    else:
        check_shape(ankle_height, (F,), "ankle_height")
    feet = feet.to(goals.device)
    has = weights[:, feet] > 0  # (B, F, 2)
    pos = torch.where(has[..., None], goals[:, feet], joints[:, feet])  # (B, F, 2, 3)
    sole = sole_heights(pos, ankle_height)  # (B, F)
    support = sole.argmin(-1)  # (B,)
    b = torch.arange(B, device=goals.device)
    moved = pos[b, support]  # (B, 2, 3), a copy (advanced indexing)
    moved[..., 2] += (floor_z - sole[b, support])[:, None]
    idx = feet[support]  # (B, 2)
    # the ankle always gets a goal; the toe only where the blobs gave it one (a toe goal taken from the joints
    # would hold the foot's pitch at the prediction's)
    keep = has[b, support]  # (B, 2)
    keep[:, 0] = True
    out_g = goals.clone()
    out_w = weights.clone()
    cur_g, cur_w = goals[b[:, None], idx], weights[b[:, None], idx]
    out_g[b[:, None], idx] = torch.where(keep[..., None], moved, cur_g)
    out_w[b[:, None], idx] = torch.where(keep, cur_w.clamp(min=min_weight), cur_w)
    return out_g, out_w
