"""Marker capture from video: the colour detector against the rendered balls, then the marker tracker on its output.

Each case renders `torchtrack synth --markers` video (a motion, a rig, a ball colour, lighting), learns the colour and
links the detections from frame 0's labels (`torchtrack detect`), tracks them (`torchtrack track --mode
markers`) and scores:
- the detector against the renderer's labelled pixels (every 5th frame): the share of balls that touch no other in the
  image found within 1.5 px of their visible pixels' centre, the mean distance of those, false detections per view
  (farther than 6 px from every ball);
- the labelling: the share of balls showing at least 4 pixels whose first candidate is within 3 px of them;
- the track: MMTA (50 mm) and MMTP against the balls' true centres, frames lost, seconds per frame; and the MMTA
  and MMTP of the rigid body's markers alone (`markers3d_body`).

    .venv/bin/python scripts/eval_marker_video.py [--cases NAME ...] [--work out/eval_marker_video]
        [--apf FIELD=VALUE ...]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from torchtrack.checks import InputError, with_overrides  # noqa: E402
from torchtrack.eval.metrics import evaluate  # noqa: E402
from torchtrack.io.markers2d import save_markers2d  # noqa: E402
from torchtrack.io.outputs import script_work_folder  # noqa: E402
from torchtrack.io.poses import load_poses, save_poses  # noqa: E402
from torchtrack.io.sequence import SequenceFolder  # noqa: E402
from torchtrack.markers.detect import detect_blobs, detect_sequence, read_marker_labels  # noqa: E402
from torchtrack.markers.track import track_markers  # noqa: E402
from torchtrack.tracking.particles import APFConfig  # noqa: E402
from torchtrack.synth.markers import MarkerStyle  # noqa: E402
from torchtrack.synth.scene import SceneConfig  # noqa: E402
from torchtrack.synth.sequence import RigConfig, SynthConfig, is_current, write_sequence  # noqa: E402

BVH = REPO.parent / "shared" / "data" / "mocap" / "cmu" / "131_01.bvh"
YELLOW = MarkerStyle(colour=(1.0, 0.85, 0.05))
#: name -> the rendered sequence (2 s of motion after a 1 s starfish unless said).
CASES = {
    "walk_8": SynthConfig(motion="walk", markers=MarkerStyle()),
    "kick_8": SynthConfig(motion="kick", markers=MarkerStyle(), seed=1),
    "bvh_8_shadow": SynthConfig(motion=str(BVH), markers=MarkerStyle(), scene=SceneConfig(shadow=True, seed=2),
                                seed=2),
    "walk_8_yellow_light": SynthConfig(motion="walk", markers=YELLOW,
                                       scene=SceneConfig(illumination_change=0.25, seed=3), seed=3),
    "squat_6_small": SynthConfig(motion="squat", rig=RigConfig(num_cameras=6), markers=MarkerStyle(radius_m=0.015),
                                 seed=4),
    "turn_4": SynthConfig(motion="turn", rig=RigConfig(num_cameras=4), markers=MarkerStyle(), seed=5),
}


def detector_scores(folder: Path) -> tuple[float, float, float]:
    """Recall of isolated balls within 1.5 px, their mean error (px), false detections per view."""
    gt = np.load(folder / "gt.npz")
    labels = read_marker_labels(folder / "marker_labels.csv")
    seq = SequenceFolder(folder)
    model = labels.colour_model(seq.read_frame(labels.frame), seq.camera_names)
    hits, err, false = [], [], []
    for t in range(0, seq.num_frames, 5):
        for c, b in enumerate(detect_blobs(seq.read_frame(t), model)):
            px = gt["marker_pixels"][t, c]
            truth, r = gt["marker_uv"][t, c][px >= 4], np.sqrt(px[px >= 4] / np.pi)
            apart = np.linalg.norm(truth[:, None] - truth[None], axis=-1) + 1e9 * np.eye(len(truth))
            alone = apart.min(1) > 4 * r
            d = np.linalg.norm(truth[:, None] - b[None], axis=-1).reshape(len(truth), len(b))
            near = d.min(1) if len(b) else np.full(len(truth), np.inf)
            hits += list(near[alone] < 1.5)
            err += list(near[alone][near[alone] < 1.5])
            false.append(int((d.min(0) > 6).sum()) if len(truth) else len(b))
    seq.close()
    return float(np.mean(hits)), float(np.mean(err)), float(np.mean(false))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    ap.add_argument("--duration", type=float, default=2.0, help="seconds of motion after the starfish (default: 2)")
    ap.add_argument("--work", type=Path, default=Path("out/eval_marker_video"), help="rendered sequences, tracks")
    ap.add_argument("--apf", nargs="*", default=[], metavar="FIELD=VALUE",
                    help="the filter's settings (APFConfig fields), e.g. outlier_rad=0.012 (default: as `track`)")
    args = ap.parse_args()
    try:
        apf = with_overrides(APFConfig(), args.apf, "--apf")
    except InputError as exc:
        ap.error(str(exc))
    torch.set_num_threads(1)
    work = script_work_folder(args.work, "eval_marker_video.py", empty=False)
    print(f"{'case':<20} {'frames':>6} {'found%':>7} {'err px':>6} {'false':>6} {'first%':>7} {'MMTA@50':>8} "
          f"{'MMTP mm':>8} {'lost':>5} {'s/frame':>8} {'body MMTA':>9} {'body MMTP':>9}")
    for name in args.cases:
        cfg = dataclasses.replace(CASES[name], duration_s=args.duration)
        folder = work / name
        if not is_current(folder, cfg):
            write_sequence(cfg, folder, progress=False)
        found, err, false = detector_scores(folder)
        labels = read_marker_labels(folder / "marker_labels.csv")
        data = detect_sequence(folder, labels, progress=False)
        save_markers2d(data, folder / "markers2d.npz")
        gt = np.load(folder / "gt.npz")
        idx = [list(gt["marker_names"]).index(n) for n in data.marker_names]
        seen = gt["marker_pixels"][:, :, idx] >= 4
        first = np.linalg.norm(data.uv[..., 0, :] - gt["marker_uv"][:, :, idx], axis=-1) < 3
        t0 = time.perf_counter()
        result = track_markers(folder, apf, progress=False)
        seconds = time.perf_counter() - t0
        save_poses(result.poses, folder / "poses.npz")
        truth = load_poses(folder / "gt.npz")
        rep = evaluate(result.poses, truth)
        m, T = rep.markers, result.poses.num_frames
        body_markers = result.poses.extra["markers3d_body"]
        body = evaluate(dataclasses.replace(result.poses, markers3d=body_markers), truth).markers
        print(f"{name:<20} {T:>6} {100 * found:>6.1f}% {err:>6.2f} {false:>6.2f} {100 * first[seen].mean():>6.1f}% "
              f"{100 * m.mmta:>7.2f}% {m.mmtp_mm:>8.1f} {rep.frames_lost:>5} {seconds / T:>8.2f} "
              f"{100 * body.mmta:>8.2f}% {body.mmtp_mm:>9.1f}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
