"""End-to-end markerless tracking speed: frames per second of reading, observation, EM and IK.

Cases (issue targets on the 2-core CPU):
* hull: 4 cameras 320x240, colour hull to 1.5 cm (target >= 30 fps; Caillette & Howard ran 15 fps on one PC);
* bayes: 8 cameras 640x480, Bayesian grid 64^3;
* throughput of several sequences tracked at once (--sequences, observation batched over them), the figure
  to take on a GPU.

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
          device: torch.device, config: dict, sequences: int = 1) -> dict[str, float]:
    """Track the first ``frames`` frames of ``seq`` at ``scale``; ms per tracked frame by stage (frame 0, the
    initialisation, timed apart). With ``sequences`` > 1, that many copies of the sequence are tracked in
    lockstep, one tracker each, the observation batched over them (the Bayesian grid takes the batch in one
    pass): throughput of a batch of sequences, as on a GPU serving several recordings."""
    folder, observer = _setup(seq, scale, model, voxel, grid_n, device, config)
    W, H = (int(v) for v in observer.rig.image_size_wh[0].tolist())
    trackers = [MarkerlessTracker(Skeleton.from_urdf().to(device), TrackerConfig.from_dict(config["tracker"]))
                for _ in range(sequences)]
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
        S = len(trackers)
        observations = observer(fb.images.expand(S, *fb.images.shape[1:]), fb.valid.expand(S, -1))
        sync()
        c = time.perf_counter()
        for tracker, obs in zip(trackers, observations):
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
    S = len(trackers)
    return {**{f"{k}_ms": 1e3 * v / (m * S) for k, v in t.items()}, "init_s": t_init,
            "fps": m * S / sum(t.values())}


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
    ap.add_argument("--sequences", type=int, default=4,
                    help="also time this many sequences tracked in lockstep (observation batched); 1: skip")
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
    if args.sequences > 1:  # batched throughput: the tracker's default processing, several sequences at once
        print(f"\n{args.sequences} sequences tracked in lockstep (per tracked frame; fps summed over sequences)")
        seq = sequence(args.work, 8, 640, 480, 2.0)
        for model in ("bayes", "hull"):
            r = bench(seq, 0.5, model, 0.03, None, args.frames, device, load_config("markerless.yaml"),
                      sequences=args.sequences)
            print(f"{model + ' 8 cams at 320x240, 3 cm':40s} {'markerless.yaml':22s} {'in turn':7s} "
                  f"{r['read_ms']:6.1f}ms "
                  f"{r['observe_ms']:6.1f}ms {r['track_ms']:6.1f}ms {r['fps']:6.1f}", flush=True)


if __name__ == "__main__":
    main()
