"""Functional hips (:class:`~torchtrack.tracking.markerless.MarkerlessTracker`'s part, ``functional_hips``): the
thighs' axes gathered over accepted frames locate where they pivot (:mod:`torchtrack.tracking.functional`), and the
subject's hips are moved there once, the tracked states re-stated in the new body.
"""

from __future__ import annotations

import logging

import torch

from torchtrack.checks import check_shape
from torchtrack.skeleton.model import Skeleton, root_rotation_matrix
from torchtrack.tracking.functional import AxisPivot
from torchtrack.tracking.step import CCD_GOALS, FrameResult

log = logging.getLogger(__name__)

#: functional_hips: the thigh blobs whose axes locate the hips, and the joints (on the pelvis) they move. Only a
#: shift up, of at most FUNCTIONAL_HIPS_MAX_M and leaving the pelvis at least a fifth of its length, is made: the
#: bone fit's bias runs up (EM gives the thighs' tops to the pelvis blob), so a pivot below the fitted hips is the
#: axes' error (docs/results.md, "Tracker settings"); anything else is logged and the body left as fitted.
THIGH_BLOBS, HIP_JOINTS, SPINE_JOINT = ("l_thigh", "r_thigh"), ("l_hip_flex", "r_hip_flex"), "spine_flex"
HIP_FRAMES = ("l_thigh", "r_thigh")  # the hips' positions among JOINT_FRAMES
FUNCTIONAL_HIPS_MAX_M = 0.08


def with_hips_raised(skeleton: Skeleton, dz_m: float) -> Skeleton:
    """The body with its hips ``dz_m`` higher on the trunk (``functional_hips``): the pelvis' origin, which the
    hips sit on, moved up by ``dz_m`` along its z axis, the spine's joint on it down as much and the thighs
    ``dz_m`` longer. A state whose root is moved up as much (:meth:`MarkerlessTracker.restate`) puts the trunk,
    arms and head where the body's old state put them, and the knees and feet too where the thighs hang straight.
    The blobs follow the bones: the thigh blobs grow with the thighs, and the pelvis blob, whose extent along the
    trunk is a share of the pelvis' length (to the spine's joint), shrinks with it; the pelvis keeps at least a
    fifth of its length (FUNCTIONAL_HIPS_MAX_M)."""
    spine = skeleton.joint_origin(SPINE_JOINT)
    lengths = dict(zip(skeleton.bone_names, skeleton.bone_lengths.tolist()))
    return skeleton.with_joint_origins({SPINE_JOINT: (spine[0], spine[1], spine[2] - dz_m)}).with_bone_lengths(
        {b: lengths[b] + dz_m for b in THIGH_BLOBS})


