"""Functional hip centres: where each thigh pivots on the pelvis, from the axes its blob took over the frames.

The bone fit of initialisation (:meth:`MarkerlessTracker._fit_bone_lengths`) reads the hips' height off blob means,
and EM hands the top of each thigh to the pelvis blob: the thigh blobs' means sit low, and the fit puts the hips low,
the thighs short and the torso long. A thigh blob's main axis, though, runs along the femur whatever share of its top
it loses (that share moves its mean along the axis, not across it). Over frames in which the thigh swings, the axes it
took, seen in the pelvis' frame, all pass through the hip's centre of rotation: the point closest to them in the
least-squares sense is the functional hip centre (the functional method gait labs use on marker clusters, here on
blobs; how much closer to the true hips it lands: docs/results.md, "Tracker settings").

Each line ``m + s d`` (blob mean ``m``, unit main axis ``d``, both in the pelvis' frame) adds ``w (I - d d^T)`` to
the normal matrix ``A`` and ``w (I - d d^T) m`` to the right-hand side ``b``; the centre solves ``A c = b``. The
smallest eigenvalue of ``A`` is the information along the direction the axes tell least about: for a thigh
swinging in one plane, its length direction, ``sum w sin^2(angle off the mean axis)``, which is what the hip's
height rests on.
"""

from __future__ import annotations

import torch

from torchtrack.checks import check_shape


class AxisPivot:
    """The least-squares point closest to lines in the frame of a moving parent, one point per limb.

    Args:
        limbs: how many pivots (e.g. 2: the left and right hips).
    """

    def __init__(self, limbs: int, dtype: torch.dtype = torch.float64, device: torch.device | str = "cpu") -> None:
        self.normal = torch.zeros((limbs, 3, 3), dtype=dtype, device=device)  # (L, 3, 3) A
        self.rhs = torch.zeros((limbs, 3), dtype=dtype, device=device)  # (L, 3) b
        self.lines = torch.zeros(limbs, dtype=torch.long, device=device)  # lines added with weight > 0

    def add(self, parent_to_world: torch.Tensor, means: torch.Tensor, covs: torch.Tensor,
            weights: torch.Tensor) -> None:
        """Add one frame's line per limb.

        Args:
            parent_to_world: (4, 4) the parent's frame (e.g. the pelvis) in the world.
            means: (L, 3) world points on the lines (blob means). covs: (L, 3, 3) world covariances whose main
                eigenvector is each line's direction. weights: (L,) >= 0 per line (0: not seen this frame).
        """
        L = self.normal.shape[0]
        check_shape(parent_to_world, (4, 4), "parent_to_world")
        check_shape(means, (L, 3), "means")
        check_shape(covs, (L, 3, 3), "covs")
        check_shape(weights, (L,), "weights")
        T = parent_to_world.to(self.normal)
        R, o = T[:3, :3], T[:3, 3]
        m = (means.to(self.normal) - o) @ R  # (L, 3) R^T (m - o), in the parent's frame
        d = torch.linalg.eigh(covs.to(self.normal)).eigenvectors[..., -1] @ R  # (L, 3) main axes, parent frame
        w = weights.to(self.normal).clamp(min=0)
        P = torch.eye(3, dtype=m.dtype, device=m.device) - d[:, :, None] * d[:, None, :]  # (L, 3, 3) I - d d^T
        self.normal += w[:, None, None] * P
        self.rhs += w[:, None] * (P @ m[:, :, None])[..., 0]
        self.lines += (w > 0).long()

    def information(self) -> torch.Tensor:
        """(L,) the smallest eigenvalue of each limb's normal matrix (0 before two lines that differ)."""
        return torch.linalg.eigvalsh(self.normal)[:, 0]

    def centres(self) -> torch.Tensor:
        """(L, 3) each limb's pivot in the parent's frame (call once :meth:`information` is large enough)."""
        return torch.linalg.solve(self.normal, self.rhs[..., None])[..., 0]
