"""The body's kinematic chain: a URDF evaluated with pytorch-kinematics, batch first.

This is the only module that imports pytorch-kinematics. The state vector ``angles (B, D)`` holds, in the
URDF's joint order, the root translation (m, the pelvis position), the root rotation (yaw, pitch, roll about
Z, Y, X, rad) and the 1-DOF joint angles (rad); it is shared by IK, particle filters and outputs.

Names used here:
    frame    every URDF link (pytorch-kinematics "frame"), including intermediate DOF links and sites
    joint    a kinematic joint position: pelvis, torso base, neck, shoulders, ..., plus end sites (F_j)
    bone     a rigid body part carrying appearance blobs (pelvis, torso, head, upper arms, ...); its frame's
             origin is the bone's proximal joint and ``bone_dirs_local`` points to its distal joint
    landmark the 16 output points of ``torchtrack.conventions.LANDMARKS``
"""

from __future__ import annotations

import copy
import xml.etree.ElementTree as ET
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import pytorch_kinematics as pk
import torch
from torch import nn

from torchtrack.checks import InputError, check_finite, check_shape
from torchtrack.conventions import LANDMARKS
from torchtrack.resources import builtin_config, config_path

#: Landmark -> the URDF link whose origin is that landmark.
LANDMARK_FRAMES: dict[str, str] = {
    "pelvis": "pelvis", "spine": "thorax", "neck": "head", "head": "head_center",
    "l_shoulder": "l_upperarm", "l_elbow": "l_forearm", "l_wrist": "l_hand",
    "r_shoulder": "r_upperarm", "r_elbow": "r_forearm", "r_wrist": "r_hand",
    "l_hip": "l_thigh", "l_knee": "l_shank", "l_ankle": "l_foot",
    "r_hip": "r_thigh", "r_knee": "r_shank", "r_ankle": "r_foot",
}

#: Points written to poses.npz after the 16 landmarks: name -> URDF link.
EXTRA_OUTPUT_FRAMES: dict[str, str] = {
    "lumbar": "torso", "head_top": "head_top", "l_hand_tip": "l_hand_tip", "r_hand_tip": "r_hand_tip",
    "l_toe": "l_toe", "r_toe": "r_toe",
}

#: Bone -> the link at its distal end (its direction and length).
BONE_ENDS: dict[str, str] = {
    "pelvis": "torso", "torso": "head", "head": "head_top",
    "l_upperarm": "l_forearm", "l_forearm": "l_hand", "l_hand": "l_hand_tip",
    "r_upperarm": "r_forearm", "r_forearm": "r_hand", "r_hand": "r_hand_tip",
    "l_thigh": "l_shank", "l_shank": "l_foot", "l_foot": "l_toe",
    "r_thigh": "r_shank", "r_shank": "r_foot", "r_foot": "r_toe",
}

#: Kinematic joint positions (22): the root, every joint with DOFs and the end sites.
JOINT_FRAMES: tuple[str, ...] = (
    "pelvis", "torso", "thorax", "head", "head_center", "head_top",
    "l_upperarm", "l_forearm", "l_hand", "l_hand_tip", "r_upperarm", "r_forearm", "r_hand", "r_hand_tip",
    "l_thigh", "l_shank", "l_foot", "l_toe", "r_thigh", "r_shank", "r_foot", "r_toe",
)

DEFAULT_URDF = "body.urdf"


def root_rotation_matrix(rz_ry_rx: torch.Tensor) -> torch.Tensor:
    """(..., 3) root angles (rz, ry, rx) -> (..., 3, 3) ``Rz @ Ry @ Rx``, the URDF's root_rz/ry/rx chain."""
    return pk.transforms.euler_angles_to_matrix(rz_ry_rx, "ZYX")


