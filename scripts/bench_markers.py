"""Frames per second of the marker tracker's annealed particle filter (one frame: its layers and the polish).

A simulated Plug-in-Gait capture in the real 4-camera rig of the Pose2Sim demo (p_miss 0.2, 0.1 false detections,
sigma 2 px); the subject fitted from its detections; then the filter timed over frames at each particles x layers
setting (PARSEC bodytrack runs 4000 x 5), same run, and the forward kinematics of that many states alone. With
``--lockstep``: Q such captures (each its own detections and fitted subject) tracked in lockstep by one filter, the
frames per second summed over them. The lost-track test of `torchtrack track` is not included.

    .venv/bin/python scripts/bench_markers.py [--frames 30] [--settings 1000x5 4000x5] [--device cpu] [--threads 1]
        [--lockstep 1 4 16 [--lockstep-setting 1000x5]]
    .venv/bin/python scripts/bench_markers.py --settings 1000x5 4000x5 --polish 20 --before DIR [--pairs 3]
    .venv/bin/python scripts/bench_markers.py --settings 4000x5 --ops      # operations a frame (GPU launches)

``--before DIR`` times the package of another checkout (e.g. ``git worktree add /tmp/before <commit>``) against
this one, each in a process of its own, alternated ``--pairs`` times in one run (this host's speed moves by a fifth
within the hour), and prints each run, the medians and their ratio; both run this script and its data, the
package from their checkout (``--code``).
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
# --code DIR: the package of another checkout (a --before run's child); this script and its data stay this one's
CODE = Path(sys.argv[sys.argv.index("--code") + 1]).resolve() if "--code" in sys.argv[:-1] else REPO
sys.path.insert(0, str(CODE))

from torchtrack.cameras import load_calibration  # noqa: E402
from torchtrack.markers.capture import simulated_capture  # noqa: E402
try:
    from torchtrack.markers.capture import marker_scene  # noqa: E402
except ImportError:  # a checkout before the scene had a function of its own (a --before run)
    marker_scene = None
from torchtrack.markers.model import subject_from_markers  # noqa: E402
from torchtrack.markers.simulate import DetectorModel  # noqa: E402
from torchtrack.markers.triangulate import triangulate_candidates  # noqa: E402
try:
    from torchtrack.tracking.epipolar import pinhole_pixels, projection_matrices  # noqa: E402
except ImportError:  # a checkout before the cost had a module of its own (a --before run)
    from torchtrack.tracking.particles import pinhole_pixels, projection_matrices  # noqa: E402
from torchtrack.tracking.particles import APFConfig, MarkerAPF  # noqa: E402

DATA = REPO.parent / "shared" / "data"
CAPTURE = DATA / "mocap" / "btk" / "c3d" / "PiG_Motion-FlatFoot-Full.c3d"
RIG = DATA / "pose2sim_demo" / "calibration" / "Calib_qualisys_pose2sim.toml"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=30, help="frames timed per setting (default: 30)")
    ap.add_argument("--settings", nargs="+", default=["1000x5", "4000x5"], metavar="PxL",
                    help="particles x layers (default: 1000x5 4000x5)")
    ap.add_argument("--polish", type=int, nargs="+", default=[20, 0], metavar="N",
                    help="the Levenberg-Marquardt polish's steps, each setting timed with each (default: 20 0)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=1, help="torch intra-op threads (default: 1, as `track`)")
    ap.add_argument("--lockstep", type=int, nargs="*", default=[], metavar="Q",
                    help="numbers of sequences tracked in lockstep, each timed; only these are timed (default: none)")
    ap.add_argument("--lockstep-setting", default="1000x5", metavar="PxL",
                    help="particles x layers of the lockstep runs, with the polish (default: %(default)s)")
    ap.add_argument("--ops", action="store_true",
                    help="count the torch operations a frame of each setting makes instead of timing it (about one "
                         "GPU kernel launch each), by where they are made; the GPU's path: no CPU chunks")
    ap.add_argument("--before", type=Path, default=None, metavar="DIR",
                    help="time the package of the checkout DIR against this one, alternated (see above)")
    ap.add_argument("--pairs", type=int, default=3, help="--before: alternated pairs of runs (default: 3)")
    ap.add_argument("--code", type=Path, default=None, metavar="DIR", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.before is not None:
        return before_and_after(args)
    torch.set_num_threads(args.threads)
    dev = torch.device(args.device)
    rig = load_calibration(RIG, warn_units=False).double()
    if args.lockstep:
        return lockstep(args, rig, dev)
    skel_d, mset_d, start, zd = capture(rig, args.frames, 0, dev)
    rig_d = rig.to(dev)
    if args.ops:
        return count_ops(args, skel_d, mset_d, rig_d, start, zd, dev)
    print(f"{'particles x layers':<19} {'polish':>6} {'frames/s':>9} {'ms/frame':>9}   ({args.device}, "
          f"{args.threads} thread(s), {mset_d.num_markers} markers, {rig.num_cameras} cameras)")
    for setting in args.settings:
        P, L = (int(v) for v in setting.lower().split("x"))
        for polish in args.polish:
            cfg = APFConfig(particles=P, layers=L, polish_steps=polish)
            apf = MarkerAPF(skel_d, mset_d, rig_d, cfg, torch.Generator(device=dev).manual_seed(0))
            apf.reset(start)
            dt = seconds_per_frame(apf.step, zd, args.frames, dev)
            print(f"{setting:<19} {polish:>6} {1 / dt:>9.1f} {1e3 * dt:>9.1f}", flush=True)
    # the part of a layer that the forward kinematics of the particles takes: the filter's lean chain
    # (Skeleton.bone_poses) and pytorch-kinematics' general one (Skeleton.forward)
    for setting in args.settings:
        P = int(setting.lower().split("x")[0])
        for name, fk in (("lean", skel_d.bone_poses), ("pytorch-kinematics", skel_d.forward)):
            for dtype in (torch.float64, torch.float32):
                states = start.to(dtype)[None].repeat(P, 1)
                fk(states)
                if dev.type == "cuda":
                    torch.cuda.synchronize()
                t0 = time.perf_counter()
                for _ in range(10):
                    fk(states)
                if dev.type == "cuda":
                    torch.cuda.synchronize()
                print(f"forward kinematics of {P} states, {name}, {str(dtype).split('.')[-1]}: "
                      f"{1e3 * (time.perf_counter() - t0) / 10:.1f} ms", flush=True)
    return 0


def count_ops(args: argparse.Namespace, skel, mset, rig, start: torch.Tensor, z: torch.Tensor,  # noqa: ANN001
              dev: torch.device, frames: int = 5) -> int:
    """``--ops``: the torch operations other than views a frame of the filter makes at each setting and polish,
    over ``frames`` frames after the warm-up, with the particles weighed in one piece as on a GPU (a CPU's chunks,
    ``CPU_CHUNK_STATES``, repeat a layer's operations per chunk), and where the most are made."""
    from _op_count import OpCount

    import torchtrack.tracking.particles as particles

    particles.CPU_CHUNK_STATES = 1 << 30
    for setting in args.settings:
        P, L = (int(v) for v in setting.lower().split("x"))
        for polish in args.polish:
            apf = MarkerAPF(skel, mset, rig, APFConfig(particles=P, layers=L, polish_steps=polish),
                            torch.Generator(device=dev).manual_seed(0))
            apf.reset(start)
            apf.step(z[60])
            with OpCount() as count:
                for t in range(61, 61 + frames):
                    apf.step(z[t])
            total = sum(count.places.values()) / frames
            print(f"{setting} polish {polish}: {total:.0f} operations a frame, views not counted", flush=True)
            count.report(frames)
    return 0


def before_and_after(args: argparse.Namespace) -> int:
    """``--before``: this script with each checkout's package in turn, ``--pairs`` times; the frames/s of every
    particles x layers and polish row, each run's and the medians, and this checkout's over the other's."""
    if not (args.before / "torchtrack").is_dir():
        raise SystemExit(f"--before {args.before}: no torchtrack package there (a checkout's root?)")
    if args.pairs < 1:
        raise SystemExit(f"--pairs must be >= 1, got {args.pairs}")
    runs: dict[str, dict[str, list[float]]] = {"before": {}, "this checkout": {}}
    for _ in range(args.pairs):
        for name, code in (("before", args.before), ("this checkout", REPO)):
            cmd = [sys.executable, str(Path(__file__).resolve()), "--code", str(code.resolve()), "--frames",
                   str(args.frames), "--device", args.device, "--threads", str(args.threads), "--settings",
                   *args.settings, "--polish", *map(str, args.polish)]
            done = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "PYTHONPATH": ""})
            if done.returncode != 0:
                raise SystemExit(f"{' '.join(cmd)} failed:\n{done.stderr[-3000:]}")
            for line in done.stdout.splitlines():
                parts = line.split()
                if len(parts) == 4 and parts[0] in args.settings:  # "1000x5  20  31.1  32.2"
                    runs[name].setdefault(f"{parts[0]} polish {parts[1]}", []).append(float(parts[2]))
            print(f"{name:<14} " + "  ".join(f"{k}: {v[-1]:.1f}" for k, v in runs[name].items()), flush=True)
    for row, after in runs["this checkout"].items():
        old, new = statistics.median(runs["before"][row]), statistics.median(after)
        print(f"{row}: {old:.1f} -> {new:.1f} frames/s (medians of {args.pairs}; {new / old:.2f}x)")
    return 0


