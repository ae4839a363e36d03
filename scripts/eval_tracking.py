"""Markerless tracking accuracy on synthetic sequences: MPJPE over the 16 landmarks per motion, camera count
and observation model (issue targets: 8 cameras <= 30 mm with no frame over 100 mm; 4 cameras <= 45 mm).

Renders each sequence once (cached under --work), tracks it with the library's defaults
(configs/markerless.yaml) and evaluates against its gt.npz.

    .venv/bin/python scripts/eval_tracking.py                       # everything (about 100 minutes on 2 cores)
    .venv/bin/python scripts/eval_tracking.py --motions walk --cameras 8 --models bayes
    .venv/bin/python scripts/eval_tracking.py --motions squat --cameras 4 --background shadow_min_ratio=0
    .venv/bin/python scripts/eval_tracking.py --motions cmu:131_02 --cameras 8 --proportions
    .venv/bin/python scripts/eval_tracking.py --motions walk --tracker fit_bone_lengths=false   # one scale
    .venv/bin/python scripts/eval_tracking.py --motions cmu:131_01 --cameras 8 --true-body    # without the fit
    .venv/bin/python scripts/eval_tracking.py --motions cmu:131_02 --cameras 8 --models hull --trunk  # pelvis tilt
    .venv/bin/python scripts/eval_tracking.py --cameras 4 --outside            # the voxels' share outside the body
    .venv/bin/python scripts/eval_tracking.py --cameras 4 --oracle-margin 0.04 # ghosts removed by the truth
    .venv/bin/python scripts/eval_tracking.py --motions cmu:131_02 --cameras 4 --models hull --fit-rounds 10
    .venv/bin/python scripts/eval_tracking.py --cameras 8 --hips     # where the thighs pivot (functional_hips)
    .venv/bin/python scripts/eval_tracking.py --motions cmu:131_01 --cameras 4 --models hull --start --blob-activity
    .venv/bin/python scripts/eval_tracking.py --motions cmu:131_01 --cameras 4 --models hull --log-searches \
        --tracker lost_hand_frames=10
    .venv/bin/python scripts/eval_tracking.py --motions squat --cameras 4 --models hull --coverage  # what voxels miss
    .venv/bin/python scripts/eval_tracking.py --cameras 4 --models hull --refit passes=0  # without the body refit
    .venv/bin/python scripts/eval_tracking.py --smoothing cutoff_hz=0   # the track as tracked, not smoothed
    .venv/bin/python scripts/eval_tracking.py --motions kick --cameras 4 --models hull --cutoffs 3 4 6 10

The row is the finished track as `torchtrack track` writes it: after the body refit, smoothed in time (the
config's ``smoothing`` section); the column ``unsm.`` is its MPJPE before the smoothing. Rows come from the
library call `torchtrack.track`; the diagnostics that look inside a track (--true-body, --oracle-margin,
--outside, --coverage, --blob-activity, --hips, --refit-passes) assemble the same pipeline from its parts with a
recording tracker and observer.
"""

from __future__ import annotations

import argparse
import logging
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from torchtrack.background import BackgroundConfig, BackgroundModel
from torchtrack.blobs.shape import unit_ball_samples
from torchtrack.checks import InputError, with_overrides
from torchtrack.conventions import LANDMARKS
from torchtrack.eval import evaluate
from torchtrack.io.poses import load_poses
from torchtrack.io.sequence import SequenceFolder
from torchtrack.io.video import frame_ranges
from torchtrack.occupancy.metrics import inside_ellipsoids
from torchtrack.skeleton import Skeleton, root_rotation_matrix
from torchtrack.synth.scene import SceneConfig
from torchtrack.synth.sequence import RigConfig, SynthConfig, is_current, write_sequence
from torchtrack.tracking.body_refit import BodyRefitConfig, mean_ik_residual_m, track_with_body_refit
from torchtrack.tracking.pipeline import load_config, observer_from_config
from torchtrack.tracking.pipeline import track as library_track
from torchtrack.tracking.refine import track_body
from torchtrack.tracking.markerless import BONE_FIT_VOXEL_M, FrameResult, MarkerlessTracker, TrackerConfig
from torchtrack.tracking.observation import VoxelObservation
from torchtrack.tracking.run import track_sequence
from torchtrack.tracking.smoothing import SmoothingConfig, smooth_track

