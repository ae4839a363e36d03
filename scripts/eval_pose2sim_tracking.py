#!/usr/bin/env python
"""Markerless tracking of the real Pose2Sim demo against Pose2Sim's reference keypoints.

The demo has no empty background frames (the background is estimated from the moving clip, the subject's
static parts painted out unless ``--no-fill``) and starts with
the subject balancing arms out. Points compared (``torchtrack.io.pose2sim.LANDMARK_MAP``): pelvis = mean of
RHip/LHip, neck, shoulders, elbows, wrists, hips, knees, ankles (14 of our 16 landmarks; the reference has no
thorax and no head centre) and the head top (BODY_25B's ``Head``). Prints MPJPE per landmark and lost frames;
saves a picture of one tracked frame in the four views. The track is :func:`torchtrack.track`'s, the library call
behind `torchtrack track` (only ``--reference-silhouettes``, which replaces the observation, tracks by hand).

``--init-from-reference`` starts from the pose and the body fitted to the reference's 15 points of frame 0
(:func:`torchtrack.tracking.landmark_fit.fit_to_landmarks`: bone lengths and the neck's and shoulders' height on
the trunk; de Bem's saved initialisation); ``--scale-only``: the template scaled to the subject's height instead.

Without empty frames the background is refined from the track (``torchtrack.tracking.refine``: the config's
``background_refinement.passes`` re-estimations at most, each followed by a new track; ``--refine-passes N``); each
pass prints its error, lost frames, mean IK residual and how far it moved the track, and the result is the pass
``background_refinement.keep`` names (``fit``: the refined pass with the fewest lost frames and then the lowest
residual, tracked once more at the end; ``--refine keep=last``: the last).

``--save-passes DIR`` keeps each pass's track; ``--init-from-reference --background-from DIR/pass_NN.npz
--refine-passes 0`` then tracks once on the background refined from one of them, from the same start: the pass
that followed it, replayed in a minute (it gives the same track on a CPU), to compare tracker settings on one
refined background.

``--reference-silhouettes`` separates the observation from the tracker: instead of the estimated background,
each view's silhouette is drawn from Pose2Sim's 21 keypoints of that frame (capsules of :data:`CAPSULES` radii
between them, the trunk a rounded quadrilateral of shoulders and hips) and the Bayesian grid's voxels are carved
from them (shape-from-silhouette; every camera must see a voxel). It is a diagnostic with the reference's own
keypoints, not a result.

``--reference-background`` is the other half of that diagnostic: the observation is computed from the images as
usual, but each pixel's background is the median of the frames where those drawn silhouettes (dilated by
:data:`REFERENCE_MARGIN_PX`) leave it free (``BackgroundModel.from_sequence(..., subject_masks=...)``): the
background an estimator that knew where the subject is would find in this clip.

Usage: .venv/bin/python scripts/eval_pose2sim_tracking.py [--scale 0.25] [--voxel 0.03] [--model bayes] [--no-fill]
       [--init-from-reference [--scale-only]] [--fill-prior-log-odds 0]
       [--reference-silhouettes | --reference-background] [--reference-fit [--scale-only]]
       [--refine-passes 3] [--refine blob_scale=1.3 ...] [--tracker velocity=0 ...] [--smoothing cutoff_hz=0]
       [--cutoffs 3 4 5 6 8 10]
       [--picture docs/images/pose2sim_tracking.jpg] [--save-poses POSES.npz] [--continue-from POSES.npz] [--bias]
       [--velocities 0.5 0.47 0.53 0.45 0.55] [--save-passes DIR] [--background-from POSES.npz]
       [--start-scores 0 20 50]
"""

from __future__ import annotations

import argparse
import logging
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from torch import nn

from torchtrack.background import BackgroundConfig, BackgroundModel
from torchtrack.background.estimate import MIN_CLEAN_FRAMES, dilate, subsample
from torchtrack.checks import InputError, with_overrides
from torchtrack.eval import evaluate
from torchtrack.cameras import CameraRig
from torchtrack.io.pose2sim import REFERENCE_FILTERED, pose2sim_sequence, reference_keypoints, reference_landmarks
from torchtrack.io.poses import Poses, load_poses, save_poses
from torchtrack.io.sequence import SequenceFolder
from torchtrack.occupancy.silhouette import carve
from torchtrack.skeleton import Skeleton
from torchtrack.tracking.body_refit import BodyRefitConfig, mean_ik_residual_m
from torchtrack.tracking.goals import weighted_kabsch
from torchtrack.tracking.landmark_fit import fit_pose, fit_to_landmarks, initial_pose
from torchtrack.tracking.markerless import MarkerlessTracker, TrackerConfig
from torchtrack.tracking.observation import Observer, VoxelObservation
from torchtrack.tracking.pipeline import load_config, observer_from_config, read_start_pose, track
from torchtrack.tracking.refine import RefineConfig, track_change_m, tracked_body
from torchtrack.tracking.run import track_sequence
from torchtrack.tracking.smoothing import SmoothingConfig, smooth_track

DEMO = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "pose2sim_demo"

