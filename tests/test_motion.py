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
