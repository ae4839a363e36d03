#!/usr/bin/env python
"""CCD (torchtrack.skeleton.ik) against pytorch-kinematics' PseudoInverseIK on the same goals: error vs time.

Problems (goals reachable by construction: FK of a random pose, its DOFs drawn in the middle 40 % of their
limits, the root at rest):

  arm, leg    single goal: one limb as a serial chain (torso -> l_hand_tip, pelvis -> r_toe), the goal its end
              site, only the chain's 5 DOFs solved.
  landmarks   whole body, 16 goals: the landmark joints (pelvis, thorax, neck, head centre, shoulders,
              elbows, wrists, hips, knees, ankles); all 26 non-root DOFs solved.
  joints      whole body, 22 goals: every kinematic joint and end site (hand tips, toes, head top).

Starts: ``near`` = the answer plus N(0, 0.2 rad) per joint (clamped), as a tracker's previous frame; ``rest``
= the rest pose; ``starfish`` = arms and legs spread (whole body only).

PseudoInverseIK takes one end-effector frame of one serial chain (``pk.SerialChain``): it cannot take
several goals at once. Whole-body goals are given to it the only way its API allows, one solve per chain
on that chain's end goal: the trunk (pelvis -> head centre or head top: spine and neck DOFs) first, then the
arms from the solved torso, and the legs; the other landmarks (thorax, shoulders, elbows, knees, ...) are not
seen by it. The table reports the error over all goals and over the end goals alone ("ends"). It runs
position-only (orientation weight 0, converged when within --pinv-tolerance, stopped per problem when
converged or not improving: pk's early stopping), its angles clamped to the limits after every step
(pk's ``clamp_to_limits``, the cheapest of its ways to respect limits); the chain root frames at the start
are given to it (untimed), the torso frame after its trunk solve is an FK inside its time.

CCD settings (--ccd): "ETA[/root][/gnK][/TOL]": damping eta (0.3 is the paper's), root-to-leaves order, K
Levenberg-Marquardt refinement steps after the sweeps (not CCD: see torchtrack.skeleton.ik; a "0 sweeps" row
of such a setting is Levenberg-Marquardt alone), early-stop tolerance in rad. Each budget (CCD sweeps, PseudoInverseIK iterations) is a row: time per problem (the fastest
of --repeats runs, solving B problems per call: --batch; B = 1 is one tracked frame) and the error of the
result in mm (mean and max over goals and problems). A PseudoInverseIK row is "dominated by" a CCD setting when
a row of that setting has both a lower or equal time and a lower or equal mean error; the last table counts
them per case.

Usage: .venv/bin/python scripts/bench_ik.py [--cases arm leg landmarks joints] [--starts near rest starfish]
    [--batch 1 64] [--problems 64] [--repeats 3] [--threads 1] [--sweeps ...] [--ccd 0.3 1.0/root ...]
    [--pinv-iterations ...]   (all defaults: ~25 min on 2 CPU cores)
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from dataclasses import dataclass

import pytorch_kinematics as pk
import torch

from torchtrack.skeleton import Skeleton
from torchtrack.skeleton.ik import CCDConfig, CCDSolver
from torchtrack.skeleton.model import JOINT_FRAMES, LANDMARK_FRAMES

SPINE = ["spine_flex", "spine_abd", "spine_twist"]
NECK = ["neck_flex", "neck_abd", "neck_twist"]


def limb_dofs(side: str, limb: str) -> list[str]:
    names = ["shoulder_flex", "shoulder_abd", "shoulder_twist", "elbow_flex", "wrist_flex"] if limb == "arm" else \
        ["hip_flex", "hip_abd", "hip_twist", "knee_flex", "ankle_flex"]
    return [f"{side}_{n}" for n in names]


@dataclass(frozen=True)
class Case:
    """A goal set: the goal joints, the DOFs solved, and PseudoInverseIK's chains (root, end, DOFs)."""

    goals: tuple[str, ...]
    dofs: tuple[str, ...]
    chains: tuple[tuple[str, str, tuple[str, ...]], ...]  # solved in this order


def make_case(name: str) -> Case:
    if name == "arm":
        dofs = tuple(limb_dofs("l", "arm"))
        return Case(("l_hand_tip",), dofs, (("torso", "l_hand_tip", dofs),))
    if name == "leg":
        dofs = tuple(limb_dofs("r", "leg"))
        return Case(("r_toe",), dofs, (("pelvis", "r_toe", dofs),))
    full = name == "joints"
    goals = JOINT_FRAMES if full else tuple(LANDMARK_FRAMES.values())
    ends = {"head": "head_top" if full else "head_center", "arm": "hand_tip" if full else "hand",
            "leg": "toe" if full else "foot"}
    chains = [("pelvis", ends["head"], tuple(SPINE + NECK))]
    chains += [("torso", f"{s}_{ends['arm']}", tuple(limb_dofs(s, "arm"))) for s in "lr"]
    chains += [("pelvis", f"{s}_{ends['leg']}", tuple(limb_dofs(s, "leg"))) for s in "lr"]
    return Case(tuple(goals), tuple(d for c in chains for d in c[2]), tuple(chains))


