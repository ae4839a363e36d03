#!/usr/bin/env python
"""The start search on its own: started from random frames of every motion, how often it lands within 50 mm.

For each motion (the procedural ones and the real CMU captures, retargeted) and rig (8 and 4 cameras), a sequence
is rendered once under --work (a drawn body, colours and shadow as scripts/eval_robustness.py draws them); from
--frames random frames of it (fixed seed) the tracker is started cold, as on the first frame of a recording
(:meth:`MarkerlessTracker.step` on it: the search, then EM/CCD and the bone fit), tracked on over the start race
(``TrackerConfig.start_race_s``: the start turned round tracked beside it, the better kept) and the track back
(``settle_back_s``; where the sequence ends first, as the tracker ends it: :meth:`MarkerlessTracker.finish`), and
the start frame's pose as it stands then is scored against the ground truth (the search's prior of real poses
without the captured subject's own: ``TrackerConfig.start_prior_exclude``): MPJPE over the 16 landmarks. Prints
per motion and rig the share within 50 mm, the median error and the seconds per start (the race included); the
search's own error before EM/CCD; and the share within 50 mm before the race (``--search-only`` skips the tracker).

    .venv/bin/python scripts/eval_start.py                       # 50 frames per motion and rig
    .venv/bin/python scripts/eval_start.py --motions walk squat --cameras 8 --frames 10
    .venv/bin/python scripts/eval_start.py --frames 3 --real-poses          # with the real captured poses
    .venv/bin/python scripts/eval_start.py --motions cmu:131_01 --cameras 8 --frames 5 --search-only --truth-score
    .venv/bin/python scripts/eval_start.py --frames 8 --search-only --search particles=384   # a larger search
    .venv/bin/python scripts/eval_start.py --cameras 8 --frames 3 --search-only --search sweep=false  # no limb sweep
    .venv/bin/python scripts/eval_start.py --from-truth          # the ceiling: the tracker's fit from the true pose
    .venv/bin/python scripts/eval_start.py --cameras 4 --frames 10 --true-answer   # the start from a perfect search
    .venv/bin/python scripts/eval_start.py --cameras 4 --frames 10 --tracker init_passes=6   # a tracker setting
    .venv/bin/python scripts/eval_start.py --cameras 4 --frames 10 --voxels   # the search on the voxels alone
    .venv/bin/python scripts/eval_start.py --cameras 8 --motions cmu:131_02 --at 76 80 --per-start  # given frames

``--from-truth`` starts no search: the tracker is given the true pose and the subject's own body (the rendered
``body.urdf``) and fits the start frame from them as it tracks any frame (EM/CCD from the predicted pose); the share
within 50 mm is then what the observation and the fit allow a start to reach at best, whatever the search.
``--true-answer`` runs the tracker's start as it is but hands it the true pose, on the template's body at the
subject's height, as the search's one answer: what the start's finishing (EM/CCD, the bone fit, the checks, the
race) makes of a perfect search.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import math
import time
import tomllib
from dataclasses import replace
from pathlib import Path
from unittest import mock

import numpy as np
import torch
import yaml

from torchtrack.background import BackgroundConfig, BackgroundModel
from torchtrack.checks import InputError
from torchtrack.blobs.model import BlobModel, load_blob_specs
from torchtrack.conventions import LANDMARKS
from torchtrack.io.outputs import script_work_folder
from torchtrack.io.poses import load_poses
from torchtrack.io.sequence import SequenceFolder
from torchtrack.skeleton import Skeleton
from torchtrack.synth.sequence import is_current, write_sequence
from torchtrack.tracking.markerless import MarkerlessTracker, TrackerConfig
from torchtrack.tracking.pipeline import load_config, observer_from_config
from torchtrack.tracking.search import SearchConfig, SearchResult, score_states, search_pose

import eval_robustness as rob

MOTIONS = ("walk", "turn", "arm_raise", "squat", "kick", "cmu:131_01", "cmu:131_02")
WITHIN_MM = 50.0


def sequence(work: Path, motion: str, cameras: int, seed: int) -> Path:
    case = rob.Case(f"start_{motion.replace(':', '_')}_{cameras}", motion, cameras, seed, start="none")
    seq = work / case.name
    cfg = rob.synth_config(case, duration=4.0, fps=30.0)
    if not is_current(seq, cfg):
        write_sequence(cfg, seq, progress=False)
    return seq


def landmark_error_mm(res, truth: np.ndarray) -> float:
    """MPJPE (mm) of a tracked frame's 16 landmarks against ``truth (16, 3)``; inf for an invalid frame."""
    if not res.valid:
        return float("inf")
    return float(1e3 * np.linalg.norm(res.output_points[:len(LANDMARKS)].numpy() - truth, axis=-1).mean())


