#!/usr/bin/env python
"""Picture of one tracked frame: every camera's image with the pose's skeleton drawn over it, tiled.

Usage: .venv/bin/python scripts/pose_picture.py SEQ POSES.npz OUT.jpg [--frame N] [--scale 0.5] [--columns 4] [--crop]
(default frame: the valid frame of median landmark error when SEQ has a gt.npz, else the middle valid frame)
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from torchtrack.io.poses import load_poses
from torchtrack.io.sequence import SequenceFolder
from torchtrack.tracking.draw import draw_pose_overlays


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("seq", type=Path)
    ap.add_argument("poses", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--frame", type=int, default=None)
    ap.add_argument("--scale", type=float, default=0.5)
    ap.add_argument("--columns", type=int, default=4)
    ap.add_argument("--crop", action="store_true", help="cut every view to the subject")
    ap.add_argument("--crop-size", type=int, default=360, help="height of a cropped view in pixels")
    args = ap.parse_args()
    import cv2

    folder = SequenceFolder(args.seq)
    poses = load_poses(args.poses)
    ok = np.flatnonzero(poses.valid)
    if ok.size == 0:
        raise SystemExit(f"{args.poses}: no valid frame")
    k = None
    if args.frame is not None:
        hits = np.flatnonzero(poses.frame_index == args.frame)
        if hits.size == 0:
            raise SystemExit(f"{args.poses}: no frame {args.frame}")
        k = int(hits[0])
    elif (args.seq / "gt.npz").is_file():
        from torchtrack.eval import evaluate

        rep = evaluate(poses, load_poses(args.seq / "gt.npz"))
        t_med = int(rep.frame_index[np.argsort(rep.per_frame_mm)[len(rep.per_frame_mm) // 2]])
        k = int(np.flatnonzero(poses.frame_index == t_med)[0])
    else:
        k = int(ok[len(ok) // 2])
    t = int(poses.frame_index[k])
    W, H = (int(round(float(v) * args.scale)) for v in folder.rig.image_size_wh[0])
    rig = folder.rig.resized(W, H).float()
    img = torch.nan_to_num(folder.read_frame(t, size_wh=(W, H)))
    drawn = draw_pose_overlays(img, rig, torch.as_tensor(poses.landmarks()[k]))
    tiles = [np.ascontiguousarray((d.permute(1, 2, 0).numpy() * 255).astype(np.uint8)[..., ::-1]) for d in drawn]
    if args.crop:  # each view cut to the projected skeleton plus a margin, all at one size
        uv, valid = rig.project(torch.as_tensor(poses.landmarks()[k]).float())
        cut = []
        for c, tile in enumerate(tiles):
            p = uv[c][valid[c]].numpy()
            if len(p) < 2:
                cut.append(cv2.resize(tile, (args.crop_size // 2, args.crop_size)))
                continue
            (u0, v0), (u1, v1) = p.min(0), p.max(0)
            h = (v1 - v0) * 1.5 + 20
            cu, cv_ = (u0 + u1) / 2, (v0 + v1) / 2
            top, left = int(max(cv_ - h / 2, 0)), int(max(cu - h / 4, 0))
            crop = tile[top:int(min(cv_ + h / 2, H)), left:int(min(cu + h / 4, W))]
            cut.append(cv2.resize(crop, (args.crop_size // 2, args.crop_size)))
        tiles = cut
    for tile, name in zip(tiles, rig.names):
        cv2.putText(tile, name, (6, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (255, 255, 255), 1, cv2.LINE_AA)
    while len(tiles) % args.columns:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.concatenate(tiles[i:i + args.columns], axis=1) for i in range(0, len(tiles), args.columns)]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(args.out), np.concatenate(rows, axis=0), [cv2.IMWRITE_JPEG_QUALITY, 85])
    print(f"frame {t}: landmarks drawn over {len(drawn)} views")


if __name__ == "__main__":
    main()
