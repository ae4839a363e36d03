#!/usr/bin/env python
"""Occupancy quality on synthetic sequences: IoU with the ground-truth body volume and phantom components.

Renders (or reuses, under --work) synthetic sequences, builds the background model from their background/
frames and runs the Bayesian grid (P > 0.5), the hierarchical hull and binary silhouette carving at
--voxel metres; prints per configuration the mean/min IoU over the evaluated frames and the largest
connected component that touches no part of the body (its voxels and extent).

Usage: .venv/bin/python scripts/eval_occupancy.py [--voxel 0.02] [--frames 6] [--work out/eval_occupancy]
       [--hull FIELD=VALUE ...] [--background FIELD=VALUE ...]   (e.g. --background shadow_min_ratio=0)
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from torchtrack.background import BackgroundConfig, BackgroundModel
from torchtrack.cameras import load_calibration
from torchtrack.io.sequence import SequenceFolder
from torchtrack.checks import InputError, with_overrides
from torchtrack.occupancy import BayesConfig, BayesianGrid, GridSpec, SilhouetteCarving
from torchtrack.occupancy.hull import HierarchicalHull, HullConfig
from torchtrack.occupancy.metrics import false_components, inside_ellipsoids, iou
from torchtrack.synth.scene import SceneConfig
from torchtrack.synth.sequence import RigConfig, SynthConfig, is_current, write_sequence

VOLUME = ((-1.3, -1.3, 0.0), (1.3, 1.3, 2.1))  # the synthetic motions stay within ~1.1 m of the origin

CASES = {
    "8cam": dict(cams=8, scene={}),
    "4cam": dict(cams=4, scene={}),
    "8cam+shadow+illum+distractor": dict(cams=8, scene=dict(shadow=True, illumination_change=0.25,
                                                            distractor=True)),
}


def ensure_sequence(work: Path, name: str, cams: int, scene: dict, motion: str, fmt: str) -> Path:
    out = work / f"{name}_{motion}_{fmt}"
    cfg = SynthConfig(motion=motion, duration_s=1.0, starfish_s=0.5, fps=15, background_frames=10,
                      video_format=fmt, rig=RigConfig(num_cameras=cams),
                      scene=dataclasses.replace(SceneConfig(), **scene))
    if not is_current(out, cfg):
        write_sequence(cfg, out)
    return out


def evaluate(seq: Path, voxel: float, frames: int, hull_overrides: Sequence[str] = (),
             background: BackgroundConfig = BackgroundConfig(), bayes: BayesConfig = BayesConfig()
             ) -> dict[str, tuple[list[float], list]]:
    rig = load_calibration(seq / "calibration.toml")
    folder = SequenceFolder(seq, rig)
    bg = BackgroundModel.from_folder(folder, background)
    spec = GridSpec(VOLUME[0], VOLUME[1], voxel)
    gt = np.load(seq / "gt.npz")
    centres_v = spec.centres()
    models = {"bayes": BayesianGrid(rig, spec, bg, bayes), "silhouette": SilhouetteCarving(rig, spec, bg)}
    hull = HierarchicalHull(rig, with_overrides(HullConfig(lower_m=VOLUME[0], upper_m=VOLUME[1],
                                                           finest_voxel_m=voxel), hull_overrides, "--hull"))
    res: dict[str, tuple[list[float], list]] = {k: ([], []) for k in (*models, "hull")}
    idx = np.linspace(0, folder.num_frames - 1, frames).round().astype(int)
    for t in idx:
        images = folder.read_frame(int(t))[None]
        truth = inside_ellipsoids(centres_v, torch.from_numpy(gt["blob_centres"][t]),
                                  torch.from_numpy(gt["blob_R_world"][t]), torch.from_numpy(gt["blob_semi_axes"]))
        preds = {k: m(images).occupied()[0] for k, m in models.items()}
        vox = hull.from_images(bg, images[0])
        preds["hull"] = vox.to_dense(spec.lower_m, spec.voxel_size_m, spec.shape).reshape(-1)
        for k, pred in preds.items():
            res[k][0].append(iou(pred, truth))
            res[k][1].append(false_components(pred, truth, spec))
    return {k: v for k, v in res.items() if v[0]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--voxel", type=float, default=0.02)
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--motion", default="walk")
    ap.add_argument("--work", type=Path, default=Path("out/eval_occupancy"))
    ap.add_argument("--format", choices=("png", "mp4"), default="png",
                    help="png: lossless frames; mp4: OpenCV's mp4v codec, whose blur at edges costs IoU")
    ap.add_argument("--hull", nargs="*", default=[], metavar="FIELD=VALUE",
                    help="HullConfig overrides, e.g. t_low=3 t_high=8 t_finest_edge=8 (the tracking settings)")
    ap.add_argument("--background", nargs="*", default=[], metavar="FIELD=VALUE",
                    help="BackgroundConfig overrides, e.g. shadow_min_ratio=0 (the paper's plain relaxation)")
    ap.add_argument("--bayes", nargs="*", default=[], metavar="FIELD=VALUE",
                    help="BayesConfig overrides of the grid's sensor model, e.g. pd=0.95 (the tracking's on 7+ cameras)")
    args = ap.parse_args()
    try:
        with_overrides(HullConfig(), args.hull, "--hull")
        background = with_overrides(BackgroundConfig(), args.background, "--background")
        bayes = with_overrides(BayesConfig(), args.bayes, "--bayes")
    except InputError as exc:
        raise SystemExit(str(exc)) from None
    torch.set_grad_enabled(False)
    for name, case in CASES.items():
        seq = ensure_sequence(args.work, name, case["cams"], case["scene"], args.motion, args.format)
        t0 = time.perf_counter()
        results = evaluate(seq, args.voxel, args.frames, args.hull, background, bayes)
        for model, (ious, comps) in results.items():
            worst = max(comps, key=lambda c: c.largest_voxels)
            print(f"{name:32s} {model:10s} IoU mean {np.mean(ious):.3f} min {np.min(ious):.3f}   "
                  f"largest false component {worst.largest_voxels} voxels ({worst.largest_extent_m:.2f} m), "
                  f"false components per frame {np.mean([c.count for c in comps]):.1f}")
        print(f"    ({args.frames} frames of {seq}, {time.perf_counter() - t0:.1f} s)")


if __name__ == "__main__":
    main()