def start_report(res, truth: np.ndarray, height: float, true_height: float, girth: float, true_girth: float) -> str:
    """One start's line for --per-start: MPJPE, how far its heading (the hips' horizontal normal) and pelvis (and its
    height: a body sunk into a few views' hull) are from the truth's, its worst landmark, and the fitted body's height
    and girth (the blobs' cross semi-axes over the template's) against the subject's."""
    if not res.valid:
        return "refused"
    got = res.output_points[:len(LANDMARKS)].numpy().astype(np.float64)
    err = np.linalg.norm(got - truth, axis=-1)
    hips = [LANDMARKS.index("l_hip"), LANDMARKS.index("r_hip")]

    def heading(p: np.ndarray) -> float:
        across = p[hips[0]] - p[hips[1]]
        return float(np.arctan2(across[0], -across[1]))  # the hips' axis turned a right angle (Z up); only
        # the difference of two such angles is printed

    turn = np.degrees(np.angle(np.exp(1j * (heading(got) - heading(truth)))))
    worst = int(err.argmax())
    return (f"{1e3 * err.mean():6.1f} mm, heading {turn:+5.0f} deg, pelvis {1e3 * err[0]:5.0f} mm (z "
            f"{1e3 * (got[0, 2] - truth[0, 2]):+4.0f}), worst {LANDMARKS[worst]} {1e3 * err[worst]:.0f} mm, body "
            f"{height:.2f} m ({true_height:.2f}), girth {girth:.2f} ({true_girth:.2f})")


