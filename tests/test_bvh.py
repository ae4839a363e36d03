"""BVH parser, FK and world conversion, against a plain scipy reference and the real CMU files."""

from __future__ import annotations

import re

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from conftest import shared_data
from torchtrack.checks import InputError
from torchtrack.io.bvh import (BVH, CMU_UNIT_M, bvh_forward_kinematics, bvh_to_world, parse_bvh, read_bvh,
                               write_bvh)

CMU_FILES = ["131_01.bvh", "131_02.bvh"]

SMALL = """HIERARCHY
ROOT Hips
{
  OFFSET 1.0 2.0 3.0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Chest
  {
    OFFSET 0.0 2.0 0.0
    CHANNELS 3 Xrotation Yrotation Zrotation
    JOINT Upper Arm
    {
      OFFSET 1.0 0.0 0.0
      CHANNELS 2 Yrotation Zrotation
      End Site
      {
        OFFSET 0.0 0.0 1.5
      }
    }
  }
  JOINT Leg
  {
    OFFSET 0.5 -1.0 0.0
    CHANNELS 1 Zrotation
    End Site
    {
      OFFSET 0.0 -2.0 0.0
    }
  }
}
MOTION
Frames: 3
Frame Time: 0.04
0 0 0 0 0 0 0 0 0 0 0 0
10 20 30 90 0 0 0 0 0 0 0 0
1 2 3 10 20 30 40 50 60 70 80 -30
"""


def reference_fk(bvh: BVH) -> np.ndarray:
    """Plain per-frame, per-joint loop with scipy's intrinsic (upper-case) Euler composition: (T, J, 3)."""
    T, J = bvh.num_frames, bvh.num_joints
    out = np.zeros((T, J, 3))
    for t in range(T):
        R_world, p_world = [None] * J, [None] * J
        for j in range(J):
            chans = bvh.channels[j]
            values = bvh.motion[t, bvh.channel_start[j]:bvh.channel_start[j] + len(chans)]
            seq = "".join(c[0] for c in chans if c.endswith("rotation"))
            angles = [v for c, v in zip(chans, values) if c.endswith("rotation")]
            R = Rotation.from_euler(seq.upper(), angles, degrees=True).as_matrix() if seq else np.eye(3)
            trans = np.array(bvh.offsets[j], dtype=float)
            for c, v in zip(chans, values):
                if c.endswith("position"):
                    trans["XYZ".index(c[0])] += v
            p = bvh.parents[j]
            if p < 0:
                R_world[j], p_world[j] = R, trans
            else:
                R_world[j] = R_world[p] @ R
                p_world[j] = p_world[p] + R_world[p] @ trans
            out[t, j] = p_world[j]
    return out


# ------------------------------------------------------------------------------------------------ synthetic


def test_parse_small_structure():
    b = parse_bvh(SMALL, "small.bvh")
    assert b.joint_names == ["Hips", "Chest", "Upper Arm", "Upper Arm_end", "Leg", "Leg_end"]
    assert b.parents.tolist() == [-1, 0, 1, 2, 0, 4]
    assert b.is_end_site.tolist() == [False, False, False, True, False, True]
    assert b.channel_start.tolist() == [0, 6, 9, 11, 11, 12]
    assert b.channels[2] == ("Yrotation", "Zrotation")
    assert b.motion.shape == (3, 12) and b.num_channels == 12
    assert b.frame_time == pytest.approx(0.04) and b.fps == pytest.approx(25.0)
    np.testing.assert_allclose(b.offsets[1], [0, 2, 0])


def test_fk_hand_computed():
    b = parse_bvh(SMALL)
    P = bvh_forward_kinematics(b)  # (3, 6, 3)
    # rest: positions are accumulated offsets
    np.testing.assert_allclose(P[0], [[1, 2, 3], [1, 4, 3], [2, 4, 3], [2, 4, 4.5], [1.5, 1, 3], [1.5, -1, 3]])
    # frame 1: root translated by (10, 20, 30) on top of its offset and turned 90 deg about Z (x -> y, y -> -x)
    root = np.array([11.0, 22.0, 33.0])
    np.testing.assert_allclose(P[1, 0], root, atol=1e-12)
    np.testing.assert_allclose(P[1, 1], root + [-2, 0, 0], atol=1e-12)  # chest offset (0, 2, 0) -> (-2, 0, 0)
    np.testing.assert_allclose(P[1, 2], root + [-2, 1, 0], atol=1e-12)  # arm offset (1, 0, 0) -> (0, 1, 0)
    np.testing.assert_allclose(P[1, 4], root + [1, 0.5, 0], atol=1e-12)  # leg offset (0.5, -1, 0) -> (1, 0.5, 0)
    np.testing.assert_allclose(P[1, 5], root + [1, 0.5, 0] + [2, 0, 0], atol=1e-12)


