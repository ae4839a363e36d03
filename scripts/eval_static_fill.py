#!/usr/bin/env python
"""What painting the static subject out of an estimated background brings, and costs, on synthetic scenes.

For each motion: a short sequence seen by three 128x96 cameras, the background estimated from its frames
(temporal median, second pass) with and without ``fill_static_subject``, and, as the reference, the model of
the empty-scene frames. Prints per camera the silhouette IoU and recall of ``mahalanobis2 > 16`` against the
true silhouettes (re-rendered without noise). arm_raise and squat stay in place (the median keeps the subject);
walk moves through the scene (the median is clean).

Usage: .venv/bin/python scripts/eval_static_fill.py [--motions arm_raise squat walk]
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
from pathlib import Path

import numpy as np
import torch

from torchtrack.background import FOREGROUND_MAHALANOBIS2, BackgroundConfig, BackgroundModel
from torchtrack.io.sequence import SequenceFolder
from torchtrack.synth.scene import SceneConfig, SceneRenderer
from torchtrack.synth.sequence import RigConfig, SynthConfig, make_ring_rig, write_sequence


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--motions", nargs="+", default=["arm_raise", "squat", "walk"])
    args = ap.parse_args()
    torch.set_grad_enabled(False)
    scene = SceneConfig()
    for motion in args.motions:
        cfg = SynthConfig(motion=motion, duration_s=3.0, starfish_s=0.3, fps=6, background_frames=10,
                          video_format="png", rig=RigConfig(num_cameras=3, width=128, height=96), scene=scene)
        with tempfile.TemporaryDirectory() as tmp:
            root = write_sequence(cfg, Path(tmp) / "seq", progress=False)
            folder = SequenceFolder(root)
            frames = torch.cat([b.images for b in folder.iter_batches(64)])  # (T, C, 3, H, W)
            gt = np.load(root / "gt.npz")
            renderer = SceneRenderer(make_ring_rig(cfg.rig).float(), dataclasses.replace(scene, noise_std=0.0))
            sil = torch.stack([renderer.render(
                torch.from_numpy(gt["blob_centres"][t]), torch.from_numpy(gt["blob_R_world"][t]),
                torch.from_numpy(gt["blob_semi_axes"]), torch.full((len(gt["blob_semi_axes"]), 3), 0.5),
                frame=t, num_frames=len(frames))[1] for t in range(len(frames))])  # (T, C, H, W)
            models = {"empty-scene frames": BackgroundModel.from_frames(folder.background_frames(60)),
                      "median": BackgroundModel.from_sequence(frames),
                      "median, static subject painted out": BackgroundModel.from_sequence(
                          frames, BackgroundConfig(fill_static_subject=True))}
        print(f"{motion} ({len(frames)} frames, 3 cameras 128x96)")
        for name, model in models.items():
            fg = model.mahalanobis2(frames) > FOREGROUND_MAHALANOBIS2
            inter = (fg & sil).sum((0, 2, 3))
            iou, recall = inter / (fg | sil).sum((0, 2, 3)), inter / sil.sum((0, 2, 3))
            print(f"  {name:36s} IoU {' '.join(f'{v:.2f}' for v in iou.tolist())} (mean {float(iou.mean()):.2f})"
                  f"   recall {' '.join(f'{v:.2f}' for v in recall.tolist())}")


if __name__ == "__main__":
    main()
