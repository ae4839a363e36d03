"""End-to-end markerless tracking speed: frames per second of reading, observation, EM and IK.

Cases (issue targets on the 2-core CPU):
* hull: 4 cameras 320x240, colour hull to 1.5 cm (target >= 30 fps; Caillette & Howard ran 15 fps on one PC);
* bayes: 8 cameras 640x480, Bayesian grid 64^3;
* ``--lockstep [B ...]``: the tracker's throughput on B different synthetic sequences tracked in lockstep (one
  batched step per frame for all of them, :mod:`torchtrack.tracking.lockstep`), frames/s summed over the B
  sequences for each B (default 1, 4, 16; a GPU's figure: add 64), observations made beforehand, timed after the
  starts (tracked once for all B, ``--start truth``: from the true first pose instead of the trackers' search);
  on CUDA also the host synchronisations a frame of the lockstep step.

Renders the sequences once under --work (synthetic walk), then tracks them with the defaults of
configs/markerless.yaml apart from the observation settings named here, and prints ms per frame by stage.
Each case runs twice on a CPU: "in turn" (read, observe, track, one after the other in this process) and
"worker" (reading and observation in a worker process ahead of the tracker, as `torchtrack track` does with
observation.workers: 1; its first column is the time the tracker waited for a frame, its observe column the
worker's, overlapped with tracking).

    .venv/bin/python scripts/bench_track.py [--device cuda] [--frames 60]

``--demo`` times instead what a new user runs on the real Pose2Sim demo (100 frames, 4 cameras, no background
frames, so the background refinement's passes; the README's worked example without ``--init-pose``): `torchtrack
track SEQ --scale 0.25 --fill-static-subject`, end to end in a process of its own, and prints its wall clock time
and MPJPE against Pose2Sim's keypoints. ``--before DIR`` first runs the same command with the code of another
checkout (e.g. ``git worktree add /tmp/before <commit>``), in the same run, as hosts' speeds drift by a third
from hour to hour:

    .venv/bin/python scripts/bench_track.py --demo --before /tmp/before
"""

from __future__ import annotations

import argparse
import itertools
import logging
import os
import subprocess
import sys
import time
from pathlib import Path

import torch

from torchtrack.background import BackgroundModel
from torchtrack.io.poses import load_poses
from torchtrack.io.sequence import SequenceFolder
from torchtrack.occupancy import grid_from_rig
from torchtrack.skeleton import Skeleton
from torchtrack.synth.sequence import RigConfig, SynthConfig, is_current, write_sequence
from torchtrack.tracking.pipeline import load_config, observer_from_config
from torchtrack.tracking.markerless import MarkerlessTracker, TrackerConfig
from torchtrack.tracking.stream import observe_batches

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / ".." / "shared" / "data" / "pose2sim_demo"


def sequence(work: Path, cameras: int, width: int, height: int, seconds: float) -> Path:
    out = work / f"walk_{cameras}cam_{width}x{height}"
    cfg = SynthConfig(motion="walk", duration_s=seconds, starfish_s=0.5, video_format="mp4",
                      rig=RigConfig(num_cameras=cameras, width=width, height=height))
    if not is_current(out, cfg):
        write_sequence(cfg, out, progress=False)
    return out