CMU = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "mocap" / "cmu"
MOTIONS = ("walk", "turn", "arm_raise", "squat", "kick", "cmu:131_01", "cmu:131_02")


#: Printed by --fit-rounds.
FIT_PROPORTIONS = ("torso", "neck_above_shoulders", "head", "l_upperarm", "l_thigh")
#: Printed by --proportions (Skeleton.proportions keys).
PROPORTIONS = ("height", "torso", "neck_above_shoulders", "head", "l_upperarm", "l_forearm", "l_thigh", "l_shank")


def sequence(work: Path, motion: str, cameras: int, duration: float, fmt: str) -> Path:
    out = work / f"{motion.replace(':', '_')}_{cameras}cam"
    src = str(CMU / f"{motion[4:]}.bvh") if motion.startswith("cmu:") else motion
    cfg = SynthConfig(motion=src, duration_s=duration, starfish_s=0.5, video_format=fmt,
                      rig=RigConfig(num_cameras=cameras), scene=SceneConfig())
    if not is_current(out, cfg):  # rendered before with other settings or another body model
        write_sequence(cfg, out, device="cpu", progress=False)
    return out


#: --outside: a voxel counts as outside the body beyond this distance from its ellipsoids (m).
OUTSIDE_M = 0.04


class AgainstTruth(torch.nn.Module):
    """Diagnostic around an observer, for frames observed in order from frame 0 in this process: records the share
    of each frame's voxel weight outside the rendered body's ellipsoids grown by OUTSIDE_M (ghosts, shadows), and
    with ``margin`` set leaves out the voxels outside them grown by ``margin`` (an oracle: tracking without
    ghosts)."""

    def __init__(self, observer: torch.nn.Module, truth: dict, margin: float | None) -> None:
        super().__init__()
        self.inner, self.truth, self.margin = observer, truth, margin
        self.rig, self.model = observer.rig, observer.model
        self.frame, self.outside = 0, []
        self.first: VoxelObservation | None = None  # the first frame's observation (--coverage)

    def _inside(self, obs: VoxelObservation, t: int, grow: float) -> torch.Tensor:
        g = self.truth
        return inside_ellipsoids(obs.points.double(), torch.from_numpy(g["blob_centres"][t]).double(),
                                 torch.from_numpy(g["blob_R_world"][t]).double(),
                                 torch.from_numpy(g["blob_semi_axes"]).double() + grow)

    def forward(self, images: torch.Tensor, cameras_valid: torch.Tensor | None = None) -> list[VoxelObservation]:
        out = []
        for obs in self.inner(images, cameras_valid):
            t, self.frame = self.frame, self.frame + 1
            if t == 0:
                self.first = obs
            w = obs.weights.double()
            self.outside.append(float(w[~self._inside(obs, t, OUTSIDE_M)].sum() / w.sum().clamp(min=1e-30)))
            if self.margin is not None:
                keep = self._inside(obs, t, self.margin)
                obs = VoxelObservation(obs.points[keep], obs.sizes[keep], obs.weights[keep], obs.colours[keep],
                                       obs.cameras_valid, camera_centres=obs.camera_centres, volume_m=obs.volume_m)
            out.append(obs)
        return out


#: --coverage: a sample of a rendered blob's inside counts as missed farther than this from every voxel cube (m),
#: and the blobs listed are those missed by more than COVERAGE_LIST of their inside.
COVERAGE_M, COVERAGE_LIST = 0.01, 0.05


