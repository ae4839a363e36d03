#!/usr/bin/env python
"""Tile one frame of every camera of a sequence folder with its ground-truth skeleton projected on it.

Usage: .venv/bin/python scripts/synth_preview.py SEQ OUT.png [--frame N] [--cols 4] [--width 320]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
import torch

from torchtrack.cameras import load_calibration
from torchtrack.conventions import LANDMARK_EDGES
from torchtrack.io.poses import load_poses
from torchtrack.io.sequence import SequenceFolder


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("seq", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--frame", type=int, default=None, help="frame to show (default: the middle one)")
    ap.add_argument("--cols", type=int, default=4)
    ap.add_argument("--width", type=int, default=320, help="width of each tile in pixels")
    args = ap.parse_args()
    rig = load_calibration(args.seq / "calibration.toml").double()
    gt = load_poses(args.seq / "gt.npz")
    with SequenceFolder(args.seq, rig) as folder:
        t = folder.num_frames // 2 if args.frame is None else args.frame
        images = folder.read_frame(t)  # (C, 3, H, W)
    uv, valid = rig.project(torch.from_numpy(gt.landmarks()[t]).double())  # (C, 16, 2)
    tiles = []
    for c in range(rig.num_cameras):
        img = np.ascontiguousarray((images[c].permute(1, 2, 0).numpy() * 255).astype(np.uint8)[..., ::-1])
        s = args.width / img.shape[1]
        img = cv2.resize(img, (args.width, round(img.shape[0] * s)), interpolation=cv2.INTER_AREA)
        p = (uv[c].numpy() * s).round().astype(int)
        for a, b in LANDMARK_EDGES:
            if valid[c, a] and valid[c, b]:
                cv2.line(img, tuple(p[a]), tuple(p[b]), (255, 255, 255), 1, cv2.LINE_AA)
        for j in range(p.shape[0]):
            if valid[c, j]:
                cv2.circle(img, tuple(p[j]), 2, (0, 0, 0), -1, cv2.LINE_AA)
        cv2.putText(img, rig.names[c], (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(img)
    while len(tiles) % args.cols:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.concatenate(tiles[i:i + args.cols], axis=1) for i in range(0, len(tiles), args.cols)]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(args.out), np.concatenate(rows, axis=0))
    print(f"wrote {args.out} (frame {t})")


if __name__ == "__main__":
    main()
