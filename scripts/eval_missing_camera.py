"""How much a camera that ends early or stops decoding costs a track: a synthetic 8-camera walk tracked with the
full rig, with one camera's frames cut after a third of the sequence (PNG frames deleted), and with that camera
as an AVI cut in half (it opens, and its second half does not decode). Prints, per case, the frames the camera
was left out of, the mean distance of those frames' landmarks from the full rig's track and the MPJPE of those
frames against the ground truth.

    .venv/bin/python scripts/eval_missing_camera.py [--out out/missing_camera] [--cameras 8] [--camera 2]
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
from pathlib import Path

import cv2
import numpy as np

from torchtrack.cli import main as torchtrack
from torchtrack.io.poses import load_poses
from torchtrack.io.video import write_video
from torchtrack.io.outputs import script_work_folder
from torchtrack.synth.scene import SceneConfig
from torchtrack.synth.sequence import RigConfig, SynthConfig, write_sequence

TRACK = ["--log-every", "0", "--refit-passes", "0"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("out/missing_camera"),
                    help="work folder: new, empty, or this script's earlier one (replaced)")
    ap.add_argument("--cameras", type=int, default=8, help="cameras on the ring (default: 8)")
    ap.add_argument("--camera", type=int, default=2, help="the camera that fails (default: 2)")
    ap.add_argument("--duration", type=float, default=2.0, help="seconds of walk after the start (default: 2)")
    args = ap.parse_args()
    script_work_folder(args.out, "eval_missing_camera")
    cfg = SynthConfig(motion="walk", duration_s=args.duration, starfish_s=0.2, fps=20, background_frames=4,
                      video_format="png", rig=RigConfig(num_cameras=args.cameras, width=320, height=240),
                      scene=dataclasses.replace(SceneConfig(), noise_std=1 / 255))
    seq = write_sequence(cfg, args.out / "seq", progress=False)
    cam = f"cam{args.camera}"
    files = sorted((seq / "video" / cam).glob("*.png"))
    T = len(files)

    short = args.out / "short"
    shutil.copytree(seq, short)
    for f in sorted((short / "video" / cam).glob("*.png"))[T // 3:]:
        f.unlink()
    cut = args.out / "cut"
    shutil.copytree(seq, cut)
    frames = [cv2.cvtColor(cv2.imread(str(f)), cv2.COLOR_BGR2RGB) for f in files]
    shutil.rmtree(cut / "video" / cam)
    avi = cut / "video" / f"{cam}.avi"
    write_video(avi, frames, fps=cfg.fps, fourccs=["MJPG"])
    avi.write_bytes(avi.read_bytes()[: avi.stat().st_size // 2])

    tracks = {}
    for name, folder in (("full", seq), ("short", short), ("cut", cut)):
        assert torchtrack(["track", str(folder), "--out", str(args.out / f"track_{name}"), *TRACK]) == 0
        tracks[name] = load_poses(args.out / f"track_{name}" / "poses.npz")
    gt = load_poses(seq / "gt.npz").landmarks()
    full = tracks["full"]
    print(f"\n{args.cameras} cameras, {T} frames, camera {cam} fails (`--refit-passes 0`)")
    print("case   frames without it   valid   from full rig (mm)   MPJPE there (mm)   full rig there (mm)")
    for name in ("short", "cut"):
        p = tracks[name]
        gone = ~p.extra["cameras_valid"][:, args.camera]
        d = 1e3 * np.linalg.norm(p.landmarks()[gone] - full.landmarks()[gone], axis=-1).mean()
        e = 1e3 * np.linalg.norm(p.landmarks()[gone] - gt[gone], axis=-1).mean()
        f = 1e3 * np.linalg.norm(full.landmarks()[gone] - gt[gone], axis=-1).mean()
        print(f"{name:<6} {int(gone.sum()):>17}   {int(p.valid.sum()):>3}/{T}   {d:>18.1f}   {e:>16.1f}   {f:>19.1f}")


if __name__ == "__main__":
    main()