def coverage(obs: VoxelObservation, truth: dict, t: int = 0, samples: int = 500) -> tuple[dict[str, float], float]:
    """--coverage: what a frame's voxels miss of the rendered body. Returns each blob's share of its solid ellipsoid
    (``samples`` points uniform inside it, those in the observed volume) farther than COVERAGE_M from every voxel
    cube (the exact distance, over all cubes), and how far the highest voxel centre within the head's ellipsoid
    grown by OUTSIDE_M lies under the ellipsoid's top (m; NaN without such a voxel). The shape fit
    (``bone_fit: shape``) takes what is missed for the body's shape."""
    names = [str(n) for n in truth["blob_names"]]
    c = torch.from_numpy(truth["blob_centres"][t]).double()  # (K, 3)
    R = torch.from_numpy(truth["blob_R_world"][t]).double()  # (K, 3, 3)
    a = torch.from_numpy(truth["blob_semi_axes"]).double()  # (K, 3)
    p, size = obs.points.double(), obs.sizes.double()
    q = c[:, None, :] + torch.einsum("kij,kmj->kmi", R, a[:, None, :] * unit_ball_samples(samples)[None])  # (K, M, 3)
    q = q.reshape(-1, 3)
    d = torch.cat([((x[:, None, :] - p[None]).abs() - size[None, :, None] / 2).clamp(min=0).norm(dim=-1).amin(1)
                   for x in q.split(64)]).reshape(len(names), samples)  # (K, M) to the nearest cube
    seen = torch.ones_like(d, dtype=torch.bool)
    if obs.volume_m is not None:  # the observed box's sides and top (nothing stands below the floor)
        lower, upper = (q.new_tensor(v) for v in obs.volume_m)
        seen = ((q[:, :2] >= lower[:2]).all(-1) & (q <= upper).all(-1)).reshape(d.shape)
    missed = ((d > COVERAGE_M) & seen).sum(1) / seen.sum(1).clamp(min=1)
    h = names.index("head")
    top = float(c[h, 2] + (R[h, 2] * a[h]).norm())  # the ellipsoid's highest point
    near = inside_ellipsoids(p, c[h:h + 1], R[h:h + 1], a[h:h + 1] + OUTSIDE_M)
    under = top - float(p[near, 2].max()) if bool(near.any()) else float("nan")
    return dict(zip(names, missed.tolist())), under


def coverage_line(missed: dict[str, float], head_under: float) -> str:
    listed = ", ".join(f"{n} {100 * v:.1f}" for n, v in missed.items() if v > COVERAGE_LIST) or "none"
    return (f"first frame, the rendered blobs' inside farther than {100 * COVERAGE_M:g} cm from the voxels (%, over "
            f"{100 * COVERAGE_LIST:g}): {listed}; the head's highest voxel centre {100 * head_under:.1f} cm under "
            "its top")


class RecordingTracker(MarkerlessTracker):
    """A tracker that keeps, for every frame it is given, which blobs were active after EM (``active``: (K,) bool
    arrays, None for a frame not tracked): --blob-activity."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.active: list[np.ndarray | None] = []

    def step(self, obs: VoxelObservation) -> FrameResult:
        res = super().step(obs)
        self.active.append(None if res.blobs is None else res.blobs.active.cpu().numpy().copy())
        return res

    def skip(self) -> FrameResult:
        self.active.append(None)
        return super().skip()

    def initialize_from_pose(self, *args, **kwargs) -> None:
        self.active = []  # a new track of the sequence (the body refit's)
        super().initialize_from_pose(*args, **kwargs)


def blob_activity(tracker: RecordingTracker) -> list[str]:
    """--blob-activity: each blob that was de-activated in some tracked frame, and the frames."""
    names = tracker.subject.blobs.names
    lines = []
    for k, name in enumerate(names):
        off = [t for t, a in enumerate(tracker.active) if a is not None and not a[k]]
        if off:
            lines.append(f"{name} off in {len(off)} frame{'s' if len(off) > 1 else ''}: {frame_ranges(off)}")
    return lines or ["every blob active in every tracked frame"]


def start_heights(poses, truth) -> str:
    """--start: each landmark's height in the first frame, tracked less true (cm)."""
    d = 100 * (poses.landmarks()[0, :, 2] - truth.landmarks()[0, :, 2])
    return "first frame, height tracked - true (cm): " + ", ".join(f"{n} {v:+.1f}" for n, v in zip(LANDMARKS, d))


def _observer(seq: Path, model: str, config: dict, background: BackgroundConfig) -> tuple[SequenceFolder, object]:
    """The sequence folder and the observer the config's ``observation`` section makes for it."""
    folder = SequenceFolder(seq)
    ocfg = config["observation"]
    scale = float(ocfg.get("scale", 1.0))
    W, H = (int(round(float(v) * scale)) for v in folder.rig.image_size_wh[0])
    rig = folder.rig.resized(W, H).float()
    bg = BackgroundModel.from_folder(folder, background, size_wh=(W, H))
    return folder, observer_from_config(rig, bg, ocfg, model, float(ocfg.get("voxel_m", 0.03)))


