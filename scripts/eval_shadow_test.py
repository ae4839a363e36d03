#!/usr/bin/env python
"""What the background's shadow test brings, and costs, on the track: one short walk with dark grey shoes on the
patterned grey floor (the template's colours), rendered without and with a floor shadow.

Each sequence (8 cameras at 320x240, 20 fps, 1.2 s) is tracked as `torchtrack track` tracks it (default config,
no body refit) with the shadow test off (``shadow_min_gain: 1``, the default), by colour alone
(``shadow_min_gain: 0.4``, ``shadow_min_ncc: 0``) and by colour and texture (``shadow_min_ncc: 0.7``). Prints
MPJPE over the 16 landmarks and the ankles' mean error (mm) on the valid frames, and the invalid ones: without a
shadow the test can only take the dark shoes away; with one it should take the shadow's ghost away.

Usage: .venv/bin/python scripts/eval_shadow_test.py [--work out/eval_shadow_test]
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np

from torchtrack.conventions import LANDMARKS
from torchtrack.io.outputs import script_work_folder
from torchtrack.io.poses import load_poses
from torchtrack.synth.scene import SceneConfig
from torchtrack.synth.sequence import RigConfig, SynthConfig, is_current, write_sequence
from torchtrack.tracking.pipeline import load_config, track

SETTINGS = (("off", {"shadow_min_gain": 1.0}), ("colour alone", {"shadow_min_gain": 0.4, "shadow_min_ncc": 0.0}),
            ("colour and texture", {"shadow_min_gain": 0.4, "shadow_min_ncc": 0.7}))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, default=Path("out/eval_shadow_test"), help="rendered sequences")
    args = ap.parse_args()
    work = script_work_folder(args.work, "eval_shadow_test.py", empty=False)
    ankles = [i for i, n in enumerate(LANDMARKS) if "ankle" in n]
    print(f"{'sequence':<12} {'shadow test':<20} {'MPJPE mm':>9} {'ankles mm':>10} {'invalid':>8}")
    for shadow in (False, True):
        name = "shadow" if shadow else "no_shadow"
        cfg = SynthConfig(motion="walk", duration_s=1.2, starfish_s=0.2, fps=20, background_frames=4,
                          video_format="png", rig=RigConfig(num_cameras=8, width=320, height=240),
                          scene=dataclasses.replace(SceneConfig(), noise_std=1 / 255, shadow=shadow))
        seq = work / name
        if not is_current(seq, cfg):
            write_sequence(cfg, seq, progress=False)
        gt = load_poses(seq / "gt.npz")
        for label, background in SETTINGS:
            config = load_config("markerless.yaml")
            config["background"] = {**config["background"], **background}
            poses = track(seq, config=config, refit_passes=0, progress=False).poses
            err = np.linalg.norm(poses.landmarks() - gt.landmarks()[poses.frame_index], axis=-1)[poses.valid]
            print(f"{name:<12} {label:<20} {1e3 * err.mean():>9.1f} {1e3 * err[:, ankles].mean():>10.1f} "
                  f"{int((~poses.valid).sum()):>4}/{poses.num_frames}", flush=True)


if __name__ == "__main__":
    main()