def test_fk_matches_reference_small():
    b = parse_bvh(SMALL)
    np.testing.assert_allclose(bvh_forward_kinematics(b), reference_fk(b), atol=1e-12)


def test_fk_frame_selection():
    b = parse_bvh(SMALL)
    full = bvh_forward_kinematics(b)
    np.testing.assert_allclose(bvh_forward_kinematics(b, frames=[2, 0]), full[[2, 0]])
    np.testing.assert_allclose(bvh_forward_kinematics(b, frames=slice(1, 3)), full[1:3])


def test_write_read_round_trip(tmp_path):
    b = parse_bvh(SMALL, "small.bvh")
    path = tmp_path / "out.bvh"
    write_bvh(path, b)
    c = read_bvh(path)
    assert c.joint_names == b.joint_names and c.channels == b.channels
    assert c.parents.tolist() == b.parents.tolist()
    np.testing.assert_allclose(c.motion, b.motion, atol=1e-6)
    np.testing.assert_allclose(c.offsets, b.offsets, atol=1e-6)
    assert c.frame_time == pytest.approx(b.frame_time, abs=1e-7)


def test_bvh_to_world_axes_and_units():
    p = np.array([[1.0, 2.0, 3.0]])
    np.testing.assert_allclose(bvh_to_world(p, unit_to_m=0.5), [[1.5, 0.5, 1.0]])
    # the mapping is a rotation (det +1): it keeps handedness
    M = bvh_to_world(np.eye(3), unit_to_m=1.0)  # row i = image of bvh axis i
    assert np.linalg.det(M) == pytest.approx(1.0)
    torch = pytest.importorskip("torch")
    np.testing.assert_allclose(bvh_to_world(torch.tensor(p), unit_to_m=0.5).numpy(), [[1.5, 0.5, 1.0]])
    with pytest.raises(InputError):
        bvh_to_world(np.zeros((2, 4)), unit_to_m=1.0)


def _line_of(text: str, needle: str) -> int:
    return next(n + 1 for n, ln in enumerate(text.splitlines()) if needle in ln)


@pytest.mark.parametrize("case", ["truncated", "extra_rows", "short_row", "channel_count", "channel_count_short",
                                  "unknown_channel", "bad_number", "no_motion", "bad_offset", "duplicate_name"])
def test_bad_input_names_file_and_line(case, tmp_path):
    text = SMALL
    if case == "truncated":
        text = "\n".join(SMALL.splitlines()[:-1]) + "\n"
        line = len(text.splitlines())
    elif case == "extra_rows":
        text = SMALL + "0 0 0 0 0 0 0 0 0 0 0 0\n"
        line = len(text.splitlines())
    elif case == "short_row":
        text = SMALL.replace("10 20 30 90 0 0 0 0 0 0 0 0", "10 20 30 90 0 0 0 0 0 0 0")
        line = _line_of(text, "10 20 30 90")
    elif case == "channel_count":
        text = SMALL.replace("CHANNELS 2 Yrotation Zrotation", "CHANNELS 1 Yrotation Zrotation")
        line = _line_of(text, "CHANNELS 1 Yrotation")
    elif case == "channel_count_short":
        text = SMALL.replace("CHANNELS 2 Yrotation Zrotation", "CHANNELS 3 Yrotation Zrotation")
        line = _line_of(text, "CHANNELS 3 Yrotation")
    elif case == "unknown_channel":
        text = SMALL.replace("CHANNELS 1 Zrotation", "CHANNELS 1 Wrotation")
        line = _line_of(text, "Wrotation")
    elif case == "bad_number":
        text = SMALL.replace("1 2 3 10 20 30", "1 2 x 10 20 30")
        line = _line_of(text, "1 2 x")
    elif case == "no_motion":
        text = SMALL.split("MOTION")[0]
        line = None
    elif case == "bad_offset":
        text = SMALL.replace("OFFSET 0.5 -1.0 0.0", "OFFSET 0.5 abc 0.0")
        line = _line_of(text, "abc")
    else:
        text = SMALL.replace("JOINT Leg", "JOINT Chest")
        line = [n + 1 for n, ln in enumerate(text.splitlines()) if "JOINT Chest" in ln][1]
    path = tmp_path / f"{case}.bvh"
    path.write_text(text)
    with pytest.raises(InputError) as e:
        read_bvh(path)
    msg = str(e.value)
    assert str(path) in msg
    if line is not None:
        assert f"line {line}" in msg, msg


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_bvh(tmp_path / "nope.bvh")


