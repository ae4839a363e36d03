"""Real rig, real videos: Pose2Sim's reference keypoints project onto the moving person in all four views.

The region that moves is found without the calibration: per pixel, the 90th percentile over the 100 frames
of the absolute difference to the temporal median (OpenCV/numpy), thresholded, opened, and the bounding box of
its largest connected component (the subject; the operator in the back of cam01/cam02 and treadmill
reflections are smaller).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from conftest import shared_data

from torchtrack.cameras import load_calibration
from torchtrack.io.trc import read_trc, y_up_to_world

DOWNSCALE = 4  # motion analysis at 1/4 resolution
FRAMES = (0, 20, 40, 60, 80, 99)


def _trc_to_world(xyz: np.ndarray) -> torch.Tensor:
    """TRC is Y-up: world (Z up) = (Z', X', Y')."""
    return torch.from_numpy(y_up_to_world(xyz))


def _motion_box(video: Path) -> tuple[tuple[int, int, int, int], tuple[int, int]]:
    """Bounding box (x0, y0, x1, y1) in full-resolution pixels of the largest moving region, and (W, H)."""
    cap = cv2.VideoCapture(str(video))
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        gray = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
        frames.append(cv2.resize(gray, None, fx=1 / DOWNSCALE, fy=1 / DOWNSCALE, interpolation=cv2.INTER_AREA))
    cap.release()
    assert len(frames) == 100, f"{video.name}: decoded {len(frames)} frames"
    stack = np.stack(frames).astype(np.int16)  # (T, h, w)
    deviation = np.abs(stack - np.median(stack, axis=0))
    energy = np.percentile(deviation, 90, axis=0).astype(np.uint8)
    mask = (cv2.GaussianBlur(energy, (5, 5), 0) > 20).astype(np.uint8)
    mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, np.ones((5, 5), np.uint8))
    mask = cv2.dilate(mask, np.ones((9, 9), np.uint8))  # join the limbs into one component
    count, _, stats, _ = cv2.connectedComponentsWithStats(mask)
    assert count > 1, f"{video.name}: nothing moves"
    biggest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    x, y, w, h = (int(v) * DOWNSCALE for v in stats[biggest, :4])
    size = (frames[0].shape[1] * DOWNSCALE, frames[0].shape[0] * DOWNSCALE)
    return (x, y, x + w, y + h), size


@pytest.fixture(scope="module")
def boxes():
    """Motion boxes per video name (cam01 .. cam04), computed once."""
    return {f"cam0{i}": _motion_box(shared_data("pose2sim_demo", "videos", f"cam0{i}.mp4")) for i in range(1, 5)}


@pytest.fixture(scope="module", params=["Calib_qualisys_pose2sim.toml", "Calib.qca.txt"])
def scene(request, boxes):
    """Both calibrations of the rig: Pose2Sim's TOML (cameras cam_0N) and the Qualisys export (cam0N)."""
    rig = load_calibration(shared_data("pose2sim_demo", "calibration", request.param), dtype=torch.float64)
    trc = read_trc(shared_data("pose2sim_demo", "reference_3d", "S00_P00_T01_BalancingTrial_0-100.trc"))
    names, xyz = trc.marker_names, trc.positions
    return rig, names, xyz, {cam: boxes[cam.replace("_", "")] for cam in rig.names}


def _inside(uv: np.ndarray, box, margin: float) -> np.ndarray:
    x0, y0, x1, y1 = box
    return (uv[..., 0] >= x0 - margin) & (uv[..., 0] <= x1 + margin) & \
           (uv[..., 1] >= y0 - margin) & (uv[..., 1] <= y1 + margin)


def test_reference_pelvis_projects_onto_the_moving_person(scene):
    rig, names, xyz, boxes = scene
    assert xyz.shape == (100, 21, 3) and {"RHip", "LHip", "Head", "RAnkle"} <= set(names)
    world = _trc_to_world(xyz)  # (T, 21, 3)
    pelvis = (world[:, names.index("RHip")] + world[:, names.index("LHip")]) / 2  # (T, 3)
    uv, valid = rig.project(pelvis[list(FRAMES)])  # (C, F, 2)
    for c, cam in enumerate(rig.names):
        box, (w, h) = boxes[cam]
        assert (box[2] - box[0]) * (box[3] - box[1]) < 0.5 * w * h, f"{cam}: motion box {box} is not specific"
        assert valid[c].all(), f"{cam}: pelvis outside the calibrated image"
        inside = _inside(uv[c].numpy(), box, margin=0.03 * w)
        assert inside.all(), f"{cam}: pelvis {uv[c].tolist()} outside the moving region {box}"


def test_all_keypoints_mostly_inside_and_wrong_axes_fail(scene):
    """Most of the 21 keypoints land in the moving region; the same test with the TRC read as Z-up (no axis
    permutation) fails, so the check has teeth."""
    rig, names, xyz, boxes = scene
    right = _trc_to_world(xyz[list(FRAMES)])  # (F, 21, 3)
    wrong = torch.from_numpy(xyz[list(FRAMES)].copy())
    for points, expect_good in ((right, True), (wrong, False)):
        uv, valid = rig.project(points)  # (C, F, 21, 2)
        fractions = []
        for c, cam in enumerate(rig.names):
            box, (w, _) = boxes[cam]
            hit = _inside(uv[c].numpy(), box, margin=0.03 * w) & valid[c].numpy()
            fractions.append(hit.mean())
        if expect_good:
            assert min(fractions) > 0.9, fractions  # measured: 0.96 .. 1.0
        else:
            assert min(fractions) < 0.5, fractions  # measured: 0.0 for cam01, cam02
