#!/usr/bin/env python
"""Draw Pose2Sim's reference 3D keypoints, projected with torchtrack's CameraRig, on the four real videos.

Writes docs/images/pose2sim_overlay.png: one frame of the four views side by side (each cropped around the
projected subject and downscaled), with the 21 OpenPose BODY_25B keypoints and their bones. A visual check of the calibration readers and of the
projection (distortion included) on real footage.

    .venv/bin/python scripts/pose2sim_overlay.py [--frame 50] [--calibration Calib.qca.txt]

Data: ../shared/data/pose2sim_demo (videos/cam0N.mp4, calibration/, reference_3d/*.trc). The TRC is Y-up:
world (Z up) = (Z', X', Y'). cam01/cam02 decode 1080 px wide while calibrated at 1088, with 7 black rows at
the top and at the bottom: they look like the 1088x1920 frames scaled by 1080/1088 and letterboxed to 1920.
Drawn as-is (as Pose2Sim itself used them), which would put points up to ~7 px off towards the borders.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np
import torch

from torchtrack.cameras import load_calibration
from torchtrack.io.atomic import atomic_path
from torchtrack.io.trc import read_trc

REPO = Path(__file__).resolve().parents[1]
DATA = (REPO / ".." / "shared" / "data" / "pose2sim_demo").resolve()
TRC = "reference_3d/S00_P00_T01_BalancingTrial_0-100.trc"

# Bones by keypoint name; "Pelvis" is the mid-hip point added below. Colours (BGR): right red, left blue.
RIGHT, LEFT, MID = (40, 40, 230), (230, 120, 30), (60, 200, 60)
BONES = [
    ("RHip", "RKnee", RIGHT), ("RKnee", "RAnkle", RIGHT), ("RAnkle", "RHeel", RIGHT),
    ("RAnkle", "RBigToe", RIGHT), ("RBigToe", "RSmallToe", RIGHT),
    ("LHip", "LKnee", LEFT), ("LKnee", "LAnkle", LEFT), ("LAnkle", "LHeel", LEFT),
    ("LAnkle", "LBigToe", LEFT), ("LBigToe", "LSmallToe", LEFT),
    ("RHip", "LHip", MID), ("Pelvis", "Neck", MID), ("Neck", "Head", MID), ("Head", "Nose", MID),
    ("Neck", "RShoulder", RIGHT), ("RShoulder", "RElbow", RIGHT), ("RElbow", "RWrist", RIGHT),
    ("Neck", "LShoulder", LEFT), ("LShoulder", "LElbow", LEFT), ("LElbow", "LWrist", LEFT),
]


def read_frame(video: Path, index: int) -> np.ndarray:
    cap = cv2.VideoCapture(str(video))
    frame = None
    for _ in range(index + 1):
        ok, frame = cap.read()
        if not ok:
            raise SystemExit(f"{video}: fewer than {index + 1} frames")
    cap.release()
    return frame


def person_crop(uv: np.ndarray, frame_wh: tuple[int, int], aspect: float = 0.75) -> tuple[int, int, int, int]:
    """A box (x0, y0, x1, y1) around the keypoints ``uv (M, 2)`` with a margin, ``aspect`` = w / h, clipped."""
    lo, hi = uv.min(0), uv.max(0)
    centre, half = (lo + hi) / 2, (hi - lo) / 2 * 1.25 + 40
    half = np.maximum(half, [half[1] * aspect, half[0] / aspect])  # grow the short side to the aspect
    w, h = frame_wh
    half = np.minimum(half, [w / 2, h / 2])
    centre = np.clip(centre, half, [w - half[0], h - half[1]])
    x0, y0 = (centre - half).round().astype(int)
    x1, y1 = (centre + half).round().astype(int)
    return int(x0), int(y0), int(x1), int(y1)


def draw_view(frame: np.ndarray, uv: np.ndarray, names: list[str], label: str, height: int) -> np.ndarray:
    """Crop ``frame`` around the keypoints ``uv (M, 2)`` (full-resolution pixels), scale it to ``height`` and
    draw the keypoints and bones."""
    x0, y0, x1, y1 = person_crop(uv, (frame.shape[1], frame.shape[0]))
    scale = height / (y1 - y0)
    view = cv2.resize(frame[y0:y1, x0:x1], (round((x1 - x0) * scale), height), interpolation=cv2.INTER_AREA)
    pts = {n: (uv[i] - [x0, y0] + 0.5) * scale - 0.5 for i, n in enumerate(names)}  # pixel centres stay centres

    def px(p):
        return tuple(int(round(v * 16)) for v in p)  # 4 fractional bits for sub-pixel anti-aliased drawing

    for a, b, colour in BONES:
        cv2.line(view, px(pts[a]), px(pts[b]), colour, 2, cv2.LINE_AA, shift=4)
    for p in pts.values():
        cv2.circle(view, px(p), 3 * 16, (255, 255, 255), -1, cv2.LINE_AA, shift=4)
        cv2.circle(view, px(p), 3 * 16, (0, 0, 0), 1, cv2.LINE_AA, shift=4)
    (tw, th), _ = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, 0.45, 1)
    cv2.rectangle(view, (0, 0), (tw + 10, th + 12), (0, 0, 0), -1)
    cv2.putText(view, label, (5, th + 5), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
    return view


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DATA, help="pose2sim_demo folder")
    parser.add_argument("--frame", type=int, default=50, help="frame index (0..99)")
    parser.add_argument("--calibration", default="Calib_qualisys_pose2sim.toml",
                        help="file in DATA/calibration (Calib_qualisys_pose2sim.toml or Calib.qca.txt)")
    parser.add_argument("--height", type=int, default=360, help="height of each view in the picture (px)")
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "images" / "pose2sim_overlay.png")
    args = parser.parse_args(argv)

    rig = load_calibration(args.data / "calibration" / args.calibration, dtype=torch.float64)
    trc = read_trc(args.data / TRC)
    names, xyz = trc.marker_names, trc.positions
    world = torch.from_numpy(xyz[args.frame][:, [2, 0, 1]].copy())  # TRC Y-up -> world Z-up, (21, 3)
    pelvis = (world[names.index("RHip")] + world[names.index("LHip")]) / 2
    world = torch.cat([world, pelvis[None]])
    names = names + ["Pelvis"]
    uv, valid = rig.project(world)  # (C, 22, 2), (C, 22)

    views = []
    for c, cam in enumerate(rig.names):
        video = args.data / "videos" / f"{cam.replace('_', '')}.mp4"  # calibration cam_0N -> video cam0N
        frame = read_frame(video, args.frame)
        label = f"{cam} frame {args.frame}: {int(valid[c].sum())}/{len(names)} in view"
        views.append(draw_view(frame, uv[c].numpy(), names, label, args.height))
    picture = np.hstack(views) & 0xF8  # 5 bits per channel: invisible here, and the PNG is half the size
    with atomic_path(args.out, suffix=".png") as tmp:
        if not cv2.imwrite(str(tmp), picture, [cv2.IMWRITE_PNG_COMPRESSION, 9]):
            raise SystemExit(f"could not write {args.out}")
    print(f"wrote {args.out} ({picture.shape[1]}x{picture.shape[0]}, {args.out.stat().st_size // 1024} KiB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
