"""Recovery (:class:`~torchtrack.tracking.markerless.MarkerlessTracker`'s part that finds the body again): a lost
track re-acquired from the last good pose and the start's search, and (off by default) a lost arm searched for
again from hanging."""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import replace

import torch

from torchtrack.tracking.start import START_MAX_OUTSIDE
from torchtrack.tracking.step import FrameResult, SubjectStack, host_tensor, pad_rows
from torchtrack.tracking.voxels import VoxelObservation

log = logging.getLogger(__name__)

#: hold_lost_feet: after a re-acquisition, a remembered foot farther than this from the re-acquired pose's is no
#: longer held (the subject may have moved on while it was lost).
REACQUIRED_FOOT_M = 0.1
#: While lost, the re-acquisition searches for the whole state (a second or more on a CPU) every this many frames.
REACQUIRE_SEARCH_EVERY = 5
#: Re-acquisition: of its fits that pass the checks, those within this of the best two-way score
#: (:func:`~torchtrack.tracking.search.score_states`, 0-1) compete by EM/IK's fit cost. The score tells a wrong
#: heading or pose from the right one, but it also prefers a limb no view shows (a stance leg learnt into the
#: background) moved onto voxels; the fit cost leaves such a limb where the pose puts it.
REACQUIRE_SCORE_MARGIN = 0.05
#: ``image_hold_s``: the images hold a body whose voxels the observed volume's sides cut (at least this share of
#: the weight of the voxels within IMAGE_HOLD_NEAR_M of its predicted blobs' centres, along the floor, lie within
#: two voxels of a side: a body's cross-section is a tenth or so of it) or whose predicted blobs' centres lie out
#: of the sides for at least IMAGE_HOLD_OUTSIDE of its volume.
IMAGE_HOLD_CUT = 0.1
IMAGE_HOLD_NEAR_M = 0.3
IMAGE_HOLD_OUTSIDE = 0.25


