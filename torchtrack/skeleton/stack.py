"""Forward kinematics of several bodies of one chain at once: B subjects, each its own bone lengths.

The tracker runs many sequences (and hypotheses) in lockstep, each subject with its own fitted body. The bodies
share the chain's topology, joint types, axes and limits and differ only in their joints' origins, so one frame's
local transform is ``O_b[f] @ M(theta_b)[f]``: body b's static offset of frame f (its joint's origin in the
parent link) times the joint's motion. pytorch-kinematics evaluates one chain's fixed offsets for a batch of
angles; per-body offsets are what it lacks, hence this module's small level-by-level product (checked against
pytorch-kinematics body by body in tests/test_skeleton_stack.py).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix
from torch import nn

from torchtrack.checks import InputError, check_shape
from torchtrack.skeleton.model import FKResult, Skeleton


def _local_offsets(skeleton: Skeleton, parent: torch.Tensor) -> torch.Tensor:
    """(F, 4, 4) float64: each frame's rest transform in its parent frame (the root's in the world)."""
    world = skeleton._chain_for(torch.zeros((), dtype=torch.float64)).forward_kinematics_tensor(
        torch.zeros(1, skeleton.num_dofs, dtype=torch.float64))[:, 0]  # (F, 4, 4), all joints at zero
    up = world[parent.clamp(min=0)]
    up[parent < 0] = torch.eye(4, dtype=torch.float64)
    return torch.linalg.solve(up, world)


class SkeletonStack(nn.Module):
    """B bodies of one chain (see the module docstring), batch first like :class:`Skeleton`.

    ``forward(angles (B, D))`` poses body b at ``angles[b]``; :meth:`index` takes a sub-stack (e.g. the sequences
    still running). Names, limits and output indices are the first body's (all share them).
    """

    def __init__(self, skeletons: Sequence[Skeleton]) -> None:
        super().__init__()
        if not skeletons:
            raise InputError("SkeletonStack: no bodies given")
        first = skeletons[0]
        for s in skeletons[1:]:  # compared on the host's copies: no device synchronisation
            if s.chain_key != first.chain_key:
                raise InputError(f"SkeletonStack: {s.source} is not the chain of {first.source} (frames, DOFs, "
                                 "axes and limits must be the same; only the joints' origins may differ)")
        self.skeleton = first
        joints = {j.child: j for j in first._urdf_joints()}
        names = sorted(first._frame_index, key=first._frame_index.get)  # in the order of forward_frames
        parent = torch.tensor([names.index(joints[f].parent) if f in joints and joints[f].parent in names else -1
                               for f in names])
        depth = [0] * len(names)
        for i, p in enumerate(parent.tolist()):  # pytorch-kinematics indexes a parent before its children
            if p >= i:
                raise InputError(f"{first.source}: frame {names[i]!r} is indexed before its parent")
            depth[i] = 0 if p < 0 else depth[p] + 1
        levels = [[i for i, d in enumerate(depth) if d == k] for k in range(max(depth) + 1)]
        self.level_sizes = [len(lv) for lv in levels]  # the levels as one buffer on the stack's device, split
        self.register_buffer("level_frames", torch.tensor([i for lv in levels for i in lv]), persistent=False)
        dof_of = {d: i for i, d in enumerate(first.dof_names)}
        kinds = [joints[f].kind if f in joints else "fixed" for f in names]
        dof = [dof_of.get(joints[f].name, -1) if f in joints else -1 for f in names]
        if any(k in ("revolute", "prismatic", "continuous") and d < 0 for k, d in zip(kinds, dof)):
            raise InputError(f"{first.source}: a moving joint is not among the DOFs")
        self.register_buffer("parent", parent, persistent=False)
        self.register_buffer("frame_dof", torch.tensor(dof), persistent=False)  # (F,) -1: fixed
        self.register_buffer("revolute", torch.tensor([k in ("revolute", "continuous") for k in kinds]),
                             persistent=False)
        self.register_buffer("prismatic", torch.tensor([k == "prismatic" for k in kinds]), persistent=False)
        offsets = torch.stack([_local_offsets(s, parent) for s in skeletons])  # (B, F, 4, 4) float64
        self.register_buffer("offsets", offsets, persistent=False)
        self.to(first.lower.device)

    def __len__(self) -> int:
        return int(self.offsets.shape[0])

    def index(self, rows: torch.Tensor | Sequence[int]) -> SkeletonStack:
        """The bodies at ``rows`` (a new stack sharing the chain's buffers)."""
        out = object.__new__(type(self))
        nn.Module.__init__(out)
        out.skeleton, out.level_sizes = self.skeleton, self.level_sizes
        for name, buf in self._buffers.items():
            out.register_buffer(name, buf, persistent=False)
        out.offsets = self.offsets[torch.as_tensor(rows, device=self.offsets.device)]
        return out

    def forward_frames(self, angles: torch.Tensor) -> torch.Tensor:
        """(B, D) -> (B, F, 4, 4) every frame's world transform, as :meth:`Skeleton.forward_frames` of each body
        (a stack of one body poses it at every row of ``angles``)."""
        B = angles.shape[0]
        check_shape(angles, (len(self) if len(self) > 1 else B, self.skeleton.num_dofs), "angles")
        dt, dev = angles.dtype, angles.device
        F = self.frame_dof.shape[0]
        theta = torch.where(self.frame_dof >= 0, angles[:, self.frame_dof.clamp(min=0)], 0.0)  # (B, F)
        axis = self.skeleton.axes_local.to(dev, dt)[self.frame_dof.clamp(min=0)]  # (F, 3)
        # the joint's motion: a rotation about its axis or a shift along it
        rot = axis_angle_to_rotation_matrix((theta[..., None] * axis).reshape(-1, 3)).view(B, F, 3, 3)
        R = torch.where(self.revolute[:, None, None], rot, torch.eye(3, dtype=dt, device=dev))  # (B, F, 3, 3)
        t = torch.where(self.prismatic[:, None], theta[..., None] * axis, 0.0)  # (B, F, 3)
        motion = torch.zeros(B, F, 4, 4, dtype=dt, device=dev)
        motion[..., :3, :3], motion[..., :3, 3], motion[..., 3, 3] = R, t, 1.0
        local = self.offsets.to(dt) @ motion  # (B, F, 4, 4)
        world = torch.empty_like(local)
        for k, level in enumerate(self.level_frames.split(self.level_sizes)):  # a level hangs from the one above
            world[:, level] = local[:, level] if k == 0 else world[:, self.parent[level]] @ local[:, level]
        return world

    def forward(self, angles: torch.Tensor) -> FKResult:
        """(B, D) -> :class:`FKResult` of each body at its angles (as :meth:`Skeleton.forward`)."""
        T = self.forward_frames(angles)
        s, dev = self.skeleton, T.device
        return FKResult(landmarks=T[:, s.landmark_index.to(dev), :3, 3],
                        output_points=T[:, s.output_index.to(dev), :3, 3],
                        joints=T[:, s.joint_index.to(dev), :3, 3], bone_frames=T[:, s.bone_index.to(dev)])
