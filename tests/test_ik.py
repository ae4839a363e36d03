"""CCD inverse kinematics: against a plain one-joint-at-a-time reference, convergence on reachable goals (FK of
known poses), limits, batched equals looped, ignored goals, untouched DOFs, the refinement steps."""

from __future__ import annotations

import math

import kornia
import pytest
import torch

from torchtrack.checks import InputError, ShapeError
from torchtrack.skeleton import Skeleton
from torchtrack.skeleton.ik import ROOT_DOFS, CCDConfig, CCDSolver, axis_angle_rotate
from torchtrack.skeleton.model import JOINT_FRAMES, LANDMARK_FRAMES

GOALS = [j for j in JOINT_FRAMES if j != "pelvis"]
LANDMARK_GOALS = list(LANDMARK_FRAMES.values())
ARM = ["l_shoulder_flex", "l_shoulder_abd", "l_shoulder_twist", "l_elbow_flex", "l_wrist_flex"]


@pytest.fixture(scope="module")
def skel():
    return Skeleton.from_urdf()


def _problem(skel, B, seed=0, spread=0.4, near=None, goals=GOALS, dtype=torch.float32):
    """Goals = FK of random mid-range poses (reachable by construction).

    The start is the rest pose, or with ``near`` the answer plus N(0, near) rad per joint (a tracker's previous
    frame). Returns start angles, goals, the goals' joint indices and the answer.
    """
    g = torch.Generator().manual_seed(seed)
    target = skel.rest_angles().expand(B, -1).clone()
    lo, hi = skel.lower[6:], skel.upper[6:]
    target[:, 6:] = lo + (hi - lo) * (0.5 - spread / 2 + spread * torch.rand(B, 26, generator=g).to(lo))
    idx = [skel.joint_names.index(j) for j in goals]
    init = skel.rest_angles().expand(B, -1).clone()
    if near is not None:
        init[:, 6:] = torch.clamp(target[:, 6:] + near * torch.randn(B, 26, generator=g).to(lo), lo, hi)
    target, init = target.to(dtype), init.to(dtype)
    return init, skel(target).joints[:, idx], idx, target


def _errors(skel, sol, goals, idx):
    return (skel(sol).joints[:, idx] - goals).norm(dim=-1)  # (B, G) metres


def _reference_ccd(skel, solver, angles, goals, weights=None):
    """Plain CCD (eq. 14-16 with the solver's lambda): one DOF at a time, deepest first (or shallowest first for
    root_to_leaves), every position and axis from a fresh forward kinematics of the whole body."""
    cfg = solver.config
    joints = skel._urdf_joints()
    parent_of = {j.child: j.parent for j in joints}
    child_of = {j.name: j.child for j in joints}

    def depth(link):
        return 0 if link not in parent_of else 1 + depth(parent_of[link])

    order = sorted(range(len(solver.dofs)), key=lambda i: -depth(child_of[solver.dofs[i]]))
    if cfg.order == "root_to_leaves":
        order.reverse()
    theta = angles.clone()
    goal_frames = skel.frame_index(list(solver.goal_joints))
    for _ in range(cfg.sweeps):
        for i in order:
            name = solver.dofs[i]
            k = skel.dof_names.index(name)
            T = skel.forward_frames(theta)
            frame = T[:, skel.frame_index([child_of[name]])[0]]  # (B, 4, 4)
            P, w = frame[:, :3, 3], frame[:, :3, :3] @ skel.axes_local[k].to(theta)  # (B, 3) each
            p = T[:, goal_frames, :3, 3] - P[:, None]  # (B, G, 3)
            g = goals - P[:, None]
            wb = w[:, None].expand_as(p)
            num = (wb * torch.cross(p, g, dim=-1)).sum(-1)
            den = (g * p).sum(-1) - (g * wb).sum(-1) * (p * wb).sum(-1)
            p_perp = p - (p * wb).sum(-1, keepdim=True) * wb
            g_perp = g - (g * wb).sum(-1, keepdim=True) * wb
            sines = p_perp.norm(dim=-1) * g_perp.norm(dim=-1) / (p.norm(dim=-1) * g.norm(dim=-1)).clamp(min=1e-30)
            lam = solver.weight[i].to(theta) * (1.0 if weights is None else weights)
            lam = torch.where(sines > 1e-2, lam * sines, 0.0)  # (B, G)
            step = (lam * torch.atan2(num, den)).sum(-1) / lam.sum(-1).clamp(min=1e-30)
            theta[:, k] = torch.clamp(theta[:, k] + cfg.damping * step, skel.lower[k].to(theta),
                                      skel.upper[k].to(theta))
    return theta