def track(seq: Path, model: str, config: dict, background: BackgroundConfig = BackgroundConfig(),
          tracker_overrides: Sequence[str] = (), true_body: bool = False, oracle_margin: float | None = None,
          start: tuple[torch.Tensor, Skeleton] | None = None) -> tuple[object, float, MarkerlessTracker, AgainstTruth]:
    """Track ``seq``; with ``true_body`` on the rendered body (its body.urdf) from the first ground-truth pose,
    without the starfish initialisation or the bone fit: what is left is the observation's and EM/IK's error;
    with ``start`` (angles (D,), skeleton) from that pose and body. The observer is wrapped in
    :class:`AgainstTruth` (``oracle_margin``: its margin)."""
    folder, observer = _observer(seq, model, config, background)
    observer = AgainstTruth(observer, dict(np.load(seq / "gt.npz")), oracle_margin)
    tracker_config = with_overrides(TrackerConfig.from_dict(config["tracker"], config["source"]), tracker_overrides,
                                    "--tracker")
    if true_body:
        body = Skeleton.from_urdf(seq / "body.urdf")
        tracker = RecordingTracker(body, tracker_config)
        angles = torch.from_numpy(load_poses(seq / "gt.npz").angles[0]).float()
        tracker.initialize_from_pose(angles, body.height())
    else:
        tracker = RecordingTracker(Skeleton.from_urdf(), tracker_config)
        if start is not None:
            tracker.initialize_from_pose(start[0], skeleton=start[1])
    poses, elapsed = track_sequence(folder, observer, tracker, progress=False)  # in this process, frames in order
    return poses, poses.num_frames / elapsed, tracker, observer


def with_settings(config: dict, section: str, items: Sequence[str], validated) -> dict:
    """``config`` with the ``FIELD=VALUE`` items of a command-line option set in ``section``, each value as the
    option's dataclass ``validated`` parsed it."""
    out = {k: (dict(v) if isinstance(v, dict) else v) for k, v in config.items()}
    for item in items:
        name = item.partition("=")[0]
        out.setdefault(section, {})[name] = getattr(validated, name)
    return out


def track_plain(seq: Path, model: str, config: dict) -> tuple[object, Skeleton, float]:
    """``seq`` tracked by :func:`torchtrack.track` as `torchtrack track` tracks it, before the smoothing: the
    track, its body and frames per second (the whole call's, refits included)."""
    result = library_track(seq, config=config, model=model, smooth_hz=0, workers=None, progress=False)
    return result.poses, track_body(result.poses, str(seq)), result.poses.num_frames / result.seconds


def refit_passes(seq: Path, model: str, config: dict, background: BackgroundConfig, poses, tracker: MarkerlessTracker,
                 refit: BodyRefitConfig, oracle_margin: float | None, truth, label: str):
    """The body refit's passes after the first track (:func:`track_with_body_refit`, as ``torchtrack track``),
    each pass's error, IK residual and refitted proportions printed; returns the kept track. --outside,
    --coverage and the fps column describe the first track (the observation is the same), --blob-activity the
    kept one; --hips the tracker as the refit leaves it (a given body: no hips learnt)."""
    if refit.passes == 0:
        return poses
    if oracle_margin is not None:  # the refit observes single frames, which AgainstTruth's counter cannot place
        print(f"    {label}: no body refit with --oracle-margin", flush=True)
        return poses
    folder, inner = _observer(seq, model, config, background)
    true_props = Skeleton.from_urdf(seq / "body.urdf").proportions()

    actives = {0: tracker.active}  # --blob-activity: each track's, the kept one's put back at the end
    last_kept = 0

    def show(p: int, new, kept: bool) -> None:
        nonlocal last_kept
        actives[p] = tracker.active
        last_kept = p if kept else last_kept
        fit = tracker.subject.skeleton.proportions()
        print(f"    {label}: body refit {p}: {evaluate(new, truth).mpjpe_mm:.1f} mm, IK residual "
              f"{1e3 * mean_ik_residual_m(new):.1f} mm, {'kept' if kept else 'turned down'}; body (true) m: "
              + ", ".join(f"{n} {fit[n]:.3f} ({true_props[n]:.3f})" for n in PROPORTIONS), flush=True)

    print(f"    {label}: first track {evaluate(poses, truth).mpjpe_mm:.1f} mm, IK residual "
          f"{1e3 * mean_ik_residual_m(poses):.1f} mm", flush=True)
    kept, _ = track_with_body_refit(folder, lambda: inner, tracker, poses, refit, progress=False, on_pass=show)
    tracker.active = actives[last_kept]
    return kept