# ------------------------------------------------------------------------------------------------ real CMU data


@pytest.fixture(scope="module", params=CMU_FILES)
def cmu(request) -> BVH:
    return read_bvh(shared_data("mocap", "cmu", request.param))


def test_cmu_structure(cmu):
    assert cmu.num_joints == 38 and int((~cmu.is_end_site).sum()) == 31  # 31 joints + 7 end sites
    assert cmu.num_channels == 96 and cmu.num_frames in (994, 1247)
    assert cmu.fps == pytest.approx(120.0, rel=1e-4)
    orders = {c for c in cmu.channels}
    # per-joint channel orders really vary: legs/spine ZYX, arms ZXY
    assert ("Zrotation", "Yrotation", "Xrotation") in orders and ("Zrotation", "Xrotation", "Yrotation") in orders
    assert cmu.channels[cmu.index("LeftElbow")] == ("Zrotation", "Xrotation", "Yrotation")
    assert cmu.channels[0] == ("Xposition", "Yposition", "Zposition", "Zrotation", "Yrotation", "Xrotation")


def test_cmu_fk_matches_scipy_reference_all_frames(cmu):
    np.testing.assert_allclose(bvh_forward_kinematics(cmu), reference_fk(cmu), rtol=0, atol=1e-6)


def test_cmu_world_sanity(cmu):
    P = bvh_to_world(bvh_forward_kinematics(cmu), unit_to_m=CMU_UNIT_M)  # (T, J, 3) metres, Z up
    i = cmu.index
    feet = [i(n) for n in ("LeftAnkle", "RightAnkle", "LeftToe", "RightToe", "LeftToe_end", "RightToe_end")]
    lowest = P[:, feet, 2].min(axis=1)  # (T,)
    # feet on the floor: the lowest foot point stays within a few cm of z = 0
    assert abs(np.median(lowest)) < 0.08 and lowest.min() > -0.08 and lowest.max() < 0.12
    # standing height (Head End Site above the lowest foot point). Measured: 1.43 m (131_01), 1.50 m (131_02)
    # at the 99th percentile of frames. The converted CMU skeleton has no thorax segment (lowerneck has a zero
    # offset) and the head End Site lies below the vertex, so this is below the subject's stature.
    height = np.percentile(P[:, i("Head_end"), 2] - lowest, 99)
    assert 1.35 < height < 2.0
    # bone lengths are constant over time and equal to the offsets (no position channels below the root)
    child = np.arange(1, cmu.num_joints)
    bone = np.linalg.norm(P[:, child] - P[:, cmu.parents[child]], axis=-1)  # (T, J-1)
    np.testing.assert_allclose(bone, np.broadcast_to(np.linalg.norm(cmu.offsets[child], axis=-1) * CMU_UNIT_M,
                                                     bone.shape), atol=1e-9)
    # handedness as in torchtrack.conventions (facing +X, left at +Y, so forward = left x up): the subject walks
    # the way it faces. Path-length-weighted mean cosine between facing and root velocity: measured 0.65 (131_01,
    # which also side-steps and crouches) and 0.78 (131_02); a mirrored mapping would make it negative.
    left = P[:, i("LeftHip")] - P[:, i("RightHip")]  # (T, 3)
    forward = np.cross(left, [0.0, 0.0, 1.0])[:, :2]  # (T, 2)
    forward /= np.linalg.norm(forward, axis=1, keepdims=True)
    velocity = np.gradient(P[:, 0, :2], axis=0)  # (T, 2) m/frame
    assert np.sum(forward * velocity) / np.linalg.norm(velocity, axis=1).sum() > 0.5


def test_cmu_round_trip(cmu, tmp_path):
    path = tmp_path / "copy.bvh"
    write_bvh(path, cmu)
    back = read_bvh(path)
    np.testing.assert_allclose(bvh_forward_kinematics(back), bvh_forward_kinematics(cmu), atol=1e-4)
    assert re.search(r"Frame Time: 0\.00833", path.read_text())