def from_truth(obs, truth, t: int, seq: Path, tcfg: TrackerConfig, fps: float) -> float:  # noqa: ANN001
    """MPJPE (mm) of frame ``t`` fitted by the tracker from its true pose and the subject's own body
    (``--from-truth``)."""
    tracker = MarkerlessTracker(Skeleton.from_urdf(), tcfg)
    tracker.set_frame_rate(fps)
    angles = torch.as_tensor(truth.angles[t]).to(tracker.generic.lower)
    tracker.initialize_from_pose(angles, skeleton=Skeleton.from_urdf(seq / "body.urdf").to(angles))
    idx = [truth.joint_names.index(n) for n in LANDMARKS]
    return landmark_error_mm(tracker.step(obs), truth.joints3d[t, idx])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--motions", nargs="+", default=list(MOTIONS))
    ap.add_argument("--cameras", nargs="+", type=int, default=[8, 4])
    ap.add_argument("--frames", type=int, default=50, help="random start frames per motion and rig (default: 50)")
    ap.add_argument("--at", nargs="+", type=int, default=None, metavar="FRAME",
                    help="start from these frames of each motion's sequence instead of --frames random ones")
    ap.add_argument("--search-only", action="store_true", help="score the search's best hypothesis, no EM/CCD")
    ap.add_argument("--per-start", action="store_true",
                    help="also print each start: its frame, MPJPE, heading and pelvis error, worst landmark, and the "
                         "fitted body's height and girth against the subject's")
    ap.add_argument("--real-poses", action="store_true",
                    help="the search also starts from real captured poses (TrackerConfig.start_real_poses)")
    ap.add_argument("--truth-score", action="store_true",
                    help="with --search-only, print each start's two-way score and the true pose's (on the "
                         "template's body at the subject's height): a search that scores below the truth missed it")
    scored = ap.add_mutually_exclusive_group()
    scored.add_argument("--silhouettes", action="store_true",
                        help="the search scores bodies against each camera's foreground (observation.silhouettes: "
                             "true; the config's null does so with the Bayesian grid, since 2026-12-02)")
    scored.add_argument("--voxels", action="store_true",
                        help="the search scores bodies against the voxels (observation.silhouettes: false), as on "
                             "rigs of fewer than 7 cameras before 2026-12-02")
    ap.add_argument("--search", nargs="*", default=[], metavar="KEY=VALUE",
                    help="with --search-only, SearchConfig fields for the script's own search (e.g. particles=192 "
                         "layers=20 sweep=false); the tracker's start keeps the defaults")
    ap.add_argument("--from-truth", action="store_true",
                    help="no search: the tracker started from the true pose and body fits the start frame; the "
                         "ceiling of any start")
    ap.add_argument("--true-answer", action="store_true",
                    help="the tracker's start given the true pose (on the template's body at the subject's height) "
                         "as the search's answer: what the start's finishing makes of a perfect search")
    ap.add_argument("--tracker", nargs="*", default=[], metavar="KEY=VALUE",
                    help="override the tracking config's tracker settings, e.g. init_passes=6 (YAML values)")
    ap.add_argument("--work", type=Path, default=Path("out/eval_start"))
    args = ap.parse_args()
    if args.from_truth and args.search_only:
        ap.error("--from-truth runs no search: give it without --search-only")
    if args.true_answer and (args.search_only or args.from_truth):
        ap.error("--true-answer replaces the tracker's search: give it without --search-only or --from-truth")
    fields = {f.name: f.type for f in dataclasses.fields(SearchConfig)}
    overrides = {}
    simple = ("int", "float", "bool")
    for item in args.search:
        key, sep, value = item.partition("=")
        if not sep or key not in fields or fields[key] not in simple:
            ap.error(f"--search {item!r}: KEY=VALUE with KEY one of the numeric or true/false SearchConfig fields "
                     f"({', '.join(k for k, t in fields.items() if t in simple)})")
        if fields[key] == "bool":
            if value.lower() not in ("true", "false"):
                ap.error(f"--search {item!r}: {value!r} is not true or false")
            overrides[key] = value.lower() == "true"
            continue
        try:
            overrides[key] = int(value) if fields[key] == "int" else float(value)
        except ValueError:
            ap.error(f"--search {item!r}: {value!r} is not {'an integer' if fields[key] == 'int' else 'a number'}")
    if overrides and not args.search_only:
        ap.error("--search needs --search-only (the tracker's start uses the default search)")
    try:
        SearchConfig(**overrides)  # checked before any sequence is rendered
    except InputError as exc:
        ap.error(f"--search: {exc}")
    logging.basicConfig(level=logging.ERROR)
    torch.set_grad_enabled(False)
    torch.set_num_threads(1)
    work = script_work_folder(args.work, "eval_start.py", empty=False)  # each sequence re-rendered when stale
    config = load_config("markerless.yaml")
    if args.silhouettes or args.voxels:
        config["observation"] = {**config["observation"], "silhouettes": bool(args.silhouettes)}
    for item in args.tracker:
        key, sep, value = item.partition("=")
        if not sep:
            ap.error(f"--tracker {item!r}: expected KEY=VALUE")
        config["tracker"][key] = yaml.safe_load(value)
    try:
        tcfg = TrackerConfig.from_dict(config["tracker"], config["source"])
    except InputError as exc:
        ap.error(f"--tracker: {exc}")
    template = Skeleton.from_urdf()
    blobs = BlobModel(template, *load_blob_specs(tcfg.blobs))
    print(f"{'motion':<12} {'cams':>4} {'within 50 mm':>12} {'median':>7} {'search':>7} {'before race':>11} "
          f"{'s/start':>7}", flush=True)
    totals: dict[int, list[bool]] = {}
    for cams in args.cameras:
        for j, motion in enumerate(args.motions):
            # each motion's sequence and frames drawn by its place in MOTIONS: a subset picks the same ones
            i = MOTIONS.index(motion) if motion in MOTIONS else len(MOTIONS) + j
            seq = sequence(work, motion, cams, seed=100 + i)
            folder = SequenceFolder(seq)
            scale = float(config["observation"]["scale"])
            W, H = (int(round(float(v) * scale)) for v in folder.rig.image_size_wh[0])
            rig = folder.rig.resized(W, H).float()
            bg = BackgroundModel.from_folder(folder, BackgroundConfig(**config["background"]), size_wh=(W, H))
            observer = observer_from_config(rig, bg, config["observation"], "bayes", 0.03)
            truth = load_poses(seq / "gt.npz")
            true_height = Skeleton.from_urdf(seq / "body.urdf").height()
            true_girth = float(tomllib.loads((seq / "meta.toml").read_text(encoding="utf-8"))["synth"]["body"]
                               .get("girth", 1.0))
            leave_out = tuple(rob.prior_leave_out(motion))
            idx = [truth.joint_names.index(n) for n in LANDMARKS]
            race = max(1, round(tcfg.start_race_s * folder.fps))  # the start frame and the race's others, if moving
            rng = np.random.default_rng(i)
            last = truth.num_frames - race + 1  # a start whose race ends within the sequence
            frames = np.sort(rng.choice(last, size=min(args.frames, last), replace=False))
            if args.at is not None:
                if max(args.at) >= last or min(args.at) < 0:
                    ap.error(f"--at: frames of {motion}'s sequence are 0-{last - 1} (its race ends within it)")
                frames = np.asarray(sorted(set(args.at)))
            errors, search_errors, seconds, before = [], [], [], []
            for t in frames.tolist():
                fb = next(iter(folder.iter_batches(1, t, t + 1, size_wh=(W, H))))
                obs = observer(fb.images, fb.valid)[0]
                if args.from_truth:
                    errors.append(from_truth(obs, truth, t, seq, tcfg, folder.fps))
                    if args.per_start:
                        print(f"  {motion} {cams} frame {t:>4}: {errors[-1]:6.1f} mm from the true pose", flush=True)
                    continue
                gen = torch.Generator().manual_seed(t)
                t0 = time.perf_counter()
                if not args.true_answer:  # the search's own error (the "search" column)
                    search = SearchConfig(real_poses=args.real_poses, prior_exclude=leave_out, **overrides)
                    found = search_pose(obs, template, blobs, search, generator=gen)
                    body = template.scaled_to_height(template.height() * float(found.scale[0]))
                    lm = body.forward(found.angles[:1].double()).output_points[0].numpy()
                    names = list(body.output_names)
                    search_errors.append(1e3 * np.linalg.norm(lm[[names.index(n) for n in LANDMARKS]]
                                                              - truth.joints3d[t, idx], axis=-1).mean())
                if args.search_only:
                    seconds.append(time.perf_counter() - t0)
                    errors.append(search_errors[-1])
                    if args.truth_score:  # the true pose on the template's body at the subject's height
                        sized = template.scaled_to_height(true_height)
                        mine = score_states(obs, body, BlobModel(body, *load_blob_specs(tcfg.blobs)),
                                            found.angles[:1].double())[0]
                        true = score_states(obs, sized, BlobModel(sized, *load_blob_specs(tcfg.blobs)),
                                            torch.as_tensor(truth.angles[t:t + 1]).double())[0]
                        print(f"  {motion} {cams} frame {t:>4}: search {search_errors[-1]:6.1f} mm, score "
                              f"{float(mine[0]):.3f} (scale {float(found.scale[0]):.2f}); true pose "
                              f"{float(true[0]):.3f}", flush=True)
                    continue
                tracker = MarkerlessTracker(Skeleton.from_urdf(), replace(tcfg, start_real_poses=args.real_poses,
                                                                      start_prior_exclude=leave_out))
                tracker.set_frame_rate(folder.fps)
                t0 = time.perf_counter()
                if args.true_answer:  # the start's search (imported from its module when it runs) answers the truth
                    one = torch.ones(1)
                    answer = SearchResult(torch.as_tensor(truth.angles[t:t + 1]).float(),
                                          one * true_height / template.height(),
                                          one, one, one, 0 * one, 1)
                    with mock.patch("torchtrack.tracking.search.search_pose", return_value=answer) as searched:
                        first = tracker.step(obs)
                    if not searched.called:  # the start no longer imports the search where it runs
                        raise SystemExit("--true-answer: the tracker's start did not call search_pose")
                else:
                    first = tracker.step(obs)  # the start (a refusal: an invalid frame)
                before.append(landmark_error_mm(first, truth.joints3d[t, idx]) <= WITHIN_MM)
                if first.valid and (tracker.racing or tracker.settling):  # on until the race is decided and the
                    # frames since the start tracked back (or the sequence ends)
                    since = 0
                    for fb in folder.iter_batches(1, t + 1, truth.num_frames, size_wh=(W, H)):
                        tracker.step(observer(fb.images, fb.valid)[0])
                        since += 1
                        revised = tracker.take_revised()
                        if len(revised) > since:  # the revision reaches back to the start frame
                            first = revised[-1 - since][0]
                        if not (tracker.racing or tracker.settling):
                            break
                    else:  # the sequence ended first: the race and track back as the tracker ends a sequence
                        tracker.finish()
                        revised = tracker.take_revised()
                        if len(revised) > since:
                            first = revised[-1 - since][0]
                seconds.append(time.perf_counter() - t0)
                errors.append(landmark_error_mm(first, truth.joints3d[t, idx]))
                if args.per_start:
                    height = tracker.subject.skeleton.height() if tracker.subject is not None else math.nan
                    report = start_report(first, truth.joints3d[t, idx], height, true_height, tracker.girth,
                                          true_girth)
                    print(f"  {motion} {cams} frame {t:>4}: {report}", flush=True)
            e = np.asarray(errors)
            ok = e <= WITHIN_MM
            totals.setdefault(cams, []).extend(ok.tolist())
            early = f"{100 * np.mean(before):.0f}%" if before else "-"
            searched = f"{np.median(search_errors):.1f}" if search_errors else "-"
            secs = f"{np.mean(seconds):.2f}" if seconds else "-"
            print(f"{motion:<12} {cams:>4} {100 * ok.mean():>11.0f}% {np.median(e):>7.1f} "
                  f"{searched:>7} {early:>11} {secs:>7}", flush=True)
    for cams, ok in totals.items():
        print(f"{cams} cameras: {100 * np.mean(ok):.1f}% of {len(ok)} starts within {WITHIN_MM:g} mm")


if __name__ == "__main__":
    main()
