#!/usr/bin/env python
"""The stress table: the markerless tracker on synthetic recordings unlike the template's, as `torchtrack track`
tracks them (torchtrack.track with the default config).

Each case fixes a motion (procedural, or a real capture retargeted: CMU's BVH skeletons, the joint centres of
the C3D marker captures), a camera count, a start and where the
subject goes; its seed draws the rest: body height, bone proportions and girth, clothing colours (normal, or close
to the floor's and the walls'), a floor shadow and the light, the ring's radius and height, lens distortion.
Sequences are rendered once under --work (re-rendered when their settings change).

    .venv/bin/python scripts/eval_robustness.py                     # every case (about 22 minutes on 2 cores)
    .venv/bin/python scripts/eval_robustness.py --cases walk_8 cross_8    # a subset
    .venv/bin/python scripts/eval_robustness.py --cases cmu131_01_8 --stop 24   # the start: its first 24 frames
    .venv/bin/python scripts/eval_robustness.py --set background.shadow_min_gain=1 --all-views  # as before (2026-11-27)
    .venv/bin/python scripts/eval_robustness.py --fps 60 --no-background-frames --work out/eval_robustness60
        # recordings without empty frames (the background estimated from the video, refined from the track)

Columns: MPJPE over the 16 landmarks (mm) on the frames where the subject is in view (every landmark inside at
least 3 images), the worst such frame, invalid frames among them, and the start: the first frame within 50 mm
(its time from the first frame), as docs/results.md's stress table reports them; the subject's height as the
track fitted it (and the truth).
"""

from __future__ import annotations

import argparse
import logging
import math
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
import yaml

from torchtrack.cameras import load_calibration
from torchtrack.checks import InputError
from torchtrack.conventions import LANDMARKS
from torchtrack.io.outputs import script_work_folder
from torchtrack.io.poses import load_poses, save_poses
from torchtrack.io.sequence import read_meta
from torchtrack.synth.scene import _WALL_PALETTE, SceneConfig
from torchtrack.synth.sequence import BodyConfig, RigConfig, SynthConfig, is_current, write_sequence
from torchtrack.tracking.pipeline import NothingTracked, load_config, track

CMU = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "mocap" / "cmu"
#: The floor's two checker tones (torchtrack/synth/scene.py): low-contrast trousers and shoes are drawn near them.
FLOOR_TONES = ((0.60, 0.55, 0.47), (0.38, 0.40, 0.44))
#: Blobs dressed alike.
GARMENTS = {"top": ("abdomen", "chest", "l_upperarm", "r_upperarm"),
            "trousers": ("pelvis", "l_thigh", "r_thigh", "l_shank", "r_shank"),
            "skin": ("neck", "l_forearm", "r_forearm", "l_hand", "r_hand"), "hair": ("head",),
            "shoes": ("l_foot", "r_foot")}
#: Bones whose length is drawn (both sides alike), and how far from the template's proportion.
BONES = ("torso", "head", "upperarm", "forearm", "thigh", "shank")
BONE_SPREAD = 0.08
#: Starfish styles: (arm abduction, leg abduction) in radians; "none" starts in the motion itself.
STARTS = {"starfish": (1.25, 0.3), "high": (1.75, 0.25), "low": (0.95, 0.35), "none": None}
#: Start target: within this MPJPE (m) ...
START_MM = 50.0
#: ... by this time from the first frame (s).
START_S = 1.0
#: A frame is "in view" when every landmark projects inside at least this many images.
IN_VIEW = 3
#: The mean pace (m/s) at which the subject walks the "cross" and "leave" paths: a walker's (the smoothstep between
#: waypoints peaks at 1.5 times it). The walk walks its path, facing the way it goes
#: (:func:`torchtrack.synth.motion.walks_path`).
PATH_PACE_M_S = 1.2
#: The issue's targets: MPJPE (mm) with 8 cameras and more, and with fewer; no invalid frame while in view.
TARGET_MANY_MM, TARGET_FEW_MM = 40.0, 60.0


@dataclass(frozen=True)
class Case:
    """One row of the table. path: "none", "cross" (to where only some cameras see the subject and back) or
    "leave" (out of the capture area and back)."""

    name: str
    motion: str
    cameras: int
    seed: int
    start: str = "starfish"
    path: str = "none"
    overhead: bool = False
    low_contrast: bool = False