def make_problems(skel: Skeleton, case: Case, start: str, n: int, g: torch.Generator
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """(n, D) start states and (n, G, 3) goals (FK of random mid-range poses of the case's DOFs)."""
    idx = skel.dof_index(case.dofs)
    lo, hi = skel.lower[idx], skel.upper[idx]
    target = skel.rest_angles().expand(n, -1).clone()
    target[:, idx] = lo + (hi - lo) * (0.3 + 0.4 * torch.rand(n, len(idx), generator=g))
    goals = skel(target).joints[:, [JOINT_FRAMES.index(j) for j in case.goals]]  # (n, G, 3)
    init = (skel.starfish_angles() if start == "starfish" else skel.rest_angles()).expand(n, -1).clone()
    init[:, skel.dof_names.index("root_tz")] = target[:, skel.dof_names.index("root_tz")]  # same root
    if start == "near":
        init[:, idx] = torch.clamp(target[:, idx] + 0.2 * torch.randn(n, len(idx), generator=g), lo, hi)
    return init, goals


class PInvWholeBody:
    """pytorch-kinematics' PseudoInverseIK, one solve per chain of ``case`` on the chain's end goal."""

    def __init__(self, skel: Skeleton, case: Case, iterations: int, tolerance: float) -> None:
        self.skel, self.case = skel, case
        self.solvers = []
        for root, end, dofs in case.chains:
            chain = pk.build_serial_chain_from_urdf(skel.urdf_text, end, root)
            names = chain.get_joint_parameter_names()
            assert set(names) == set(dofs), (names, dofs)
            ik = pk.PseudoInverseIK(chain, max_iterations=iterations, retry_configs=torch.zeros(1, len(names)),
                                    orientation_weight=0.0, pos_tolerance=tolerance, rot_tolerance=float("inf"),
                                    early_stopping_any_converged=True, enforce_joint_limits=False,
                                    clamp_to_limits=True)
            self.solvers.append((ik, skel.dof_index(names), case.goals.index(end), skel.frame_index([root])[0]))

    def root_frames(self, init: torch.Tensor) -> torch.Tensor:
        """(B, F, 4, 4) the frames at the start (the chain roots pk is given)."""
        return self.skel.forward_frames(init)

    def __call__(self, init: torch.Tensor, goals: torch.Tensor, frames: torch.Tensor) -> torch.Tensor:
        state = init.clone()
        torso_moved = "spine_flex" in self.case.dofs  # the arms' root moves with the trunk solve
        for (root, _, _), (ik, idx, goal_j, root_f) in zip(self.case.chains, self.solvers):
            if root == "torso" and torso_moved:
                frames, torso_moved = self.skel.forward_frames(state), False
            T = frames[:, root_f]  # (B, 4, 4) chain root in the world
            goal_root = ((goals[:, goal_j] - T[:, :3, 3])[:, None] @ T[:, :3, :3])[:, 0]  # (B, 3) in the root frame
            ik.initial_config = state[:, idx][:, None]  # (B, 1, DOF): one start per problem
            state[:, idx] = ik.solve(pk.Transform3d(pos=goal_root)).solutions[:, 0]
        return state


def timed(fn: Callable[[], torch.Tensor], repeats: int) -> tuple[float, torch.Tensor]:
    """The fastest of ``repeats`` runs after a warm-up (the least disturbed by other work on the CPU)."""
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return min(times), out


def run_batches(solve: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], init: torch.Tensor,
                goals: torch.Tensor, batch: int, repeats: int) -> tuple[float, torch.Tensor]:
    """Median seconds per problem and the solutions, solving ``batch`` problems per call."""
    chunks = [(init[i:i + batch], goals[i:i + batch]) for i in range(0, len(init), batch)]
    t, out = timed(lambda: torch.cat([solve(a, g) for a, g in chunks]), repeats)
    return t / len(init), out


def errors_mm(skel: Skeleton, case: Case, sol: torch.Tensor, goals: torch.Tensor) -> dict[str, float]:
    err = 1e3 * (skel(sol).joints[:, [JOINT_FRAMES.index(j) for j in case.goals]] - goals).norm(dim=-1)  # (B, G)
    ends = err[:, [case.goals.index(c[1]) for c in case.chains]]
    return {"mean": float(err.mean()), "max": float(err.max()), "ends": float(ends.mean())}