def fit_rounds(seq: Path, model: str, config: dict, rounds: int, background: BackgroundConfig = BackgroundConfig(),
               tracker_overrides: Sequence[str] = ()) -> None:
    """--fit-rounds: the bone fit alone, round after round, on the observation of the first frame at its true
    pose, from the template scaled to the true height: its ridge towards that start (the tracker's) and towards
    each round's own body (the alternative; docs/results.md, "Tracker settings"). Prints the fitted proportions after each round."""
    folder, observer = _observer(seq, model, config, background)
    W, H = (int(v) for v in observer.rig.image_size_wh[0].tolist())
    fb = next(iter(folder.iter_batches(1, 0, 1, size_wh=(W, H))))
    obs = observer(fb.images, fb.valid)[0].split(BONE_FIT_VOXEL_M)
    body = Skeleton.from_urdf(seq / "body.urdf")
    res = FrameResult(angles=torch.from_numpy(load_poses(seq / "gt.npz").angles[0]).float(), output_points=None,
                      confidence=None, valid=True, residual_m=0.0, explained=1.0, reinitialised=False, blobs=None,
                      bone_frames=None)
    true = body.proportions()
    print("    true: " + ", ".join(f"{k} {true[k]:.3f}" for k in FIT_PROPORTIONS))
    for anchored in (True, False):
        tracker_config = with_overrides(TrackerConfig.from_dict(config["tracker"], config["source"]),
                                        tracker_overrides, "--tracker")
        tracker = MarkerlessTracker(Skeleton.from_urdf(), tracker_config)
        tracker._setup(body.height(), torch.device("cpu"))
        start = tracker.subject.skeleton
        for r in range(rounds):
            fitted, change = tracker._fit_bone_lengths(obs, res, start if anchored else tracker.subject.skeleton)
            tracker._use(fitted)
            p = fitted.proportions()
            print(f"    ridge towards {'the start' if anchored else 'each round'}, round {r + 1}: "
                  + ", ".join(f"{k} {p[k]:.3f}" for k in FIT_PROPORTIONS) + f" (change {change:.3f})", flush=True)


def trunk_errors(poses, truth, skeleton: Skeleton) -> tuple[np.ndarray, np.ndarray]:
    """--trunk, per valid frame: the angle (deg) between the tracked and the true pelvis' up axes (from the root's
    rotation), and whether a tracked thigh is at its hip extension limit (within 0.5 deg)."""
    names = list(poses.dof_names)
    rot = [names.index(n) for n in ("root_rz", "root_ry", "root_rx")]
    ok = poses.valid & truth.valid[:len(poses.valid)]
    up = [root_rotation_matrix(torch.from_numpy(np.asarray(p.angles)[ok][:, rot]).double())[:, :, 2]
          for p in (poses, truth)]
    tilt = np.degrees(np.arccos(np.clip((up[0] * up[1]).sum(-1).numpy(), -1.0, 1.0)))
    hips = skeleton.dof_index(["l_hip_flex", "r_hip_flex"])
    lower = skeleton.lower[hips].double().numpy()
    at_limit = (np.asarray(poses.angles)[ok][:, hips.numpy()] <= lower + np.radians(0.5)).any(-1)
    return tilt, at_limit