CASES = (
    Case("walk_8", "walk", 8, 1, start="high"),
    Case("turn_12", "turn", 12, 2, start="low", overhead=True),
    Case("arm_raise_6", "arm_raise", 6, 3, start="none", low_contrast=True),
    Case("squat_10", "squat", 10, 4, start="starfish"),
    Case("kick_8", "kick", 8, 5, start="none"),
    Case("cmu131_01_8", "cmu:131_01", 8, 6, start="starfish", low_contrast=True),
    Case("cmu131_02_12", "cmu:131_02", 12, 7, start="high", overhead=True),
    Case("cross_8", "walk", 8, 8, start="starfish", path="cross"),
    Case("leave_8", "walk", 8, 9, start="low", path="leave"),
    Case("walk_4", "walk", 4, 10, start="starfish"),
    Case("squat_4", "squat", 4, 11, start="none", low_contrast=True),
    Case("cmu131_01_4", "cmu:131_01", 4, 12, start="high"),
    Case("cmu85_02_8", "c3d:cmu/85_02.c3d", 8, 13, start="none"),
    Case("pig_walk_8", "c3d:btk/c3d/PiG_Motion-FlatFoot-Full.c3d", 8, 14, start="low", low_contrast=True),
    Case("cmu85_02_4", "c3d:cmu/85_02.c3d", 4, 15, start="starfish"),
)


def _colour(rng: np.random.Generator, near: tuple[float, float, float] | None) -> tuple[float, float, float]:
    if near is None:
        return tuple(float(v) for v in rng.uniform(0.05, 0.95, 3))
    return tuple(float(np.clip(v + rng.uniform(-0.05, 0.05), 0, 1)) for v in near)


def prior_leave_out(motion: str) -> list[str]:
    """The real captures' poses the start search leaves out on ``motion`` (``TrackerConfig.start_prior_exclude``):
    its subject's, whose captures are named ``SUBJECT_...`` (CMU ``131_01``, ``131_02``; ``PiG_...``)."""
    if ":" not in motion:
        return []  # a procedural motion: in no capture
    stem = Path(motion.split(":", 1)[1]).stem
    return [stem.split("_", 1)[0] + "_"]


def synth_config(case: Case, duration: float, fps: float, background_frames: int = 20) -> SynthConfig:
    """The case's sequence: its fixed settings and the seed's draws; ``background_frames`` empty-scene frames."""
    rng = np.random.default_rng(case.seed)
    skin = tuple(float(v) for v in np.array([0.85, 0.62, 0.48]) * rng.uniform(0.45, 1.1))
    colours = []
    for garment, blobs in GARMENTS.items():
        if garment == "skin":
            rgb = skin
        elif case.low_contrast and garment in ("trousers", "shoes"):
            rgb = _colour(rng, FLOOR_TONES[int(rng.integers(2))])
        elif case.low_contrast and garment == "top":
            rgb = _colour(rng, _WALL_PALETTE[int(rng.integers(len(_WALL_PALETTE)))])
        else:
            rgb = _colour(rng, None)
        colours += [(b, rgb) for b in blobs]
    scale = [(side + bone, f) for bone in BONES for f in [float(rng.uniform(1 - BONE_SPREAD, 1 + BONE_SPREAD))]
             for side in (("l_", "r_") if bone not in ("torso", "head") else ("",))]
    body = BodyConfig(bone_scale=tuple(scale), girth=float(rng.uniform(0.85, 1.3)), colours=tuple(colours))
    elevation, azimuth = rng.uniform(math.radians(45), math.radians(80)), rng.uniform(0, 2 * math.pi)
    light = (math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth), math.sin(elevation))
    scene = replace(SceneConfig(), light_dir=light, ambient=float(rng.uniform(0.3, 0.5)), shadow=True,
                    shadow_strength=float(rng.uniform(0.3, 0.55)), illumination_change=float(rng.uniform(0, 0.15)),
                    seed=case.seed)
    radius = float(rng.uniform(3.0, 4.5))  # the field of view keeps the default ring's width at the centre
    rig = RigConfig(num_cameras=case.cameras, radius_m=radius, height_m=float(rng.uniform(1.8, 2.8)),
                    hfov_deg=math.degrees(2 * math.atan(3.5 * math.tan(math.radians(31.0)) / radius)),
                    k1=float(rng.uniform(-0.12, 0.0)), overhead=case.overhead)
    path: tuple[tuple[float, float, float], ...] = ()
    start = STARTS[case.start]
    starfish_s = 0.0 if start is None else 1.0
    t0 = starfish_s + 0.3
    heading = float(rng.uniform(0, 2 * math.pi))
    if case.path in ("cross", "leave"):
        # cross: to 0.7 of the ring's radius, where only some cameras see the subject, a pause, and back; leave:
        # behind the cameras, out of the capture area, and back; each way at PATH_PACE_M_S
        far, pause = (0.7 * radius, 0.8) if case.path == "cross" else (radius + 1.2, 0.7)
        way = far / PATH_PACE_M_S
        x, y = far * math.cos(heading), far * math.sin(heading)
        path = ((t0, 0.0, 0.0), (t0 + way, x, y), (t0 + way + pause, x, y), (t0 + 2 * way + pause, 0.0, 0.0))
    if path:
        duration = max(duration, path[-1][0] - starfish_s + 0.7)
    if case.motion.startswith("cmu:"):
        motion = str(CMU / f"{case.motion[4:]}.bvh")
    elif case.motion.startswith("c3d:"):  # a marker capture's joint centres (torchtrack.synth.c3d_motion)
        motion = str(CMU.parent / case.motion[4:])
    else:
        motion = case.motion
    arms, legs = start if start is not None else (1.25, 0.3)
    return SynthConfig(motion=motion, duration_s=duration, starfish_s=starfish_s, fps=fps,
                       subject_height_m=float(rng.uniform(1.55, 1.95)), rig=rig, scene=scene, body=body,
                       starfish_arms=arms, starfish_legs=legs, path=path, seed=case.seed,
                       background_frames=background_frames)


