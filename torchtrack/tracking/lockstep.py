"""Several sequences tracked in lockstep: one batched per-frame step for all that are tracking as usual.

Each sequence keeps its own :class:`~torchtrack.tracking.markerless.MarkerlessTracker` (its subject, pose, colour
model, held feet, counters). Per frame, the trackers whose frame needs only the plain step
(:meth:`~MarkerlessTracker.routine_ready`, :func:`~torchtrack.tracking.recovery.routine_tests`: started, not lost,
not racing a start, no re-acquisition left to check, someone there, the images not holding the body) advance
together in one :func:`~torchtrack.tracking.step.track_step` over their stacked subjects and padded voxels, and each
takes in its row (:meth:`~MarkerlessTracker.accept`); the others (a start, a re-acquisition, a start race, a
re-acquisition being checked, nobody there, a body the images hold, an unreadable frame) take their own
:meth:`~MarkerlessTracker.step`, as alone. The tests that need
the device run on the batched step's own prediction and are read with its results, in the one read of the frame
(the root fit's SVD waits on a GPU too: :mod:`~torchtrack.tracking.step`).
Each sequence's track is the one it gets alone, up to floating-point rounding (tests/test_lockstep.py).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence

import torch

from torchtrack.checks import InputError
from torchtrack.tracking.markerless import FrameResult, MarkerlessTracker
from torchtrack.tracking.recovery import routine_tests
from torchtrack.tracking.voxels import VoxelObservation
from torchtrack.tracking.step import SubjectStack, VoxelBatch, moved_feet, track_step

log = logging.getLogger(__name__)

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
        Returns each one's result, and the errors of those whose own step failed (the others go on; where the
        batched step fails, each of its sequences steps on its own that frame, with a warning)."""
        out: dict[int, FrameResult] = {}
        errors: dict[int, Exception] = {}
        ready: list[tuple[int, VoxelObservation]] = []  # the frames the trackers' own state lets the plain step take
        own: list[int] = []  # the frames each tracker steps on its own
        for i, obs in frames.items():
            try:
                if obs is not None and self.trackers[i].routine_ready(obs):
                    ready.append((i, self.trackers[i].routine_obs(obs)))
                else:
                    own.append(i)
            except Exception as exc:  # noqa: BLE001 - this sequence's error, for the caller to report
                errors[i] = exc
        passed: list[tuple[int, VoxelObservation, FrameResult, tuple[torch.Tensor, torch.Tensor]]] = []
        if ready:
            try:
                passed = self._batched(ready, frames)
            except Exception:  # noqa: BLE001 - each then steps on its own, where its own error is its own
                log.warning("lockstep: the batched step failed; its %d sequences step on their own this frame",
                            len(ready), exc_info=True)
            done = {i for i, *_ in passed}
            own += [i for i, _ in ready if i not in done]
        self.batched = len(passed)
        for i in sorted(own):
            obs, tracker = frames[i], self.trackers[i]
            try:
                out[i] = tracker.skip() if obs is None else tracker.step(obs)
            except Exception as exc:  # noqa: BLE001 - this sequence's error, for the caller to report
                errors[i] = exc
        for i, obs, res, feet in passed:
            tracker = self.trackers[i]
            try:
                version = tracker.body_version
                out[i] = tracker.accept(obs, res, feet)
                tracker._hold_back(obs, out[i], True)  # as step() does
                tracker._settle_step(obs, out[i], version)
            except Exception as exc:  # noqa: BLE001 - e.g. a re-acquisition's own error
                errors[i] = exc
        return dict(sorted(out.items())), errors

    def _batched(self, ready: list[tuple[int, VoxelObservation]], frames: Mapping[int, VoxelObservation | None]
                 ) -> list[tuple[int, VoxelObservation, FrameResult, tuple[torch.Tensor, torch.Tensor]]]:
        """The batched step on every ready frame (``(i, obs)``: tracker i's frame as the plain step takes it), and the
        routine tests (someone there, not held in the images) on its prediction, read with its results in one host
        synchronisation. Returns the rows that pass, each with its result and held feet; a frame that fails the
        tests (rare) is then stepped on its own, its row dropped."""
        trackers = [self.trackers[i] for i, _ in ready]
        first, stack = trackers[0], self._stack(trackers)
        state = MarkerlessTracker.step_states(trackers)
        batch = VoxelBatch.of([obs for _, obs in ready], first.config.ghost_max_cameras)
        stepped = track_step(stack, batch, state, first._step_config, True,
                             math.radians(first.config.max_root_rotation_deg))
        tests = routine_tests(trackers, [frames[i] for i, _ in ready], stack,
                              (stepped.prediction, stepped.prediction_bones))
        residual, explained, ok = torch.stack([stepped.residual_m.double(), stepped.explained.double(),
                                               tests.double()]).tolist()
        # the held feet's update of every row at once (a tracker with none yet leaves its row unused)
        seen, still = moved_feet(stepped.feet, stepped.feet_observed, state.feet_seen, state.feet_still,
                                 first.config.hold_max_step_m)
        results = first._results(stepped, (residual, explained))
        return [(i, obs, results[b], (seen[b], still[b])) for b, (i, obs) in enumerate(ready) if ok[b]]