def capture(rig, frames: int, seed: int, dev: torch.device, scene=None) -> tuple:  # noqa: ANN001
    """The simulated capture's detections drawn with ``seed`` (61 + ``frames`` frames at 30 frames/s; from
    ``scene``, the capture placed in the rig, where given) and its subject fitted on the first 60 frames'
    triangulated markers: the skeleton, the marker set, the pose of frame 59 and the detections ``(T, C, M, K, 2)``
    in pinhole pixels, on ``dev``."""
    model = DetectorModel(p_miss=0.2, false_rate=0.1, sigma_px=2.0)
    if scene is None:
        det, _ = simulated_capture(CAPTURE, rig, 30.0, (frames + 61) / 30.0, model, seed=seed)
    else:
        det = scene.detections(model, seed)
    uv = torch.from_numpy(det.uv.astype("float64"))
    z = pinhole_pixels(rig, uv.permute(1, 0, 2, 3, 4)).permute(1, 0, 2, 3, 4)
    X, _ = triangulate_candidates(z[:60], projection_matrices(rig))
    skel, mset, angles = subject_from_markers(X, det.marker_names, det.fps)
    return (skel.to(dev), replace(mset, bone=mset.bone.to(dev), offset=mset.offset.to(dev)), angles[59].to(dev),
            z.to(dev))


