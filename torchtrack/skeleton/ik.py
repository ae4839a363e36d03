"""Cyclic-Coordinate-Descent inverse kinematics on the body chain (de Bem eq. 11-16), batched over B.

For 1-DOF joint i with world axis w and base P (the joint's position), and each goal joint j below it,
currently at Q_j with goal G_j, p = Q_j - P and g = G_j - P:

    delta_j = atan2( w . (p x g),  g . p - (g . w)(p . w) )                        (eq. 14)
    delta   = sum_j lambda_j delta_j / sum_j lambda_j,  lambda_j = 1 / (joints between i and j)   (eq. 15)
    theta_i <- clamp(theta_i + eta * delta, theta_min, theta_max)                 (eq. 16)

Joints are visited from the leaves to the root. After each joint's step its whole subtree (goal joints,
the positions and axes of the joints below) is rotated about its axis in closed form: one forward kinematics
at the start, then a few tensor ops per joint and sweep, for all B problems at once.
Root translation and rotation are left to the caller (the tracker fits them to the trunk first).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import nn

from torchtrack.checks import InputError, check_shape
from torchtrack.skeleton.model import JOINT_FRAMES, Skeleton

ROOT_DOFS = ("root_tx", "root_ty", "root_tz", "root_rz", "root_ry", "root_rx")


@dataclass(frozen=True)
class CCDConfig:
    """CCD settings: ``damping`` is eta of eq. 16 (0.3 in the paper), ``sweeps`` leaves-to-root passes."""

    damping: float = 0.3
    sweeps: int = 20

    def __post_init__(self) -> None:
        if not 0.0 < self.damping <= 1.0:
            raise InputError(f"CCDConfig.damping must be in (0, 1], got {self.damping}")
        if self.sweeps < 1:
            raise InputError(f"CCDConfig.sweeps must be >= 1, got {self.sweeps}")


def _rotate(v: torch.Tensor, axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Rodrigues rotation of vectors ``v (B, n, 3)`` about unit ``axis (B, 3)`` by ``angle (B,)``."""
    k = axis[:, None, :]
    c, s = angle.cos()[:, None, None], angle.sin()[:, None, None]
    return v * c + torch.cross(k.expand_as(v), v, dim=-1) * s + k * (k * v).sum(-1, keepdim=True) * (1 - c)