def trunk_headings(poses, truth, skeleton: Skeleton) -> dict[str, np.ndarray]:
    """--trunk, per valid frame (deg): how far the tracked pelvis' and torso's headings (the yaw of their bones'
    left axes, by ``skeleton``'s forward kinematics: the heading does not depend on the bones' lengths) lie from
    the true ones, and from the mean of the true two (where a trunk that will not twist puts both); and the true
    and the tracked twist between them."""
    ok = poses.valid & truth.valid[:len(poses.valid)]
    bones = [skeleton.bone_names.index(b) for b in ("pelvis", "torso")]

    def headings(p) -> np.ndarray:  # (n, 2) pelvis, torso
        left = skeleton.forward(torch.from_numpy(np.asarray(p.angles, np.float32)[ok])).bone_frames[:, bones, :3, 1]
        return np.degrees(np.arctan2(left[..., 1].numpy(), left[..., 0].numpy()))

    def wrap(x: np.ndarray) -> np.ndarray:
        return (x + 180.0) % 360.0 - 180.0

    tracked, true = headings(poses), headings(truth)
    twist = wrap(true[:, 1] - true[:, 0])
    mean = true[:, 0] + 0.5 * twist
    off = np.abs(wrap(tracked - true))
    from_mean = np.abs(wrap(tracked - mean[:, None]))
    return {"pelvis": off[:, 0], "torso": off[:, 1], "pelvis_from_mean": from_mean[:, 0],
            "torso_from_mean": from_mean[:, 1], "true_twist": np.abs(twist),
            "tracked_twist": np.abs(wrap(tracked[:, 1] - tracked[:, 0]))}


def headings_line(h: dict[str, np.ndarray]) -> str:
    """--trunk: :func:`trunk_headings` in one line (deg)."""
    def both(keys: Sequence[str], suffix: str = "") -> str:
        return ", ".join(f"{k} {h[k + suffix].mean():.1f} / {h[k + suffix].max():.1f}" for k in keys)

    return (f"headings off the true ones (deg, mean / worst frame): {both(('pelvis', 'torso'))}; off the mean of the "
            f"true two: {both(('pelvis', 'torso'), '_from_mean')}; twist between them: "
            f"{both(('true', 'tracked'), '_twist')}")