#: The refinement's passes from this one on (1 = the first track), past its approach from the first background,
#: are compared: the correlation of their mean IK residual with their error (what ``keep: fit`` relies on).
FIRST_COMPARED_PASS = 5
#: Body segments of the reference silhouettes: two BODY_25B keypoints and a radius (m), an adult's limb girths.
CAPSULES = (("RHip", "RKnee", 0.07), ("RKnee", "RAnkle", 0.05), ("RAnkle", "RBigToe", 0.035),
            ("RHeel", "RBigToe", 0.035), ("LHip", "LKnee", 0.07), ("LKnee", "LAnkle", 0.05),
            ("LAnkle", "LBigToe", 0.035), ("LHeel", "LBigToe", 0.035), ("RShoulder", "RElbow", 0.045),
            ("RElbow", "RWrist", 0.035), ("LShoulder", "LElbow", 0.045), ("LElbow", "LWrist", 0.035),
            ("Neck", "Head", 0.06), ("Head", "Nose", 0.09))
#: The trunk: the quadrilateral of shoulders and hips, rounded by this radius (m).
TRUNK_ROUNDING_M = 0.06
#: ``--reference-background``: the drawn silhouettes are grown by this many pixels (at the processing size) before
#: they exclude a frame from a pixel's background (the capsules are approximate and the reference is a few cm off).
REFERENCE_MARGIN_PX = 6


def reference_silhouettes(rig: CameraRig, names: list[str], points: np.ndarray, samples: int = 24) -> torch.Tensor:
    """(T, C, H, W) bool silhouettes of a body drawn around keypoints ``points (T, K, 3)`` named ``names``: discs
    of each capsule's radius (at each sample's depth) along :data:`CAPSULES` and the rounded trunk."""
    import cv2

    W, H = (int(v) for v in rig.image_size_wh[0].tolist())
    k = {n: i for i, n in enumerate(names)}
    s = np.linspace(0.0, 1.0, samples)[:, None]
    quad = ("LShoulder", "RShoulder", "RHip", "LHip")
    out = np.zeros((points.shape[0], len(rig), H, W), bool)
    for t, p in enumerate(points):
        centres, radii = [], []
        for a, b, r in CAPSULES:
            centres.append(p[k[a]] * (1 - s) + p[k[b]] * s)
            radii.append(np.full(samples, r))
        for a, b in zip(quad, quad[1:] + quad[:1]):
            centres.append(p[k[a]] * (1 - s) + p[k[b]] * s)
            radii.append(np.full(samples, TRUNK_ROUNDING_M))
        pts = torch.as_tensor(np.concatenate(centres), dtype=torch.float32)
        uv, _ = rig.project(pts)
        depth = rig.world_to_camera(pts)[..., 2]  # (C, M)
        corners, _ = rig.project(torch.as_tensor(p[[k[n] for n in quad]], dtype=torch.float32))
        px = (rig.K[:, 0, 0, None] * torch.as_tensor(np.concatenate(radii), dtype=torch.float32) / depth).round()
        for c in range(len(rig)):
            mask = np.zeros((H, W), np.uint8)
            cv2.fillPoly(mask, [corners[c].round().numpy().astype(np.int32)], 1)
            for (u, v), r in zip(uv[c].round().int().tolist(), px[c].int().tolist()):
                cv2.circle(mask, (u, v), max(r, 1), 1, -1)
            out[t, c] = mask > 0
    return torch.from_numpy(out)


class SilhouetteObserver(nn.Module):
    """The Bayesian grid's voxels carved from given binary silhouettes ``(T, C, H, W)`` (frame by frame, in order;
    :func:`torchtrack.occupancy.carve` through the grid's voxel -> pixel table) instead of fused from the
    background model's foreground; voxel colours still come from the images."""

    def __init__(self, observer: Observer, silhouettes: torch.Tensor) -> None:
        super().__init__()
        self.observer, self.silhouettes, self.next_frame = observer, silhouettes, 0
        self.rig, self.model = observer.rig, observer.model
        self.volumes_m3: list[float] = []

    def forward(self, images: torch.Tensor, cameras_valid: torch.Tensor) -> list[VoxelObservation]:
        mask = self.silhouettes[self.next_frame:self.next_frame + images.shape[0]].to(images.device)
        self.next_frame += images.shape[0]
        occupied = carve(mask, self.observer.grid.lookup, min_views=len(self.rig))  # (B, V)
        out = self.observer.from_probability(occupied.to(images.dtype), self.observer.background.normalise(images),
                                             cameras_valid)
        self.volumes_m3 += [o.volume_m3() for o in out]
        return out


def reference_poses(names: list[str], ref: np.ndarray, fps: float, joint_names: list[str]) -> Poses:
    """The reference as a Poses with our joint names (joints it lacks are NaN; frames all valid)."""
    T = ref.shape[0]
    j3d = np.full((T, len(joint_names), 3), np.nan, np.float32)
    for i, n in enumerate(names):
        j3d[:, joint_names.index(n)] = ref[:, i]
    return Poses(fps=fps, frame_index=np.arange(T), joint_names=joint_names, joints3d=j3d, dof_names=[],
                 angles=np.zeros((T, 0), np.float32), valid=np.ones(T, bool),
                 confidence=np.ones((T, len(joint_names)), np.float32))


def score(path: Path, demo: Path, per_landmark: bool = False) -> None:
    """Print the MPJPE of a poses.npz of the demo against Pose2Sim's raw and filtered keypoints (with
    ``per_landmark``, each landmark's too)."""
    poses = load_poses(path)
    for filtered in (False, True):
        names, ref = reference_landmarks(demo, filtered=filtered)
        r = evaluate(poses, reference_poses(names, ref, poses.fps, poses.joint_names), landmarks=names)
        print(f"{path} against Pose2Sim's {'filtered' if filtered else 'raw'} keypoints: MPJPE {r.mpjpe_mm:.1f} mm, "
              f"{int((~poses.valid).sum())} of {poses.num_frames} frames invalid")
        if per_landmark:
            print("  " + " ".join(f"{n} {v:.1f}" for n, v in zip(r.landmark_names, r.per_landmark_mm)))


