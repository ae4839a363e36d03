"""The start race (:class:`~torchtrack.tracking.markerless.MarkerlessTracker`'s part, ``start_race_s``): after a
searched start or a re-acquisition, the start turned round is tracked beside it until the body's motion tells
which way it faces, and the better of the two goes on, its frames replacing the others' (:meth:`take_revised`).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import torch

from torchtrack.tracking.step import FrameResult
from torchtrack.tracking.voxels import VoxelObservation

if TYPE_CHECKING:
    from torchtrack.tracking.markerless import MarkerlessTracker

log = logging.getLogger(__name__)

#: The start race (``TrackerConfig.start_race_s``): the start turned round replaces the search's start only if its
#: mean fit cost (:meth:`MarkerlessTracker._fit_cost`) over the race is lower, its mean two-way score
#: (:func:`~torchtrack.tracking.search.score_states`, 0-1) not lower by more than this, and one of the two wins
#: clearly: the score by more than this, or the cost by :data:`START_RACE_COST_RATIO`. On a 4-camera hull's ghosts
#: the score alone preferred the turned round twin of a wrong start, which was wronger; on a walk from a starfish
#: the two scored the same and only the fit cost (knees that bend one way) told them apart (docs/results.md,
#: "The start race"). The starfish's fast path takes the same margin: a searched start replaces the starfish's only
#: if it scores higher by more than this.
START_RACE_MARGIN = 0.01
#: The fit cost's clear win in the start race: the twin's mean cost below this fraction of the start's.
START_RACE_COST_RATIO = 0.8
#: The race's ``start_race_s`` counts from the first frame where the body has moved (a landmark of the start's
#: track this far from where the start put it, relative to the pelvis), and only the frames from there decide it: a
#: still body's silhouette is the same turned round, and over such frames the race would only compare how the two
#: fits happened to settle, which turned a 4-camera squat's start round (docs/results.md, "The start race").
START_RACE_MOVED_M = 0.1
#: A race waits this long for the body to move, then is decided on all its frames (at a sequence's end before
#: that, :meth:`MarkerlessTracker.finish` drops it).
START_RACE_WAIT_S = 2.0


@dataclass
class _Race:
    """A start race in progress: the twin tracker (started turned round), the frames left, each side's scores and
    the twin's results with the body version each was tracked in."""

    twin: MarkerlessTracker
    frames_left: int
    origin: torch.Tensor  # the start's output points relative to its pelvis, for START_RACE_MOVED_M
    fits: list[tuple[float, float, float, float]] = field(default_factory=list)  # scores, then fit costs
    results: list[tuple[FrameResult, int]] = field(default_factory=list)
    moved_at: int | None = None  # the index in fits of the first frame where the body had moved
    # image_hold_s: the invalid frames before the re-acquisition that started it (MarkerlessTracker._hold_back)
    unheld: list = field(default_factory=list)

