"""`torchtrack init-pose`: the start pose and body fitted to 3D keypoints in a TRC file, against the ground truth of
a synthetic body written as Pose2Sim writes keypoints (BODY_25B names, Y up, mm), and on the real demo."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import shared_data
from torchtrack.cli import main
from torchtrack.io.poses import load_poses
from torchtrack.skeleton import Skeleton
from torchtrack.synth.motion import procedural_motion

#: BODY_25B keypoints and the output point each one is (the hips' mean is the pelvis).
BODY25B = {"RHip": "r_hip", "RKnee": "r_knee", "RAnkle": "r_ankle", "LHip": "l_hip", "LKnee": "l_knee",
           "LAnkle": "l_ankle", "Neck": "neck", "Head": "head_top", "RShoulder": "r_shoulder", "RElbow": "r_elbow",
           "RWrist": "r_wrist", "LShoulder": "l_shoulder", "LElbow": "l_elbow", "LWrist": "l_wrist"}


def write_trc(path: Path, names: list[str], xyz_m: np.ndarray, fps: float = 60.0, y_up: bool = True,
              prefix: str = "") -> None:
    """A TRC file as OpenSim / Pose2Sim write it: ``xyz_m (T, M, 3)`` Z-up world metres, written in mm with Y up
    (world (x, y, z) = file (Z, X, Y)) or as they are."""
    T, M, _ = xyz_m.shape
    pts = xyz_m[..., [1, 2, 0]] if y_up else xyz_m
    lines = [f"PathFileType\t4\t(X/Y/Z)\t{path.name}",
             "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames",
             f"{fps}\t{fps}\t{T}\t{M}\tmm\t{fps}\t0\t{T}",
             "Frame#\tTime\t" + "\t\t\t".join(prefix + n for n in names),
             "\t\t" + "\t".join(f"X{i + 1}\tY{i + 1}\tZ{i + 1}" for i in range(M))]
    for t in range(T):
        lines.append(f"{t + 1}\t{t / fps}\t" + "\t".join(f"{v:.4f}" for v in (1e3 * pts[t]).reshape(-1)))
    path.write_text("\n".join(lines) + "\n")


@pytest.fixture(scope="module")
def subject() -> Skeleton:
    """A 1.68 m body with longer shanks and a shorter torso than the template's."""
    subj = Skeleton.from_urdf().scaled_to_height(1.68)
    length = dict(zip(subj.bone_names, subj.bone_lengths.tolist()))
    return subj.with_bone_lengths({"torso": 0.9 * length["torso"], "l_shank": 1.1 * length["l_shank"],
                                   "r_shank": 1.1 * length["r_shank"]})


@pytest.fixture(scope="module")
def walk(subject) -> tuple[torch.Tensor, np.ndarray]:
    """A few frames of a walk: states (T, D) and the output points (T, J, 3)."""
    angles = procedural_motion(subject, "walk", 0.3, 30, starfish_s=0.0)[:6]
    with torch.no_grad():
        return angles, subject.forward(angles).output_points.numpy()


@pytest.mark.parametrize("frame,y_up,prefix", [(0, True, ""), (4, False, "Subject1:")])
def test_init_pose_recovers_the_pose_and_body_of_body25b_keypoints(tmp_path, subject, walk, frame, y_up, prefix,
                                                                    capsys):
    angles, points = walk
    out = list(subject.output_names)
    names = list(BODY25B)
    trc = tmp_path / "keypoints.trc"
    write_trc(trc, names, points[:, [out.index(BODY25B[n]) for n in names]], y_up=y_up, prefix=prefix)
    args = ["init-pose", str(trc), "--out", str(tmp_path / "start.npz"), "--frame", str(frame)]
    assert main(args + ([] if y_up else ["--up", "z"])) == 0
    assert "15 keypoints fitted" in capsys.readouterr().out  # 14 keypoints and the pelvis from the hips
    start = load_poses(tmp_path / "start.npz")
    assert start.num_frames == 1 and start.valid.all()
    body = Skeleton(str(start.extra["body_urdf"]))
    assert abs(body.height() - subject.height()) < 0.03
    # the fitted body at the fitted pose lands on the true joints, the hidden ones (spine, head centre) included
    with torch.no_grad():
        fitted = body.forward(torch.as_tensor(start.angles)).output_points[0].numpy()
    err = np.linalg.norm(fitted[:16] - points[frame, :16], axis=-1)
    assert err.mean() < 0.01 and err.max() < 0.03, err
    np.testing.assert_allclose(start.joints3d[0], fitted, atol=1e-5)


