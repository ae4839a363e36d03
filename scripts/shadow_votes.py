#!/usr/bin/env python
"""The shadow test in the Bayesian grid's floor layer, voxel by voxel, on one frame of a stress-table sequence.

For the floor layer's voxels that the grid occupies without the shadow test, grouped by their distance from the
true feet (ankles and toes: near < 0.12 m, between, away > 0.3 m, i.e. a shadow's ghost), prints how many of
them each rule keeps: every camera's shadow taken (``shadow_min_share: 0``) and the cameras' vote at several
shares (``BayesConfig.shadow_min_share``), with the share of the cameras seeing foreground that see a shadow
(quartiles). The sequence is rendered by scripts/eval_robustness.py first.

Usage: .venv/bin/python scripts/shadow_votes.py CASE [CASE ...] [--frame 0] [--work out/eval_robustness]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from torchtrack.background import BackgroundConfig, BackgroundModel
from torchtrack.io.poses import load_poses
from torchtrack.io.sequence import SequenceFolder
from torchtrack.occupancy.bayes import shadow_votes
from torchtrack.tracking.pipeline import load_config, observer_from_config

SHARES = (0.0, 0.5, 0.67)
NEAR_M, AWAY_M = 0.12, 0.3


def votes(seq: Path, frame: int) -> None:
    folder = SequenceFolder(seq)
    cfg = load_config("markerless")
    bg_config = BackgroundConfig(**{**cfg["background"], "shadow_min_gain": 0.4})
    W, H = (int(v) for v in folder.rig.image_size_wh[0])
    bg = BackgroundModel.from_folder(folder, bg_config, size_wh=(W, H), progress=False)
    grid = observer_from_config(folder.rig.float(), bg, cfg["observation"], "bayes", 0.03).grid
    lit, shadowed, _ = bg.log_likelihood_and_yuv(folder.read_frame(frame)[None], shadows=True)
    ev_lit, ev_sh = grid.floor_evidence(lit)[0], grid.floor_evidence(shadowed)[0]  # (C, L) each
    votes, seeing = shadow_votes(ev_lit[None], ev_sh[None])
    share = votes[0] / seeing[0].clamp(min=1)  # (L,)
    occupied = ev_lit.sum(0) > 0  # the prior is even: log odds > 0
    gt = load_poses(seq / "gt.npz")
    feet = [i for i, n in enumerate(gt.joint_names) if "ankle" in n or "toe" in n]
    centres = grid.spec.centres(dtype=torch.float32)[grid.floor_index]
    dist = torch.cdist(centres.float(), torch.from_numpy(gt.joints3d[frame, feet]).float()).amin(1)
    groups = {"near feet": dist < NEAR_M, "between": (dist >= NEAR_M) & (dist <= AWAY_M), "away": dist > AWAY_M}
    print(f"{seq.name} frame {frame}: floor-layer voxels occupied without the shadow test, kept by each rule")
    print(f"  {'group':<10} {'occupied':>8}  " + "  ".join(f"share>={s:<4}" for s in SHARES)
          + "  shadow share (quartiles)")
    for name, mask in groups.items():
        m = mask & occupied
        # a voxel takes the shadow's evidence where its share reaches s, and is kept where that is positive
        kept = [int((m & ((share < s) | (ev_sh.sum(0) > 0))).sum()) for s in SHARES]
        q = share[m].quantile(torch.tensor([0.25, 0.5, 0.75])).tolist() if m.any() else []
        print(f"  {name:<10} {int(m.sum()):>8}  " + "  ".join(f"{k:>10}" for k in kept)
              + "  " + " / ".join(f"{v:.2f}" for v in q))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("cases", nargs="+", help="stress-table case names (scripts/eval_robustness.py)")
    ap.add_argument("--frame", type=int, default=0, help="frame index (default: 0)")
    ap.add_argument("--work", type=Path, default=Path("out/eval_robustness"), help="rendered sequences")
    args = ap.parse_args()
    for case in args.cases:
        votes(args.work / case, args.frame)


if __name__ == "__main__":
    main()