class RaceMixin:
    """The start race's methods of :class:`~torchtrack.tracking.markerless.MarkerlessTracker` (its state: see there)."""

    def _race_frames(self, seconds: float | None = None) -> int:
        seconds = self.config.start_race_s if seconds is None else seconds
        return max(1, round(seconds * (self.frame_rate or self.config.velocity_fps or 30.0)))

    @property
    def racing(self) -> bool:
        """A start race is in progress (``TrackerConfig.start_race_s``): :meth:`take_revised` may yet revise the
        frames since the start."""
        return self._race is not None

    def _start_race(self, obs: VoxelObservation, res: FrameResult, unswept: torch.Tensor | None = None) -> None:
        """``start_race_s``: the twin started from this start turned round, finished on ``obs`` as a start is.
        ``unswept``: the start's state before its limb sweep (``start_limb_sweep``), which the twin turns round
        instead: limbs swept for one heading fit the other badly."""
        from torchtrack.tracking.poses import turned_round

        twin = self._fork()
        twin._twin = True
        twin.angles = twin.previous = turned_round(self.subject.skeleton, res.angles if unswept is None else unswept)
        twin.colour = None
        for _ in range(self.config.init_passes):
            r = twin._track(obs, learn_colour=False, max_rot=math.radians(45), predicted=False, hold=False)
            twin.angles = twin.previous = r.angles
        if self.config.start_limb_sweep:  # its limbs swept for its own heading (a re-acquisition's twin too)
            twin._sweep_finished_limbs(obs, r)
        r = twin._learn_colour(obs)
        twin._remember_feet()
        wait = max(self._race_frames(), self._race_frames(START_RACE_WAIT_S))
        self._race = _Race(twin, wait, res.output_points - res.output_points[:1])
        self._race_step(obs, res, r, twin.body_version)

    def _race_step(self, obs: VoxelObservation | None, res: FrameResult, twin_res: FrameResult, version: int
                   ) -> None:
        """One frame of the race: both scored on ``obs`` (None: not observed), the twin's result kept with the body
        version it was tracked in; ``start_race_s`` counted from the frame where the body moved
        (``START_RACE_MOVED_M``), and the race decided at its end on the frames from there."""
        from torchtrack.tracking.search import score_states

        race = self._race
        race.results.append((twin_res, version))
        if obs is not None and math.isfinite(res.residual_m) and math.isfinite(twin_res.residual_m):  # both fitted
            both = torch.stack([res.angles, twin_res.angles]).to(self.subject.skeleton.lower)
            score = score_states(obs, self.subject.skeleton, self.subject.blobs, both)[0]
            race.fits.append((float(score[0]), float(score[1]), self._fit_cost(res), self._fit_cost(twin_res)))
            if race.moved_at is None:
                shift = (res.output_points - res.output_points[:1] - race.origin).norm(dim=-1).max()
                if float(shift) > START_RACE_MOVED_M:
                    race.moved_at = len(race.fits) - 1
                    race.frames_left = self._race_frames()
        race.frames_left -= 1
        if race.frames_left <= 0:
            self._decide_race()

    def _decide_race(self) -> None:
        """End the race: the twin goes on in this tracker's place where it won (module docstring), its results
        then revising the race's frames (:meth:`take_revised`)."""
        race, self._race = self._race, None
        fits = race.fits[race.moved_at or 0:]
        if not fits:  # nothing both fitted during the race: the search's start stays
            return
        own, other, own_cost, other_cost = (sum(col) / len(fits) for col in zip(*fits))
        log.debug("start race over %d frames (decided on the last %d, the body moved on frame %s): the search's start "
                  "scores %.3f, turned round %.3f; fit cost %.1f / %.1f mm", len(race.results), len(fits),
                  race.moved_at, own, other, 1e3 * own_cost, 1e3 * other_cost)
        if other_cost < own_cost and other >= own - START_RACE_MARGIN and (
                other > own + START_RACE_MARGIN or other_cost < START_RACE_COST_RATIO * own_cost):
            revised, settle, unheld = race.results, self._settle, self._unheld
            self.__dict__.update(race.twin.__dict__)  # this tracker goes on as the twin
            self._race, self._revised, self._twin, self._settle, self._unheld = None, revised, False, settle, unheld
            if race.unheld:  # the frames held back from the start are held back from the twin's instead
                back = self._held_back(race.unheld, revised[0][0])
                self._revised = [(r, revised[0][1]) for r in back] + revised

    def take_revised(self) -> list[tuple[FrameResult, int]]:
        """The results that replace the last ``len(...)`` frames this tracker returned, each with the body version
        it was tracked in (:attr:`body_version`), and forgets them: a start race the start turned round won
        (``TrackerConfig.start_race_s``), or the frames since a start tracked back from a settled track
        (``settle_back_s``, :mod:`~torchtrack.tracking.settle`). Empty otherwise."""
        out, self._revised = self._revised, []
        return out
