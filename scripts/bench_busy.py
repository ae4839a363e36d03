"""How much a busy machine slows `torchtrack track`: a short synthetic 8-camera walk tracked (with one body refit,
whose L-BFGS shape fit is thousands of small operations) alone and beside a busy process (a PyTorch loop of
matrix products on every core), with the tracker's intra-op threads at 1 (the default) and at the machine's
count (torch's own default). Prints the wall-clock seconds of each and the slowdown beside the busy process.

    .venv/bin/python scripts/bench_busy.py [--out out/bench_busy] [--threads 1 2] [--refit-passes 1]

Run it alone: other work on the machine is what it measures.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import subprocess
import sys
import time
from pathlib import Path

import torch

from torchtrack.io.outputs import script_work_folder
from torchtrack.synth.scene import SceneConfig
from torchtrack.synth.sequence import RigConfig, SynthConfig, write_sequence

#: The busy process: matrix products on all of torch's threads, until it is stopped.
BUSY = "import torch\na = torch.randn(1024, 1024)\nwhile True:\n    a = torch.tanh(a @ a)\n"


def timed_track(seq: Path, out: Path, threads: int, refit_passes: int) -> float:
    """Wall-clock seconds of one `torchtrack track` process."""
    cmd = [sys.executable, "-m", "torchtrack.cli", "track", str(seq), "--out", str(out), "--overwrite",
           "--log-every", "0", "--threads", str(threads), "--refit-passes", str(refit_passes)]
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("out/bench_busy"),
                    help="work folder: new, empty, or this script's earlier one (replaced)")
    ap.add_argument("--threads", type=int, nargs="+", default=[1, torch.get_num_threads()],
                    help="the tracker's intra-op thread counts to compare (default: 1 and torch's default)")
    ap.add_argument("--refit-passes", type=int, default=1, help="body refit passes (default: 1)")
    args = ap.parse_args()
    script_work_folder(args.out, "bench_busy")
    cfg = SynthConfig(motion="walk", duration_s=1.0, starfish_s=0.2, fps=20, background_frames=4,
                      video_format="png", rig=RigConfig(num_cameras=8, width=320, height=240),
                      scene=dataclasses.replace(SceneConfig(), noise_std=1 / 255))
    seq = write_sequence(cfg, args.out / "seq", progress=False)

    print(f"{os.cpu_count()} logical CPUs, torch {torch.__version__} ({torch.get_num_threads()} threads by default); "
          f"a {int(cfg.fps * (cfg.duration_s + cfg.starfish_s))}-frame 8-camera walk, --refit-passes "
          f"{args.refit_passes}")
    print("threads   alone (s)   beside a busy process (s)   slowdown")
    for threads in args.threads:
        alone = timed_track(seq, args.out / "track", threads, args.refit_passes)
        busy = subprocess.Popen([sys.executable, "-c", BUSY])
        try:
            time.sleep(2.0)  # the busy process at full speed first
            beside = timed_track(seq, args.out / "track", threads, args.refit_passes)
        finally:
            busy.kill()
            busy.wait()
        print(f"{threads:>7}   {alone:>9.1f}   {beside:>25.1f}   {beside / alone:>7.2f}x", flush=True)


if __name__ == "__main__":
    main()
