#!/usr/bin/env python
"""What the automatic initialisation measures of its starfish fit, on the synthetic starts and the real demo.

The initialisation refuses a first frame whose voxels hold more than ``STARFISH_MAX_VOLUME_RATIO`` times the
volume of a body as tall as they are, or whose fitted upper arms hang within ``STARFISH_MIN_ARM_RAISE_DEG`` of
straight down (or whose arm blobs find no voxels). This prints those measures (``MarkerlessTracker.start_check``)
for the first frame of every synthetic sequence of ``scripts/eval_tracking.py`` (rendered once under --work,
each a 0.5 s starfish then the motion) with both observation models, and for the Pose2Sim demo, which does not
start in the starfish pose, on its estimated background with and without the static-subject fill. The
thresholds must sit between the two groups. It also prints how far the toes lie ahead of the body's centre, and
where that leaves the heading to the fit (``HEADING_MARGIN_M``), each heading tried and its cost; for an accepted
synthetic start, how far the heading kept is from the true one.

    .venv/bin/python scripts/starfish_checks.py [--motions walk squat ...] [--cameras 8 4] [--work out/eval_tracking]
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import tempfile
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from eval_tracking import MOTIONS, sequence  # noqa: E402

from torchtrack.background import BackgroundConfig, BackgroundModel  # noqa: E402
from torchtrack.checks import InputError  # noqa: E402
from torchtrack.io.poses import load_poses  # noqa: E402
from torchtrack.io.sequence import SequenceFolder  # noqa: E402
from torchtrack.skeleton import Skeleton  # noqa: E402
from torchtrack.tracking.pipeline import load_config, observer_from_config  # noqa: E402
from torchtrack.tracking.markerless import (STARFISH_MAX_VOLUME_RATIO, STARFISH_MIN_ARM_RAISE_DEG,  # noqa: E402
                                            MarkerlessTracker, TrackerConfig)

DEMO = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "pose2sim_demo"


def first_frame(folder: SequenceFolder, scale: float, model: str, config: dict, fill: bool) -> str:
    """Initialise on ``folder``'s first frame; one line with the measures and the verdict."""
    W, H = (int(round(float(v) * scale)) for v in folder.rig.image_size_wh[0])
    rig = folder.rig.resized(W, H).float()
    bg = BackgroundModel.from_folder(folder, BackgroundConfig(fill_static_subject=fill), size_wh=(W, H))
    ocfg = config["observation"]
    obs = observer_from_config(rig, bg, ocfg, model, float(ocfg.get("voxel_m", 0.03)))(
        folder.read_frame(0, size_wh=(W, H))[None])[0]
    tracker = MarkerlessTracker(Skeleton.from_urdf(), TrackerConfig.from_dict(config["tracker"], config["source"]))
    try:
        tracker.step(obs)
        verdict = "accepted"
    except InputError as exc:
        verdict = "refused: " + str(exc).split(": ", 2)[-1].split(". Start", 1)[0][:70]
    c = tracker.start_check
    if c is None:  # refused before the fit (not as wide as a starfish)
        return f"{'':>6s} {'':>6s} {'':>13s} {'':>11s} {'':>5s}  {verdict}"
    if verdict == "accepted" and (folder.root / "gt.npz").is_file():  # the heading kept against the true one
        gt = load_poses(folder.root / "gt.npz")
        rz = list(gt.dof_names).index("root_rz")
        off = float(tracker.angles[rz]) - float(gt.angles[0, rz])
        verdict += f", heading {math.degrees(abs(math.remainder(off, 2 * math.pi))):.0f} deg off the true one"
    if len(c.headings) > 1:  # the fit decided between headings: each one's cost
        verdict += "; headings tried " + ", ".join(f"{h:.2f} rad {1e3 * cost:.1f} mm" for h, cost in c.headings)
    return (f"{c.height_m:6.2f} {c.volume_ratio:6.2f} {c.arm_raise_deg[0]:6.0f} {c.arm_raise_deg[1]:6.0f} "
            f"{c.arm_fill[0]:5.2f} {c.arm_fill[1]:5.2f} {100 * c.toe_ahead_m:5.1f}  {verdict}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--motions", nargs="+", default=list(MOTIONS))
    ap.add_argument("--cameras", nargs="+", type=int, default=[8, 4])
    ap.add_argument("--models", nargs="+", default=["bayes", "hull"])
    ap.add_argument("--work", type=Path, default=Path("out/eval_tracking"))
    ap.add_argument("--demo", type=Path, default=DEMO)
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)
    torch.set_grad_enabled(False)
    config = load_config("markerless.yaml")
    scale = float(config["observation"].get("scale", 1.0))
    print(f"limits: volume ratio <= {STARFISH_MAX_VOLUME_RATIO:g}, upper arms >= {STARFISH_MIN_ARM_RAISE_DEG:g} deg "
          f"from hanging, arm blob fill >= {config['tracker'].get('em', {}).get('min_fill', 0.2)}")
    print(f"{'first frame':28s} {'height':>6s} {'volume':>6s} {'arms (deg)':>13s} {'arm fill':>11s} {'toes':>5s}  "
          "verdict (toes: cm ahead of the centre; under 3 the fit decides between headings)")
    for motion in args.motions:
        for cams in args.cameras:
            seq = sequence(args.work, motion, cams, 3.0, "mp4")
            for model in args.models:
                line = first_frame(SequenceFolder(seq), scale, model, config, fill=False)
                print(f"{f'{motion} {cams} cams {model}':28s} {line}", flush=True)
    if not (args.demo / "videos").is_dir():
        print(f"{args.demo}: the Pose2Sim demo is not there; skipped")
        return
    from torchtrack.io.pose2sim import pose2sim_sequence

    with tempfile.TemporaryDirectory() as tmp:
        folder = SequenceFolder(pose2sim_sequence(args.demo, Path(tmp) / "seq"))
        for fill in (False, True):  # the real demo at the processing size of its evaluation (scale 0.25)
            line = first_frame(folder, 0.25, "bayes", config, fill=fill)
            print(f"{'pose2sim_demo, ' + ('fill' if fill else 'no fill'):28s} {line}", flush=True)


if __name__ == "__main__":
    main()