def test_init_pose_errors_name_the_file(tmp_path, walk, subject, capsys):
    _, points = walk
    out = list(subject.output_names)
    trc = tmp_path / "arms.trc"
    arms = ["RElbow", "RWrist", "LElbow", "LWrist"]  # no trunk point
    write_trc(trc, arms, points[:, [out.index(BODY25B[n]) for n in arms]])
    assert main(["init-pose", str(trc), "--out", str(tmp_path / "s.npz")]) == 2
    err = capsys.readouterr().err
    assert str(trc) in err and "lacks the hips or a shoulder" in err
    assert not (tmp_path / "s.npz").exists()
    names = list(BODY25B)
    write_trc(trc, names, points[:, [out.index(BODY25B[n]) for n in names]])
    assert main(["init-pose", str(trc), "--out", str(tmp_path / "s.npz"), "--frame", "6"]) == 2
    assert "--frame 6 is out of range (the file has 6 rows)" in capsys.readouterr().err
    assert main(["init-pose", str(tmp_path / "missing.trc"), "--out", str(tmp_path / "s.npz")]) == 2
    assert "missing.trc" in capsys.readouterr().err
    hips = ["RHip", "LHip", "RKnee", "LKnee"]  # the hips and their mean lie on one line: no rotation about it
    write_trc(trc, hips, points[:, [out.index(BODY25B[n]) for n in hips]])
    assert main(["init-pose", str(trc), "--out", str(tmp_path / "s.npz")]) == 2
    assert "lacks the hips or a shoulder" in capsys.readouterr().err
    assert not (tmp_path / "s.npz").exists()


def test_init_pose_leaves_out_missing_keypoints_and_scales_only_when_asked(tmp_path, subject, walk, capsys):
    _, points = walk
    out = list(subject.output_names)
    names = list(BODY25B)
    xyz = points[:, [out.index(BODY25B[n]) for n in names]].copy()
    xyz[0, names.index("LWrist")] = np.nan  # an empty TRC cell
    trc = tmp_path / "gap.trc"
    write_trc(trc, names, xyz)
    assert main(["init-pose", str(trc), "--out", str(tmp_path / "s.npz"), "--scale-only"]) == 0
    report = capsys.readouterr().out
    assert "14 keypoints fitted" in report and "l_wrist" not in report and "warning" not in report
    start = load_poses(tmp_path / "s.npz")
    assert np.isfinite(start.angles).all()
    # one scale for the whole template: its proportions, not the subject's (shanks 1.1x, torso 0.9x)
    body, template = Skeleton(str(start.extra["body_urdf"])), Skeleton.from_urdf()
    ratio = (body.bone_lengths / template.bone_lengths).numpy()
    np.testing.assert_allclose(ratio, ratio[0], rtol=1e-4)


def test_init_pose_on_the_pose2sim_demo(tmp_path, capsys):
    trc = shared_data("pose2sim_demo", "reference_3d", "S00_P00_T01_BalancingTrial_0-100.trc")
    assert main(["init-pose", str(trc), "--out", str(tmp_path / "start.npz")]) == 0
    report = capsys.readouterr().out
    mean_mm = float(report.split(" mm from the keypoints")[0].rsplit(" ", 1)[1])
    assert mean_mm < 15.0, report  # a body of our skeleton fits another system's 15 points of a real person
    assert "warning" not in report
    start = load_poses(tmp_path / "start.npz")
    assert 1.6 < float(start.extra["subject_height_m"]) < 1.9
    # upright in the Z-up world, standing on the floor (the TRC is Y up: its hips are 0.90 m high)
    p = dict(zip(start.joint_names, start.joints3d[0]))
    assert 0.8 < p["pelvis"][2] < 1.0
    assert p["head_top"][2] > p["pelvis"][2] + 0.4 and p["pelvis"][2] > p["l_ankle"][2] + 0.4
    # read as Z up, the same file puts the subject on its side: the CLI says so
    assert main(["init-pose", str(trc), "--out", str(tmp_path / "wrong.npz"), "--up", "z"]) == 0
    assert "check --up (z)" in capsys.readouterr().out