def seconds_per_frame(step, z: torch.Tensor, frames: int, dev: torch.device) -> float:
    """Seconds a frame of ``step`` over ``z``'s frames 61 to 60 + ``frames`` (frame 60 a warm-up)."""
    if z.shape[0] < 61 + frames:  # the capture is as long as its C3D file
        raise SystemExit(f"--frames {frames}: the capture has {z.shape[0] - 61} frames after the subject's fit and "
                         f"the warm-up; give --frames {z.shape[0] - 61} or fewer")
    step(z[60])
    if dev.type == "cuda":
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    for t in range(61, 61 + frames):
        step(z[t])
    if dev.type == "cuda":
        torch.cuda.synchronize()
    return (time.perf_counter() - t0) / frames


def lockstep(args: argparse.Namespace, rig, dev: torch.device) -> int:
    """Frames/s summed over Q sequences in lockstep (one batched filter step a frame), for each Q of
    ``--lockstep``: the sequences are the capture's detections drawn with seeds 0, 1, ... (each subject fitted on
    its own), the largest Q's sequences the pool of the others."""
    Q_max = max(args.lockstep)
    P, L = (int(v) for v in args.lockstep_setting.lower().split("x"))
    scene = None if marker_scene is None else marker_scene(CAPTURE, rig, 30.0, (args.frames + 61) / 30.0)
    pool = [capture(rig, args.frames, seed, dev, scene) for seed in range(Q_max)]  # the capture retargeted once
    print(f"{'sequences':<10} {'frames/s summed':>15} {'ms/frame':>9}   ({args.device}, {args.threads} thread(s), "
          f"{P} particles x {L} layers with the polish, {rig.num_cameras} cameras)")
    base = None
    for Q in args.lockstep:
        subjects = pool[:Q]
        apf = MarkerAPF([s[0] for s in subjects], [s[1] for s in subjects], [rig.to(dev)] * Q,
                        APFConfig(particles=P, layers=L),
                        [torch.Generator(device=dev).manual_seed(q) for q in range(Q)])
        apf.reset(torch.stack([s[2] for s in subjects]))
        Z = apf.pad_detections([s[3] for s in subjects])  # (T, Q, C, M, K, 2)
        dt = seconds_per_frame(apf.step_all, Z, args.frames, dev)
        base = base or Q / dt
        print(f"{Q:<10} {Q / dt:>15.1f} {1e3 * dt:>9.1f}   ({Q / dt / base:.1f}x the first)", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
