"""A subject's marker set: each marker fixed to one bone of the skeleton at an offset in the bone's frame.

Fitted from 3D markers over some frames (a static trial or a capture's first frames) and the skeleton's poses in
them: each marker is given to the bone it moves with most rigidly (the least spread of its position in the bone's
frame over the frames), at its mean position there; among bones it moves with equally rigidly (within
``RIGID_TOL_M``: a still start moves a thigh marker with the pelvis too), to the one whose flesh it lies on (the
body's blobs, ``configs/blobs.yaml``). Then the poses are fitted to the markers (inverse kinematics on all frames
at once) and the markers given again, a few rounds. No marker-set template is needed: any labelled set works.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from torchtrack.blobs.model import BlobModel
from torchtrack.checks import InputError, check_shape
from torchtrack.resources import builtin_config
from torchtrack.skeleton.model import Skeleton, fit_states

__all__ = ["MarkerSet", "assign_markers", "fit_marker_set", "fit_poses_to_markers", "subject_from_markers"]

#: The marker skeleton: ``configs/body.urdf`` with a shoulder girdle (each shoulder joint carried by a clavicle
#: that elevates and protracts) and an ankle that inverts (``scripts/make_body_urdf.py --markers``): markers at the
#: shoulders and on the feet follow them, which the body's 32 DOFs cannot (docs/results.md, "Marker-based capture").
MARKER_URDF = "body_markers.urdf"
#: A marker takes part in the joint centres where it is seen in at least this share of the fitting frames (markers
#: triangulated from detections are missing wherever fewer than two views found them; gaps are interpolated).
MIN_PRESENT = 0.2
#: Bones whose RMS spread of a marker lies within this of the least are equally rigid for it (about the
#: triangulated markers' noise); the marker then goes to the one whose flesh holds it (docs/results.md, "Marker-based
#: capture").
RIGID_TOL_M = 0.005


@dataclass(frozen=True)
class MarkerSet:
    """M markers on a skeleton's bones.

    Attributes:
        names: (M,) labels. bone: (M,) int64 index into ``Skeleton.bone_names``. offset: (M, 3) position in the
        bone's frame (m).
    """

    names: tuple[str, ...]
    bone: torch.Tensor
    offset: torch.Tensor

    @property
    def num_markers(self) -> int:
        return len(self.names)

    def positions_last(self, R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """Bone rotations ``(nb, 3, 3, B)`` and origins ``(nb, 3, B)`` (``Skeleton.bone_poses_last``) -> the markers
        ``(M, 3, B)``, states last."""
        bone = self.bone.to(R.device)
        return (R[bone] * self.offset.to(R)[:, None, :, None]).sum(2) + t[bone]

    def positions(self, bone_frames: torch.Tensor) -> torch.Tensor:
        """(B, nb, 4, 4) bone-to-world transforms (``Skeleton.forward(...).bone_frames``) -> (B, M, 3) markers."""
        check_shape(bone_frames, ("B", None, 4, 4), "bone_frames")
        T = bone_frames[:, self.bone.to(bone_frames.device)]  # (B, M, 4, 4)
        return (T[..., :3, :3] @ self.offset.to(T)[..., None])[..., 0] + T[..., :3, 3]


def assign_markers(skeleton: Skeleton, angles: torch.Tensor, markers: torch.Tensor, names: Sequence[str],
                   blobs: BlobModel | None = None) -> tuple[MarkerSet, torch.Tensor]:
    """Each marker to the bone in whose frame it moves least over the frames, at its mean position there; among
    the bones within ``RIGID_TOL_M`` of that least RMS spread, to the one whose blobs (``blobs``, default: the
    skeleton's built-in :class:`~torchtrack.blobs.model.BlobModel`) it lies deepest in (the least normalised radius,
    1 on a blob's surface): over frames where the body holds still, a marker on the thigh moves with the pelvis as
    rigidly as with the thigh.

    Args:
        angles: (T, D) the skeleton's poses. markers: (T, M, 3) world positions, NaN where missing.
        names: (M,) labels.

    Returns:
        the marker set and each marker's RMS spread in its bone's frame ``(M,)`` (m).

    Raises:
        InputError: a marker present in fewer than 2 frames.
    """
    T, M = markers.shape[:2]
    check_shape(angles, (T, skeleton.num_dofs), "angles")
    check_shape(markers, (T, len(names), 3), "markers")
    seen = torch.isfinite(markers).all(-1)  # (T, M)
    few = [n for n, k in zip(names, seen.sum(0).tolist()) if k < 2]
    if few:
        raise InputError(f"marker set: markers {few} are present in fewer than 2 frames")
    frames = skeleton.forward(angles.to(skeleton.lower.device, torch.float64)).bone_frames  # (T, nb, 4, 4)
    R, p = frames[..., :3, :3], frames[..., :3, 3]
    x = torch.nan_to_num(markers.to(frames))
    local = torch.einsum("tbji,tbmj->tbmi", R, x[:, None] - p[:, :, None])  # (T, nb, M, 3) in each bone's frame
    w = seen.to(frames)[:, None, :, None]  # (T, 1, M, 1)
    n = seen.sum(0).to(frames)  # (M,)
    mean = (local * w).sum(0) / n[None, :, None]  # (nb, M, 3)
    spread = (((local - mean) ** 2) * w).sum((0, 3)) / n  # (nb, M) mean squared distance from the mean
    # the bones it moves with as rigidly as with the best, and its place among each one's blobs
    rms = spread.sqrt()
    rigid = rms <= rms.amin(0, keepdim=True) + RIGID_TOL_M  # (nb, M)
    blobs = BlobModel.from_config(skeleton) if blobs is None else blobs
    k = blobs.bone_of_blob.to(frames.device)
    q = torch.einsum("kji,kmj->kmi", blobs.R_bone_blob.to(frames), mean[k] - blobs.offset_local.to(frames)[:, None])
    radius = (q / blobs.semi_axes.to(frames)[:, None]).norm(dim=-1)  # (K, M): 1 on the blob's surface
    deepest = torch.full_like(rms, math.inf).scatter_reduce(0, k[:, None].expand(-1, M), radius, "amin")  # (nb, M)
    deepest = torch.where(rigid, deepest, math.inf)
    # a marker none of whose rigid bones has a blob: the least spread
    best = torch.where(torch.isfinite(deepest).any(0), deepest.argmin(0), spread.argmin(0))  # (M,)
    idx = torch.arange(M)
    return (MarkerSet(tuple(names), best.cpu(), mean[best, idx].float().cpu()),
            spread[best, idx].sqrt().float().cpu())


def fit_poses_to_markers(skeleton: Skeleton, marker_set: MarkerSet, angles: torch.Tensor, markers: torch.Tensor,
                         iterations: int = 200, lr: float = 0.02) -> torch.Tensor:
    """Inverse kinematics of every frame at once: the poses ``(T, D)`` from ``angles`` whose markers lie nearest
    ``markers (T, M, 3)`` (NaN: missing) in the least-squares sense, within the joint limits
    (:func:`~torchtrack.skeleton.model.fit_states`)."""
    seen = torch.isfinite(markers).all(-1).to(torch.float64)  # (T, M)
    target = torch.nan_to_num(markers.double())

    def loss(fk, _theta):
        pred = marker_set.positions(fk.bone_frames)  # (T, M, 3)
        return (((pred - target) ** 2).sum(-1) * seen).sum() / seen.sum().clamp(min=1)

    return fit_states(skeleton, angles, loss, iterations, lr)


def fit_marker_set(skeleton: Skeleton, angles: torch.Tensor, markers: torch.Tensor, names: Sequence[str],
                   rounds: int = 3) -> tuple[MarkerSet, torch.Tensor]:
    """The marker set of ``markers (T, M, 3)`` on ``skeleton`` from first poses ``angles (T, D)`` (e.g. retargeted
    from the markers' joint centres): :func:`assign_markers`, then :func:`fit_poses_to_markers`, ``rounds`` times.
    Returns the marker set and the fitted poses ``(T, D)``."""
    if rounds < 1:
        raise InputError(f"fit_marker_set: rounds must be >= 1, got {rounds}")
    marker_set, _ = assign_markers(skeleton, angles, markers, names)
    for _ in range(rounds):
        angles = fit_poses_to_markers(skeleton, marker_set, angles, markers)
        marker_set, _ = assign_markers(skeleton, angles, markers, names)
    return marker_set, angles


def subject_from_markers(markers: torch.Tensor, names: Sequence[str], fps: float, rounds: int = 3,
                         source: str = "the markers") -> tuple[Skeleton, MarkerSet, torch.Tensor]:
    """A subject from its labelled 3D markers over some frames ``(T, M, 3)`` (world, m; NaN where missing): the
    skeleton (:data:`MARKER_URDF`) scaled to the joint centres that the common marker sets give (CMU, Plug-in-Gait,
    Motion Analysis: :func:`~torchtrack.synth.c3d_motion.joint_centres`), its poses retargeted onto them, then the
    marker set (:func:`fit_marker_set`). Returns the skeleton, the marker set and the frames' poses ``(T, D)``;
    errors name ``source``."""
    import numpy as np

    from torchtrack.io.c3d import C3D
    from torchtrack.synth.c3d_motion import C3D_JOINT_MAP, joint_centres
    from torchtrack.synth.retarget import retarget_positions

    check_shape(markers, ("T", len(names), 3), "markers")
    centres = joint_centres(C3D(list(names), markers.double().numpy(), float(fps), source),
                            min_present=MIN_PRESENT)
    cnames = sorted(centres)
    pos = torch.from_numpy(np.stack([centres[k] for k in cnames], 1))
    mapping = {ours: src for ours, src in C3D_JOINT_MAP.items() if all(s in cnames for s in src)}
    ret = retarget_positions(Skeleton.from_urdf(builtin_config(MARKER_URDF)), pos, cnames, mapping)
    marker_set, angles = fit_marker_set(ret.skeleton, ret.angles.double(), markers.double(), names, rounds)
    return ret.skeleton, marker_set, angles
