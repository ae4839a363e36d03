"""Counting torch operations by where torchtrack makes them, for the benchmarks' ``--ops``.

On a GPU each operation other than a view is about one kernel launch, and launches, not arithmetic, bound the
trackers' frames there (docs/results.md, Speed): the count, the same on any device, shows where a GPU's frame goes
on a machine without one.
"""

from __future__ import annotations

import collections
import os
import traceback
from collections.abc import Callable
from pathlib import Path

from torch.utils._python_dispatch import TorchDispatchMode


def place(depth: int, what: Callable[[traceback.FrameSummary], object]) -> str:
    """The caller's innermost ``depth`` frames in torchtrack, innermost first, as "file:label < file:label"
    (``what``: a frame's label, e.g. its function's name or line)."""
    ours = [f for f in traceback.extract_stack()[:-2] if f"{os.sep}torchtrack{os.sep}" in f.filename]
    return " < ".join(f"{Path(f.filename).name}:{what(f)}" for f in ours[::-1][:depth])


class OpCount(TorchDispatchMode):
    """Within ``with OpCount() as count:``, every torch operation other than a view is counted in ``count.places``
    under its innermost ``depth`` functions in torchtrack ("?" where none)."""

    def __init__(self, depth: int = 2) -> None:
        super().__init__()
        self.depth = depth
        self.places: collections.Counter = collections.Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):  # noqa: ANN001
        if not func.is_view:
            self.places[place(self.depth, lambda f: f.name) or "?"] += 1
        return func(*args, **(kwargs or {}))

    def report(self, per: int, top: int = 8) -> float:
        """Print the ``top`` places' counts divided by ``per`` (e.g. frames); return the total so divided."""
        for where, n in self.places.most_common(top):
            print(f"    {n / per:7.1f}  {where}", flush=True)
        return sum(self.places.values()) / per
