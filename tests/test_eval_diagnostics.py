"""The evaluation scripts' diagnostics that the README quotes (scripts/eval_tracking.py --trunk,
scripts/eval_pose2sim_tracking.py --bias).

References: headings of a root turned about the vertical and a spine twisted about it (closed form), and scipy's
``Rotation.align_vectors`` for the rigid alignment.
"""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path
from types import ModuleType, SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


def _script(name: str) -> ModuleType:
    spec = importlib.util.spec_from_file_location(name, SCRIPTS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def eval_tracking() -> ModuleType:
    return _script("eval_tracking")


DOFS = ["root_tx", "root_ty", "root_tz", "root_rz", "root_ry", "root_rx", "spine_flex", "spine_abd", "spine_twist"]


def _poses(yaw: np.ndarray, twist: np.ndarray) -> SimpleNamespace:
    """Poses whose root turns ``yaw`` (rad) about the vertical and whose spine twists ``twist`` above it."""
    angles = np.zeros((len(yaw), len(DOFS)))
    angles[:, DOFS.index("root_rz")] = yaw
    angles[:, DOFS.index("spine_twist")] = twist
    return SimpleNamespace(dof_names=DOFS, angles=angles, valid=np.ones(len(yaw), bool))


def test_trunk_headings_of_a_trunk_that_does_not_twist(eval_tracking):
    # the truth twists the torso by tau over the pelvis; the track turns both by half of it and does not twist:
    # each heading is tau / 2 off its true one and on the mean of the true two
    yaw = np.radians([10.0, 100.0, 175.0, -170.0])  # across the +-180 deg seam too
    tau = np.radians([20.0, -30.0, 16.0, 40.0])
    h = eval_tracking.trunk_headings(_poses(yaw + tau / 2, 0 * tau), _poses(yaw, tau))
    half = np.degrees(np.abs(tau)) / 2
    np.testing.assert_allclose(h["pelvis"], half, atol=1e-9)
    np.testing.assert_allclose(h["torso"], half, atol=1e-9)
    np.testing.assert_allclose(h["pelvis_from_mean"], 0.0, atol=1e-9)
    np.testing.assert_allclose(h["torso_from_mean"], 0.0, atol=1e-9)
    np.testing.assert_allclose(h["true_twist"], 2 * half, atol=1e-9)
    np.testing.assert_allclose(h["tracked_twist"], 0.0, atol=1e-9)
    line = eval_tracking.headings_line(h)
    assert f"pelvis {half.mean():.1f} / {half.max():.1f}" in line and "tracked 0.0 / 0.0" in line


def test_trunk_headings_skip_invalid_frames(eval_tracking):
    truth = _poses(np.zeros(3), np.zeros(3))
    track = _poses(np.radians([5.0, 90.0, 5.0]), np.zeros(3))
    track.valid = np.array([True, False, True])
    h = eval_tracking.trunk_headings(track, truth)
    np.testing.assert_allclose(h["pelvis"], [5.0, 5.0], atol=1e-9)


def test_rigid_residuals_against_scipy_alignment():
    mod = _script("eval_pose2sim_tracking")
    rng = np.random.default_rng(3)
    x = rng.normal(size=(15, 3))
    R = Rotation.from_rotvec([0.3, -1.1, 0.7])
    y = R.apply(x) + [0.5, -2.0, 1.0]
    np.testing.assert_allclose(mod.rigid_residuals(x, y), 0.0, atol=1e-9)
    y_noisy = y + rng.normal(scale=0.05, size=y.shape)
    best, _ = Rotation.align_vectors(y_noisy - y_noisy.mean(0), x - x.mean(0))
    expect = np.linalg.norm(best.apply(x - x.mean(0)) + y_noisy.mean(0) - y_noisy, axis=-1)
    np.testing.assert_allclose(mod.rigid_residuals(x, y_noisy), expect, atol=1e-9)
    assert math.isclose(mod.rigid_residuals(x, x + 1.0).max(), 0.0, abs_tol=1e-9)