def test_axis_angle_rotate_matches_kornia():
    g = torch.Generator().manual_seed(0)
    v = torch.randn(4, 5, 3, generator=g)
    axis = torch.nn.functional.normalize(torch.randn(4, 3, generator=g), dim=-1)
    angle = torch.randn(4, generator=g)
    R = kornia.geometry.conversions.axis_angle_to_rotation_matrix(axis * angle[:, None])  # (4, 3, 3)
    out = axis_angle_rotate(v.permute(2, 0, 1), axis.T[:, :, None], angle[:, None])  # coordinates first
    torch.testing.assert_close(out.permute(1, 2, 0), v @ R.mT, atol=1e-5, rtol=0)
    quarter = axis_angle_rotate(torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, 0.0, 1.0]), torch.tensor(math.pi / 2))
    torch.testing.assert_close(quarter, torch.tensor([0.0, 1.0, 0.0]), atol=1e-6, rtol=0)


def test_lambda_is_one_over_joints_between(skel):
    solver = CCDSolver(skel, GOALS)
    i = solver.dofs.index("l_shoulder_flex")
    w = dict(zip(GOALS, solver.weight[i].tolist()))
    assert w["l_forearm"] == 1.0 and w["l_hand"] == 0.5 and w["l_hand_tip"] == pytest.approx(1 / 3)
    assert w["l_upperarm"] == 0.0 and w["r_hand"] == 0.0 and w["l_shank"] == 0.0


def test_levels_step_disjoint_subtrees_together(skel):
    solver = CCDSolver(skel, GOALS)
    levels = solver.level_dofs()
    assert solver.num_levels == 8 and sum(len(lv) for lv in levels) == 26
    assert set(levels[0]) == {"neck_twist", "l_wrist_flex", "r_wrist_flex", "l_ankle_flex", "r_ankle_flex"}
    assert levels[-1] == ["spine_flex"]
    root_first = CCDSolver(skel, GOALS, CCDConfig(order="root_to_leaves")).level_dofs()
    assert root_first == levels[::-1]
    # a DOF with no goal below it is left out: one hand goal moves only the spine and that arm
    one = CCDSolver(skel, ["l_hand_tip"])
    assert sorted(d for lv in one.level_dofs() for d in lv) == sorted(ARM + ["spine_flex", "spine_abd", "spine_twist"])


