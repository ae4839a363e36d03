"""Several sequences tracked in lockstep: one batched per-frame step for all that are tracking as usual.

Each sequence keeps its own :class:`~torchtrack.tracking.markerless.MarkerlessTracker` (its subject, pose, colour
model, held feet, counters). Per frame, the trackers whose frame needs only the plain step
(:meth:`~MarkerlessTracker.routine`: started, not lost, not racing a start, someone there) advance together in one
:func:`~torchtrack.tracking.step.track_step` over their stacked subjects and padded voxels, and each takes in its
row (:meth:`~MarkerlessTracker.accept`); the others (a start, a re-acquisition, a start race, nobody there, an
unreadable frame) take their own :meth:`~MarkerlessTracker.step`, as alone. Each sequence's track is the one it
gets alone, up to floating-point rounding (tests/test_lockstep.py).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

from torchtrack.checks import InputError
from torchtrack.tracking.markerless import FrameResult, MarkerlessTracker, moved_feet, routine_tests
from torchtrack.tracking.voxels import VoxelObservation
from torchtrack.tracking.step import SubjectStack, VoxelBatch, track_step

#: Subject stacks kept for the sets of subjects recently stepped together (a set changes when a sequence starts,
#: is lost, races or ends).
_STACKS_KEPT = 8


class Lockstep:
    """Trackers of several sequences, stepped together (see the module docstring). They must share one
    :class:`~torchtrack.tracking.markerless.TrackerConfig` (the batched step runs one)."""

    def __init__(self, trackers: Sequence[MarkerlessTracker]) -> None:
        if not trackers:
            raise InputError("Lockstep: no trackers given")
        config = trackers[0].config
        if any(t.config != config for t in trackers[1:]):
            raise InputError("Lockstep: the trackers' settings differ; sequences tracked in lockstep share one "
                             "tracker config")
        self.trackers = list(trackers)
        self._stacks: dict[tuple, SubjectStack] = {}
        self.batched = 0  #: the sequences that the last step advanced in the batched step

    def _stack(self, trackers: list[MarkerlessTracker]) -> SubjectStack:
        key = tuple(t.subject for t in trackers)  # the subjects themselves: an id could be reused after they go
        if key not in self._stacks:
            if len(self._stacks) >= _STACKS_KEPT:
                self._stacks.clear()
            self._stacks[key] = SubjectStack(list(key))
        return self._stacks[key]

    def step(self, frames: Mapping[int, VoxelObservation | None]
             ) -> tuple[dict[int, FrameResult], dict[int, Exception]]:
        """One frame of the sequences in ``frames``: tracker ``i``'s observation, or None for a frame it cannot
        observe (:meth:`~MarkerlessTracker.skip`); sequences not in ``frames`` (ended) are left as they are.
        Returns each one's result, and the errors of those whose own step failed (the others go on; an error of
        the batched step itself is raised)."""
        out: dict[int, FrameResult] = {}
        errors: dict[int, Exception] = {}
        ready: list[int] = []  # the trackers whose own state lets the plain step take their frame
        for i, obs in frames.items():
            try:
                if obs is not None and self.trackers[i].routine_ready(obs):
                    ready.append(i)
            except Exception as exc:  # noqa: BLE001 - this sequence's error, for the caller to report
                errors[i] = exc
        passed: set[int] = set()
        if ready:  # all of them tested at once and read in one host synchronisation
            trackers = [self.trackers[i] for i in ready]
            tests = routine_tests(trackers, [frames[i] for i in ready], self._stack(trackers)).tolist()
            passed = {i for i, ok in zip(ready, tests) if ok}
        plain: list[tuple[int, VoxelObservation]] = []
        for i, obs in frames.items():
            if i in errors:
                continue
            tracker = self.trackers[i]
            try:
                if i in passed:
                    plain.append((i, tracker.routine_obs(obs)))
                else:
                    out[i] = tracker.skip() if obs is None else tracker.step(obs)
            except Exception as exc:  # noqa: BLE001 - this sequence's error, for the caller to report
                errors[i] = exc
        self.batched = len(plain)
        if plain:
            trackers = [self.trackers[i] for i, _ in plain]
            first = trackers[0]
            state = MarkerlessTracker.step_states(trackers)
            batch = VoxelBatch.of([obs for _, obs in plain], first.config.ghost_max_cameras)
            stepped = track_step(self._stack(trackers), batch, state, first._step_config, True,
                                 math.radians(first.config.max_root_rotation_deg))
            # the held feet's update of every row at once (a tracker with none yet leaves its row unused)
            seen, still = moved_feet(stepped.feet, stepped.feet_observed, state.feet_seen, state.feet_still,
                                     first.config.hold_max_step_m)
            for b, ((i, obs), tracker, res) in enumerate(zip(plain, trackers, first._results(stepped))):
                try:
                    version = tracker.body_version
                    out[i] = tracker.accept(obs, res, (seen[b], still[b]))
                    tracker._hold_back(obs, out[i], True)  # as step() does
                    tracker._settle_step(obs, out[i], version)
                except Exception as exc:  # noqa: BLE001 - e.g. a re-acquisition's own error
                    errors[i] = exc
        return dict(sorted(out.items())), errors