class RecoveryMixin:
    """The recovery's methods of :class:`~torchtrack.tracking.markerless.MarkerlessTracker` (its state: see there)."""

    def _search_lost_arms(self, obs: VoxelObservation, res: FrameResult) -> tuple[FrameResult, list[torch.Tensor]]:
        """``lost_hand_frames``: an accepted frame's result, or the frame tracked again with a lost arm at rest
        where that fits better (see :class:`TrackerConfig`), and the DOF indices of each arm so found. Counts each
        hand's de-activated frames since it went off or was last searched for."""
        n = self.config.lost_hand_frames
        found_arms: list[torch.Tensor] = []
        if n <= 0:
            return res, found_arms
        sub = self.subject
        again = None  # the frame tracked once more as it is: once for both arms, until a search is kept
        for i, side in enumerate(("l", "r")):
            k = sub.blobs.names.index(f"{side}_hand")
            self.hands_off[i] = 0 if bool(res.blobs.active[k]) else self.hands_off[i] + 1
            if self.hands_off[i] < n:
                continue
            self.hands_off[i] = 0  # the next search n frames on: a hand no view shows costs 2 passes per n frames
            hanging = res.angles.clone()
            hanging[sub.arm_dofs[i]] = sub.arm_rest[i]
            # both from this frame's solution, one more pass each: a second pass alone lowers the cost (the rest of
            # the body fits again), so the search is measured against the frame tracked again as it is
            if again is None:
                again = self._track_again(obs, res.angles)
            trial = self._track_again(obs, sub.skeleton.clamp(hanging[None])[0])
            cost, trial_cost = self._fit_cost(again), self._fit_cost(trial)
            found = trial_cost < cost and not self._diverging(trial)
            log.debug("the %s hand off for %d frames: the arm searched from hanging fits at %.1f mm against %.1f: %s",
                      side, n, 1e3 * trial_cost, 1e3 * cost, "kept" if found else "refused")
            if found:
                res, again = trial, None
                found_arms.append(sub.arm_dofs[i])
        return res, found_arms

    def _track_again(self, obs: VoxelObservation, angles: torch.Tensor) -> FrameResult:
        """The frame tracked once more from ``angles``, without velocity; the tracker's pose is left as it was."""
        kept = self.angles, self.previous
        self.angles = self.previous = angles
        try:
            return self._track(obs, learn_colour=True, max_rot=math.radians(self.config.max_root_rotation_deg))
        finally:
            self.angles, self.previous = kept

    def _searched(self, obs: VoxelObservation) -> FrameResult | None:
        """The subject's body searched for in ``obs`` from any pose (:mod:`torchtrack.tracking.search`, its size
        fixed), the best hypothesis finished by EM/IK; None where it lies out of the observed volume."""
        from torchtrack.tracking.search import SearchConfig, search_pose

        gen = torch.Generator(device=obs.points.device).manual_seed(self.config.search_seed)
        found = search_pose(obs, self.subject.skeleton, self.subject.blobs, SearchConfig(
            scale_range=(1.0, 1.0), real_poses=self.config.start_real_poses,
            prior_exclude=self.config.start_prior_exclude), gen, n=1)
        if float(found.outside[0]) > START_MAX_OUTSIDE:
            return None
        self.angles = self.previous = found.angles[0].to(obs.points.dtype)
        res = None
        for _ in range(max(2, self.config.init_passes // 2)):
            res = self._track(obs, learn_colour=False, max_rot=math.radians(45), predicted=False, hold=False)
            self.angles = self.previous = res.angles
        return res

    def _hold_prediction(self, obs: VoxelObservation) -> torch.Tensor | None:
        """``image_hold_s``: the predicted state ``(D,)`` where the images are to track this frame (the observed
        volume's sides cut the body's voxels, or its prediction lies out of them: IMAGE_HOLD_CUT,
        IMAGE_HOLD_OUTSIDE; the track not yet lost, held for fewer than ``image_hold_s`` in a row, the cameras'
        foreground kept); else None."""
        if not self._hold_applies(obs):
            return None
        predicted, hold = hold_tests([self], [obs], self.subject.stack)
        return predicted[0] if bool(hold[0]) else None

    def _hold_applies(self, obs: VoxelObservation) -> bool:
        """Whether the image hold may take this frame: on, the cameras' foreground kept, the volume known, the
        track started and not yet lost or racing, held for fewer than ``image_hold_s`` in a row."""
        hold_frames = self._hold_frames()
        return not (hold_frames < 1 or obs.silhouettes is None or obs.volume_m is None or self.subject is None
                    or self.angles is None or self._race is not None or self._twin or self.held >= hold_frames
                    or self.lost >= self.config.lost_frames)

    def _hold_frames(self) -> int:
        """``image_hold_s`` in frames of the sequence."""
        return round(self.config.image_hold_s * (self.frame_rate or self.config.velocity_fps or 30.0))

    def _near_in_images(self, obs: VoxelObservation, predicted: torch.Tensor, seed: int) -> FrameResult | None:
        """The body near ``predicted (D,)`` in ``obs``' images as a held frame (confidence
        ``image_hold_confidence``), or None where fewer than ``image_hold_min_cameras`` cameras show it."""
        from torchtrack.tracking.search import search_near_in_images

        cfg, skel = self.config, self.subject.skeleton
        gen = torch.Generator(device=obs.silhouettes.fg.device).manual_seed(seed)
        found = search_near_in_images(obs.silhouettes, obs.cameras_valid, skel, self.subject.blobs, predicted, gen)
        if found.cameras < cfg.image_hold_min_cameras:
            log.debug("image hold: %d cameras show the body (score %.3f), fewer than %d", found.cameras,
                      found.score, cfg.image_hold_min_cameras)
            return None
        angles = found.angles.to(predicted)
        fk = skel.forward(angles[None])
        J = fk.output_points.shape[1]
        # no IK residual and no voxel weight explained: the images, not the voxels, placed it
        return FrameResult(angles, fk.output_points[0], fk.output_points.new_full((J,), cfg.image_hold_confidence),
                           True, math.nan, math.nan, False, None, fk.bone_frames[0])

    def _held_back(self, unheld: list[VoxelObservation | None], res: FrameResult) -> list[FrameResult]:
        """``image_hold_s``: the invalid frames ``unheld`` just before a re-acquisition ``res`` (oldest first),
        tracked back from it in their images (:meth:`_near_in_images`, the motion of the frames held so far
        carried on) while at least ``image_hold_min_cameras`` cameras show the body: the walker who came back
        into the volume was in the views before it. Returns the held frames, oldest first (the last of them the
        frame before ``res``)."""
        skel = self.subject.skeleton
        out: list[FrameResult] = []
        later, last = res.angles, res.angles
        for k, obs in enumerate(reversed(unheld)):
            if obs is None or obs.silhouettes is None:
                break
            predicted = skel.clamp((last + self.prediction_velocity * (last - later))[None])[0]
            held = self._near_in_images(obs, predicted, self.config.search_seed + k)
            if held is None:
                break
            out.append(held)
            later, last = last, held.angles
        return out[::-1]

    def _held_in_images(self, obs: VoxelObservation) -> FrameResult | None:
        """``image_hold_s``: the frame tracked in the images (:meth:`_near_in_images` from the prediction) where
        :meth:`_hold_prediction` says so and the cameras show the body; else None (the frame goes on as without
        it)."""
        predicted = self._hold_prediction(obs)
        if predicted is None:
            return None
        held = self._near_in_images(obs, predicted, self.config.search_seed + self.held)
        if held is None:
            return None
        if self.lost == 0:
            self.previous = self.angles
        self.angles = held.angles.clone()
        self.lost, self.held = 0, self.held + 1  # held counts until the voxels accept a frame again
        self._settle = None  # the frames to track back end here: the voxels cannot track these again
        if self.feet_seen is not None:  # the feet move on with the held body, not held until seen still
            self.feet_seen = self.subject.skeleton.forward(self.angles[None]).joints[0, self.subject.feet]
            self.feet_still = torch.zeros_like(self.feet_still)
        return held

    def _reacquire(self, obs: VoxelObservation) -> FrameResult:
        """Re-initialise: around the last good pose (moved onto the voxels' centroid, four headings) and, at once
        and then every REACQUIRE_SEARCH_EVERY lost frames, from any pose by the start's search. Of the fits that
        do not diverge, those within REACQUIRE_SCORE_MARGIN of the best two-way score (EM/IK's residual alone
        cannot tell a body turned a quarter or half round from the right one) compete by the fit cost; the winner
        races its twin turned round as a start does (``start_race_s``). The colour model goes: the fits go without
        it and the re-acquired frame learns it afresh. The re-acquisition is checked later (``recheck_s``)."""
        from torchtrack.tracking.search import score_states

        pts, w = obs.points, obs.weights
        c = (w[:, None] * pts).sum(0) / w.sum()
        skel = self.subject.skeleton
        base = self.angles.clone()
        self.colour = None  # learnt before the loss (elsewhere in the room, or from frames losing the body)
        ix, iy, irz = (skel.dof_names.index(n) for n in ("root_tx", "root_ty", "root_rz"))
        starts = base.repeat(4, 1)
        starts[:, ix], starts[:, iy] = c[0], c[1]
        starts[:, irz] = base[irz] + torch.tensor([0.0, 0.5, 1.0, -0.5], dtype=base.dtype, device=base.device) * math.pi
        fits = self._fit_many(obs, starts, max(2, self.config.init_passes // 2), math.radians(45))
        if (self.lost - self.config.lost_frames) % REACQUIRE_SEARCH_EVERY == 0:
            found = self._searched(obs)
            if found is not None:
                fits.append(found)
        held = [r for r in fits if not self._diverging(r)]
        if not held:  # keep searching from the last good pose on the next frame
            self.angles = self.previous = base
            self.lost += 1
            return replace(min(fits, key=self._fit_cost), valid=False, reinitialised=True)
        score = score_states(obs, skel, self.subject.blobs, torch.stack([r.angles for r in held]))[0]
        log.debug("re-acquisition: %d of %d fits hold, scores %s; fit costs %s mm", len(held), len(fits),
                  " ".join(f"{float(x):.3f}" for x in score), " ".join(f"{1e3 * self._fit_cost(r):.1f}" for r in held))
        close = [r for r, x in zip(held, score.tolist()) if x >= float(score.max()) - REACQUIRE_SCORE_MARGIN]
        self.unchecked = self._race_frames(self.config.recheck_s) if self.config.recheck_s > 0 else 0
        return self._take(obs, min(close, key=self._fit_cost))

    def _take(self, obs: VoxelObservation, best: FrameResult) -> FrameResult:
        """The tracker goes on from a re-acquired fit ``best``: its colour model learnt afresh, the held feet it left
        let go, and the start race begun."""
        self.angles = self.previous = best.angles
        self.lost = self.held = 0
        self.hands_off = [0, 0]
        if self.feet_seen is not None and best.feet is not None:  # a held foot the new pose left is let go
            far = (best.feet[0] - self.feet_seen).norm(dim=-1) > REACQUIRED_FOOT_M
            self.feet_still = self.feet_still & ~far
        best = self._learn_colour(obs)
        if (self.config.start == "search" and self.config.start_race_s > 0 and self._race is None
                and not self._twin):
            self._start_race(obs, best)
        return best

    def _check_reacquired(self, obs: VoxelObservation, res: FrameResult) -> FrameResult | None:
        """``recheck_s``, on a frame after a re-acquisition, ``res`` this frame's plain track. A frame where ``res``
        diverges or the tracked body lies partly out of the observed volume (where the search does not look) uses
        up one frame of the check and leaves it pending. Else the search runs (:meth:`_searched`) and the check is
        over: its answer is taken as a re-acquisition where its two-way score beats ``res``'s by more than
        REACQUIRE_SCORE_MARGIN and its fit cost is no higher (a clear win only: a track that holds stands against an
        equal answer, and on a few views' hull the score alone can prefer a wrong body); else None, and ``res``
        stands."""
        from torchtrack.tracking.search import score_states

        self.unchecked -= 1
        if self._diverging(res):
            return None
        skel, blobs = self.subject.skeleton, self.subject.blobs
        own, _, _, outside = score_states(obs, skel, blobs, res.angles[None])
        if float(outside[0]) > START_MAX_OUTSIDE:
            return None
        self.unchecked = 0
        kept = self.angles, self.previous, self.colour
        self.colour = None  # the search's fits go without it, as a re-acquisition's do
        try:
            found = self._searched(obs)
        finally:
            self.angles, self.previous, self.colour = kept
        if found is None or self._diverging(found):
            return None
        other = score_states(obs, skel, blobs, found.angles[None])[0]
        log.debug("re-acquisition check: the track scores %.3f, the search's answer %.3f; fit costs %.1f / %.1f mm",
                  float(own[0]), float(other[0]), 1e3 * self._fit_cost(res), 1e3 * self._fit_cost(found))
        if float(other[0]) <= float(own[0]) + REACQUIRE_SCORE_MARGIN or self._fit_cost(found) > self._fit_cost(res):
            return None
        return self._take(obs, found)


def hold_tests(trackers: Sequence[RecoveryMixin], observations: Sequence[VoxelObservation], stack: SubjectStack,
               prediction: tuple[torch.Tensor, torch.Tensor] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The image hold's test (:meth:`RecoveryMixin._hold_prediction`) of several started trackers of one chain on
    their frames at once, ``stack`` their subjects stacked (a stack of one for one tracker): each one's predicted
    state ``(R, D)`` and ``(R,)`` bool, true where the volume's sides cut the body's voxels (IMAGE_HOLD_CUT) or its
    prediction lies out of them (IMAGE_HOLD_OUTSIDE). Whether the hold may take a frame at all is each tracker's
    :meth:`~RecoveryMixin._hold_applies`; a frame whose volume is unknown is tested against an unbounded one.
    ``prediction``: the predicted states and their bone frames where the caller has them (the batched step's,
    :class:`~torchtrack.tracking.step.Stepped`)."""
    if prediction is None:  # as the step predicts
        angles, previous = (torch.stack([getattr(t, f) for t in trackers]) for f in ("angles", "previous"))
        v = host_tensor([t.prediction_velocity for t in trackers], angles)[:, None]
        predicted = stack.clamp(angles + v * (angles - previous))
        bones = stack.skeleton.forward(predicted).bone_frames
    else:
        predicted, bones = prediction
    c, _ = stack.blobs.ellipsoids(bones)  # (R, K, 3); no finite check
    unbounded = [(-math.inf,) * 2, (math.inf,) * 2]
    # (R, 2, 2): each volume's lower and upper corner along the floor
    box = host_tensor([unbounded if o.volume_m is None else [corner[:2] for corner in o.volume_m]
                       for o in observations], c)
    lower, upper = box[:, None, 0], box[:, None, 1]  # (R, 1, 2)
    out = ((c[..., :2] < lower) | (c[..., :2] > upper)).any(-1)  # (R, K)
    vol = stack.blobs.semi_axes.to(c).prod(-1)
    hold = (vol * out).sum(-1) / vol.sum(-1) >= IMAGE_HOLD_OUTSIDE
    if max(o.num_voxels for o in observations) == 0:
        return predicted, hold
    # the voxels padded (NaN points, no weight): a padded voxel is no body's
    p = pad_rows([o.points for o in observations], math.nan)[..., :2].to(c)
    w = pad_rows([o.weights for o in observations], 0.0).to(c)
    edge = 2 * pad_rows([o.sizes for o in observations], 0.0).amax(-1).to(c)[:, None, None]
    body = torch.cdist(p, c[..., :2]).amin(-1) < IMAGE_HOLD_NEAR_M  # the body's voxels, not a ghost's or clutter's
    cut = ((p - lower < edge) | (upper - p < edge)).any(-1)
    w = w * body
    # no body voxels: 0 / 0, NaN, which no threshold passes
    return predicted, hold | ((w * cut).sum(-1) / w.sum(-1) >= IMAGE_HOLD_CUT)


def routine_tests(trackers: Sequence[RecoveryMixin], observations: Sequence[VoxelObservation],
                  stack: SubjectStack, prediction: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
    """Whether the plain per-frame step takes each frame, for trackers whose own state lets it (their
    ``routine_ready``): (R,) bool, true where someone is there (the voxels' volume, as ``_has_person``) and the
    images do not hold the body (:func:`hold_tests`).
    ``stack``: the trackers' subjects stacked (a stack of one for one tracker); ``prediction``: their predicted states
    and bone frames where the caller has them. All trackers at once and nothing read back: a driver of many reads
    the answers with the step's results, in one synchronisation."""
    cfg = trackers[0].config
    sizes = pad_rows([o.sizes.to(o.points.device) for o in observations], 0.0).double()
    ok = (sizes ** 3).sum(-1) >= cfg.min_volume_m3
    applies = [t._hold_applies(o) for t, o in zip(trackers, observations)]
    if any(applies):
        hold = hold_tests(trackers, observations, stack, prediction)[1]
        if not all(applies):
            hold = hold & host_tensor(applies, hold)
        ok = ok & ~hold
    return ok
