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
from kornia.geometry.epipolar import cross_product_matrix
from torch import nn

from torchtrack.checks import InputError, check_shape
from torchtrack.skeleton.model import FKResult, Skeleton, run_slice


def _local_offsets(skeleton: Skeleton, parent: torch.Tensor) -> torch.Tensor:
    """(F, 4, 4) float64: each frame's rest transform in its parent frame (the root's in the world)."""
    world = skeleton._chain_for(torch.zeros((), dtype=torch.float64)).forward_kinematics_tensor(
        torch.zeros(1, skeleton.num_dofs, dtype=torch.float64))[:, 0]  # (F, 4, 4), all joints at zero
    up = world[parent.clamp(min=0)]
    up[parent < 0] = torch.eye(4, dtype=torch.float64)
    return torch.linalg.solve(up, world)


def _run(index: list[int]) -> slice | None:
    """``index`` as a slice where it runs one by one (:func:`run_slice`), or as a one-long slice where all of it is
    one value (which broadcasts against a level of several frames); else None."""
    run = run_slice(index)
    if run is None and len(set(index)) == 1:
        run = slice(index[0], index[0] + 1)
    return run


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
        # each level's frames and their parents as slices where they run one by one (or share one parent, which
        # broadcasts): views, where an index costs a gather (a small batch's FK is mostly such per-level
        # operations); the others as index buffers on the stack's device
        self._plan: list[tuple[slice | str, slice | str | None]] = []
        for k, lv in enumerate(levels):
            up = parent[lv].tolist()
            here, there = _run(lv), (None if k == 0 else _run(up))
            if here is None:
                here = f"level_{k}"
                self.register_buffer(here, torch.tensor(lv), persistent=False)
            if k and there is None:
                there = f"level_{k}_parents"
                self.register_buffer(there, torch.tensor(up), persistent=False)
            self._plan.append((here, there))
        dof_of = {d: i for i, d in enumerate(first.dof_names)}
        kinds = [joints[f].kind if f in joints else "fixed" for f in names]
        dof = [dof_of.get(joints[f].name, -1) if f in joints else -1 for f in names]
        if any(k in ("revolute", "prismatic", "continuous") and d < 0 for k, d in zip(kinds, dof)):
            raise InputError(f"{first.source}: a moving joint is not among the DOFs")
        self.register_buffer("parent", parent, persistent=False)
        self.register_buffer("frame_dof", torch.tensor(dof), persistent=False)  # (F,) -1: fixed
        self.register_buffer("frame_moves", torch.tensor(dof) >= 0, persistent=False)
        # each frame's joint as Rodrigues' terms about its fixed unit axis: the cross-product matrix K and K^2 of a
        # revolute joint (zeros elsewhere: the identity), the axis of a prismatic one (zeros elsewhere)
        axis = first.axes_local[torch.tensor(dof).clamp(min=0)].double()  # (F, 3)
        axis = axis / axis.norm(dim=-1, keepdim=True).clamp(min=1e-12)
        revolute = torch.tensor([k in ("revolute", "continuous") for k in kinds])
        K = cross_product_matrix(axis) * revolute[:, None, None]
        self.register_buffer("frame_k", K, persistent=False)
        self.register_buffer("frame_k2", K @ K, persistent=False)
        prismatic = torch.tensor([k == "prismatic" for k in kinds])
        self.register_buffer("frame_shift", axis * prismatic[:, None], persistent=False)
        offsets = torch.stack([_local_offsets(s, parent) for s in skeletons])  # (B, F, 4, 4) float64
        self.register_buffer("offsets", offsets, persistent=False)
        self.to(first.lower.device)

    def __len__(self) -> int:
        return int(self.offsets.shape[0])

    def index(self, rows: torch.Tensor | Sequence[int]) -> SkeletonStack:
        """The bodies at ``rows`` (a new stack sharing the chain's buffers)."""
        out = object.__new__(type(self))
        nn.Module.__init__(out)
        out.skeleton, out._plan = self.skeleton, self._plan
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
        theta = torch.where(self.frame_moves, angles[:, self.frame_dof.clamp(min=0)], 0.0)  # (B, F)
        # the joint's motion: a rotation about its unit axis, I + sin K + (1 - cos) K^2 (Rodrigues; the axes are
        # fixed, so this takes a tenth of the operations of kornia's general axis-angle conversion), or a shift
        # along it
        sin, cos = theta.sin()[..., None, None], theta.cos()[..., None, None]
        R = torch.eye(3, dtype=dt, device=dev) + sin * self.frame_k.to(dt) + (1 - cos) * self.frame_k2.to(dt)
        t = theta[..., None] * self.frame_shift.to(dt)  # (B, F, 3)
        motion = torch.zeros(B, F, 4, 4, dtype=dt, device=dev)
        motion[..., :3, :3], motion[..., :3, 3], motion[..., 3, 3] = R, t, 1.0
        local = self.offsets.to(dt) @ motion  # (B, F, 4, 4)
        world = torch.empty_like(local)
        for k, (here, there) in enumerate(self._plan):  # a level hangs from the one above
            here = getattr(self, here) if isinstance(here, str) else here
            if k == 0:
                world[:, here] = local[:, here]
            else:
                there = getattr(self, there) if isinstance(there, str) else there
                world[:, here] = world[:, there] @ local[:, here]
        return world

    def forward(self, angles: torch.Tensor) -> FKResult:
        """(B, D) -> :class:`FKResult` of each body at its angles (as :meth:`Skeleton.forward`)."""
        T = self.forward_frames(angles)
        s, dev = self.skeleton, T.device
        return FKResult(landmarks=T[:, s.landmark_index.to(dev), :3, 3],
                        output_points=T[:, s.output_index.to(dev), :3, 3],
                        joints=T[:, s.joint_index.to(dev), :3, 3], bone_frames=T[:, s.bone_index.to(dev)])