def in_view(seq: Path, truth: np.ndarray) -> np.ndarray:
    """(T,) bool: every landmark of the frame inside at least IN_VIEW images (truth: (T, J, 3))."""
    rig = load_calibration(seq / "calibration.toml")
    T, J, _ = truth.shape
    _, valid = rig.project(torch.from_numpy(truth.reshape(-1, 3)).double())  # (C, T * J)
    return (valid.reshape(-1, T, J).sum(0) >= IN_VIEW).all(-1).numpy()


def score(seq: Path, poses, stop: int | None = None) -> dict:
    gt = load_poses(seq / "gt.npz")
    idx = [gt.joint_names.index(n) for n in LANDMARKS]
    truth = gt.joints3d[:stop, idx]  # (T, J, 3)
    seen = in_view(seq, truth)
    T = truth.shape[0]
    pred = np.full_like(truth, np.nan)
    valid = np.zeros(T, dtype=bool)
    if poses is not None:
        pidx = [poses.joint_names.index(n) for n in LANDMARKS]
        frames = poses.frame_index
        pred[frames] = poses.joints3d[:, pidx]
        valid[frames] = poses.valid
    err = np.linalg.norm(pred - truth, axis=-1).mean(-1) * 1e3  # (T,) mm, NaN where not tracked
    ok = valid & seen
    fps = gt.fps
    within = np.nonzero(valid & (err <= START_MM))[0]
    first = int(within[0]) if within.size else None
    dist = np.linalg.norm(pred - truth, axis=-1)[ok] * 1e3  # (T_ok, J) mm
    dz = (pred - truth)[ok][..., 2] * 1e3
    return {"frames": T, "in_view": int(seen.sum()), "invalid": int((seen & ~valid).sum()),
            "per_landmark": (dist.mean(0), dz.mean(0)) if ok.any() else None,
            "mpjpe": float(np.nanmean(err[ok])) if ok.any() else float("nan"),
            "worst": float(np.nanmax(err[ok])) if ok.any() else float("nan"),
            "start_s": None if first is None else first / fps, "per_frame": (err, seen, valid)}