def bench_streamed(seq: Path, scale: float, model: str, voxel: float | None, grid_n: int | None, frames: int,
                   device: torch.device, config: dict) -> dict[str, float]:
    """As :func:`bench` for one sequence, the frames read and observed in a worker process ahead of the tracker
    (``observe_batches(workers=1)``, what ``torchtrack track`` does on a CPU): ms per frame the tracker waited
    for a frame, the worker's observation (overlapped) and the tracking; fps is the wall-clock rate."""
    folder, observer = _setup(seq, scale, model, voxel, grid_n, device, config)
    tracker = MarkerlessTracker(Skeleton.from_urdf().to(device), TrackerConfig.from_dict(config["tracker"]))
    t = {"wait": 0.0, "observe": 0.0, "track": 0.0}
    n, t_init, t_first, t_worker = 0, 0.0, 0.0, 0.0
    stream = observe_batches(folder, observer, 0, min(frames, folder.num_frames), batch=1, device=device, workers=1,
                             cell_m=tracker.config.em_cell_m)
    t_start = t_last = time.perf_counter()
    for ob in stream:  # the worker's start (spawn, imports) is timed apart, as the initialisation
        b = time.perf_counter()
        tracker.step(ob.observations[0])
        c = time.perf_counter()
        if n:
            t["wait"] += b - t_last
            t["observe"] += ob.seconds
            t["track"] += c - b
        else:
            t_init, t_first, t_worker = c - b, c, b - t_start
        t_last = c
        n += 1
    m = max(n - 1, 1)
    return {**{f"{k}_ms": 1e3 * v / m for k, v in t.items()}, "init_s": t_init, "worker_start_s": t_worker,
            "fps": m / (t_last - t_first)}


def _setup(seq: Path, scale: float, model: str, voxel: float | None, grid_n: int | None, device: torch.device,
           config: dict) -> tuple[SequenceFolder, object]:
    folder = SequenceFolder(seq)
    W, H = (int(round(float(v) * scale)) for v in folder.rig.image_size_wh[0])
    rig = folder.rig.resized(W, H).float().to(device)
    bg = BackgroundModel.from_folder(folder, size_wh=(W, H), device=device)
    if grid_n is not None:  # voxel so that the common-view box is grid_n voxels along its longest side
        box = grid_from_rig(rig, 0.05)
        voxel = max(u - lo for lo, u in zip(box.lower_m, box.upper_m)) / grid_n
    return folder, observer_from_config(rig, bg, config["observation"], model, voxel).to(device)


def bench(seq: Path, scale: float, model: str, voxel: float | None, grid_n: int | None, frames: int,
          device: torch.device, config: dict) -> dict[str, float]:
    """Track the first ``frames`` frames of ``seq`` at ``scale``; ms per tracked frame by stage (frame 0, the
    initialisation, timed apart)."""
    folder, observer = _setup(seq, scale, model, voxel, grid_n, device, config)
    W, H = (int(v) for v in observer.rig.image_size_wh[0].tolist())
    tracker = MarkerlessTracker(Skeleton.from_urdf().to(device), TrackerConfig.from_dict(config["tracker"]))
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    t = {"read": 0.0, "observe": 0.0, "track": 0.0}
    n, t_init = 0, 0.0
    batches = folder.iter_batches(1, 0, min(frames, folder.num_frames), device=device, size_wh=(W, H))
    while True:
        a = time.perf_counter()
        fb = next(batches, None)
        if fb is None:
            break
        b = time.perf_counter()
        obs = observer(fb.images, fb.valid)[0]
        sync()
        c = time.perf_counter()
        tracker.step(obs)
        sync()
        d = time.perf_counter()
        if n:
            t["read"] += b - a
            t["observe"] += c - b
            t["track"] += d - c
        else:
            t_init = d - c
        n += 1
    m = max(n - 1, 1)
    return {**{f"{k}_ms": 1e3 * v / m for k, v in t.items()}, "init_s": t_init, "fps": m / sum(t.values())}


def lockstep_observations(work: Path, count: int, device: torch.device, config: dict
                          ) -> tuple[list[Path], list[list]]:
    """``count`` different synthetic sequences (4 cameras 320x240, 30 fps: a 0.5 s starfish, then 3 s of one of
    the procedural motions, subjects 1.60-1.90 m tall), rendered once under ``work``: their folders and
    observations (the Bayesian grid, 3 cm)."""
    from torchtrack.synth.motion import MOTIONS

    seqs, out = [], []
    for i in range(count):
        motion, height = MOTIONS[i % len(MOTIONS)], 1.60 + 0.30 * ((7 * i) % 16) / 15
        seq = work / f"lockstep_{i:02d}_{motion}_{round(100 * height)}cm"
        cfg = SynthConfig(motion=motion, duration_s=3.0, starfish_s=0.5, subject_height_m=height,
                          background_frames=10, seed=i, rig=RigConfig(num_cameras=4, width=320, height=240))
        if not is_current(seq, cfg):
            write_sequence(cfg, seq, progress=False)
        folder, observer = _setup(seq, 1.0, "bayes", 0.03, None, device, config)
        seqs.append(seq)
        out.append([o for b in observe_batches(folder, observer, 0, folder.num_frames, batch=4, device=device)
                    for o in b.observations])
    return seqs, out


