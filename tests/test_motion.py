"""Procedural motions: starfish start, limits, continuity, staying in the capture volume."""

from __future__ import annotations

import pytest
import torch

from torchtrack.checks import InputError
from torchtrack.conventions import LANDMARKS
from torchtrack.skeleton import Skeleton
from torchtrack.synth.motion import MOTIONS, procedural_motion


@pytest.fixture(scope="module")
def skel():
    return Skeleton.from_urdf()


@pytest.mark.parametrize("kind", MOTIONS)
def test_motion_properties(skel, kind):
    fps = 30.0
    a = procedural_motion(skel, kind, duration_s=4.0, fps=fps)
    assert a.shape == (round(5.0 * fps), skel.num_dofs)
    assert bool(((a >= skel.lower) & (a <= skel.upper)).all())
    # one second of the starfish pose (root position aside)
    star = skel.starfish_angles()
    torch.testing.assert_close(a[: int(fps), 4:], star[4:].expand(int(fps), -1))
    joints = skel(a).joints  # (T, 22, 3)
    lm = skel.landmarks(a)
    # continuous: no landmark moves more than 20 cm between frames at 30 fps (6 m/s, a kicking foot)
    assert (lm[1:] - lm[:-1]).norm(dim=-1).max() < 0.2
    # stays near the origin and above the floor; the soles touch the floor
    assert lm[..., :2].norm(dim=-1).max() < 1.6
    toes = joints[:, [skel.joint_names.index("l_toe"), skel.joint_names.index("r_toe")], 2]
    assert toes.min() > -0.02 and toes.min(dim=1).values.median() < 0.03
    # arms spread in the starfish: wrists far from the body axis
    wrist = lm[0, LANDMARKS.index("l_wrist")] - lm[0, LANDMARKS.index("pelvis")]
    assert wrist[:2].norm() > 0.45


def test_unknown_motion(skel):
    with pytest.raises(InputError, match="unknown motion 'fly'"):
        procedural_motion(skel, "fly", 1.0, 30)


def test_walk_on_a_path_faces_the_way_it_goes_and_turns_where_it_pauses(skel):
    """The walk on a path (out 3 m, a pause, back): the pelvis passes the waypoints, the hips face the way the
    pelvis moves (read from the body's joints, not the heading it was given), the half turn falls in the pause,
    and the legs stride while moving and stand still before the first move."""
    import math

    fps, t0, out, pause = 30.0, 1.5, 2.5, 0.8
    heading = 2.2
    far = (3.0 * math.cos(heading), 3.0 * math.sin(heading))
    path = ((t0, 0.0, 0.0), (t0 + out, *far), (t0 + out + pause, *far), (t0 + 2 * out + pause, 0.0, 0.0))
    a = procedural_motion(skel, "walk", duration_s=7.0, fps=fps, starfish_s=1.0, path=path)
    assert bool(((a >= skel.lower) & (a <= skel.upper)).all())
    lm = skel.landmarks(a).double()
    pelvis = lm[:, LANDMARKS.index("pelvis"), :2]
    frame = [round(w[0] * fps) for w in path]
    for f, w in zip(frame, path):
        assert float((pelvis[f] - torch.tensor(w[1:], dtype=torch.float64)).norm()) < 0.06
    hips = lm[:, LANDMARKS.index("l_hip"), :2] - lm[:, LANDMARKS.index("r_hip"), :2]
    facing = torch.atan2(-hips[:, 0], hips[:, 1])  # the hips' forward normal: left hip to the left of forward
    step = pelvis[2:] - pelvis[:-2]
    moving = step.norm(dim=-1) * fps / 2 > 0.5
    off = torch.remainder(torch.atan2(step[:, 1], step[:, 0]) - facing[1:-1] + math.pi, 2 * math.pi) - math.pi
    assert int(moving.sum()) > 3 * fps and float(off[moving].abs().max()) < math.radians(20)
    turned = torch.remainder(facing[frame[2]] - facing[frame[1]], 2 * math.pi)
    assert abs(float(turned) - math.pi) < math.radians(20)  # the half turn, done within the pause
    halfway = torch.remainder(facing[(frame[1] + frame[2]) // 2] - facing[frame[1]], 2 * math.pi)
    assert abs(float(halfway) - math.pi / 2) < math.radians(20)  # turning through the pause, not at one end
    step_turn = torch.remainder(facing[1:] - facing[:-1] + math.pi, 2 * math.pi) - math.pi
    assert float(step_turn.abs().max()) < math.radians(15)  # no frame turns the body at once
    hip = a[:, skel.dof_names.index("l_hip_flex")]
    assert float(hip[frame[0] - 5:frame[0]].abs().max()) < 0.02  # standing before the walk sets off
    walking = slice(frame[0] + round(0.7 * fps), frame[1] - round(0.7 * fps))
    assert float(hip[walking].max() - hip[walking].min()) > 0.6  # striding at full pace
    # the strides keep up with the body as the circle walk's do at its own pace (the lower toe's forward speed
    # over the pelvis's, while moving; a procedural gait's feet are not truly planted in either)
    circle = procedural_motion(skel, "walk", duration_s=4.0, fps=fps, starfish_s=0.0)
    assert abs(_toe_drift(skel, a, fps) - _toe_drift(skel, circle, fps)) < 0.15


def _toe_drift(skel, a: torch.Tensor, fps: float) -> float:
    """The lower toe's forward speed over the pelvis's, mean over the frames where the pelvis moves > 0.5 m/s."""
    joints = skel(a).joints.double()
    toes = joints[:, [skel.joint_names.index("l_toe"), skel.joint_names.index("r_toe")]]  # (T, 2, 3)
    lower = toes[:-1, :, 2].argmin(1)  # (T - 1,)
    rows = torch.arange(len(lower))
    toe_v = (toes[1:, :, :2] - toes[:-1, :, :2])[rows, lower] * fps  # (T - 1, 2)
    pelvis = joints[:, skel.joint_names.index("pelvis"), :2]
    v = (pelvis[1:] - pelvis[:-1]) * fps
    speed = v.norm(dim=-1)
    moving = speed > 0.5
    return float(((toe_v * v).sum(-1) / speed.square())[moving].mean())


def test_a_walk_on_a_path_turns_smoothly_over_a_split_pause_and_refuses_a_corner_without_one(skel):
    """A pause given as two waypoints turns once across both (no frame turns far); a corner with no pause is
    refused, naming the waypoint; a path of one waypoint stands there."""
    import math

    fps = 10.0
    a = procedural_motion(skel, "walk", 3.0, fps, 0.0, ((0, 0, 0), (1, 1, 0), (1.5, 1, 0), (2, 1, 0), (3, 0, 0)))
    heading = a[:, skel.dof_names.index("root_rz")]
    assert float((heading[1:] - heading[:-1]).abs().max()) < math.radians(30)
    assert float(heading[-1] - heading[0]) == pytest.approx(math.pi, abs=1e-5)
    with pytest.raises(InputError, match=r"turns at waypoint 1 \(1, 1, 0\) without a pause"):
        procedural_motion(skel, "walk", 2.0, fps, 0.0, ((0, 0, 0), (1, 1, 0), (2, 1, 1)))
    still = procedural_motion(skel, "walk", 1.0, fps, 0.5, ((1.0, 0.5, -0.5),))
    torch.testing.assert_close(still[:, :2], torch.tensor([0.5, -0.5]).expand(still.shape[0], 2))