class CCDSolver(nn.Module):
    """CCD over the non-root revolute DOFs of ``skeleton`` towards goals for some of its joints.

    Args:
        skeleton: the body chain.
        goal_joints: names from ``Skeleton.joint_names`` that get goals.
        config: damping and sweeps.
        dofs: the DOFs to solve (default: every non-root DOF); the others keep their values.
    """

    def __init__(self, skeleton: Skeleton, goal_joints: Sequence[str], config: CCDConfig = CCDConfig(),
                 dofs: Sequence[str] | None = None) -> None:
        super().__init__()
        self.skeleton, self.config = skeleton, config
        unknown = [g for g in goal_joints if g not in JOINT_FRAMES]
        if unknown:
            raise InputError(f"CCD goals {unknown} are not joints; joints: {list(JOINT_FRAMES)}")
        self.goal_joints = tuple(goal_joints)
        joints = skeleton._urdf_joints()
        parent_of = {j.child: j.parent for j in joints}
        child_of = {j.name: j.child for j in joints}
        children: dict[str, list[str]] = {}
        for j in joints:
            children.setdefault(j.parent, []).append(j.child)

        def ancestors(link: str) -> list[str]:  # link itself first, up to the world
            out = [link]
            while out[-1] in parent_of:
                out.append(parent_of[out[-1]])
            return out

        def joint_of(link: str) -> str:  # the kinematic joint at a DOF's child link (down its DOF ensemble)
            while link not in JOINT_FRAMES:
                link = children[link][0]
            return link

        self.dofs = tuple(d for d in skeleton.dof_names if d not in ROOT_DOFS and (dofs is None or d in dofs))
        if dofs is not None and len(self.dofs) != len(set(dofs)):
            raise InputError(f"CCD dofs must be non-root DOFs of the skeleton; got {list(dofs)}")
        D, G = len(self.dofs), len(self.goal_joints)
        weight = torch.zeros(D, G)  # lambda_j, 0 where goal j is not below DOF i
        dof_below = torch.zeros(D, D, dtype=torch.bool)  # [i, k]: DOF k lies in DOF i's subtree
        depth = []
        for i, d in enumerate(self.dofs):
            link = child_of[d]
            base_joint = joint_of(link)
            depth.append(len(ancestors(link)))
            for j, goal in enumerate(self.goal_joints):
                up = ancestors(goal)
                if link in up:
                    between = [a for a in up[:up.index(link)] if a in JOINT_FRAMES and a != base_joint]
                    between += [goal] if goal == base_joint else []
                    n = len({a for a in between if a != base_joint})
                    if n > 0:
                        weight[i, j] = 1.0 / n
            for k, e in enumerate(self.dofs):
                dof_below[i, k] = k != i and link in ancestors(child_of[e])
        # leaves to the root: deepest DOFs first
        self.order = sorted(range(D), key=lambda i: -depth[i])
        self.register_buffer("weight", weight, persistent=False)
        self.register_buffer("dof_below", dof_below, persistent=False)
        self.register_buffer("dof_index", skeleton.dof_index(self.dofs), persistent=False)
        self._state_index = self.dof_index.tolist()  # python ints: no device sync inside the sweeps
        self._dofs_below = [dof_below[i].nonzero()[:, 0].tolist() for i in range(D)]
        self.register_buffer("dof_frame", skeleton.frame_index([child_of[d] for d in self.dofs]), persistent=False)
        self.register_buffer("goal_frame", skeleton.frame_index(list(self.goal_joints)), persistent=False)

    def forward(self, angles: torch.Tensor, goals: torch.Tensor, goal_weights: torch.Tensor | None = None
                ) -> torch.Tensor:
        """Move ``angles`` towards putting the goal joints on ``goals``.

        Args:
            angles: (B, D_all) initial state vectors (the root is kept).
            goals: (B, G, 3) goal positions (world, m) of ``goal_joints``.
            goal_weights: (B, G) optional confidences multiplying lambda (0 ignores a goal, e.g. a missing one).

        Returns:
            (B, D_all) the solved state vectors, within the joint limits.
        """
        skel = self.skeleton
        B = angles.shape[0]
        check_shape(angles, ("B", skel.num_dofs), "angles")
        check_shape(goals, (B, len(self.goal_joints), 3), "goals")
        theta = angles.clone()
        dev, dt = angles.device, angles.dtype
        lam = self.weight.to(dev, dt)[None].expand(B, -1, -1)  # (B, D, G)
        if goal_weights is not None:
            check_shape(goal_weights, (B, len(self.goal_joints)), "goal_weights")
            lam = lam * goal_weights.to(dev, dt)[:, None, :]
        lower = skel.lower.to(dev, dt)[self.dof_index.to(dev)]
        upper = skel.upper.to(dev, dt)[self.dof_index.to(dev)]
        axes_local = skel.axes_local.to(dev, dt)[self.dof_index.to(dev)]  # (D, 3)
        eta = self.config.damping
        T = skel.forward_frames(theta)  # (B, F, 4, 4): one FK; the sweeps then update the chain in closed form
        Tq = T[:, self.dof_frame.to(dev)]  # (B, D, 4, 4)
        base = Tq[..., :3, 3].clone()  # (B, D, 3)
        axis = torch.einsum("bdij,dj->bdi", Tq[..., :3, :3], axes_local)  # (B, D, 3)
        q = T[:, self.goal_frame.to(dev), :3, 3].clone()  # (B, G, 3) current goal-joint positions
        for _ in range(self.config.sweeps):
            for i in self.order:
                w, P = axis[:, i], base[:, i]  # (B, 3)
                li = lam[:, i]  # (B, G)
                p, g = q - P[:, None], goals - P[:, None]  # (B, G, 3)
                wb = w[:, None].expand_as(p)
                num = (wb * torch.cross(p, g, dim=-1)).sum(-1)
                den = (g * p).sum(-1) - (g * wb).sum(-1) * (p * wb).sum(-1)
                delta = torch.atan2(num, den)  # (B, G), eq. 14
                # eq. 15, with each lambda_j scaled by how far p and g are from the axis (sine of their angle to
                # it): a goal on the axis (the elbow for the upper arm's twist) has no defined angle and would
                # otherwise add noise with full weight.
                lever = torch.sqrt(((p.norm(dim=-1) ** 2 - (p * wb).sum(-1) ** 2).clamp(min=0))
                                   * ((g.norm(dim=-1) ** 2 - (g * wb).sum(-1) ** 2).clamp(min=0)))
                sines = lever / (p.norm(dim=-1) * g.norm(dim=-1)).clamp(min=1e-12)  # (B, G)
                # within ~6 degrees of the axis the angle is ill-defined (noise would decide it): no vote
                lj = torch.where(sines > 1e-2, li * sines, 0.0)
                total = lj.sum(-1)
                step = torch.where(total > 1e-12, (lj * delta).sum(-1) / total.clamp(min=1e-12), 0.0)
                k = self._state_index[i]
                new = torch.clamp(theta[:, k] + eta * step, lower[i], upper[i])  # eq. 16
                applied = new - theta[:, k]
                theta[:, k] = new
                # rotate the subtree: goal joints below, and the bases and axes of the DOFs below
                below_g = li > 0  # (B, G) goals under this joint (weight > 0)
                moved = _rotate(q - P[:, None], w, applied) + P[:, None]
                q = torch.where(below_g[..., None], moved, q)
                below = self._dofs_below[i]  # python list of DOF positions in this joint's subtree
                if below:
                    base[:, below] = _rotate(base[:, below] - P[:, None], w, applied) + P[:, None]
                    axis[:, below] = _rotate(axis[:, below], w, applied)
        return theta