def count_ops(observations: list[list], seqs: list[Path], sizes: list[int], device: torch.device, config: dict,
              timed_from: int, frames: int = 5) -> None:
    """``--ops``: the torch operations other than views that a frame of the lockstep step makes for each B, counted
    under their innermost two functions in torchtrack. On a GPU each is about one kernel launch, and launches bound
    the step there (docs/results.md, Speed), so this count, the same on any device, shows where a GPU's frame goes
    on a machine without one. The trackers start from the generator's pose at frame ``timed_from``, whose step
    builds the subject stacks; the ``frames`` after it are counted."""
    from _op_count import OpCount

    from torchtrack.tracking.lockstep import Lockstep

    last = None  # the B and count before: what each further sequence costs
    for B in sizes:
        trackers = []
        for i in range(B):
            seq = seqs[i % len(seqs)]
            t = MarkerlessTracker(Skeleton.from_urdf().to(device), TrackerConfig.from_dict(config["tracker"]))
            t.set_frame_rate(30.0)
            angles = torch.as_tensor(load_poses(seq / "gt.npz").angles[timed_from], dtype=torch.float32,
                                     device=device)
            t.initialize_from_pose(angles, skeleton=Skeleton.from_urdf(seq / "body.urdf").to(device))
            trackers.append(t)
        lockstep = Lockstep(trackers)
        obs = observations
        lockstep.step({i: obs[i % len(obs)][timed_from] for i in range(B)})  # builds the subject stacks
        with OpCount() as count:
            for k in range(timed_from + 1, timed_from + 1 + frames):
                lockstep.step({i: obs[i % len(obs)][k] for i in range(B)})
        total = sum(count.places.values()) / frames
        further = "" if last is None else f"; {(total - last[1]) / (B - last[0]):.0f} each sequence over B = {last[0]}"
        print(f"B = {B:3d}: {total:.0f} operations a frame, views not counted ({total / B:.0f} a sequence{further})",
              flush=True)
        last = B, total
        count.report(frames)