@pytest.mark.parametrize("order", ["leaves_to_root", "root_to_leaves"])
@pytest.mark.parametrize("damping", [0.3, 1.0])
def test_matches_one_joint_at_a_time_reference(skel, order, damping):
    # float64: the closed-form subtree updates and the level grouping must give the reference's angles
    init, goals, _, _ = _problem(skel, 3, seed=1, near=0.2, dtype=torch.float64)
    weights = torch.rand(3, len(GOALS), generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    solver = CCDSolver(skel, GOALS, CCDConfig(damping=damping, sweeps=3, order=order))
    ref = _reference_ccd(skel, solver, init, goals, weights)
    torch.testing.assert_close(solver(init, goals, weights), ref, atol=1e-9, rtol=0)


def test_converges_on_reachable_goals_from_rest(skel):
    init, goals, idx, _ = _problem(skel, 32)
    before = _errors(skel, init, goals, idx)
    sol = CCDSolver(skel, GOALS, CCDConfig(sweeps=30))(init, goals)
    after = _errors(skel, sol, goals, idx)
    # measured: 370 mm -> mean ~10 mm, median ~5 mm (CCD is local: a few problems keep a flipped limb)
    assert float(after.median()) < 0.01
    assert float(after.mean()) < 0.25 * float(before.mean())
    assert bool(((sol >= skel.lower) & (sol <= skel.upper)).all())
    torch.testing.assert_close(sol[:, :6], init[:, :6])  # the root is not touched


@pytest.mark.parametrize("config, mean_mm", [
    (CCDConfig(), 5.0),  # the paper's eta = 0.3, 20 sweeps: measured ~3 mm
    (CCDConfig(damping=1.0, sweeps=5, order="root_to_leaves"), 2.0),  # measured ~1 mm
    (CCDConfig(damping=1.0, sweeps=1, order="root_to_leaves", refine_steps=3), 0.2),  # measured ~0.05 mm
    (CCDConfig(sweeps=0, refine_steps=4), 0.2),  # Levenberg-Marquardt alone from a warm start: ~0.001 mm
])
def test_warm_start_whole_body(skel, config, mean_mm):
    init, goals, idx, _ = _problem(skel, 32, seed=4, near=0.2, goals=LANDMARK_GOALS)
    sol = CCDSolver(skel, LANDMARK_GOALS, config)(init, goals)
    assert float(_errors(skel, sol, goals, idx).mean()) < mean_mm * 1e-3
    assert bool(((sol >= skel.lower) & (sol <= skel.upper)).all())


def test_refinement_keeps_an_exact_answer(skel):
    # at zero error the Levenberg-Marquardt damping vanishes; the floor keeps the rank-deficient normal
    # equations (the neck twist moves no goal) from amplifying float32 noise (measured 4e-3 rad without it)
    _, goals, _, target = _problem(skel, 16, seed=13)
    sol = CCDSolver(skel, GOALS, CCDConfig(sweeps=0, refine_steps=3))(target, goals)
    torch.testing.assert_close(sol, target, atol=1e-4, rtol=0)


def test_single_goal_chain_touches_only_its_dofs(skel):
    init, _, _, target = _problem(skel, 16, seed=6, near=0.2)
    target[:, 6:] = init[:, 6:]
    k = skel.dof_index(ARM)
    target[:, k] = torch.clamp(init[:, k] + 0.3, skel.lower[k], skel.upper[k])  # the arm moved since
    tip = skel.joint_names.index("l_hand_tip")
    goal = skel(target).joints[:, tip]  # (B, 3)
    config = CCDConfig(damping=1.0, sweeps=5, refine_steps=3)
    sol = CCDSolver(skel, ["l_hand_tip"], config, dofs=ARM)(init, goal[:, None])
    assert float((skel(sol).joints[:, tip] - goal).norm(dim=-1).max()) < 1e-3
    others = [i for i in range(skel.num_dofs) if i not in k.tolist()]
    torch.testing.assert_close(sol[:, others], init[:, others], atol=0, rtol=0)


def test_root_is_never_solved(skel):
    with pytest.raises(InputError, match="non-root"):
        CCDSolver(skel, GOALS, dofs=["root_rz", "l_elbow_flex"])
    solver = CCDSolver(skel, GOALS, CCDConfig(sweeps=3, refine_steps=2))
    assert not set(ROOT_DOFS) & set(solver.dofs)
    init, goals, _, _ = _problem(skel, 4, seed=7)
    init[:, :6] = torch.tensor([0.2, -0.1, 0.9, 0.3, 0.1, -0.2])
    torch.testing.assert_close(solver(init, goals)[:, :6], init[:, :6], atol=0, rtol=0)


@pytest.mark.parametrize("refine", [0, 3])
def test_limits_hold_for_unreachable_goals(skel, refine):
    init, goals, _, _ = _problem(skel, 8, seed=8)
    far = goals + torch.randn(goals.shape, generator=torch.Generator().manual_seed(9))  # ~1 m off: unreachable
    sol = CCDSolver(skel, GOALS, CCDConfig(damping=1.0, sweeps=10, refine_steps=refine))(init, far)
    assert bool(torch.isfinite(sol).all())
    assert bool(((sol >= skel.lower) & (sol <= skel.upper)).all())


@pytest.mark.parametrize("config", [CCDConfig(sweeps=5), CCDConfig(damping=1.0, sweeps=2, order="root_to_leaves",
                                                                     refine_steps=2)])
def test_batched_equals_looped(skel, device, config):
    init, goals, _, _ = _problem(skel, 6, seed=3)
    weights = torch.rand(6, len(GOALS), generator=torch.Generator().manual_seed(3))
    solver = CCDSolver(skel, GOALS, config).to(device)
    init, goals, weights = init.to(device), goals.to(device), weights.to(device)
    batched = solver(init, goals, weights)
    looped = torch.cat([solver(init[i:i + 1], goals[i:i + 1], weights[i:i + 1]) for i in range(6)])
    torch.testing.assert_close(batched, looped, atol=1e-5, rtol=0)


@pytest.mark.parametrize("refine", [0, 2])
def test_zero_weight_goals_are_ignored(skel, refine):
    init, goals, _, _ = _problem(skel, 4, seed=5)
    weights = torch.ones(4, len(GOALS))
    weights[:, GOALS.index("l_hand_tip")] = 0
    weights[1, GOALS.index("r_shank")] = 0
    moved = goals.clone()
    moved[:, GOALS.index("l_hand_tip")] += 5.0  # an absurd goal, switched off
    moved[1, GOALS.index("r_shank")] = float("nan")  # a missing goal
    solver = CCDSolver(skel, GOALS, CCDConfig(sweeps=5, refine_steps=refine))
    sol = solver(init, moved, weights)
    assert bool(torch.isfinite(sol).all())
    torch.testing.assert_close(sol, solver(init, goals, weights))
    # (G,) weights are shared by the batch
    shared = weights[0]
    torch.testing.assert_close(solver(init, goals, shared), solver(init, goals, shared.expand(4, -1)))


def test_tolerance_stops_early(skel):
    init, goals, _, _ = _problem(skel, 4, seed=10, near=0.2)
    one = CCDSolver(skel, GOALS, CCDConfig(damping=1.0, sweeps=1))(init, goals)
    stopped = CCDSolver(skel, GOALS, CCDConfig(damping=1.0, sweeps=50, tolerance=10.0))(init, goals)
    torch.testing.assert_close(stopped, one, atol=0, rtol=0)


def test_float64_agrees_with_float32(skel):
    init, goals, _, _ = _problem(skel, 4, seed=11, near=0.2)
    solver = CCDSolver(skel, GOALS, CCDConfig(sweeps=4, refine_steps=1))
    torch.testing.assert_close(solver(init.double(), goals.double()).float(), solver(init, goals), atol=1e-4,
                               rtol=0)


def test_bad_input(skel):
    with pytest.raises(InputError, match="tail"):
        CCDSolver(skel, ["tail"])
    with pytest.raises(InputError, match="damping"):
        CCDConfig(damping=0)
    with pytest.raises(InputError, match="sweeps"):
        CCDConfig(sweeps=0)
    with pytest.raises(InputError, match="order"):
        CCDConfig(order="random")
    with pytest.raises(InputError, match="tolerance"):
        CCDConfig(tolerance=-1.0)
    solver = CCDSolver(skel, GOALS)
    with pytest.raises(ShapeError, match="goals"):
        solver(skel.rest_angles()[None], torch.zeros(1, 3, 3))
    with pytest.raises(ShapeError, match="goal_weights"):
        solver(skel.rest_angles()[None], torch.zeros(1, len(GOALS), 3), torch.ones(2, len(GOALS)))
