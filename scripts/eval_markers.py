"""Marker-based tracking on simulated detections of real captures: MMTA, MMTP, landmark error per capture.

Each capture (real 3D markers from ../shared/data/mocap) is projected into the real 4-camera rig of the Pose2Sim
demo through the simulated detector (`torchtrack synth markers`) with the marker-based issue's corruption (p_miss
0.2, 0.1 false detections per view and frame, sigma 2 px) and without any, then tracked as `torchtrack track` does
(the subject from the detections alone) and scored as `torchtrack eval` does. Beside each row: the share of the
scored markers placed by their own triangulation (`measured`), and the MMTA and MMTP of the rigid body's markers
alone (`markers3d_body`).

With ``--seeds N`` each row is run N times, the detections and the filter drawn with seeds 0 to N - 1, and the
mean and the worst of the runs printed after them: the filter is chaotic, and one seed's MMTA moves by a few points.

With ``--ceiling`` each run also prints what the rigid body model can reach, whatever the filter does: the
tracker's subject (its marker set refitted along the final track, near the set the tracker's second track used)
posed by inverse kinematics on the true 3D markers (every marker; only those the frame's
detections show in two views or more), and a subject fitted on every frame's true markers, posed the same way.

    .venv/bin/python scripts/eval_markers.py [--captures NAME ...] [--fps 30] [--duration S] [--seeds N]
        [--apf FIELD=VALUE ...] [--ceiling]
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from torchtrack.checks import InputError, with_overrides  # noqa: E402
from torchtrack.cameras import load_calibration  # noqa: E402
from torchtrack.eval.metrics import evaluate  # noqa: E402
from torchtrack.io.outputs import script_work_folder  # noqa: E402
from torchtrack.io.poses import Poses, save_poses  # noqa: E402
from torchtrack.markers.capture import marker_scene, write_marker_capture  # noqa: E402
from torchtrack.markers.gaps import MEASURED, NONE  # noqa: E402
from torchtrack.markers.model import fit_poses_to_markers, subject_from_markers  # noqa: E402
from torchtrack.markers.simulate import DetectorModel  # noqa: E402
from torchtrack.markers.track import load_marker_sequence, refit_marker_set, track_markers  # noqa: E402
from torchtrack.tracking.particles import APFConfig  # noqa: E402

DATA = REPO.parent / "shared" / "data"
CAPTURES = {"cmu85_02": DATA / "mocap" / "cmu" / "85_02.c3d",
            "pig_motion": DATA / "mocap" / "btk" / "c3d" / "PiG_Motion-FlatFoot-Full.c3d"}
RIG = DATA / "pose2sim_demo" / "calibration" / "Calib_qualisys_pose2sim.toml"
SETTINGS = {"corrupted": DetectorModel(p_miss=0.2, false_rate=0.1, sigma_px=2.0),
            "clean": DetectorModel(p_miss=0.0, false_rate=0.0, sigma_px=0.0)}


def ceilings(folder: Path, tracked: Poses, truth: Poses, apf: APFConfig) -> list[tuple[str, float, float]]:
    """(what, MMTA %, MMTP mm) of the rigid body model's best fits to the true 3D markers (``--ceiling``), each
    pose started from the track's and scored as the track is (:func:`evaluate`). The tracker's subject: its first
    fit, and the refit along the track where ``apf.refit_m`` asks for it (near the one the track used)."""
    s = load_marker_sequence(folder)
    if apf.refit_m > 0:
        try:
            s = refit_marker_set(s, tracked, apf.refit_m)
        except InputError as exc:  # as the tracker, the first fit stays
            print(f"  (the marker set not refitted: {exc})")
    names = [s.det.marker_names[i] for i in s.keep.tolist()]
    X = torch.from_numpy(truth.markers3d[:, [list(truth.marker_names).index(n) for n in names]]).double()
    start = torch.from_numpy(tracked.angles).double()
    views = torch.isfinite(s.z[:, :, s.keep]).all(-1).any(-1).sum(1)  # (T, M) views with a candidate
    fits = [("the tracker's subject on every true marker", s.skeleton, s.marker_set, X),
            ("on the true markers two views show", s.skeleton, s.marker_set,
             torch.where((views >= 2)[..., None], X, math.nan))]
    try:
        skel, mset, _ = subject_from_markers(X, names, tracked.fps, source=f"{folder}: the true markers")
        fits.append(("a subject fitted on every frame's true markers", skel, mset, X))
    except InputError as exc:  # markers that do not give every joint centre: the other two still tell
        print(f"  (no subject from the true markers: {exc})")
    out = []
    for what, skel, mset, target in fits:
        with torch.no_grad():
            A = fit_poses_to_markers(skel, mset, start, target, iterations=400).detach()
            markers = np.full(tracked.markers3d.shape, np.nan, dtype=np.float32)
            markers[:, s.keep.numpy()] = mset.positions(skel.forward(A).bone_frames).float().numpy()
        m = evaluate(replace(tracked, markers3d=markers), truth).markers
        out.append((what, 100 * m.mmta, m.mmtp_mm))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--captures", nargs="+", default=list(CAPTURES), choices=list(CAPTURES))
    ap.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=list(SETTINGS))
    ap.add_argument("--fps", type=float, default=30.0, help="frame rate the captures are resampled to (default: 30)")
    ap.add_argument("--duration", type=float, default=None, help="seconds of each capture (default: all)")
    ap.add_argument("--work", type=Path, default=Path("out/eval_markers"), help="simulated captures and tracks")
    ap.add_argument("--seeds", type=int, default=1, help="runs of each row, seeds 0 to N - 1 (default: 1)")
    ap.add_argument("--apf", nargs="*", default=[], metavar="FIELD=VALUE",
                    help="the filter's settings (APFConfig fields), e.g. outlier_rad=0.012 (default: as `track`)")
    ap.add_argument("--ceiling", action="store_true",
                    help="also print the rigid body model's best fits to the true 3D markers (see above)")
    args = ap.parse_args()
    try:
        apf = with_overrides(APFConfig(), args.apf, "--apf")
    except InputError as exc:
        ap.error(str(exc))
    torch.set_num_threads(1)
    work = script_work_folder(args.work, "eval_markers.py", empty=False)
    rig = load_calibration(RIG, warn_units=False)
    print(f"{'capture':<12} {'setting':<12} {'frames':>6} {'markers':>7} {'MMTA@50':>8} {'MMTP mm':>8} "
          f"{'landmarks mm':>12} {'lost':>5} {'s/frame':>8} {'measured':>8} {'body MMTA':>9} {'body MMTP':>9}")
    for name in args.captures:
        scene = marker_scene(CAPTURES[name], rig, args.fps, args.duration)  # retargeted once for every run
        for setting in args.settings:
            runs = []
            for seed in range(args.seeds):
                det, truth = scene.detections(SETTINGS[setting], seed=seed), scene.truth
                folder = write_marker_capture(work / f"{name}_{setting}" / f"seed{seed}", rig, det, truth)
                t0 = time.perf_counter()
                result = track_markers(folder, apf, seed=seed, progress=False)
                seconds = time.perf_counter() - t0
                save_poses(result.poses, folder / "poses.npz")
                rep = evaluate(result.poses, truth)
                m = rep.markers
                T = result.poses.num_frames
                body = evaluate(replace(result.poses, markers3d=result.poses.extra["markers3d_body"]), truth).markers
                source = result.poses.extra["markers3d_source"][result.poses.valid]
                measured = 100 * float((source == MEASURED).sum()) / max(int((source != NONE).sum()), 1)
                runs.append((100 * m.mmta, m.mmtp_mm, rep.mpjpe_mm, rep.frames_lost, 100 * body.mmta, body.mmtp_mm))
                label = setting if args.seeds == 1 else f"{setting} {seed}"
                print(f"{name:<12} {label:<12} {T:>6} {m.markers:>7} {100 * m.mmta:>7.2f}% {m.mmtp_mm:>8.1f} "
                      f"{rep.mpjpe_mm:>12.1f} {rep.frames_lost:>5} {seconds / T:>8.2f} {measured:>7.1f}% "
                      f"{100 * body.mmta:>8.2f}% {body.mmtp_mm:>9.1f}", flush=True)
                if not math.isfinite(m.mmta):
                    return 1
                if args.ceiling:
                    for what, mmta, mmtp in ceilings(folder, result.poses, truth, apf):
                        print(f"{'':<12} {'':<12} {'':>6} {'':>7} {mmta:>7.2f}% {mmtp:>8.1f}   ceiling: {what}",
                              flush=True)
            if args.seeds > 1:
                mean = [sum(r[i] for r in runs) / len(runs) for i in range(6)]
                print(f"{name:<12} {setting + ' mean':<12} {'':>6} {'':>7} {mean[0]:>7.2f}% {mean[1]:>8.1f} "
                      f"{mean[2]:>12.1f} {sum(r[3] for r in runs):>5} {'':>8} {'':>8} {mean[4]:>8.2f}% "
                      f"{mean[5]:>9.1f}   (lost: summed over the seeds; worst MMTA {min(r[0] for r in runs):.2f}%, "
                      f"worst MMTP {max(r[1] for r in runs):.1f} mm)", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