def parse_setting(setting: str) -> tuple[float, str, int, float]:
    """'ETA[/root][/gnK][/TOL]' -> damping, order, refinement steps, tolerance."""
    eta, *rest = setting.split("/")
    order = "root_to_leaves" if "root" in rest else "leaves_to_root"
    refine = int(next((r[2:] for r in rest if r.startswith("gn")), 0))
    tol = float(next((r for r in rest if r != "root" and not r.startswith("gn")), 0))
    return float(eta), order, refine, tol


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=["arm", "leg", "landmarks", "joints"],
                    choices=["arm", "leg", "landmarks", "joints"])
    ap.add_argument("--starts", nargs="+", default=["near", "rest", "starfish"], choices=["near", "rest", "starfish"])
    ap.add_argument("--batch", nargs="+", type=int, default=[1, 64], help="problems per solver call")
    ap.add_argument("--problems", type=int, default=64)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads (1: stable timings on a shared CPU)")
    ap.add_argument("--sweeps", nargs="+", type=int, default=[0, 1, 2, 3, 5, 8, 12, 20, 30],
                    help="CCD budgets (0: only with refinement steps)")
    ap.add_argument("--ccd", nargs="+", default=["0.3", "1.0", "1.0/root", "1.0/gn3", "1.0/root/gn3"],
                    help="CCD settings: damping eta, then optionally /root (root-to-leaves order), /gnK (K refinement "
                         "steps), /TOL (early-stop tolerance, rad); e.g. 1.0/root/gn2")
    ap.add_argument("--pinv-iterations", nargs="+", type=int, default=[1, 2, 3, 5, 8, 12, 20, 50])
    ap.add_argument("--pinv-tolerance", type=float, default=1e-4, help="PseudoInverseIK's pos_tolerance (m)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    skel = Skeleton.from_urdf()
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s), {args.problems} problems per case; "
          f"time per problem in ms, error in mm")
    summary = {}
    with torch.inference_mode():
        for name in args.cases:
            case = make_case(name)
            for start in args.starts:
                if start == "starfish" and len(case.goals) == 1:
                    continue
                init, goals = make_problems(skel, case, start, args.problems, torch.Generator().manual_seed(0))
                for batch in args.batch:
                    title = f"{name}/{start}/B={batch}"
                    summary[title] = bench_case(skel, case, title, init, goals, batch, args)
    print("\n## PseudoInverseIK rows dominated (a CCD row of the setting with time <= and mean error <=), per case")
    print(f"{'case':24s} " + " ".join(f"{s:>13s}" for s in args.ccd))
    for title, counts in summary.items():
        print(f"{title:24s} " + " ".join(f"{counts[s]:>13s}" for s in args.ccd))


def bench_case(skel: Skeleton, case: Case, title: str, init: torch.Tensor, goals: torch.Tensor, batch: int,
               args: argparse.Namespace) -> dict[str, str]:
    """Print one table; return 'dominated / PseudoInverseIK rows' per CCD setting."""
    rows = []  # (setting or "PseudoInverseIK", budget, ms per problem, errors)
    for setting in args.ccd:
        eta, order, refine, tol = parse_setting(setting)
        for sweeps in args.sweeps:
            if sweeps == 0 and refine == 0:
                continue
            config = CCDConfig(damping=eta, sweeps=sweeps, order=order, tolerance=tol, refine_steps=refine)
            ccd = CCDSolver(skel, case.goals, config, dofs=case.dofs)
            t, sol = run_batches(ccd, init, goals, batch, args.repeats)
            rows.append((setting, f"{sweeps} sweeps", 1e3 * t, errors_mm(skel, case, sol, goals)))
    for iterations in args.pinv_iterations:
        pinv = PInvWholeBody(skel, case, iterations, args.pinv_tolerance)
        frames = pinv.root_frames(init)  # given to pk, untimed
        chunks = [(init[i:i + batch], goals[i:i + batch], frames[i:i + batch]) for i in range(0, len(init), batch)]
        t, sol = timed(lambda: torch.cat([pinv(a, g, f) for a, g, f in chunks]), args.repeats)
        rows.append(("PseudoInverseIK", f"{iterations} iterations", 1e3 * t / len(init),
                     errors_mm(skel, case, sol, goals)))
    start_err = errors_mm(skel, case, init, goals)
    print(f"\n## {title}: {len(case.goals)} goal(s), {len(case.dofs)} DOFs; start error mean "
          f"{start_err['mean']:.1f} mm, max {start_err['max']:.1f} mm")
    print(f"{'solver':20s} {'budget':14s} {'ms/problem':>10s} {'mean mm':>9s} {'max mm':>9s} {'ends mm':>9s}  "
          f"dominated by CCD")
    dominated = dict.fromkeys(args.ccd, 0)
    for label, budget, ms, err in rows:
        mark = ""
        if label == "PseudoInverseIK":
            by = [s for s in args.ccd if any(r[0] == s and r[2] <= ms and r[3]["mean"] <= err["mean"] for r in rows)]
            mark = ", ".join(by) if by else "NONE"
            for s in by:
                dominated[s] += 1
        name = label if label == "PseudoInverseIK" else f"CCD {label}"
        print(f"{name:20s} {budget:14s} {ms:10.3f} {err['mean']:9.2f} {err['max']:9.2f} {err['ends']:9.2f}  {mark}")
    total = len(args.pinv_iterations)
    return {s: f"{n}/{total}" for s, n in dominated.items()}


if __name__ == "__main__":
    main()