def bench_lockstep(observations: list[list], sizes: list[int], device: torch.device, config: dict,
                   timed_from: int, truths: list[Path] | None = None) -> None:
    """Track the first B of ``observations``' sequences in lockstep (:class:`Lockstep`) for each B in ``sizes``
    (sequence i is ``observations[i % len(observations)]``); print frames/s summed over the B sequences over the
    frames from ``timed_from`` on, and the share of them the batched step took. On CUDA also the host
    synchronisations per frame of ``Lockstep.step`` on those frames (torch's sync debug mode: one warning per
    synchronising call) and the places in torchtrack that make most of them (file:line, innermost first).

    The frames before ``timed_from`` (the starts and their races, which each tracker runs on its own) are tracked
    once, all sequences in lockstep; each B then starts from copies of those trackers. With ``truths`` (the
    sequences' folders) each tracker starts instead from its generator's true first pose and body (gt.npz,
    body.urdf), without the start search."""
    import collections
    import copy
    import warnings

    from _op_count import place

    from torchtrack.tracking.lockstep import Lockstep

    places: collections.Counter = collections.Counter()

    def seen(message, category, filename, lineno, file=None, line=None) -> None:  # noqa: ANN001
        """A sync debug warning: counted under its innermost three frames in torchtrack (others are dropped)."""
        if "synchroniz" not in str(message):
            return
        places[place(3, lambda f: f.lineno) or f"{filename}:{lineno}"] += 1

    def step(lockstep: Lockstep, frames: dict) -> None:
        _, errors = lockstep.step(frames)
        if errors:
            raise next(iter(errors.values()))

    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    T = min(len(o) for o in observations)
    primed = [MarkerlessTracker(Skeleton.from_urdf().to(device), TrackerConfig.from_dict(config["tracker"]))
              for _ in observations]
    for i, t in enumerate(primed):
        t.set_frame_rate(30.0)
        if truths is not None:
            angles = torch.as_tensor(load_poses(truths[i] / "gt.npz").angles[0], dtype=torch.float32, device=device)
            t.initialize_from_pose(angles, skeleton=Skeleton.from_urdf(truths[i] / "body.urdf").to(device))
    started = Lockstep(primed)
    t0 = time.perf_counter()
    for k in range(timed_from):
        step(started, {i: seq[k] for i, seq in enumerate(observations)})
    print(f"frames 0-{timed_from - 1} of {len(observations)} sequences ("
          f"{'from the true first pose' if truths is not None else 'their starts'}): "
          f"{time.perf_counter() - t0:.0f} s", flush=True)
    base = None
    for B in sizes:
        trackers = [copy.deepcopy(primed[i % len(primed)]) for i in range(B)]
        lockstep = Lockstep(trackers)
        plain, syncs = 0, []
        places.clear()
        sync()
        t0 = time.perf_counter()
        for k in range(timed_from, T):
            frames = {i: observations[i % len(observations)][k] for i in range(B)}
            counting = device.type == "cuda"
            before = sum(places.values())
            with warnings.catch_warnings():
                if counting:
                    warnings.simplefilter("always")
                    warnings.showwarning = seen  # restored as the block ends
                    torch.cuda.set_sync_debug_mode("warn")
                try:
                    step(lockstep, frames)
                    plain += lockstep.batched
                finally:
                    if counting:
                        torch.cuda.set_sync_debug_mode("default")
            if counting:
                syncs.append(sum(places.values()) - before)
        sync()
        fps = B * (T - timed_from) / (time.perf_counter() - t0)
        base = fps if base is None else base
        print(f"B = {B:3d}: {fps:7.1f} frames/s summed ({fps / base:.1f}x B = {sizes[0]}); "
              f"{plain / (B * (T - timed_from)):.0%} of the frames in the batched step"
              + (f"; host synchronisations a frame: mean {sum(syncs) / len(syncs):.1f}, most {max(syncs)}"
                 if syncs else ""), flush=True)
        for where, n in places.most_common(6):
            print(f"    {n / len(syncs):6.2f} a frame  {where}", flush=True)