def start_scores(folder: SequenceFolder, background: BackgroundModel, config: dict, args: argparse.Namespace,
                 size_wh: tuple[int, int]) -> None:
    """``--start-scores``: the automatic start on each given frame alone, against the pose fitted to that frame's
    reference points: the start's error, and the two-way score (score, explained, filled;
    :func:`~torchtrack.tracking.search.score_states`) of both on the frame's voxels. A start that scores above
    the reference's pose is the score's failure on this data; one below it, the search's."""
    from torchtrack.blobs.model import BlobModel
    from torchtrack.tracking.search import score_states

    names, ref = reference_landmarks(args.demo)
    rig = folder.rig.resized(*size_wh).float()
    observer = observer_from_config(rig, background, dict(config["observation"]), args.model, args.voxel)
    tcfg = TrackerConfig.from_dict(config["tracker"], config.get("source", "config"))
    print("frame  voxels  start: error mm, height m, score (explained, filled) | reference pose: height m, score "
          "(explained, filled)")
    for t in args.start_scores:
        if not 0 <= t < len(ref):
            raise SystemExit(f"--start-scores {t}: the demo has frames 0-{len(ref) - 1}")
        obs = observer(folder.read_frame(t, size_wh=size_wh)[None])[0]
        tracker = MarkerlessTracker(Skeleton.from_urdf(), tcfg)
        res = tracker.step(obs)
        if not res.valid:
            why = tracker.start_refusals[-1] if tracker.start_refusals else "invalid"
            print(f"{t:>5}  {obs.num_voxels:>6}  no start: {why.split('. ')[0]}")
            continue
        body = tracker.subject.skeleton
        out = list(body.output_names)
        err = 1e3 * np.linalg.norm(res.output_points.numpy()[[out.index(n) for n in names]] - ref[t], axis=-1).mean()
        found = [float(x[0]) for x in score_states(obs, body, tracker.subject.blobs, res.angles[None])[:3]]
        angles, ref_body = fit_to_landmarks(Skeleton.from_urdf(), names, ref[t])
        truth = [float(x[0]) for x in score_states(obs, ref_body, BlobModel.from_config(ref_body), angles[None])[:3]]
        print(f"{t:>5}  {obs.num_voxels:>6}  {err:6.0f}, {body.height():.2f}, {found[0]:.3f} ({found[1]:.3f}, "
              f"{found[2]:.3f}) | {ref_body.height():.2f}, {truth[0]:.3f} ({truth[1]:.3f}, {truth[2]:.3f})",
              flush=True)


def reference_fit(demo: Path, fit_bones: bool) -> None:
    """``--reference-fit``: how close our skeleton can come to the reference at all. The body the reference start
    uses (fitted to frame 0's points, :func:`fit_to_landmarks`), posed on every reference frame at once
    (:func:`fit_pose`, batched over frames) and scored on the same landmarks as the tracking."""
    names, ref = reference_landmarks(demo)
    a0, body = fit_to_landmarks(Skeleton.from_urdf(), names, ref[0], fit_bones=fit_bones)
    out = list(body.output_names)
    p0 = body.forward(a0[None]).output_points[0, [out.index(n) for n in names]].numpy()
    err0 = 1e3 * np.linalg.norm(p0 - ref[0], axis=-1).mean()
    print(f"frame 0, the start the body is fitted to: mean point error {err0:.1f} mm")
    angles = fit_pose(body, names, torch.as_tensor(ref, dtype=torch.float32))  # (T, D)
    j3d = body.forward(angles).output_points.numpy()
    fps = 30.0  # the evaluation does not use it
    fitted = Poses(fps=fps, frame_index=np.arange(len(ref)), joint_names=out, joints3d=j3d, dof_names=[],
                   angles=np.zeros((len(ref), 0), np.float32), valid=np.ones(len(ref), bool),
                   confidence=np.ones((len(ref), len(out)), np.float32))
    print(f"the body of the reference start ({body.height():.2f} m, "
          f"{'bones fitted to' if fit_bones else 'the template scaled to'} frame 0's points), posed on each of the "
          f"{len(ref)} reference frames (the model's floor for this comparison)")
    print(evaluate(fitted, reference_poses(names, ref, fps, out), landmarks=names).format())