def run_case(case: Case, work: Path, duration: float, fps: float, config: dict, save: Path | None = None,
             stop: int | None = None, background_frames: int = 20) -> dict:
    seq = work / case.name
    cfg = synth_config(case, duration, fps, background_frames)
    if not is_current(seq, cfg):
        write_sequence(cfg, seq, progress=False)
    t0 = time.perf_counter()
    note = ""
    try:
        passes = {} if stop is None else {"stop": stop, "refine_passes": 0, "refit_passes": 0}
        poses = track(seq, config=config, workers=None, progress=False, **passes).poses  # workers: the config's
    except NothingTracked as e:
        poses, note = e.poses, f"nothing tracked: {e}"
    except InputError as e:
        poses, note = None, f"refused: {str(e).splitlines()[0][:90]}"
    if save is not None and poses is not None:
        save_poses(poses, save / f"{case.name}.npz")
    out = score(seq, poses, stop)
    fitted = None if poses is None else poses.extra.get("subject_height_m")
    out.update(seconds=time.perf_counter() - t0, note=note, cameras=case.cameras + int(case.overhead),
               height=float("nan") if fitted is None else float(fitted),
               true_height=read_meta(seq / "meta.toml").subject_height_m or float("nan"))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", nargs="+", default=[c.name for c in CASES], metavar="NAME",
                    help=f"cases to run (default: all: {' '.join(c.name for c in CASES)})")
    ap.add_argument("--duration", type=float, default=3.0, help="seconds of motion after the start (default: 3)")
    ap.add_argument("--fps", type=float, default=30.0, help="frame rate of the sequences (default: 30)")
    ap.add_argument("--no-background-frames", action="store_true",
                    help="render no empty-scene frames: the background is estimated from the video and refined "
                         "from the track, as on recordings without them (give another --work)")
    ap.add_argument("--work", type=Path, default=Path("out/eval_robustness"), help="rendered sequences")
    ap.add_argument("--config", default="markerless.yaml", help="tracking config (default: markerless.yaml)")
    ap.add_argument("--set", nargs="*", default=[], metavar="SECTION.KEY=VALUE",
                    help="override config settings, e.g. background.shadow_min_gain=1 (YAML values)")
    ap.add_argument("--save", type=Path, metavar="DIR",
                    help="also write each case's track to DIR/<case>.npz (an existing folder), to look into")
    ap.add_argument("--per-frame", action="store_true",
                    help="also print each case's MPJPE frame by frame (mm; NaN: not tracked), whether the subject "
                         "is in view and whether the frame is valid")
    ap.add_argument("--per-landmark", action="store_true",
                    help="also print each case's mean error per landmark and its mean height error (mm, + too high) "
                         "over the frames in view and valid")
    ap.add_argument("--stop", type=int, default=None, metavar="N",
                    help="track and score only the first N frames, without refinement or body refit (the start)")
    ap.add_argument("--all-views", action="store_true",
                    help="voxels must be seen by every camera (observation.min_views = the rig's count)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    by_name = {c.name: c for c in CASES}
    unknown = [n for n in args.cases if n not in by_name]
    if unknown:
        raise SystemExit(f"unknown cases {unknown}; cases: {list(by_name)}")
    work = script_work_folder(args.work, "eval_robustness.py", empty=False)  # each case re-rendered when stale
    if args.save is not None and not args.save.is_dir():
        raise SystemExit(f"--save {args.save}: not a folder")
    print(f"{'case':<14} {'cams':>4} {'start':<8} {'path':<6} {'MPJPE':>7} {'worst':>7} {'invalid':>9} "
          f"{'start within 50 mm':>19} {'height m':>12} {'s':>5}  note")
    config = load_config(args.config)
    for item in args.set:
        key, sep, value = item.partition("=")
        section, dot, field = key.partition(".")
        if not sep or not dot or section not in config:
            raise SystemExit(f"--set {item!r}: expected SECTION.KEY=VALUE with a section of {args.config}")
        config[section][field] = yaml.safe_load(value)
    rows = []
    for name in args.cases:
        case = by_name[name]
        if args.all_views:
            config["observation"]["min_views"] = case.cameras + int(case.overhead)
        config["tracker"]["start_prior_exclude"] = prior_leave_out(case.motion)
        r = run_case(case, work, args.duration, args.fps, config, args.save, args.stop,
                     0 if args.no_background_frames else 20)
        rows.append((case, r))
        start = "never" if r["start_s"] is None else f"{r['start_s']:.2f} s"
        print(f"{case.name:<14} {r['cameras']:>4} {case.start:<8} {case.path:<6} {r['mpjpe']:>7.1f} {r['worst']:>7.1f} "
              f"{r['invalid']:>4}/{r['in_view']:<4} {start:>19} {r['height']:>5.2f} ({r['true_height']:.2f}) "
              f"{r['seconds']:>5.0f}  {r['note']}", flush=True)
        if args.per_landmark and r["per_landmark"] is not None:
            mean, dz = r["per_landmark"]
            print("  " + "  ".join(f"{n} {m:.0f} ({z:+.0f})" for n, m, z in zip(LANDMARKS, mean, dz)))
        if args.per_frame:
            for t, (e, seen, ok) in enumerate(zip(*r["per_frame"])):
                print(f"  {case.name} frame {t:>4} {e:>8.1f} mm  {'in view' if seen else 'out':<7}  "
                      f"{'valid' if ok else 'invalid'}")
    for label, sel, target in (("8 cameras and more", lambda c: c.cameras >= 8, TARGET_MANY_MM),
                               ("fewer", lambda c: c.cameras < 8, TARGET_FEW_MM)):
        chosen = [r for c, r in rows if sel(c)]
        if chosen:
            vals = [r["mpjpe"] for r in chosen]
            met = sum(r["mpjpe"] <= target and r["invalid"] == 0 for r in chosen)
            print(f"mean MPJPE, {label}: {np.nanmean(vals):.1f} mm over {len(vals)} cases "
                  f"({sum(math.isnan(v) for v in vals)} without a track); within {target:.0f} mm with no invalid "
                  f"frame in view: {met} of {len(chosen)}")
    starts = [r["start_s"] for _, r in rows]
    late = [c.name for c, r in rows if r["start_s"] is None or r["start_s"] > START_S]
    if starts:
        latest = "never" if None in starts else f"{max(starts):.2f} s"
        print(f"starts within {START_MM:.0f} mm: the latest {latest}; later than {START_S:.0f} s: "
              f"{', '.join(late) or 'none'}")


if __name__ == "__main__":
    main()