def root_rotation_angles(R: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotation -> (..., 3) root angles (rz, ry, rx) with ``R = Rz Ry Rx``, ry in [-pi/2, pi/2]."""
    return pk.transforms.matrix_to_euler_angles(R, "ZYX")


@dataclass(frozen=True)
class _UrdfJoint:
    name: str
    kind: str  # revolute | prismatic | fixed
    parent: str
    child: str
    xyz: tuple[float, float, float]


def _parse_urdf_joints(text: str, source: str) -> list[_UrdfJoint]:
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise InputError(f"{source}: not valid URDF XML ({exc})") from None
    out = []
    for j in root.iter("joint"):
        name = j.get("name", "?")
        try:
            origin = j.find("origin")
            xyz = tuple(float(v) for v in origin.get("xyz", "0 0 0").split()) if origin is not None else (0, 0, 0)
            out.append(_UrdfJoint(name, j.get("type"), j.find("parent").get("link"), j.find("child").get("link"),
                                  xyz))
        except (AttributeError, ValueError) as exc:
            raise InputError(f"{source}: joint {name!r} is malformed ({exc})") from None
    return out


class Skeleton(nn.Module):
    """Batch-first forward kinematics of the body chain.

    Device and dtype follow the ``angles`` given to :meth:`forward` (one pytorch-kinematics chain is kept
    per device/dtype). Joint limits and local axes are buffers.

    Attributes:
        dof_names: (D,) names in state-vector order; the first six are the root.
        lower, upper: (D,) joint limits (m or rad).
        axes_local: (D, 3) joint axes in the frame of the link they move.
        bone_names: bones carrying blobs; ``bone_dirs_local (nb, 3)`` unit direction to the distal joint in
            the bone's frame, ``bone_lengths (nb,)`` in metres.
    """

    def __init__(self, urdf_text: str, source: str = "<urdf>") -> None:
        super().__init__()
        self.urdf_text = urdf_text
        self.source = source
        try:
            chain = pk.build_chain_from_urdf(urdf_text)
        except Exception as exc:  # the URDF parser raises a variety of errors
            raise InputError(f"{source}: pytorch-kinematics cannot build a chain ({exc})") from None
        self._chains: dict[tuple[torch.device, torch.dtype], pk.Chain] = {}
        self._chain = chain
        self.dof_names: tuple[str, ...] = tuple(chain.get_joint_parameter_names())
        self.frame_names: tuple[str, ...] = tuple(chain.get_frame_names(exclude_fixed=False))
        missing = [f for f in (*LANDMARK_FRAMES.values(), *BONE_ENDS, *BONE_ENDS.values(), *JOINT_FRAMES)
                   if f not in self.frame_names]
        if missing:
            raise InputError(f"{source}: the body URDF lacks links {sorted(set(missing))}")
        self._frame_index = {chain.idx_to_frame[i]: i for i in chain.get_all_frame_indices().tolist()}
        self.landmark_names: tuple[str, ...] = LANDMARKS
        self.bone_names: tuple[str, ...] = tuple(BONE_ENDS)
        self.joint_names: tuple[str, ...] = JOINT_FRAMES
        self.register_buffer("landmark_index", self.frame_index([LANDMARK_FRAMES[n] for n in LANDMARKS]),
                             persistent=False)
        self.register_buffer("bone_index", self.frame_index(self.bone_names), persistent=False)
        #: names of :attr:`FKResult.output_points`: the 16 landmarks, then EXTRA_OUTPUT_FRAMES
        self.output_names: tuple[str, ...] = LANDMARKS + tuple(EXTRA_OUTPUT_FRAMES)
        self.register_buffer("output_index", self.frame_index(
            [LANDMARK_FRAMES[n] for n in LANDMARKS] + list(EXTRA_OUTPUT_FRAMES.values())), persistent=False)
        self.register_buffer("joint_index", self.frame_index(JOINT_FRAMES), persistent=False)
        low, high = chain.get_joint_limits()
        self.register_buffer("lower", torch.as_tensor(low, dtype=torch.float32), persistent=False)
        self.register_buffer("upper", torch.as_tensor(high, dtype=torch.float32), persistent=False)
        self.register_buffer("axes_local", chain.axes.detach().clone().float(), persistent=False)
        #: the chain's frames, DOFs, limits and axes as host values, which bodies of one chain share (compared
        #: without a device synchronisation)
        self.chain_key = (self.frame_names, self.dof_names, tuple(self.lower.tolist()), tuple(self.upper.tolist()),
                          tuple(map(tuple, self.axes_local.tolist())))
        # Bone geometry from the rest pose (root at the origin): distal joint in the bone's frame.
        rest = chain.forward_kinematics_tensor(torch.zeros(1, chain.n_joints))[:, 0]  # (F, 4, 4)
        T_bone = rest[self.bone_index]  # (nb, 4, 4)
        end = rest[self.frame_index([BONE_ENDS[b] for b in self.bone_names])][:, :3, 3]  # (nb, 3)
        d_local = torch.einsum("bji,bj->bi", T_bone[:, :3, :3], end - T_bone[:, :3, 3])  # (nb, 3)
        length = d_local.norm(dim=-1)
        self.register_buffer("bone_lengths", length.float(), persistent=False)
        self.register_buffer("bone_dirs_local", (d_local / length[:, None]).float(), persistent=False)
        self.rest_frames = rest  # (F, 4, 4) float32, CPU; rest pose with the root at the origin

    # ----------------------------------------------------------------------------------------- building
    @classmethod
    def from_urdf(cls, path: str | Path | None = None) -> Skeleton:
        """Load the body chain; ``path`` None is the built-in ``configs/body.urdf``."""
        p = builtin_config(DEFAULT_URDF) if path is None else config_path(path)
        return cls(p.read_text(encoding="utf-8"), source=str(p))

    def frame_index(self, names: Sequence[str]) -> torch.Tensor:
        """(len(names),) int64 indices into the frames of :meth:`forward_frames`."""
        try:
            return torch.tensor([self._frame_index[n] for n in names], dtype=torch.int64)
        except KeyError as exc:
            raise InputError(f"{self.source}: no link named {exc.args[0]!r}") from None

    @property
    def num_dofs(self) -> int:
        return len(self.dof_names)

    def dof_index(self, names: Sequence[str]) -> torch.Tensor:
        """(len(names),) int64 positions of DOF names in the state vector."""
        lookup = {n: i for i, n in enumerate(self.dof_names)}
        missing = [n for n in names if n not in lookup]
        if missing:
            raise InputError(f"unknown DOF names {missing}; known: {list(self.dof_names)}")
        return torch.tensor([lookup[n] for n in names], dtype=torch.int64)

    def _urdf_joints(self) -> list[_UrdfJoint]:
        return _parse_urdf_joints(self.urdf_text, self.source)

    def _rescaled(self, scale_of_parent: Mapping[str, float]) -> Skeleton:
        """A new skeleton whose joint origins are multiplied by ``scale_of_parent[parent link]``."""
        root = ET.fromstring(self.urdf_text)
        for j in root.iter("joint"):
            s = scale_of_parent.get(j.find("parent").get("link"), 1.0)
            origin = j.find("origin")
            if origin is not None and s != 1.0:
                xyz = [float(v) * s for v in origin.get("xyz", "0 0 0").split()]
                origin.set("xyz", " ".join(repr(v) for v in xyz))
        return type(self)(ET.tostring(root, encoding="unicode"), source=f"{self.source} (scaled)").to(
            self.lower.device)

    def with_joint_origins(self, origins_m: Mapping[str, Sequence[float]]) -> Skeleton:
        """Set URDF joint origins (the joint's position in its parent link, metres) by joint name.

        For a bone, name the first joint of its ensemble (e.g. ``l_shoulder_flex`` places the left shoulder
        in the torso's frame, ``l_hip_flex`` the left hip in the pelvis' frame).
        """
        root = ET.fromstring(self.urdf_text)
        joints = {j.get("name"): j for j in root.iter("joint")}
        for name, xyz in origins_m.items():
            if name not in joints:
                raise InputError(f"{self.source}: no joint named {name!r}")
            xyz = [float(v) for v in xyz]
            if len(xyz) != 3 or not all(abs(v) < 3.0 for v in xyz):
                raise InputError(f"joint {name!r}: origin must be 3 values in metres, got {xyz}")
            origin = joints[name].find("origin")
            if origin is None:
                origin = ET.SubElement(joints[name], "origin", rpy="0 0 0")
            origin.set("xyz", " ".join(repr(v) for v in xyz))
        return type(self)(ET.tostring(root, encoding="unicode"), source=f"{self.source} (edited)").to(
            self.lower.device)

    def with_joints_raised(self, dz_m: Mapping[str, float]) -> Skeleton:
        """Each named joint's origin moved by ``dz_m[name]`` metres along its parent link's z axis (e.g. the
        neck's or the shoulders' height on the torso), the rest of the body unchanged."""
        return self.with_joint_origins({name: (*self.joint_origin(name)[:2], self.joint_origin(name)[2] + float(dz))
                                        for name, dz in dz_m.items()})

    def joint_origin(self, name: str) -> tuple[float, float, float]:
        """The origin (m) of URDF joint ``name`` in its parent link."""
        for j in self._urdf_joints():
            if j.name == name:
                return j.xyz
        raise InputError(f"{self.source}: no joint named {name!r}")

    def height(self) -> float:
        """Standing height in metres: head top above the soles (toe sites) in the rest pose."""
        z = self.rest_frames[self.frame_index(["head_top", "l_toe", "r_toe"])][:, 2, 3]
        return float(z[0] - z[1:].min())

    def standing_root_height(self) -> float:
        """Pelvis height above the soles in the rest pose (``root_tz`` of a subject standing on z = 0)."""
        z = self.rest_frames[self.frame_index(["pelvis", "l_toe", "r_toe"])][:, 2, 3]
        return float(z[0] - z[1:].min())

    def proportions(self) -> dict[str, float]:
        """The subject's proportions in metres: every bone's length by name, ``height``, and
        ``neck_above_shoulders`` (the neck landmark's height above the shoulders' in the rest pose; negative where
        the neck base sits below the shoulder joints)."""
        z = self.rest_frames[self.frame_index(["head", "l_upperarm", "r_upperarm"])][:, 2, 3]
        out = dict(zip(self.bone_names, (float(v) for v in self.bone_lengths)))
        out.update(height=self.height(), neck_above_shoulders=float(z[0] - z[1:].mean()))
        return out

    def scaled_to_height(self, height_m: float) -> Skeleton:
        """Every length scaled uniformly so that :meth:`height` becomes ``height_m``."""
        if not (0.3 < float(height_m) < 3.0):
            raise InputError(f"subject height must be in metres, between 0.3 and 3.0; got {height_m}")
        s = float(height_m) / self.height()
        links = {j.parent for j in self._urdf_joints()}
        return self._rescaled({link: s for link in links if link != "world"})

    def with_bone_lengths(self, lengths_m: Mapping[str, float]) -> Skeleton:
        """Set bone lengths (m) by name; every child offset of a bone scales with it (e.g. the torso's length
        moves its neck, shoulders and thorax site together)."""
        scale = {}
        for bone, length in lengths_m.items():
            if bone not in self.bone_names:
                raise InputError(f"unknown bone {bone!r}; bones: {list(self.bone_names)}")
            if not (0.01 < float(length) < 2.0):
                raise InputError(f"bone {bone!r}: length must be in metres in (0.01, 2); got {length}")
            scale[bone] = float(length) / float(self.bone_lengths[self.bone_names.index(bone)])
        return self._rescaled(scale)

    # ------------------------------------------------------------------------------------------- poses
    def rest_angles(self, root_height_m: float | None = None) -> torch.Tensor:
        """(D,) the rest pose standing on the floor at the origin, facing +X."""
        angles = torch.zeros(self.num_dofs, dtype=self.lower.dtype, device=self.lower.device)
        angles[self.dof_names.index("root_tz")] = (self.standing_root_height() if root_height_m is None
                                                   else root_height_m)
        return angles

    def starfish_angles(self, arm_abduction: float = 1.25, leg_abduction: float = 0.3) -> torch.Tensor:
        """(D,) the starfish pose subjects take at the start of a sequence: arms and legs spread."""
        angles = self.rest_angles()
        for side in ("l", "r"):
            angles[self.dof_names.index(f"{side}_shoulder_abd")] = arm_abduction
            angles[self.dof_names.index(f"{side}_hip_abd")] = leg_abduction
        # Spread legs lower the pelvis: keep the soles on the floor.
        angles[self.dof_names.index("root_tz")] *= float(torch.cos(torch.tensor(leg_abduction)))
        return angles

    def clamp(self, angles: torch.Tensor) -> torch.Tensor:
        """(..., D) angles clamped to the joint limits."""
        return torch.clamp(angles, self.lower.to(angles), self.upper.to(angles))

    # ---------------------------------------------------------------------------------------------- FK
    def _chain_for(self, x: torch.Tensor) -> pk.Chain:
        key = (x.device, x.dtype)
        if key not in self._chains:  # a copy of the parsed chain: the same tensors, a third of a parse's time
            self._chains[key] = copy.deepcopy(self._chain).to(dtype=x.dtype, device=x.device)
        return self._chains[key]

    def forward_frames(self, angles: torch.Tensor) -> torch.Tensor:
        """World transforms of every frame.

        Args:
            angles: (B, D) state vectors.

        Returns:
            (B, F, 4, 4) link-to-world transforms, F = ``len(frame_names)``, indexed by :meth:`frame_index`.
        """
        check_shape(angles, ("B", self.num_dofs), "angles")
        check_finite(angles, "angles")
        T = self._chain_for(angles).forward_kinematics_tensor(angles)  # (F, B, 4, 4)
        return T.transpose(0, 1)

    def bone_poses(self, angles: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The bones' frames of many states, lean: ``angles (B, D)`` -> rotations ``(B, nb, 3, 3)`` and origins
        ``(B, nb, 3)`` (world), the same as :meth:`forward`'s ``bone_frames`` (tested against it), differentiable.

        The annealed particle filter weighs thousands of states per layer, where pytorch-kinematics' general
        path (4 x 4 transforms for every link, selected by joint type) took a third of the layer: this one reads
        the chain's own offsets, axes and levels from pytorch-kinematics and composes 3 x 3 rotations and
        origins level by level."""
        R, t = self.bone_poses_last(angles)
        return R.permute(3, 0, 1, 2), t.permute(2, 0, 1)

    def bone_poses_last(self, angles: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`bone_poses` laid out states last: ``(nb, 3, 3, B)`` and ``(nb, 3, B)``."""
        check_shape(angles, ("B", self.num_dofs), "angles")
        R, t = self._lean_chain(angles)(angles)  # (F, 3, 3, B), (F, 3, B)
        idx = self.bone_index.to(angles.device)
        return R[idx], t[idx]

    def _lean_chain(self, x: torch.Tensor) -> _LeanChain:
        key = ("lean", x.device, x.dtype)
        if key not in self._chains:
            self._chains[key] = _LeanChain(self._chain_for(x))
        return self._chains[key]

    def forward(self, angles: torch.Tensor) -> FKResult:
        """Landmarks, kinematic joints and bone frames of a batch of poses.

        Args:
            angles: (B, D).

        Returns:
            FKResult with ``landmarks (B, 16, 3)``, ``joints (B, 22, 3)``, ``bone_frames (B, nb, 4, 4)`` and
            ``output_points (B, 22, 3)`` (named by :attr:`output_names`, the points poses.npz stores).
        """
        T = self.forward_frames(angles)  # (B, F, 4, 4)
        dev = T.device
        return FKResult(landmarks=T[:, self.landmark_index.to(dev), :3, 3],
                        output_points=T[:, self.output_index.to(dev), :3, 3],
                        joints=T[:, self.joint_index.to(dev), :3, 3],
                        bone_frames=T[:, self.bone_index.to(dev)])

    def landmarks(self, angles: torch.Tensor) -> torch.Tensor:
        """(B, D) -> (B, 16, 3) world landmark positions."""
        return self.forward(angles).landmarks


#: From this many states :class:`_LeanChain` composes each level's 3 x 3 products as three elementwise
#: multiply-adds (their memory traffic a third of a product-and-sum's, 1.4-3x faster at 1000-4000 states on a CPU);
#: below it as one product and a sum (fewer operations, whose overhead is then most of the time).
LEAN_MANY_STATES = 512


def run_slice(index: Sequence[int]) -> slice | None:
    """Host indices that run one by one (``[4, 5, 6]``) as a slice, which takes a view where an index would gather
    (and, from a host list into a device tensor, copy and synchronise); else None."""
    index = list(index)
    return slice(index[0], index[0] + len(index)) if index == list(range(index[0], index[0] + len(index))) else None


def _as_slice(index: torch.Tensor) -> slice | torch.Tensor:
    """:func:`run_slice` of an index tensor, or the tensor as it is. The chain's levels and most of their parents
    run so: a small batch's forward kinematics is mostly such per-level operations."""
    run = run_slice(index.tolist())
    return index if run is None else run


class _LeanChain:
    """Forward kinematics of a pytorch-kinematics chain in 3 x 3 rotations and origins (:meth:`Skeleton.bone_poses`):
    each link's local transform is its static offset times its joint's rotation (Rodrigues' formula) or
    translation, composed with its parent's level by level as pytorch-kinematics does."""

    def __init__(self, chain: pk.Chain) -> None:
        off = chain._static_offsets  # (F, 4, 4) the links' fixed offsets, in the chain's dtype and device
        self.R0, self.t0 = off[:, :3, :3], off[:, :3, 3]
        self.joint = chain._joint_indices_clamped  # (F,) the DOF that moves each link
        kind = chain.joint_type_indices.to(off.device)
        self.revolute, self.prismatic = kind == 1, kind == 2
        a = chain.axes.to(off)[self.joint]  # (F, 3) each link's joint axis
        z = torch.zeros_like(a[:, 0])
        K = torch.stack([z, -a[:, 2], a[:, 1], a[:, 2], z, -a[:, 0], -a[:, 1], a[:, 0], z], -1).reshape(-1, 3, 3)
        # the local rotation R0 (I + sin q K + (1 - cos q) K^2) as R0 + sin q (R0 K) + (1 - cos q) (R0 K^2)
        self.R0K, self.R0K2, self.axis = self.R0 @ K, self.R0 @ K @ K, a
        self.slide = (self.R0 @ a[..., None])[..., 0]  # (F, 3) a sliding joint's axis in its parent's frame
        parent = chain._direct_parent_idx
        # (F, depth) each link's chain from the root to itself (pytorch-kinematics' parents_indices), -1 padded
        self.ancestors = torch.nn.utils.rnn.pad_sequence(list(chain.parents_indices), batch_first=True,
                                                         padding_value=-1).to(off.device)
        self.levels = [(_as_slice(lvl.to(off.device)), _as_slice(parent[lvl].to(off.device)), bool(parent[lvl[0]] < 0))
                       for lvl in chain._bfs_levels]

    def __call__(self, angles: torch.Tensor, origins: torch.Tensor | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor]:
        """``angles (*batch, D)`` -> ``(F, 3, 3, *batch)`` link-to-world rotations and ``(F, 3, *batch)`` origins,
        states last, so that each operation runs along the states' contiguous axis. ``origins``: the links' fixed
        origins ``(F, 3, ...)`` broadcasting against ``(F, 3, *batch)``, for bodies of other bone lengths on the
        same chain (:class:`LockstepBodies`); default: this chain's."""
        q = angles.movedim(-1, 0)[self.joint]  # (F, *batch)
        ones = (1,) * (q.dim() - 1)
        turn = torch.where(self.revolute.view(-1, *ones), q, 0.0)[:, None, None]  # (F, 1, 1, *batch)
        R0, R0K, R0K2 = (m.view(*m.shape, *ones) for m in (self.R0, self.R0K, self.R0K2))
        R = torch.mul(turn.sin(), R0K).addcmul_(1 - turn.cos(), R0K2).add_(R0)  # (F, 3, 3, *batch): offset, joint
        t0 = self.t0.view(*self.t0.shape, *ones) if origins is None else origins
        slide = self.slide.view(*self.slide.shape, *ones)
        t = torch.addcmul(t0, slide, torch.where(self.prismatic.view(-1, *ones), q, 0.0)[:, None])  # (F, 3, *batch)
        Rw, tw = torch.empty_like(R), torch.empty_like(t)
        grad = torch.is_grad_enabled() and (R.requires_grad or t.requires_grad)
        many = q.shape[-1] >= LEAN_MANY_STATES  # by the last axis alone: bodies in lockstep round as one alone
        for level, parent, root in self.levels:
            if root:
                Rw[level], tw[level] = R[level], t[level]
                continue
            Rp = Rw[parent]  # (n, 3, 3, *batch)
            if grad and isinstance(parent, slice):  # a view of Rw, which the next levels write: autograd keeps a copy
                Rp = Rp.clone()
            Rl, tl = R[level], t[level]
            # written straight into the level's rows where they are a view and no gradient is kept
            direct = isinstance(level, slice) and not grad
            outR, outt = (Rw[level], tw[level]) if direct else (None, None)
            if many:  # the products as three elementwise multiply-adds each (no (n, 3, 3, 3, *batch) temporary)
                Rn = torch.mul(Rp[:, :, :1], Rl[:, :1], out=outR).addcmul_(Rp[:, :, 1:2], Rl[:, 1:2]).addcmul_(
                    Rp[:, :, 2:], Rl[:, 2:])
                tn = torch.addcmul(tw[parent], Rp[:, :, 0], tl[:, :1], out=outt).addcmul_(
                    Rp[:, :, 1], tl[:, 1:2]).addcmul_(Rp[:, :, 2], tl[:, 2:])
            else:  # as one elementwise product and a sum each: fewer operations
                Rn = torch.sum(Rp[:, :, :, None] * Rl[:, None], 2, out=outR)
                tn = torch.add((Rp * tl[:, None]).sum(2), tw[parent], out=outt)
            if not direct:
                Rw[level], tw[level] = Rn, tn
        return Rw, tw


class LockstepBodies:
    """The lean forward kinematics (:meth:`Skeleton.bone_poses`) of Q bodies in one batch: skeletons of one chain
    (the same joints, axes and offsets' rotations) with their own bone lengths, each with its own states.

    Args:
        skeletons: the Q bodies. dtype, device: of the states to be given.

    Raises:
        InputError: skeletons of different chains.
    """

    def __init__(self, skeletons: Sequence[Skeleton], dtype: torch.dtype, device: torch.device | str) -> None:
        probe = torch.empty(0, dtype=dtype, device=device)
        chains = [s._lean_chain(probe) for s in skeletons]
        first = chains[0]
        for s, c in zip(skeletons[1:], chains[1:]):
            same = (s.dof_names == skeletons[0].dof_names and s.frame_names == skeletons[0].frame_names
                    and s.bone_names == skeletons[0].bone_names and torch.equal(c.joint, first.joint)
                    and torch.equal(c.revolute, first.revolute) and torch.equal(c.prismatic, first.prismatic)
                    and torch.allclose(c.R0, first.R0, atol=1e-9) and torch.allclose(c.axis, first.axis))
            if not same:
                raise InputError(f"lockstep bodies: {s.source} is not the chain of {skeletons[0].source}")
        self.chain = first
        self.origins = torch.stack([c.t0 for c in chains], -1)[..., None]  # (F, 3, Q, 1)
        self.bone_index = skeletons[0].bone_index.to(device)

    def __call__(self, angles: torch.Tensor, bodies: slice | torch.Tensor = slice(None)
                 ) -> tuple[torch.Tensor, torch.Tensor]:
        """``angles (Q, N, D)``, N states of each body (of those ``bodies``, a slice or indices) -> the bones'
        rotations ``(nb, 3, 3, Q, N)`` and origins ``(nb, 3, Q, N)`` (world)."""
        R, t = self.links(angles, bodies)
        return R[self.bone_index], t[self.bone_index]

    def links(self, angles: torch.Tensor, bodies: slice | torch.Tensor = slice(None)
              ) -> tuple[torch.Tensor, torch.Tensor]:
        """As :meth:`__call__`, every link's frame: ``(F, 3, 3, Q, N)`` and ``(F, 3, Q, N)``."""
        return self.chain(angles, self.origins[:, :, bodies])

    def dof_axes(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Each DOF's link ``(D,)`` (the link its joint moves), joint axis in that link's frame ``(D, 3)`` and
        whether it turns ``(D,)`` (else it slides): a DOF turns its link's subtree about the world axis ``R_link
        axis`` through the link's origin, or slides it along that axis (the link's frame is its joint's, after the
        joint's own motion, which leaves the axis where it is)."""
        c = self.chain
        moving = (c.revolute | c.prismatic).nonzero()[:, 0]
        link = torch.full((int(c.joint.max()) + 1,), -1, dtype=torch.long, device=moving.device)
        link[c.joint[moving]] = moving
        if bool((link < 0).any()) or len(moving) != len(link):
            raise InputError("lockstep bodies: a DOF that no joint of the chain moves, or one that two move")
        return link, c.axis[link], c.revolute[link]

    def descends(self, link: torch.Tensor) -> torch.Tensor:
        """``(F, L)``: whether each link lies in the subtree of each of the links ``link (L,)`` (itself included)."""
        return (self.chain.ancestors[:, :, None] == link.to(self.chain.ancestors.device)).any(1)


@dataclass(frozen=True)
class FKResult:
    """Forward kinematics output (see :meth:`Skeleton.forward`)."""

    landmarks: torch.Tensor  # (B, 16, 3)
    joints: torch.Tensor  # (B, 22, 3)
    bone_frames: torch.Tensor  # (B, nb, 4, 4)
    output_points: torch.Tensor  # (B, 22, 3), named by Skeleton.output_names


def fit_states(skeleton: Skeleton, theta0: torch.Tensor, loss: Callable[[FKResult, torch.Tensor], torch.Tensor],
               iterations: int, lr: float) -> torch.Tensor:
    """State vectors ``(B, D)`` from ``theta0`` that minimise ``loss(skeleton(theta), theta)`` (a scalar tensor):
    Adam on the differentiable forward kinematics, projected onto the joint limits after every step, its rate a
    third from halfway. In float64, also under ``torch.no_grad``; returns the states detached, in ``theta0``'s
    dtype. Batched over B: the retargeting's frames, the marker fit's frames."""
    lower, upper = skeleton.lower.double(), skeleton.upper.double()
    theta = theta0.detach().double().clone().requires_grad_(True)
    opt = torch.optim.Adam([theta], lr=lr)
    with torch.enable_grad():
        for it in range(iterations):
            opt.zero_grad()
            loss(skeleton(theta), theta).backward()
            opt.step()
            with torch.no_grad():
                theta.copy_(torch.clamp(theta, lower, upper))
            if it == iterations // 2:
                for group in opt.param_groups:
                    group["lr"] = lr / 3
    return theta.detach().to(theta0.dtype)