def demo_run(code: Path, seq: Path, out: Path) -> tuple[float, str]:
    """`torchtrack track` of the demo with the package at ``code`` (its root, on PYTHONPATH) in a process of its
    own: wall clock seconds, and its error against Pose2Sim's keypoints as eval_pose2sim_tracking.py prints it."""
    env = {**os.environ, "PYTHONPATH": str(code.resolve())}
    cmd = [sys.executable, "-m", "torchtrack.cli", "track", str(seq.resolve()), "--out", str(out.resolve()),
           "--scale", "0.25", "--fill-static-subject", "--overwrite"]
    t0 = time.perf_counter()  # run in the checkout: `python -m` puts the working directory first on sys.path
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=code.resolve())
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} (code {code}) failed:\n{done.stderr[-3000:]}")
    score = subprocess.run([sys.executable, str(Path(__file__).resolve().parent / "eval_pose2sim_tracking.py"),
                            "--score", str(out.resolve() / "poses.npz")], capture_output=True, text=True, check=True)
    return wall, score.stdout.splitlines()[0].split(": ", 1)[-1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--work", type=Path, default=Path("out/bench_track"))
    ap.add_argument("--lockstep", type=int, nargs="*", default=None, metavar="B",
                    help="time instead the tracker's step on B different synthetic sequences in lockstep, for each B "
                         "given (default 1 4 16; GPU: add 64): frames/s summed over the B sequences")
    ap.add_argument("--start", choices=("search", "truth"), default="search",
                    help="with --lockstep: the trackers' start, their own (default) or the generator's true first "
                         "pose and body (a GPU's quick figure: 16 starts of small operations take minutes there)")
    ap.add_argument("--ops", action="store_true",
                    help="with --lockstep: count instead the torch operations (not views) a frame of the step makes, "
                         "by place: about a GPU's kernel launches")
    ap.add_argument("--config", nargs="+", default=["markerless.yaml", "markerless_fast.yaml"],
                    help="tracking configs to time")
    ap.add_argument("--demo", action="store_true",
                    help="time `torchtrack track` on the real Pose2Sim demo end to end instead (see above)")
    ap.add_argument("--before", type=Path, default=None, metavar="DIR",
                    help="with --demo: first time the same command with the code of the checkout DIR")
    args = ap.parse_args()
    if args.demo:
        from torchtrack.io.pose2sim import pose2sim_sequence

        seq = pose2sim_sequence(DEMO, args.work / "pose2sim_demo")
        runs = ([("before", args.before)] if args.before is not None else []) + [("this checkout", ROOT)]
        walls = {}
        for name, code in runs:
            walls[name], err = demo_run(code, seq, args.work / f"pose2sim_track_{name.replace(' ', '_')}")
            print(f"Pose2Sim demo, `torchtrack track --scale 0.25 --fill-static-subject`, {name} ({code}): "
                  f"{walls[name]:.0f} s wall clock; {err}", flush=True)
        if args.before is not None:
            print(f"this checkout takes {walls['this checkout'] / walls['before']:.2f} of the time before")
        return
    logging.basicConfig(level=logging.WARNING)
    torch.set_grad_enabled(False)
    device = torch.device(args.device)
    if args.lockstep is not None:
        sizes = args.lockstep or [1, 4, 16]
        print(f"device {device}, torch {torch.__version__}, {torch.get_num_threads()} threads; the tracker's step on "
              f"sequences in lockstep (observations made beforehand)", flush=True)
        config = load_config("markerless.yaml")
        seqs, observations = lockstep_observations(args.work, min(max(sizes), 16), device, config)
        if args.ops:
            count_ops(observations, seqs, sizes, device, config, timed_from=45)
            return
        bench_lockstep(observations, sizes, device, config, timed_from=45,
                       truths=seqs if args.start == "truth" else None)
        return
    cases = [("hull 4 cams 320x240, 1.5 cm", (4, 320, 240), 1.0, "hull", 0.015, None, 30.0),
             ("hull 4 cams 320x240, 3 cm", (4, 320, 240), 1.0, "hull", 0.03, None, None),
             ("bayes 8 cams 640x480, 64^3", (8, 640, 480), 1.0, "bayes", None, 64, None),
             ("bayes 8 cams 640x480 at 320x240, 3 cm", (8, 640, 480), 0.5, "bayes", 0.03, None, None)]
    print(f"device {device}, torch {torch.__version__}, {torch.get_num_threads()} threads")
    print(f"{'case':40s} {'config':22s} {'frames':7s} {'read':>8s} {'observe':>8s} {'EM+IK':>8s} {'fps':>6s}  init")
    print(f"{'':40s} {'':22s} {'':7s} {'(wait)':>8s}")
    modes = ("in turn", "worker") if device.type == "cpu" else ("in turn",)
    for (name, (cams, w, h), scale, model, voxel, grid_n, target), cname, mode in itertools.product(
            cases, args.config, modes):
        seq = sequence(args.work, cams, w, h, 2.0)
        if mode == "worker":
            r = bench_streamed(seq, scale, model, voxel, grid_n, args.frames, device, load_config(cname))
            first = r["wait_ms"]
        else:
            r = bench(seq, scale, model, voxel, grid_n, args.frames, device, load_config(cname))
            first = r["read_ms"]
        verdict = "" if target is None else ("  PASS" if r["fps"] >= target else f"  MISS (target {target:.0f})")
        start = f" + {r['worker_start_s']:.1f}s worker start" if mode == "worker" else ""
        print(f"{name:40s} {cname:22s} {mode:7s} {first:6.1f}ms {r['observe_ms']:6.1f}ms {r['track_ms']:6.1f}ms "
              f"{r['fps']:6.1f}  {r['init_s']:.1f}s{start}{verdict}", flush=True)


if __name__ == "__main__":
    main()
