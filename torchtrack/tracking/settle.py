"""Tracking back from a settled track (:class:`~torchtrack.tracking.markerless.MarkerlessTracker`'s part,
``settle_back_s``): after a start or a re-acquisition the first frames are tracked from a guess (a limb out of the
volume, arms on the trunk's voxels, colours learnt on one frame) and the track may take a second to find the
body. Once it has held for ``settle_back_s``, a copy of the tracker at that frame tracks the frames since the
start again in reverse order, from the settled state; where that track fits them better (a lower mean fit cost,
:meth:`~MarkerlessTracker._fit_cost`, over all of them) its frames replace the forward ones
(:meth:`~MarkerlessTracker.take_revised`), else the forward ones stay.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from typing import TYPE_CHECKING

import torch

from torchtrack.tracking.step import FrameResult
from torchtrack.tracking.voxels import VoxelObservation

if TYPE_CHECKING:
    from torchtrack.tracking.markerless import MarkerlessTracker

log = logging.getLogger(__name__)


def splice_index(forward: torch.Tensor, backward: torch.Tensor) -> int:
    """The splice of two tracks' per-frame costs ``forward``, ``backward`` (n,): the k in 0..n of the least
    ``sum(forward[:k]) + sum(backward[k:])``, the latest of equal ones (n: the forward track throughout)."""
    # sum(forward[:k]) + sum(backward[k:]) = sum(backward) + sum((forward - backward)[:k])
    total = torch.cat([forward.new_zeros(1), (forward - backward).cumsum(0)])
    return len(forward) - int(total.flip(0).argmin())


class SettleMixin:
    """The settle-back's methods of :class:`~torchtrack.tracking.markerless.MarkerlessTracker` (its state: the
    frames since the last start, ``_settle``)."""

    @property
    def settling(self) -> bool:
        """Frames since a start or re-acquisition are kept to be tracked back once the track has held
        (``TrackerConfig.settle_back_s``): :meth:`take_revised` may yet revise them."""
        return self._settle is not None

    def _settle_step(self, obs: VoxelObservation, res: FrameResult, version: int) -> None:
        """Called with each frame's result as the tracker returns it (:meth:`step`, or a lockstep driver after
        :meth:`accept`) and the body version it was tracked in: a start or re-acquisition opens the frames to track
        back, an invalid frame drops them (the track did not hold), and once ``settle_back_s`` of them held and no
        start race is on, they are tracked back (:meth:`_settle_back`). A start race's revision (:attr:`_revised`,
        the twin's frames up to this one) takes the place of the frames it revises."""
        if self._twin or self.config.settle_back_s <= 0:
            return
        if res.valid and res.reinitialised:
            self._settle = []
        if self._settle is None:
            return
        entry = [(obs, res, version)]
        if self._revised:  # the race's twin won: its results for the race's last frames, this one the last
            m = min(len(self._revised), len(self._settle) + 1)  # the kept frames it revises, this one included
            seen = [o for o, _, _ in self._settle[len(self._settle) - (m - 1):]] + [obs]
            del self._settle[len(self._settle) - (m - 1):]
            entry = [(o, r, v) for o, (r, v) in zip(seen, self._revised[-m:])]
        if not all(r.valid for _, r, _ in entry):
            self._settle = None
            return
        self._settle += entry
        if self._race is None and len(self._settle) >= self._race_frames(self.config.settle_back_s):
            self._settle_back()

    def _settle_revised(self) -> None:
        """A race decided after its last frame (:meth:`finish`): the twin's results, where it won, take the place
        of the kept frames they revise."""
        if self._settle is None or not self._revised:
            return
        m = min(len(self._revised), len(self._settle))
        if not all(r.valid for r, _ in self._revised[-m:]):
            self._settle = None
            return
        kept = self._settle[len(self._settle) - m:]
        self._settle[len(self._settle) - m:] = [(o, r, v) for (o, _, _), (r, v) in zip(kept, self._revised[-m:])]

    def _settle_back(self) -> None:
        """Track the kept frames back from the last one and splice (module docstring). A backward track that
        loses the body on some frame offers only the frames after it."""
        frames, self._settle = self._settle, None
        if len(frames) < 2:
            return
        fork: MarkerlessTracker = self._fork()
        fork._twin, fork._race, fork.hips = True, None, None  # the hips learn from the forward frames only
        fork.previous = fork.angles  # no velocity at the turn
        back = []
        for obs, _, _ in reversed(frames[:-1]):
            res = fork._step(obs)
            if not res.valid:
                log.debug("settle-back: the backward track lost the body %d frames back", len(back) + 1)
                break
            back.append((res, fork.body_version))
        if not back:
            return
        back.reverse()
        ahead = frames[len(frames) - 1 - len(back):-1]  # the forward frames the backward track covers
        if len(ahead) == len(frames) - 1:  # still the frame the track started on
            back[0] = (replace(back[0][0], reinitialised=True), back[0][1])
        # one splice: the forward frames up to k, the backward ones from k on, k of the least total fit cost (the
        # backward track may lose a limb near the volume's edge that the forward one had, and the other way round)
        forward = torch.tensor([self._fit_cost(r) for _, r, _ in ahead], dtype=torch.float64)
        backward = torch.tensor([self._fit_cost(r) for r, _ in back], dtype=torch.float64)
        n, k = len(back), splice_index(forward, backward)
        log.debug("settle-back over %d frames: mean fit cost forward %.1f mm, backward %.1f mm; the backward track "
                  "kept from frame %d of them", n, 1e3 * float(forward.mean()), 1e3 * float(backward.mean()), k)
        if k < n:  # on the frame a start race was decided, its revision stands before the splice
            new = back[k:] + [(frames[-1][1], frames[-1][2])]
            self._revised = self._revised[:max(0, len(self._revised) - len(new))] + new