class HipsMixin:
    """The functional hips' methods of :class:`~torchtrack.tracking.markerless.MarkerlessTracker`."""

    @property
    def body_version(self) -> int:
        """How many times the subject's body has been changed since initialisation (``functional_hips``)."""
        return len(self.hip_shifts)

    def _start_hips(self, learn: bool) -> None:
        self.hip_shifts, self.bodies, self.hip_estimate = [], [], None
        self.hips = AxisPivot(2, device=self.subject.skeleton.lower.device) if (
            learn and self.config.functional_hips > 0) else None

    def _learn_hips(self, res: FrameResult) -> None:
        """Add the frame's thigh axes; once both thighs' information reaches ``functional_hips``, move the hips
        to their functional centres (:mod:`torchtrack.tracking.functional`) and stop learning."""
        sub = self.subject
        k = [sub.blobs.names.index(n) for n in THIGH_BLOBS]
        blobs = res.blobs
        weights = blobs.active[k].to(blobs.fill) * blobs.fill[k].clamp(0, 1)
        self.hips.add(res.bone_frames[sub.skeleton.bone_names.index("pelvis")], blobs.mean[k], blobs.cov[k],
                      weights)
        if not bool((self.hips.information() >= self.config.functional_hips).all()):
            return
        skel = sub.skeleton
        hips_z = torch.tensor([skel.joint_origin(j)[2] for j in HIP_JOINTS], dtype=self.hips.rhs.dtype)
        above = self.hips.centres().cpu()[:, 2] - hips_z  # (2,)
        self.hip_estimate = (above, self.hips.information().cpu())
        dz = float(above.mean())
        self.hips = None
        spine = skel.joint_origin(SPINE_JOINT)
        if not 0.0 <= dz <= FUNCTIONAL_HIPS_MAX_M or spine[2] - dz < 0.2 * spine[2]:
            log.warning("functional hips: the thighs pivot %.0f mm above the fitted hips (a move up of at most %.0f "
                        "mm is made); the body is left as fitted", 1e3 * dz, 1e3 * FUNCTIONAL_HIPS_MAX_M)
            return
        log.info("functional hips: the thighs pivot %.0f mm above the fitted hips (left %.0f, right %.0f); the hips "
                 "and the pelvis' origin are moved up, the thighs lengthened", 1e3 * dz, *(1e3 * above).tolist())
        self.move_hips(dz)

    def move_hips(self, dz_m: float) -> None:
        """Raise the subject's hips by ``dz_m`` on its trunk (:func:`with_hips_raised`; a new
        :attr:`body_version`), the tracked state re-stated in the new body (:meth:`restate`)."""
        skel = self.subject.skeleton
        self.bodies.append(skel)
        self._use(with_hips_raised(skel, dz_m).to(skel.lower.device))
        self.hip_shifts.append(float(dz_m))
        self.angles, self.previous = (None if a is None else self.restate(a[None], self.body_version - 1)[0]
                                      for a in (self.angles, self.previous))

    def restate(self, angles: torch.Tensor, version: int | torch.Tensor = 0) -> torch.Tensor:
        """State vectors of the subject's body as it was at ``version`` (:attr:`body_version`) in its current
        body (``functional_hips``): the root (the pelvis' origin) moved up along the pelvis' z axis as the hips
        were, which keeps the trunk, arms and head where they were, then CCD (the tracker's) towards the joints
        the body of that version put there but the hips, which bends the longer thighs back towards the knees
        and the feet: exactly where the thigh hangs straight under the hip, off by about dz (1 - cos flexion)
        otherwise (a longer thigh from a higher hip cannot reach a flexed knee: 1.4 cm off at 1 rad for dz 3 cm,
        3 cm at 1.6 rad). A NaN state stays NaN.

        Args:
            angles: (N, D). version: one version, or (N,) per state.
        """
        check_shape(angles, ("N", self.generic.num_dofs), "angles")
        V = self.body_version
        since = torch.tensor([sum(self.hip_shifts[v:]) for v in range(V + 1)], dtype=angles.dtype,
                             device=angles.device)  # (V + 1,) how far the hips moved since each version
        version = torch.as_tensor(version, device=angles.device).expand(angles.shape[0]).clamp(0, V)  # (N,)
        dz = since[version]  # (N,)
        names = self.generic.dof_names
        rot = root_rotation_matrix(angles[:, [names.index(n) for n in ("root_rz", "root_ry", "root_rx")]])
        out = angles.clone()
        t = [names.index(n) for n in ("root_tx", "root_ty", "root_tz")]
        out[:, t] = angles[:, t] + rot[:, :, 2] * dz[:, None]
        sub = self.subject
        goal_w = torch.tensor([0.0 if j in HIP_FRAMES else 1.0 for j in CCD_GOALS], dtype=angles.dtype,
                              device=angles.device)
        finite = torch.isfinite(angles).all(1)
        for v in range(V):
            sel = (version == v) & finite
            if bool(sel.any()):
                old = self.bodies[v].to(angles.device).forward(angles[sel]).joints[:, sub.ccd_goal_index]
                out[sel] = sub.ccd(out[sel], old, goal_w)
        return out