def hips_outcome(tracker: MarkerlessTracker, cameras: int) -> str:
    """--hips: what the functional hips did on a tracked sequence."""
    cfg = tracker.config
    if tracker.hip_estimate is not None:
        above, info = (1e3 * tracker.hip_estimate[0]).tolist(), tracker.hip_estimate[1].tolist()
        done = (f"moved up {1e3 * tracker.hip_shifts[0]:.1f} mm" if tracker.hip_shifts
                else "not moved (a move up of at most FUNCTIONAL_HIPS_MAX_M is made)")
        return (f"hips: the thighs pivot {above[0]:.0f} / {above[1]:.0f} mm above the fitted hips (information "
                f"{info[0]:.1f} / {info[1]:.1f}): {done}")
    if cfg.functional_hips <= 0:
        return "hips: functional_hips off"
    if cameras < cfg.functional_hips_min_cameras:
        return f"hips: not learnt ({cameras} cameras < functional_hips_min_cameras {cfg.functional_hips_min_cameras})"
    if tracker.hips is None:
        return "hips: not learnt (a given body)"
    info = tracker.hips.information().tolist()
    return (f"hips: the thighs gathered information {info[0]:.1f} / {info[1]:.1f} of the {cfg.functional_hips:g} "
            "needed: not moved")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--motions", nargs="+", default=list(MOTIONS))
    ap.add_argument("--cameras", nargs="+", type=int, default=[8, 4])
    ap.add_argument("--models", nargs="+", default=["bayes", "hull"])
    ap.add_argument("--duration", type=float, default=3.0, help="seconds of motion after the starfish start")
    ap.add_argument("--format", choices=("mp4", "png"), default="mp4")
    ap.add_argument("--config", default="markerless.yaml")
    ap.add_argument("--work", type=Path, default=Path("out/eval_tracking"))
    ap.add_argument("--background", nargs="*", default=[], metavar="FIELD=VALUE",
                    help="BackgroundConfig overrides, e.g. shadow_min_ratio=0 (the paper's plain relaxation)")
    ap.add_argument("--proportions", action="store_true",
                    help="also print the tracked subject's proportions against the rendered body's")
    ap.add_argument("--tracker", nargs="*", default=[], metavar="FIELD=VALUE",
                    help="TrackerConfig overrides of the config's tracker section, e.g. fit_bone_lengths=false")
    ap.add_argument("--true-body", action="store_true",
                    help="track with the rendered body from the first ground-truth pose (no initialisation, no "
                         "bone fit): separates the fit's share of the error")
    ap.add_argument("--trunk", action="store_true",
                    help="also print how far the tracked pelvis tilts from the true one (mean and worst frame), the "
                         "share of frames with a thigh at its extension limit, and how far the pelvis' and the "
                         "torso's headings lie from the true ones and from the mean of the true two")
    ap.add_argument("--outside", action="store_true",
                    help=f"also print the share of the voxel weight outside the rendered body grown by "
                         f"{OUTSIDE_M * 100:g} cm (ghosts, shadows), mean over frames")
    ap.add_argument("--oracle-margin", type=float, default=None, metavar="M",
                    help="diagnostic: leave out the voxels outside the rendered body grown by M metres (tracking "
                         "without ghosts)")
    ap.add_argument("--hips", action="store_true",
                    help="also print the functional hips' outcome (TrackerConfig.functional_hips): each thigh's "
                         "pivot above the fitted hip and its information, or the information gathered when no "
                         "estimate was made; and the hips' and pelvis' errors")
    ap.add_argument("--start", action="store_true",
                    help="also print each landmark's height in the first frame, tracked less true (the started "
                         "body's fit to the starfish)")
    ap.add_argument("--blob-activity", action="store_true",
                    help="also print the frames in which each blob was de-activated (its fill under em.min_fill)")
    ap.add_argument("--fit-rounds", type=int, default=0, metavar="N",
                    help="diagnostic, instead of tracking: N rounds of the bone fit on the first frame's voxels at "
                         "the true pose, its ridge towards the start and towards each round's body")
    ap.add_argument("--coverage", action="store_true",
                    help="also print the share of each rendered blob's inside that the first frame's voxels miss "
                         "and how far under the head's top its highest voxel lies (what the shape fit takes for "
                         "the body's shape)")
    ap.add_argument("--refit", nargs="*", default=[], metavar="FIELD=VALUE",
                    help="overrides of the config's body_refit section (BodyRefitConfig), e.g. passes=0 (the first "
                         "track alone) or min_gain=0 (every pass that lowers the IK residual kept)")
    ap.add_argument("--refit-passes", action="store_true",
                    help="print each body refit pass's error, IK residual and refitted proportions (the row is the "
                         "kept track's)")
    ap.add_argument("--smoothing", nargs="*", default=[], metavar="FIELD=VALUE",
                    help="overrides of the config's smoothing section (SmoothingConfig), e.g. cutoff_hz=0 (off)")
    ap.add_argument("--cutoffs", nargs="*", type=float, default=[], metavar="HZ",
                    help="also print each finished track smoothed at these cut-offs (0: not smoothed)")
    ap.add_argument("--log-searches", action="store_true",
                    help="print the tracker's searches (lost arms, headings, bone fit rounds) with their costs")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    if args.log_searches:
        logging.getLogger("torchtrack.tracking.markerless").setLevel(logging.DEBUG)
    config = load_config(args.config)
    try:
        background = with_overrides(BackgroundConfig(**config["background"]), args.background, "--background")
        tracker_cfg = with_overrides(TrackerConfig.from_dict(config["tracker"], config["source"]), args.tracker,
                                     "--tracker")
        refit = with_overrides(BodyRefitConfig.from_dict(config["body_refit"], config["source"]), args.refit,
                               "--refit")
        smoothing = with_overrides(SmoothingConfig.from_dict(config["smoothing"], config["source"]),
                                   args.smoothing, "--smoothing")
    except InputError as exc:
        raise SystemExit(str(exc)) from None
    plain_config = config
    for section, items, validated in (("background", args.background, background),
                                      ("tracker", args.tracker, tracker_cfg), ("body_refit", args.refit, refit)):
        plain_config = with_settings(plain_config, section, items, validated)
    internals = (args.true_body or args.oracle_margin is not None or args.outside or args.coverage
                 or args.blob_activity or args.hips or args.refit_passes)
    torch.set_grad_enabled(False)
    rows = []
    print(f"{'motion':12s} {'cams':>4s} {'model':6s} {'MPJPE':>7s} {'unsm.':>7s} {'worst':>7s} {'PCK50':>6s} "
          f"{'lost':>5s} {'fps':>5s}  worst landmarks", flush=True)
    for motion in args.motions:
        for cams in args.cameras:
            seq = sequence(args.work, motion, cams, args.duration, args.format)
            truth = load_poses(seq / "gt.npz")
            for model in args.models:
                if args.fit_rounds:
                    print(f"{motion} {cams} cameras {model}: the bone fit at the true pose", flush=True)
                    fit_rounds(seq, model, config, args.fit_rounds, background, args.tracker)
                    continue
                tracker = seen = None
                if internals:
                    poses, fps, tracker, seen = track(seq, model, config, background, args.tracker, args.true_body,
                                                      args.oracle_margin)
                    if not args.true_body:
                        poses = refit_passes(seq, model, config, background, poses, tracker, refit,
                                             args.oracle_margin, truth, f"{motion} {cams} {model}")
                    body = tracker.subject.skeleton if tracker.subject is not None else None
                else:
                    poses, body, fps = track_plain(seq, model, plain_config)
                unsmoothed = evaluate(poses, truth).mpjpe_mm
                if body is not None and args.cutoffs:  # the same track smoothed at other cut-offs
                    sweep = []
                    for hz in args.cutoffs:
                        other = smooth_track(poses, body, replace(smoothing, cutoff_hz=hz))
                        sweep.append(f"{hz:g} Hz {evaluate(other, truth).mpjpe_mm:.1f}")
                    print("    cut-offs (MPJPE mm): " + ", ".join(sweep), flush=True)
                if body is not None:
                    poses = smooth_track(poses, body, smoothing)
                rep = evaluate(poses, truth)
                worst = sorted(zip(rep.per_landmark_mm, rep.landmark_names), reverse=True)[:3]
                pck50 = rep.pck[list(rep.pck_thresholds_m).index(0.05)] if 0.05 in rep.pck_thresholds_m else float("nan")
                target = 30.0 if cams >= 8 else 45.0
                ok = rep.mpjpe_mm <= target and (cams < 8 or rep.max_frame_mm <= 100.0) and rep.frames_lost == 0
                rows.append((motion, cams, model, rep.mpjpe_mm, rep.max_frame_mm, ok))
                print(f"{motion:12s} {cams:4d} {model:6s} {rep.mpjpe_mm:7.1f} {unsmoothed:7.1f} "
                      f"{rep.max_frame_mm:7.1f} {100 * pck50:5.1f}% {rep.frames_lost:5d} {fps:5.1f}  "
                      + ", ".join(f"{n} {e:.0f}" for e, n in worst) + ("" if ok else "  MISS"), flush=True)
                if args.trunk:
                    tilt, at_limit = trunk_errors(poses, truth, body)
                    print(f"    pelvis tilt off the true one: mean {tilt.mean():.1f}, worst frame {tilt.max():.1f} "
                          f"deg; a thigh at its extension limit in {100 * at_limit.mean():.0f}% of the frames",
                          flush=True)
                    print("    " + headings_line(trunk_headings(poses, truth, Skeleton.from_urdf())), flush=True)
                if args.outside:
                    print(f"    voxel weight outside the body (+{OUTSIDE_M * 100:g} cm): "
                          f"{100 * sum(seen.outside) / len(seen.outside):.1f}%", flush=True)
                if args.hips:
                    print("    " + hips_outcome(tracker, cams) + "; error (mm): " + ", ".join(
                        f"{n} {e:.1f}" for e, n in zip(rep.per_landmark_mm, rep.landmark_names)
                        if n in ("pelvis", "l_hip", "r_hip")), flush=True)
                if args.start:
                    print("    " + start_heights(poses, truth), flush=True)
                if args.coverage and seen.first is not None:
                    print("    " + coverage_line(*coverage(seen.first, seen.truth)), flush=True)
                if args.blob_activity:
                    print("\n".join("    " + line for line in blob_activity(tracker)), flush=True)
                if args.proportions and body is not None:
                    fit = body.proportions()
                    true = Skeleton.from_urdf(seq / "body.urdf").proportions()
                    print("    fitted (true) m: " + ", ".join(f"{k} {fit[k]:.3f} ({true[k]:.3f})"
                                                          for k in PROPORTIONS), flush=True)
    for cams in sorted({r[1] for r in rows}, reverse=True):
        for model in args.models:
            sel = [r for r in rows if r[1] == cams and r[2] == model]
            if sel:
                print(f"{cams} cameras, {model}: mean MPJPE {sum(r[3] for r in sel) / len(sel):.1f} mm, worst frame "
                      f"{max(r[4] for r in sel):.1f} mm, {sum(r[5] for r in sel)}/{len(sel)} sequences within target")


if __name__ == "__main__":
    main()