def print_bias(poses: Poses, names: list[str], ref: np.ndarray, demo: Path) -> None:
    """--bias: each compared landmark's mean signed offset (track - reference) over the frames both have, in mm
    along the reference's forward, left and up (left: from the right hip to the left, level; up: world z), and
    the reference's own Neck against its shoulders' midpoint in the same axes."""
    ref = ref[:poses.num_frames]
    idx = [list(poses.joint_names).index(n) for n in names]
    ok = poses.valid & np.isfinite(ref).all((1, 2))
    left = ref[:, names.index("l_hip")] - ref[:, names.index("r_hip")]
    left[:, 2] = 0.0
    left /= np.linalg.norm(left, axis=-1, keepdims=True)
    up = np.broadcast_to([0.0, 0.0, 1.0], left.shape)
    axes = np.stack([np.cross(left, up), left, up], 1)  # (T, 3, 3) rows: forward, left, up
    d = np.einsum("tij,tlj->tli", axes, poses.joints3d[:, idx] - ref)[ok]  # (n, L, 3)
    print("mean offset from the reference (mm): forward, left, up")
    for n, (f, lft, u) in zip(names, 1e3 * d.mean(0)):
        print(f"  {n:12s} {f:7.1f} {lft:7.1f} {u:7.1f}")
    kp_names, kp = reference_keypoints(demo)
    kp = kp[:poses.num_frames]
    shoulders = 0.5 * (kp[:, kp_names.index("LShoulder")] + kp[:, kp_names.index("RShoulder")])
    neck = kp[:, kp_names.index("Neck")] - shoulders
    off = 1e3 * np.einsum("tij,tj->ti", axes, neck)[ok]  # (n, 3)
    print(f"  the reference's Neck from its shoulders' midpoint: forward {off[:, 0].mean():.1f} "
          f"({np.percentile(off[:, 0], 5):.1f} to {np.percentile(off[:, 0], 95):.1f}), up {off[:, 2].mean():.1f} mm")


#: --bias: the upper and the lower body, aligned to the reference apart.
UPPER = ("neck", "head_top", "l_shoulder", "r_shoulder", "l_elbow", "r_elbow", "l_wrist", "r_wrist")
LOWER = ("pelvis", "l_hip", "r_hip", "l_knee", "r_knee", "l_ankle", "r_ankle")


def overridden(config: dict, section: str, cls: type, items: list[str], option: str) -> dict:
    """``config`` with ``FIELD=VALUE`` items set in its ``section``, each parsed and checked as ``cls``'s field."""
    checked = with_overrides(cls.from_dict(config[section], config["source"]), items, option)
    names = [item.partition("=")[0] for item in items]
    return {**config, section: {**(config[section] or {}), **{n: getattr(checked, n) for n in names}}}


def smoothing_config(config: dict) -> SmoothingConfig:
    return SmoothingConfig.from_dict(config["smoothing"], config["source"])


def track_on_silhouettes(folder: SequenceFolder, config: dict, args: argparse.Namespace, start_pose: Poses | None,
                         size_wh: tuple[int, int]) -> tuple[Poses, float]:
    """``--reference-silhouettes``: one track (no refinement, no body refit) whose observation is carved from the
    silhouettes drawn from the reference keypoints (:class:`SilhouetteObserver`), unsmoothed, and its seconds.
    The one path of this script that is not :func:`torchtrack.track`: it replaces the observation itself."""
    if args.model != "bayes":
        raise SystemExit("--reference-silhouettes feeds the Bayesian grid: use --model bayes")
    rig = folder.rig.resized(*size_wh).float()
    bg = BackgroundModel.from_folder(folder, BackgroundConfig(**config["background"]), size_wh=size_wh)
    observer = SilhouetteObserver(observer_from_config(rig, bg, config["observation"], args.model, args.voxel),
                                  reference_silhouettes(rig, *reference_keypoints(args.demo)))
    tracker = MarkerlessTracker(Skeleton.from_urdf(), TrackerConfig.from_dict(config["tracker"], config["source"]))
    if start_pose is not None:
        angles, _, body = read_start_pose(start_pose)
        tracker.initialize_from_pose(angles, skeleton=body)
    poses, seconds = track_sequence(folder, observer, tracker, progress=False)
    print(f"reference silhouettes: occupied volume {np.mean(observer.volumes_m3):.3f} m^3 per frame (a body is about "
          "0.07)")
    return poses, seconds


