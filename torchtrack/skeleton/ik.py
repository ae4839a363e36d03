"""Cyclic-Coordinate-Descent inverse kinematics on the body chain (de Bem eq. 11-16), batched over B.

For 1-DOF joint i with world axis w and base P (the joint's position), and each goal joint j below it,
currently at Q_j with goal G_j, p = Q_j - P and g = G_j - P:

    delta_j = atan2( w . (p x g),  g . p - (g . w)(p . w) )                        (eq. 14)
    delta   = sum_j lambda_j delta_j / sum_j lambda_j,  lambda_j = 1 / (joints between i and j)   (eq. 15)
    theta_i <- clamp(theta_i + eta * delta, theta_min, theta_max)                 (eq. 16)

Each lambda_j is also scaled by the sine of the goal's angle to the axis, and goals within ~0.6 degrees of
the axis do not vote: their angle is undefined (the elbow for the upper arm's twist).

Joints are visited from the leaves to the root (the paper's order; ``CCDConfig.order`` can turn it round).
After each joint's step its whole subtree (goal joints, the positions and axes of the joints below) is rotated
about its axis in closed form: one forward kinematics at the start, then a few tensor ops per step, for all B
problems at once. Two joints whose subtrees are disjoint do not see each other's steps, so the order between
them does not matter: the DOFs are grouped into levels by their height above the leaves (the wrists, ankles
and neck twist; then the elbows, knees, ...) and a level steps all its DOFs at once. A sweep over the whole
body is 8 vectorised steps instead of 26 and gives the same angles as visiting the joints one by one.

The points of a solve live in one tensor ``X (3, B, N)``, coordinates first: the small dot and cross
products are then element-wise ops and sums over the leading axis, much faster on a CPU than norms or dots
over a trailing axis of 3 or batches of tiny matmuls.

CCD converges linearly, slowly near the answer when the chain is redundant (a limb with one end goal).
``CCDConfig.refine_steps`` adds damped Gauss-Newton (Levenberg-Marquardt) steps on all goals at once after
the sweeps; they are not part of de Bem's method. Their Jacobian, w_i x (Q_j - P_i), comes from the same
points, and their update is applied by the same closed-form subtree rotations: no forward kinematics either.

Root translation and rotation are left to the caller (the tracker fits them to the trunk first).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import torch
from torch import nn

from torchtrack.checks import InputError, check_shape
from torchtrack.skeleton.model import JOINT_FRAMES, Skeleton

ROOT_DOFS = ("root_tx", "root_ty", "root_tz", "root_rz", "root_ry", "root_rx")

#: Goals whose direction from the joint is within this sine of the joint's axis (~0.6 degrees) do not vote.
_MIN_SINE = 1e-2
#: Least Levenberg-Marquardt damping, relative to the mean of diag(J^T W J): keeps float32 steps finite along
#: directions that move no goal (the neck twist for landmark goals, the null space of a limb with one end goal).
_MU_FLOOR = 1e-5


@dataclass(frozen=True)
class CCDConfig:
    """CCD settings.

    Attributes:
        damping: eta of eq. 16 (0.3 in the paper): the share of each joint's step that is taken.
        sweeps: the most passes over the chain.
        order: ``"leaves_to_root"`` (the paper's) or ``"root_to_leaves"``: the order of the joints in a pass.
            Root first converges much faster from a warm start when most joints have goals (the whole body
            from joint goals): the trunk is placed before the limbs that hang from it. From a cold start (rest,
            starfish) the paper's order gets stuck less.
        tolerance: stop after a sweep (or refinement step) that changed no angle by more than this (rad);
            0 runs them all. Checking costs one device sync per sweep.
        refine_steps: Levenberg-Marquardt steps after the sweeps (0: pure CCD, the paper's method).
        refine_damping: their damping mu = refine_damping * (weighted sum of squared goal errors, m^2), as in
            pytorch-kinematics' PseudoInverseIK: large errors take short steps, small ones Gauss-Newton steps
            (plus a floor of 1e-5 times the mean of diag(J^T W J)).
    """

    damping: float = 0.3
    sweeps: int = 20
    order: Literal["leaves_to_root", "root_to_leaves"] = "leaves_to_root"
    tolerance: float = 0.0
    refine_steps: int = 0
    refine_damping: float = 0.1

    def __post_init__(self) -> None:
        if not 0.0 < self.damping <= 1.0:
            raise InputError(f"CCDConfig.damping must be in (0, 1], got {self.damping}")
        if self.sweeps < 0 or (self.sweeps == 0 and self.refine_steps == 0):
            raise InputError(f"CCDConfig.sweeps must be >= 1 (or 0 with refine_steps), got {self.sweeps}")
        if self.order not in ("leaves_to_root", "root_to_leaves"):
            raise InputError(f"CCDConfig.order must be 'leaves_to_root' or 'root_to_leaves', got {self.order!r}")
        if not self.tolerance >= 0.0:
            raise InputError(f"CCDConfig.tolerance must be >= 0, got {self.tolerance}")
        if self.refine_steps < 0 or not self.refine_damping >= 0.0:
            raise InputError(f"CCDConfig.refine_steps and refine_damping must be >= 0, got {self.refine_steps}, "
                             f"{self.refine_damping}")


def axis_angle_rotate(v: torch.Tensor, axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Rodrigues rotation, coordinates first: ``v (3, ...)`` about unit ``axis (3, ...)`` by ``angle (...)``
    (right-hand rule; the shapes broadcast).

    Hand-written rather than kornia's ``axis_angle_to_rotation_matrix``: no 3 x 3 matrices and the
    coordinates-first layout of the solver (the tests check it against kornia).
    """
    return _turned(v, v, axis, angle)


def _turned(points: torch.Tensor, v: torch.Tensor, axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """``points + sin (w x v) + (1 - cos) w x (w x v)``: points at ``v (3, ...)`` from a base, turned about the unit
    ``axis`` w through it by ``angle`` (Rodrigues, in two multiply-adds; the shapes broadcast)."""
    axis = axis.expand_as(v)
    wv = torch.linalg.cross(axis, v, dim=0)
    return torch.addcmul(points, angle.sin(), wv).addcmul_(1.0 - angle.cos(), torch.linalg.cross(axis, wv, dim=0))


class CCDSolver(nn.Module):
    """CCD over the non-root revolute DOFs of ``skeleton`` towards goals for some of its joints.

    Args:
        skeleton: the body chain.
        goal_joints: names from ``Skeleton.joint_names`` that get goals.
        config: damping, sweeps, order, early stop and refinement.
        dofs: the DOFs to solve (default: every non-root DOF); the others (and the root) keep their values.
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
        weight = torch.zeros(D, G)  # lambda_j, 0 where goal j is not below DOF i (or sits at its base)
        goal_below = torch.zeros(D, G, dtype=torch.bool)  # [i, j]: goal joint j moves with DOF i
        dof_below = torch.zeros(D, D, dtype=torch.bool)  # [i, k]: DOF k lies in DOF i's subtree
        for i, d in enumerate(self.dofs):
            link = child_of[d]
            base_joint = joint_of(link)
            for j, goal in enumerate(self.goal_joints):
                up = ancestors(goal)
                if link in up:
                    goal_below[i, j] = True
                    n = len({a for a in up[:up.index(link)] if a in JOINT_FRAMES and a != base_joint})
                    if n > 0:
                        weight[i, j] = 1.0 / n
            for k, e in enumerate(self.dofs):
                dof_below[i, k] = k != i and link in ancestors(child_of[e])
        self.register_buffer("weight", weight, persistent=False)
        self.register_buffer("dof_below", dof_below, persistent=False)
        self.register_buffer("dof_index", skeleton.dof_index(self.dofs), persistent=False)
        self.register_buffer("goal_frame", skeleton.frame_index(list(self.goal_joints)), persistent=False)
        # DOFs with no goal below them never move: only the others (``active``) take part in a solve
        active = [i for i in range(D) if bool(goal_below[i].any())]
        self.register_buffer("active_index", self.dof_index[active], persistent=False)
        self.register_buffer("active_frame", skeleton.frame_index([child_of[self.dofs[i]] for i in active]),
                             persistent=False)
        self.register_buffer("goal_below", goal_below[active].to(torch.get_default_dtype()), persistent=False)
        self._build_levels(active, weight[active], goal_below[active], dof_below[active][:, active])

    def _build_levels(self, active: list[int], weight: torch.Tensor, goal_below: torch.Tensor,
                      dof_below: torch.Tensor) -> None:
        """Group the active DOFs by height above the leaves and store each level's index buffers.

        The points of a solve, ``X (3, B, N)``: the G goal joints' current positions, their G goals, the A
        active DOFs' bases, their bases plus their unit axes (so that one rotation about a point moves both),
        then scratch columns that pad each level's lists of moved points to the same length per DOF.
        """
        A, G = goal_below.shape
        below = [dof_below[a].nonzero()[:, 0].tolist() for a in range(A)]
        height = [0] * A
        for a in sorted(range(A), key=lambda a: len(below[a])):  # a subtree holds fewer DOFs than its root's
            height[a] = 1 + max((height[k] for k in below[a]), default=-1)
        lower = self.skeleton.lower[self.active_index]
        upper = self.skeleton.upper[self.active_index]
        levels = []
        for h in range(max(height, default=-1) + 1):
            dofs = [a for a in range(A) if height[a] == h]
            goals = sorted({j for a in dofs for j in goal_below[a].nonzero()[:, 0].tolist()})
            # the points each DOF of the level moves (the subtrees of a level are disjoint)
            moved = [goal_below[a].nonzero()[:, 0].tolist() + [2 * G + k for k in below[a]]
                     + [2 * G + A + k for k in below[a]] for a in dofs]
            levels.append({"dofs": dofs, "pairs": goals + [G + j for j in goals], "moved": moved,
                           "base_tip": [2 * G + a for a in dofs] + [2 * G + A + a for a in dofs],
                           "lam": weight[dofs][:, goals], "lower": lower[dofs], "upper": upper[dofs]})
        if self.config.order == "root_to_leaves":
            levels.reverse()
        self._levels: list[dict[str, str]] = []  # per level: key -> buffer name
        self._cache: dict[tuple[torch.device, torch.dtype], list[dict[str, torch.Tensor]]] = {}
        pad = 0
        for h, level in enumerate(levels):
            moved = level.pop("moved")
            width = max(len(m) for m in moved)
            rows = []  # (S * width,): DOF s moves rows[s * width:(s + 1) * width], padded with scratch columns
            scratch = 2 * G + 2 * A
            for m in moved:
                rows += m + list(range(scratch, scratch + width - len(m)))
                scratch += width - len(m)
            pad = max(pad, scratch - (2 * G + 2 * A))
            level["rows"] = rows
            # what a level step reads at once, per DOF: its base and axis tip, the level's goal joints and goals,
            # then the points it moves
            level["gather"] = [i for s, (b, t) in enumerate(zip(level["base_tip"][:len(moved)],
                                                               level["base_tip"][len(moved):]))
                               for i in [b, t] + level["pairs"] + rows[s * width:(s + 1) * width]]
            names = {}
            for key, value in level.items():
                names[key] = f"_level{h}_{key}"
                tensor = value if isinstance(value, torch.Tensor) else torch.tensor(value, dtype=torch.int64)
                self.register_buffer(names[key], tensor, persistent=False)
            self._levels.append(names)
        self.num_points = 2 * G + 2 * A + pad
        order = [a for lv in levels for a in lv["dofs"]]
        self.register_buffer("level_order", torch.tensor(order, dtype=torch.int64), persistent=False)

    def _level_buffers(self, dev: torch.device, dt: torch.dtype) -> list[dict[str, torch.Tensor]]:
        """The levels' buffers on ``dev``, floats in ``dt``, plus ``goals (Gl,)`` and ``state (S,)`` (the
        positions of the level's DOFs in the state vector); cached per device and dtype."""
        key = (dev, dt)
        if key not in self._cache:
            levels = []
            for names in self._levels:
                lv = {k: getattr(self, name).to(dev) for k, name in names.items()}
                lv.update(lam=lv["lam"].to(dt), lower=lv["lower"].to(dt), upper=lv["upper"].to(dt),
                          goals=lv["pairs"][:lv["lam"].shape[1]], state=self.active_index.to(dev)[lv["dofs"]])
                levels.append(lv)
            self._cache[key] = levels
        return self._cache[key]

    def _apply(self, fn, recurse=True):  # noqa: ANN001 (nn.Module's); .to(), .cuda(): drop the cached copies
        self._cache = {}
        return super()._apply(fn, recurse)

    @property
    def num_levels(self) -> int:
        """Steps per sweep: the longest chain of solved DOFs that have goals below them."""
        return len(self._levels)

    def level_dofs(self) -> list[list[str]]:
        """The DOF names of each level, in the sweep's order (the DOFs of a level step at once)."""
        names = [self.skeleton.dof_names[i] for i in self.active_index.tolist()]
        return [[names[a] for a in getattr(self, lv["dofs"]).tolist()] for lv in self._levels]

    def forward(self, angles: torch.Tensor, goals: torch.Tensor, goal_weights: torch.Tensor | None = None,
                frames: torch.Tensor | None = None) -> torch.Tensor:
        """Move ``angles`` towards putting the goal joints on ``goals``.

        Args:
            angles: (B, D_all) initial state vectors (the root is kept).
            goals: (B, G, 3) goal positions (world, m) of ``goal_joints``.
            goal_weights: (B, G) or (G,) optional confidences multiplying lambda (and weighting the squared
                errors of the refinement steps); 0 ignores a goal, which may then be NaN (a missing one).
            frames: (B, F, 4, 4) the frames of ``angles`` where the caller has them, e.g. of several bodies of
                this chain (:class:`~torchtrack.skeleton.stack.SkeletonStack`); default: the solver's skeleton's.

        Returns:
            (B, D_all) the solved state vectors, within the joint limits.
        """
        skel, cfg = self.skeleton, self.config
        B, G = angles.shape[0], len(self.goal_joints)
        check_shape(angles, ("B", skel.num_dofs), "angles")
        check_shape(goals, (B, G, 3), "goals")
        dev, dt = angles.device, angles.dtype
        if goal_weights is not None:
            if tuple(goal_weights.shape) != (G,):
                check_shape(goal_weights, (B, G), "goal_weights")
            goal_weights = goal_weights.to(dev, dt).expand(B, G)
            goals = goals.masked_fill(goal_weights[..., None] == 0, 0.0)  # an ignored goal may be NaN (missing)
        out = angles.clone()
        if not self._levels:
            return out
        active = self.active_index.to(dev)
        # one FK; the sweeps then update the chain in closed form
        T = skel.forward_frames(angles) if frames is None else frames  # (B, F, 4, 4)
        T_dof = T[:, self.active_frame.to(dev)]  # (B, A, 4, 4)
        axis = torch.einsum("bdij,dj->bdi", T_dof[..., :3, :3], skel.axes_local.to(dev, dt)[active])  # (B, A, 3)
        base = T_dof[..., :3, 3]  # (B, A, 3)
        scratch = base.new_zeros(B, self.num_points - 2 * base.shape[1] - 2 * G, 3)
        X = torch.cat([T[:, self.goal_frame.to(dev), :3, 3], goals.to(dt), base, base + axis, scratch], 1)
        X = X.permute(2, 0, 1).contiguous()  # (3, B, N)
        levels, thetas = [], []
        for lv in self._level_buffers(dev, dt):  # what stays fixed over the sweeps, per level
            if goal_weights is not None:  # lambda (S, Gl) -> (B, S, Gl)
                lv = dict(lv, lam=lv["lam"] * goal_weights.index_select(1, lv["goals"])[:, None])
            levels.append(lv)
            thetas.append(angles.index_select(1, lv["state"]))  # (B, S)
        for _ in range(cfg.sweeps):
            changes = []
            for h, lv in enumerate(levels):
                thetas[h], applied = self._level_step(X, lv, thetas[h])
                changes.append(applied)
            if cfg.tolerance > 0 and float(torch.cat(changes, 1).abs().amax()) <= cfg.tolerance:
                break
        for _ in range(cfg.refine_steps):
            change = self._refine_step(X, levels, thetas, goal_weights)
            if cfg.tolerance > 0 and float(torch.cat(change, 1).abs().amax()) <= cfg.tolerance:
                break
        out[:, active[self.level_order.to(dev)]] = torch.cat(thetas, 1)
        return out

    def _level_step(self, X: torch.Tensor, lv: dict[str, torch.Tensor], theta: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor]:
        """One CCD step (eq. 14-16) of the S DOFs of a level, then their subtrees rotated (X in place).

        A sweep is mostly such steps, each a few operations over all B problems and S DOFs: the level's points read
        in one gather, the products of eq. 14 in one multiply and sum, the subtrees turned by Rodrigues' formula in
        two multiply-adds (on a GPU each operation is a kernel launch).

        Args:
            X: (3, B, N) the solve's points (see :meth:`_build_levels`), updated in place.
            lv: the level's buffers: ``lam (S, Gl) or (B, S, Gl)`` lambda (times the goal weights),
                ``gather (S * (2 + 2 Gl + M),)`` the columns each DOF reads (its base and axis tip, the level's goal
                joints and goals, then the M points it moves, padded), ``rows (S * M,)`` those M points,
                ``goals (Gl,)`` the level's goal joints, ``lower, upper (S,)``.
            theta: (B, S) the level's angles.

        Returns:
            The new angles (B, S) and the applied change (B, S).
        """
        B, S = theta.shape
        Gl = lv["goals"].shape[0]
        Y = X.index_select(2, lv["gather"]).view(3, B, S, -1)
        D = Y[..., 1:] - Y[..., :1]  # (3, B, S, 1 + 2 Gl + M): from each DOF's base
        w, pg, v = D[..., :1], D[..., 1:1 + 2 * Gl], D[..., 1 + 2 * Gl:]  # unit axes, [joints | goals], moved points
        p, g = pg[..., :Gl], pg[..., Gl:]  # (3, B, S, Gl) each
        pxg = torch.linalg.cross(p, g, dim=0)
        # p . w, g . w, |p|^2, |g|^2, p . g and w . (p x g) in one product, (B, S, 6 Gl)
        dots = (torch.cat([pg, pg, p, pxg], -1) * torch.cat([w.expand_as(pg), pg, g, w.expand_as(pxg)], -1)).sum(0)
        pw, gw, pp, gg, pdg, num = dots.split(Gl, -1)
        den = torch.addcmul(pdg, pw, gw, value=-1.0)  # the in-plane dot product p_perp . g_perp
        # |p_perp| |g_perp| = hypot(num, den): the sine of p's and g's angles to the axis scales lambda
        sines = torch.hypot(num, den) * torch.rsqrt((pp * gg).clamp(min=1e-24))
        lam = (lv["lam"] * sines).masked_fill_(sines <= _MIN_SINE, 0.0)  # (B, S, Gl)
        step = (lam * torch.atan2(num, den)).sum(-1) / lam.sum(-1).clamp(min=1e-12)  # eq. 15; 0 if no goal votes
        new = torch.clamp(torch.add(theta, step, alpha=self.config.damping), lv["lower"], lv["upper"])  # eq. 16
        applied = new - theta  # (B, S)
        turned = _turned(Y[..., 2 + 2 * Gl:], v, w, applied[..., None])  # the moved points as read, turned
        X.index_copy_(2, lv["rows"], turned.view(3, B, -1))
        return new, applied

    @staticmethod
    def _rotate_subtrees(X: torch.Tensor, lv: dict[str, torch.Tensor], base: torch.Tensor, w: torch.Tensor,
                         angle: torch.Tensor) -> None:
        """Rotate each level DOF's subtree (goal joints, bases and axis tips below it) about its axis through
        its ``base (3, B, S, 1)``, ``w (3, B, S, 1)``, by ``angle (B, S)``; X in place."""
        B, S = angle.shape
        rows = lv["rows"]
        points = X.index_select(2, rows).view(3, B, S, -1)  # (3, B, S, M)
        X.index_copy_(2, rows, _turned(points, points - base, w, angle[..., None]).view(3, B, -1))

    def _refine_step(self, X: torch.Tensor, levels: list[dict[str, torch.Tensor]], thetas: list[torch.Tensor],
                     goal_weights: torch.Tensor | None) -> list[torch.Tensor]:
        """One Levenberg-Marquardt step on all goals, clamped to the limits and applied level by level.

        Returns the applied changes, (B, S) per level. ``thetas`` is updated in place.
        """
        G, A = len(self.goal_joints), self.goal_below.shape[0]
        B = X.shape[1]
        Q, goal, base, tip = X[:, :, :2 * G + 2 * A].split([G, G, A, A], dim=2)
        r = Q[:, :, None] - base[..., None]  # (3, B, A, G) joint j from DOF a's base
        w = (tip - base)[..., None].expand_as(r)
        J = torch.linalg.cross(w, r, dim=0) * self.goal_below.to(X)  # (3, B, A, G) d Q_j / d theta_a
        J = J.permute(1, 2, 0, 3).reshape(B, A, 3 * G)
        err = (goal - Q).transpose(0, 1).reshape(B, 3 * G)  # (B, 3 G) goal - joint, coordinate-major
        weighted = err if goal_weights is None else err * goal_weights.repeat(1, 3)
        JW = J if goal_weights is None else J * goal_weights.repeat(1, 3)[:, None]
        normal = JW @ J.mT  # (B, A, A)
        scale = normal.diagonal(dim1=1, dim2=2).mean(-1)  # (B,)
        mu = _MU_FLOOR * scale + self.config.refine_damping * (weighted * err).sum(-1)  # (B,)
        normal = normal + mu[:, None, None] * torch.eye(A, dtype=X.dtype, device=X.device)
        delta = torch.linalg.solve(normal, (JW @ err[..., None]))[..., 0]  # (B, A)
        changes = []
        for h, lv in enumerate(levels):
            S = thetas[h].shape[1]
            new = torch.clamp(thetas[h] + delta.index_select(1, lv["dofs"]), lv["lower"], lv["upper"])
            applied = new - thetas[h]
            base_tip = X.index_select(2, lv["base_tip"])  # (3, B, 2 S): the current bases and axis tips
            base = base_tip[:, :, :S, None]
            self._rotate_subtrees(X, lv, base, base_tip[:, :, S:, None] - base, applied)
            thetas[h] = new
            changes.append(applied)
        return changes
