#!/usr/bin/env python
"""CCD (torchtrack.skeleton.ik) against pytorch-kinematics' PseudoInverseIK on the same goals.

Problems: each limb as a serial chain (torso -> hand tip for the arms, pelvis -> toe for the legs), the
chain's DOFs drawn uniformly in the middle of their limits, the goal = the end site's position (reachable by
construction), both solvers starting from the same pose (--start near: ~0.2 rad per joint from the answer, as
a tracker's previous frame; rest: the rest pose), batched over the problems. Prints the final
end-site error and the time per problem for each solver (position-only goals: PseudoInverseIK's orientation
weight is 0).

Usage: .venv/bin/python scripts/bench_ik.py [--problems 256] [--sweeps 20]
"""

from __future__ import annotations

import argparse
import time

import pytorch_kinematics as pk
import torch

from torchtrack.skeleton import Skeleton
from torchtrack.skeleton.ik import CCDConfig, CCDSolver

LIMBS = {
    "left arm": ("torso", "l_hand_tip", ["l_shoulder_flex", "l_shoulder_abd", "l_shoulder_twist", "l_elbow_flex",
                                         "l_wrist_flex"]),
    "right leg": ("pelvis", "r_toe", ["r_hip_flex", "r_hip_abd", "r_hip_twist", "r_knee_flex", "r_ankle_flex"]),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--problems", type=int, default=256)
    ap.add_argument("--sweeps", type=int, default=20)
    ap.add_argument("--pinv-iterations", type=int, default=50)
    ap.add_argument("--start", choices=("rest", "near"), default="near",
                    help="rest: cold start from the rest pose; near: ~0.2 rad from the answer, as when tracking")
    args = ap.parse_args()
    torch.set_grad_enabled(False)
    skel = Skeleton.from_urdf()
    g = torch.Generator().manual_seed(0)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads; {args.problems} problems per limb")
    for name, (root, tip, dofs) in LIMBS.items():
        idx = skel.dof_index(dofs)
        B = args.problems
        target = skel.rest_angles().expand(B, -1).clone()
        lo, hi = skel.lower[idx], skel.upper[idx]
        target[:, idx] = lo + (hi - lo) * (0.3 + 0.4 * torch.rand(B, len(dofs), generator=g))
        tip_j = skel.joint_names.index(tip)
        goal = skel(target).joints[:, tip_j]  # (B, 3)
        init = skel.rest_angles().expand(B, -1).clone()
        if args.start == "near":  # tracking: the previous frame's pose, up to ~0.2 rad per joint away
            init[:, idx] = torch.clamp(target[:, idx] + 0.2 * torch.randn(B, len(dofs), generator=g), lo, hi)

        ccd = CCDSolver(skel, [tip], CCDConfig(sweeps=args.sweeps), dofs=dofs)
        ccd(init[:2], goal[:2, None])  # warm-up
        t0 = time.perf_counter()
        sol = ccd(init, goal[:, None])
        t_ccd = time.perf_counter() - t0
        err_ccd = (skel(sol).joints[:, tip_j] - goal).norm(dim=-1)

        chain = pk.build_serial_chain_from_urdf(skel.urdf_text, tip, root)
        names = chain.get_joint_parameter_names()
        rest_frames = skel.forward_frames(skel.rest_angles()[None])[0]
        T_world_root = rest_frames[skel.frame_index([root])[0]]  # the chain's root at rest (root DOFs at rest)
        goal_root = (goal - T_world_root[:3, 3]) @ T_world_root[:3, :3]  # (B, 3) in the chain's root frame
        ik = pk.PseudoInverseIK(chain, max_iterations=args.pinv_iterations, num_retries=1,
                                retry_configs=torch.zeros(1, len(names)), orientation_weight=0.0,
                                pos_tolerance=1e-4, early_stopping_any_converged=True)
        start = init[:, skel.dof_index(names)]  # (B, DOF): the same start as CCD, one per problem
        ik.initial_config = start[:, None]  # (B, 1, DOF): pytorch-kinematics' per-problem initial configs
        t0 = time.perf_counter()
        res = ik.solve(pk.Transform3d(pos=goal_root))
        t_pinv = time.perf_counter() - t0
        q = res.solutions[:, 0]  # (B, DOF)
        full = init.clone()
        full[:, skel.dof_index(names)] = q
        err_pinv = (skel(full).joints[:, tip_j] - goal).norm(dim=-1)
        for label, err, t in (("CCD", err_ccd, t_ccd), ("PseudoInverseIK", err_pinv, t_pinv)):
            print(f"{name:10s} {label:16s} end-site error mean {1e3 * err.mean():7.2f} mm, median "
                  f"{1e3 * err.median():6.2f} mm, 95th pct {1e3 * err.quantile(0.95):7.2f} mm; "
                  f"{1e3 * t / B:.3f} ms per problem ({1e3 * t:.0f} ms for the batch)")


if __name__ == "__main__":
    main()