def rigid_residuals(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(T, L, 3) points x, y -> (T, L) distances after the rigid motion that best takes each frame's x onto its y
    (:func:`~torchtrack.tracking.goals.weighted_kabsch`, batched over the frames)."""
    xt, yt = torch.from_numpy(np.asarray(x, np.float64)), torch.from_numpy(np.asarray(y, np.float64))
    R, t = weighted_kabsch(xt, yt, torch.ones(xt.shape[:2], dtype=xt.dtype))
    return (torch.einsum("tij,tlj->tli", R, xt) + t[:, None] - yt).norm(dim=-1).numpy()


def velocity_table(rows: list[tuple[float, float, float | None, int, int]]) -> str:
    """--velocities: one line per run (velocity, MPJPE against the raw and the filtered reference or None, lost
    frames, passes) and the medians of the two MPJPE columns over the runs."""
    lines = ["runs: velocity, MPJPE raw / filtered (mm), lost frames, passes"]
    for v, raw, filt, lost, passes in rows:
        lines.append(f"  {v:<6g} {raw:6.1f} / {'-' if filt is None else f'{filt:.1f}':>5s}  {lost:3d}  {passes:2d}")
    filts = [f for _, _, f, _, _ in rows if f is not None]
    med_f = f"{np.median(filts):.1f}" if len(filts) == len(rows) else "-"
    lines.append(f"  median {np.median([r for _, r, _, _, _ in rows]):6.1f} / {med_f:>5s}  over {len(rows)} runs")
    return "\n".join(lines)


def knee_bend(points: np.ndarray, names: list[str], side: str) -> np.ndarray:
    """(T, L, 3) -> (T,) the knee's bend (deg): the angle between the thigh (hip to knee) and the shank (knee to
    ankle), 0 for a straight leg."""
    hip, knee, ankle = (points[:, names.index(f"{side}_{j}")] for j in ("hip", "knee", "ankle"))
    u, v = knee - hip, ankle - knee
    # atan2 of |u x v| and u . v: well conditioned near a straight leg, where arccos of the cosine is not
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(u, v), axis=-1), (u * v).sum(-1)))


def print_alignment(poses: Poses, names: list[str], ref: np.ndarray) -> None:
    """--bias: the mean error per landmark (mm) after aligning each frame's landmarks to the reference rigidly,
    as one body and as an upper and a lower body apart (what a trunk that bends and twists freely would gain at
    most), after removing each landmark's mean offset (what is left that varies with time) and after removing
    the offset common to all of them (a shift of the whole track); and how much more the track bends each knee
    than the reference."""
    ref = ref[:poses.num_frames]
    idx = [list(poses.joint_names).index(n) for n in names]
    ok = poses.valid & np.isfinite(ref).all((1, 2))
    x, y = np.asarray(poses.joints3d)[:, idx][ok], ref[ok]
    up, low = [names.index(n) for n in UPPER], [names.index(n) for n in LOWER]
    whole = rigid_residuals(x, y).mean()
    apart = np.concatenate([rigid_residuals(x[:, up], y[:, up]), rigid_residuals(x[:, low], y[:, low])], 1).mean()
    d = x - y
    debiased = np.linalg.norm(d - d.mean(0), axis=-1).mean()
    shift = d.mean((0, 1))  # (3,) the offset common to every landmark and frame
    print(f"error after a rigid alignment per frame: {1e3 * whole:.1f} mm as one body, {1e3 * apart:.1f} mm with the "
          f"upper and the lower body aligned apart; after removing each landmark's mean offset: "
          f"{1e3 * debiased:.1f} mm; after removing their common offset ({', '.join(f'{1e3 * v:.0f}' for v in shift)}"
          f" mm, x y z): {1e3 * np.linalg.norm(d - shift, axis=-1).mean():.1f} mm")
    more = {side: knee_bend(x, names, side) - knee_bend(y, names, side) for side in ("l", "r")}
    print("knee bend, track - reference (deg): " + ", ".join(
        f"{side} mean {m.mean():.1f} (median {np.median(m):.1f})" for side, m in more.items()))


def picture(path: Path, folder: SequenceFolder, poses: Poses, t: int, scale: float) -> None:
    import cv2

    from torchtrack.tracking.draw import draw_pose_overlays

    W, H = (int(round(float(v) * scale)) for v in folder.rig.image_size_wh[0])
    rig = folder.rig.resized(W, H).float()
    img = folder.read_frame(t, size_wh=(W, H))
    lm = torch.as_tensor(poses.landmarks()[t])
    drawn = draw_pose_overlays(torch.nan_to_num(img), rig, lm, bone_width_px=3, joint_radius_px=4)
    tiles = [np.ascontiguousarray((d.permute(1, 2, 0).numpy() * 255).astype(np.uint8)[..., ::-1]) for d in drawn]
    for tile, name in zip(tiles, rig.names):
        cv2.putText(tile, f"{name} frame {t}", (6, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (255, 255, 255), 2, cv2.LINE_AA)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.concatenate(tiles, axis=1), [cv2.IMWRITE_JPEG_QUALITY, 85])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--demo", type=Path, default=DEMO)
    ap.add_argument("--scale", type=float, default=0.25)
    ap.add_argument("--voxel", type=float, default=0.03)
    ap.add_argument("--model", choices=("bayes", "hull"), default="bayes")
    ap.add_argument("--picture", type=Path, default=None)
    ap.add_argument("--init-from-reference", action="store_true",
                    help="start from the pose and body fitted to the reference keypoints of frame 0 (Kabsch + CCD "
                         "alternated with the bones' lengths; de Bem's saved initialisation) instead of the "
                         "automatic start")
    ap.add_argument("--scale-only", action="store_true",
                    help="with --init-from-reference or --reference-fit: the body is the template scaled to the "
                         "reference's height, without fitting its bones' lengths")
    ap.add_argument("--fill-prior-log-odds", type=float, default=0.0,
                    help="BackgroundConfig.fill_prior_log_odds: prior log odds of room against subject in the fill")
    ap.add_argument("--velocities", nargs="+", type=float, default=None, metavar="V",
                    help="one whole run per prediction velocity (TrackerConfig.velocity, after --tracker), then the "
                         "runs side by side with the medians of their MPJPE (the README's five: 0.5 0.47 0.53 0.45 "
                         "0.55, 4 min each); --bias, --save-poses and --picture take the last run")
    ap.add_argument("--tracker", nargs="*", default=[], metavar="FIELD=VALUE",
                    help="TrackerConfig overrides of the config's tracker section, e.g. velocity=0")
    ap.add_argument("--reference-silhouettes", action="store_true",
                    help="diagnostic: feed the Bayesian grid silhouettes drawn from the reference keypoints")
    ap.add_argument("--reference-background", action="store_true",
                    help="diagnostic: estimate each pixel's background from the frames the silhouettes drawn from "
                         "the reference keypoints leave free")
    ap.add_argument("--reference-fit", action="store_true",
                    help="print only the model's floor: the skeleton (the template scaled to the subject) fitted "
                         "to every reference frame at once, against the reference (no video)")
    ap.add_argument("--refine-passes", type=int, default=None,
                    help="background re-estimations from the track, each followed by a new track (default: the "
                         "config's background_refinement.passes; 0 with the reference diagnostics)")
    ap.add_argument("--refit", nargs="*", default=[], metavar="FIELD=VALUE",
                    help="BodyRefitConfig overrides of the config's body_refit section, e.g. passes=0 (no body refit "
                         "after the background refinement) or given_body=true (refit the body --init-from-reference "
                         "or --continue-from gives too)")
    ap.add_argument("--smoothing", nargs="*", default=[], metavar="FIELD=VALUE",
                    help="SmoothingConfig overrides of the config's smoothing section, e.g. cutoff_hz=0 (the track "
                         "as tracked; otherwise its figure before the smoothing is printed too)")
    ap.add_argument("--cutoffs", nargs="*", type=float, default=[], metavar="HZ",
                    help="also print the finished track smoothed at each of these cut-offs (0: not smoothed)")
    ap.add_argument("--refine", nargs="*", default=[], metavar="FIELD=VALUE",
                    help="RefineConfig overrides of the config's background_refinement section, e.g. blob_scale=1.5")
    ap.add_argument("--no-fill", action="store_true",
                    help="keep the subject's static parts in the estimated background (no fill_static_subject)")
    ap.add_argument("--silhouettes", action="store_true",
                    help="the start search scores bodies in each camera's foreground (observation.silhouettes: "
                         "true; the tracking config's null does so with the Bayesian grid)")
    ap.add_argument("--continue-from", type=Path, default=None, metavar="POSES",
                    help="start from a saved track of the demo (--save-poses): its first pose and body, and the "
                         "background re-estimated from it (with --refine-passes 0: one more pass of that run)")
    ap.add_argument("--background-from", type=Path, default=None, metavar="POSES",
                    help="the first track's background re-estimated from this saved track (e.g. a pass of "
                         "--save-passes) instead of the plain estimate; the start as given. With --refine-passes 0 "
                         "it replays the pass that followed that track, in a minute: a way to compare tracker "
                         "settings on one refined background")
    ap.add_argument("--save-passes", type=Path, default=None, metavar="DIR",
                    help="save each refinement pass's track as DIR/pass_NN.npz (01: the first track; files of "
                         "those names there are replaced)")
    ap.add_argument("--bias", action="store_true",
                    help="also print each landmark's mean signed offset from the reference (forward, left, up of "
                         "the reference's hips), where the reference's Neck sits against its shoulders, and the error "
                         "left after aligning each frame rigidly, as one body and as upper and lower body apart, "
                         "and how much more the track bends the knees")
    ap.add_argument("--score", type=Path, default=None, metavar="POSES",
                    help="only score POSES, a poses.npz of the demo (e.g. `torchtrack track`'s output of the "
                         "README's worked example), against the raw and the filtered reference, and exit")
    ap.add_argument("--per-landmark", action="store_true",
                    help="with --score: also print each landmark's mean error (mm)")
    ap.add_argument("--save-poses", type=Path, default=None,
                    help="write the kept track's poses.npz (with the fitted body) here, e.g. for "
                         "eval_pose2sim_occupancy.py --background-from-track")
    ap.add_argument("--start-scores", nargs="+", type=int, default=None, metavar="FRAME",
                    help="only start on each of these frames alone (the automatic start, on the background the "
                         "other options give) and print its error and two-way score against those of the pose "
                         "fitted to the frame's reference points, then exit")
    ap.add_argument("--log-searches", action="store_true",
                    help="print the tracker's searches (lost arms, headings, bone fit rounds) with their costs")
    args = ap.parse_args()
    if args.scale_only and not (args.init_from_reference or args.reference_fit):
        raise SystemExit("--scale-only changes the body of --init-from-reference or --reference-fit: give one")
    if args.reference_silhouettes and args.reference_background:
        raise SystemExit("--reference-silhouettes replaces the background: give one of the two")
    if args.continue_from is not None and (args.init_from_reference or args.reference_silhouettes
                                           or args.reference_background):
        raise SystemExit("--continue-from gives the start and the background: drop --init-from-reference and the "
                         "reference diagnostics")
    if args.background_from is not None and (args.continue_from is not None or args.reference_silhouettes
                                             or args.reference_background):
        raise SystemExit("--background-from gives the background: drop --continue-from and the reference "
                         "diagnostics")
    if args.background_from is not None and not args.init_from_reference:
        raise SystemExit("--background-from replays a pass of a reference-started run: give --init-from-reference "
                         "(the demo has no starfish start for the automatic one)")
    if args.save_passes is not None and args.velocities:
        raise SystemExit("--save-passes keeps one run's passes: drop --velocities")
    if args.save_passes is not None and not args.save_passes.is_dir():
        raise SystemExit(f"--save-passes {args.save_passes}: not a folder")
    if args.save_poses is not None and not args.save_poses.parent.is_dir():  # before minutes of tracking
        raise SystemExit(f"--save-poses {args.save_poses}: the folder {args.save_poses.parent} does not exist")
    logging.basicConfig(level=logging.WARNING)
    if args.log_searches:
        logging.getLogger("torchtrack.tracking.markerless").setLevel(logging.DEBUG)
    torch.set_grad_enabled(False)
    if not (args.demo / "videos").is_dir():
        raise SystemExit(f"{args.demo}: the Pose2Sim demo is not there")
    config = load_config("markerless.yaml")
    if args.silhouettes:
        config["observation"] = {**config["observation"], "silhouettes": True}
    if args.reference_fit:
        reference_fit(args.demo, not args.scale_only)
        return
    if args.score is not None:
        score(args.score, args.demo, args.per_landmark)
        return
    with tempfile.TemporaryDirectory() as tmp:
        folder = SequenceFolder(pose2sim_sequence(args.demo, Path(tmp) / "seq"))
        W, H = (int(round(float(v) * args.scale)) for v in folder.rig.image_size_wh[0])
        try:  # every override checked against its section's fields before minutes of tracking
            config = overridden(config, "tracker", TrackerConfig, args.tracker, "--tracker")
            config = overridden(config, "background_refinement", RefineConfig, args.refine, "--refine")
            config = overridden(config, "body_refit", BodyRefitConfig, args.refit, "--refit")
            config = overridden(config, "smoothing", SmoothingConfig, args.smoothing, "--smoothing")
        except InputError as e:
            raise SystemExit(str(e)) from None
        config["background"] = {**(config.get("background") or {}), "fill_static_subject": not args.no_fill,
                                 "fill_prior_log_odds": args.fill_prior_log_odds}
        names, ref = reference_landmarks(args.demo)
        background = None
        if args.reference_background:
            bg_config = BackgroundConfig(**config["background"])
            frames = torch.cat([b.images.half() for b in folder.iter_batches(20, size_wh=(W, H))])  # (T, C, 3, H, W)
            rig = folder.rig.resized(W, H).float()
            masks = dilate(reference_silhouettes(rig, *reference_keypoints(args.demo)), REFERENCE_MARGIN_PX)
            background = BackgroundModel.from_sequence(frames, bg_config, folder.camera_names, subject_masks=masks)
            del frames
            used = subsample(masks, bg_config.max_frames)  # the frames from_sequence took
            free = (~used).sum(0) >= MIN_CLEAN_FRAMES  # (C, H, W)
            ever = masks.any(0)
            print(f"reference background: {used.shape[0]} frames; {100 * float((free & ever).sum() / ever.sum()):.0f} "
                  f"% of the pixels the masks ever cover are free in >= {MIN_CLEAN_FRAMES} of them")
        if args.start_scores is not None:
            if background is None:
                background = BackgroundModel.from_folder(folder, BackgroundConfig(**config["background"]),
                                                         size_wh=(W, H))
            start_scores(folder, background, config, args, (W, H))
            return
        start_pose = None  # the start given to the tracker: None, the automatic one
        if args.init_from_reference:
            angles, body = fit_to_landmarks(Skeleton.from_urdf(), names, ref[0], fit_bones=not args.scale_only)
            start_pose = initial_pose(body, angles, fps=folder.fps)
            print(f"initial pose and body fitted to the reference of frame 0 (height {body.height():.2f} m, "
                  f"{'bone lengths fitted' if not args.scale_only else 'the template scaled'})")
        earlier = args.background_from
        if args.continue_from is not None:
            try:
                start_pose = earlier = load_poses(args.continue_from)
            except InputError as e:
                raise SystemExit(str(e)) from None
            print(f"continuing {args.continue_from}: its first valid frame and body, the background re-estimated "
                  "from its track")
        passes_asked = (config["background_refinement"]["passes"] if args.refine_passes is None
                        else args.refine_passes)
        if args.reference_silhouettes or args.reference_background:
            passes_asked = 0
        if args.save_passes is not None and passes_asked == 0:
            raise SystemExit("--save-passes saves the refinement's passes, and this run has none (--save-poses "
                             "keeps its one track)")
        outputs = list(Skeleton.from_urdf().output_names)
        truth = reference_poses(names, ref, folder.fps, outputs)
        filtered = None
        if (args.demo / REFERENCE_FILTERED).is_file():
            names_f, ref_f = reference_landmarks(args.demo, filtered=True)
            filtered = reference_poses(names_f, ref_f, folder.fps, outputs)
        else:
            print(f"(no {REFERENCE_FILTERED} in {args.demo}: no figure against Pose2Sim's filtered keypoints)")

        def track_once(velocity: float | None) -> tuple[Poses, object, object, int]:
            """One whole run of `torchtrack track` (every refinement pass and body refit, unsmoothed), reported pass
            by pass: the finished track, its report against the raw and (or None) the filtered reference, and its
            number of passes."""
            cfg = config if velocity is None else {**config, "tracker": {**config["tracker"], "velocity": velocity}}
            passes: list[Poses] = []
            refits: list[bool] = []

            def report_pass(p: int, poses: Poses) -> None:  # each pass's error, for the refinement's progress
                if not passes_asked:
                    return
                r = evaluate(poses, truth, landmarks=names)
                if "refinement_pass" in poses.extra:  # the kept pass, tracked once more
                    print(f"kept pass {int(poses.extra['refinement_pass'])} (the best fit), tracked again: MPJPE "
                          f"{r.mpjpe_mm:.1f} mm", flush=True)
                    return
                moved = f", moved {1e3 * track_change_m(poses, passes[-1]):.1f} mm from the pass before" if passes else ""
                print(f"pass {p + 1} (of at most {passes_asked + 1}): MPJPE {r.mpjpe_mm:.1f} mm, "
                      f"{int((~poses.valid).sum())} lost, IK residual {1e3 * mean_ik_residual_m(poses):.2f} mm"
                      f"{moved}", flush=True)
                passes.append(poses)
                if args.save_passes is not None:
                    save_poses(poses, args.save_passes / f"pass_{len(passes):02d}.npz")

            def report_refit(p: int, poses: Poses, kept: bool) -> None:  # each body refit's error
                r = evaluate(poses, truth, landmarks=names)
                print(f"body refit {p}: MPJPE {r.mpjpe_mm:.1f} mm, IK residual {1e3 * mean_ik_residual_m(poses):.1f} "
                      f"mm, {int((~poses.valid).sum())} lost, {'kept' if kept else 'turned down'}", flush=True)
                refits.append(kept)

            try:
                if args.reference_silhouettes:
                    poses, seconds = track_on_silhouettes(folder, cfg, args, start_pose, (W, H))
                else:
                    result = track(folder, config=cfg, model=args.model, voxel_m=args.voxel, scale=args.scale,
                                   init_pose=start_pose, fill_static_subject=not args.no_fill,
                                   refine_passes=passes_asked, smooth_hz=0.0, background=background,
                                   background_from_track=earlier, threads=None, progress=False,
                                   on_pass=report_pass, on_refit=report_refit)
                    poses, seconds = result.poses, result.seconds
            except InputError as e:  # e.g. no frame to start from: the message says what to do
                raise SystemExit(f"tracking failed: {e}") from None
            late = passes[FIRST_COMPARED_PASS - 1:]  # how well the track's own fit ranks the passes' errors
            if len(late) >= 3:
                err = [evaluate(q, truth, landmarks=names).mpjpe_mm for q in late]
                res = [1e3 * mean_ik_residual_m(q) for q in late]
                print(f"passes {FIRST_COMPARED_PASS}-{len(passes)}: correlation of the mean IK residual with the "
                      f"MPJPE {np.corrcoef(res, err)[0, 1]:.2f} (residual {min(res):.2f}-{max(res):.2f} mm, MPJPE "
                      f"{min(err):.1f}-{max(err):.1f} mm)", flush=True)
            body = tracked_body(poses, "the track")
            if args.cutoffs:  # the same track smoothed at other cut-offs
                line = []
                for hz in args.cutoffs:
                    other = smooth_track(poses, body, replace(smoothing_config(cfg), cutoff_hz=hz))
                    f_mm = "" if filtered is None else f" / {evaluate(other, filtered, landmarks=names_f).mpjpe_mm:.1f}"
                    line.append(f"{hz:g} Hz {evaluate(other, truth, landmarks=names).mpjpe_mm:.1f}{f_mm}")
                print("cut-offs (MPJPE mm, raw / filtered reference): " + ", ".join(line), flush=True)
            smoothed = smooth_track(poses, body, smoothing_config(cfg))  # as torchtrack track writes it
            if float(smoothed.extra["smoothing_cutoff_hz"]):
                r = evaluate(poses, truth, landmarks=names)
                line = f"before smoothing: MPJPE {r.mpjpe_mm:.1f} mm, worst frame {r.max_frame_mm:.1f} mm"
                if filtered is not None:
                    line += f"; {evaluate(poses, filtered, landmarks=names_f).mpjpe_mm:.1f} mm from the filtered"
                print(line, flush=True)
            poses = smoothed
            rep = evaluate(poses, truth, landmarks=names)
            tracks = max(len(passes), 1) + ("refinement_pass" in poses.extra) + len(refits)
            print(f"Pose2Sim demo, {args.model}, {W}x{H}, {args.voxel * 100:.0f} cm voxels, background refined "
                  f"{max(len(passes) - 1, 0)} times, body refitted {sum(refits)} of {len(refits)} times, "
                  f"{poses.num_frames * tracks / seconds:.1f} frames/s, subject height "
                  f"{float(poses.extra['subject_height_m']):.2f} m")
            print(rep.format())
            rep_f = None
            if filtered is not None:
                rep_f = evaluate(poses, filtered, landmarks=names_f)
                print(f"against Pose2Sim's filtered keypoints (its final output, REFERENCE_FILTERED): MPJPE "
                      f"{rep_f.mpjpe_mm:.1f} mm, worst frame {rep_f.max_frame_mm:.1f} mm")
            return poses, rep, rep_f, max(len(passes), 1)

        if not args.velocities:
            poses, rep, _, _ = track_once(None)
        else:  # one whole run per prediction velocity, then the runs side by side and their medians
            runs = []
            for v in args.velocities:
                print(f"--- velocity {v:g} ---", flush=True)
                runs.append((v, *track_once(v)))
            poses, rep = runs[-1][1], runs[-1][2]
            print(velocity_table([(v, r.mpjpe_mm, None if rf is None else rf.mpjpe_mm,
                                   int((~p.valid).sum()), n) for v, p, r, rf, n in runs]))
        if args.bias:
            print_bias(poses, names, ref, args.demo)
            print_alignment(poses, names, ref)
        if args.save_poses is not None:
            save_poses(poses, args.save_poses)
            print(f"wrote {args.save_poses}")
        if args.picture is not None:
            ok = np.flatnonzero(poses.valid)
            if ok.size:
                errs = rep.per_frame_mm
                t = int(rep.frame_index[np.argsort(errs)[len(errs) // 2]])
                picture(args.picture, folder, poses, t, 0.5)
                print(f"picture of frame {t} (median error) in {args.picture}")


if __name__ == "__main__":
    main()
