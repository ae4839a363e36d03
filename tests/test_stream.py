"""Frames observed in a worker process (torchtrack.tracking.stream): the same observations, images and poses as
in this process, errors handed over as they are, thread shares restored; one worker for several passes; video
sources that pickle; the folder's cache of decoded frames."""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pytest
import torch

from torchtrack.background import BackgroundModel
from torchtrack.checks import InputError
from torchtrack.io.sequence import SequenceFolder
from torchtrack.tracking.observation import Observer
from torchtrack.tracking.stream import ObservationWorker, observe_batches

from conftest import small_walk


@pytest.fixture(scope="module")
def seq(tmp_path_factory) -> Path:
    return small_walk(tmp_path_factory.mktemp("stream") / "seq", duration_s=0.3, video_format="mp4")


def _observer(seq: Path, model: str) -> tuple[SequenceFolder, Observer]:
    folder = SequenceFolder(seq)
    rig = folder.rig.resized(160, 120).float()
    bg = BackgroundModel.from_folder(folder, size_wh=(160, 120))
    return folder, Observer(rig, bg, model, voxel_size_m=0.05)


@pytest.mark.parametrize("model, cell", [("bayes", 0.0), ("hull", 0.1)])
def test_a_worker_observes_what_this_process_does(seq, model, cell):
    folder, observer = _observer(seq, model)
    threads = torch.get_num_threads()
    raw = [o for b in observe_batches(folder, observer, 1, folder.num_frames, batch=3) for o in b.observations]
    here = list(observe_batches(folder, observer, 1, folder.num_frames, batch=3, keep_images=2, cell_m=cell))
    seen_threads = []
    there = []
    for item in observe_batches(folder, observer, 1, folder.num_frames, batch=3, keep_images=2, workers=1,
                                cell_m=cell):
        seen_threads.append(torch.get_num_threads())
        there.append(item)
    for r, p in zip(raw, (o for b in here for o in b.observations)):  # merged where they were observed
        assert p.num_observed == r.num_voxels and p.cell_m == cell
        if cell:
            assert p.num_voxels < r.num_voxels
            torch.testing.assert_close(p.points, r.pooled(cell).points)
            assert p.pooled(cell) is p  # the tracker does not merge them again
    assert seen_threads and set(seen_threads) == {1}  # the caller keeps one thread while the worker runs
    assert torch.get_num_threads() == threads  # and gets its share back
    assert [b.frame_index.tolist() for b in there] == [b.frame_index.tolist() for b in here]
    frames = [t for b in here for t in b.frame_index.tolist()]
    assert frames == list(range(1, folder.num_frames))
    R = folder.rig.R_cam_world.double().numpy()
    centres = torch.from_numpy(-np.einsum("cji,cj->ci", R, folder.rig.t_cam_world.double().numpy()))  # -R^T t
    for a, b in zip(here, there):
        assert torch.equal(a.valid, b.valid)
        for oa, ob in zip(a.observations, b.observations):
            assert oa.num_voxels > 30
            for o in (oa, ob):  # the cameras' centres, for the ghost test, merged or not, from either process
                torch.testing.assert_close(o.camera_centres.double(), centres, rtol=0, atol=1e-5)
            assert (ob.num_observed, ob.cell_m) == (oa.num_observed, oa.cell_m)
            assert torch.equal(oa.points, ob.points) and torch.equal(oa.sizes, ob.sizes)
            torch.testing.assert_close(ob.weights, oa.weights, rtol=1e-5, atol=1e-12)
            torch.testing.assert_close(ob.colours, oa.colours, rtol=1e-5, atol=1e-6, equal_nan=True)
        for t, img in zip(b.frame_index.tolist(), b.images):  # the images of every 2nd frame from the start
            if (t - 1) % 2:
                assert img is None
            else:
                ref = folder.read_frame(t, size_wh=(160, 120))  # the reader's own, independent of the stream
                torch.testing.assert_close(img, ref)


def _live_workers() -> int:
    import multiprocessing

    return len(multiprocessing.active_children())


def test_a_stream_left_early_or_failing_to_start_gives_the_threads_back_and_stops_its_worker(seq):
    folder, observer = _observer(seq, "hull")
    threads = torch.get_num_threads()
    stream = observe_batches(folder, observer, 0, folder.num_frames, batch=1, workers=1)
    next(stream)
    assert torch.get_num_threads() == 1 and _live_workers() == 1
    stream.close()
    assert torch.get_num_threads() == threads and _live_workers() == 0
    observer.unpicklable = lambda: None  # the worker cannot be given it
    with pytest.raises(InputError, match="do not pickle"):
        next(observe_batches(folder, observer, 0, folder.num_frames, workers=1))
    assert torch.get_num_threads() == threads and _live_workers() == 0


def test_a_workers_warnings_reach_the_caller(tmp_path):
    from torchtrack.io.video import DataWarning

    seq = small_walk(tmp_path / "seq", duration_s=0.2, video_format="png", starfish_s=0.0, background_frames=3,
                     size_wh=(160, 120), noise=False)
    victim = sorted((seq / "video").rglob("*.png"))[2]
    victim.write_bytes(b"not a png")
    folder, observer = _observer(seq, "hull")
    with pytest.warns(DataWarning, match=victim.name):
        batches = list(observe_batches(folder, observer, 0, folder.num_frames, batch=2, workers=1))
    valid = torch.cat([b.valid for b in batches])
    assert int((~valid).sum()) == 1


def test_a_workers_input_error_reaches_the_caller_as_it_is(seq):
    folder, observer = _observer(seq, "hull")
    threads = torch.get_num_threads()
    with pytest.raises(InputError, match=r"frame range \[0, 99\) outside") as err:
        list(observe_batches(folder, observer, 0, 99, workers=1))
    assert str(folder.root) in str(err.value)
    assert torch.get_num_threads() == threads
    with pytest.raises(InputError, match="workers must be 0 or 1"):
        list(observe_batches(folder, observer, 0, 2, workers=2))
    with pytest.raises(InputError, match="keep_images and cell_m must be >= 0"):
        list(observe_batches(folder, observer, 0, 2, cell_m=-1.0))


def test_a_video_source_pickles_without_its_decoder_and_reads_the_same_frames(seq):
    folder = SequenceFolder(seq)
    src = folder.sources[0]
    out = np.empty((src.size_wh[1], src.size_wh[0], 3), np.uint8)
    assert src._decode_into(3, out)  # the original is now mid-stream
    copy = pickle.loads(pickle.dumps(src))
    assert copy._cap is None and copy.num_frames == src.num_frames and copy.size_wh == src.size_wh
    again = np.empty_like(out)
    assert copy._decode_into(3, again)
    assert np.array_equal(again, out)
    assert src._decode_into(4, out) and copy._decode_into(4, again) and np.array_equal(again, out)


def test_tracking_with_a_worker_gives_the_same_poses(seq):
    from torchtrack.skeleton import Skeleton
    from torchtrack.tracking.pipeline import load_config
    from torchtrack.tracking.markerless import MarkerlessTracker, TrackerConfig
    from torchtrack.tracking.run import track_sequence

    folder, observer = _observer(seq, "hull")
    cfg = TrackerConfig.from_dict(load_config("markerless.yaml")["tracker"])
    trackers = [MarkerlessTracker(Skeleton.from_urdf(), cfg) for _ in range(2)]
    runs = [track_sequence(folder, observer, t, progress=False, workers=w)[0] for t, w in zip(trackers, (0, 1))]
    assert [t.frame_rate for t in trackers] == [folder.fps] * 2  # the prediction's velocity is set for it
    assert runs[0].valid.all() and np.array_equal(runs[0].valid, runs[1].valid)
    # same observations; the tracker's float sums may round differently at another thread count
    np.testing.assert_allclose(runs[1].joints3d, runs[0].joints3d, atol=1e-3)
    # every 2nd frame: a sequence at half the rate, near the full rate's track at those frames
    half = MarkerlessTracker(Skeleton.from_urdf(), cfg)
    strided = track_sequence(folder, observer, half, progress=False, workers=1, step=2)[0]
    assert strided.frame_index.tolist() == list(range(0, folder.num_frames, 2)) and half.frame_rate == folder.fps / 2
    assert strided.valid.all()
    apart = np.linalg.norm(strided.landmarks() - runs[0].landmarks()[::2], axis=-1).mean()
    assert apart < 0.02, apart


def _same(a: list, b: list) -> None:
    assert [x.frame_index.tolist() for x in a] == [x.frame_index.tolist() for x in b]
    for x, y in zip(a, b):
        for ox, oy in zip(x.observations, y.observations):
            assert torch.equal(ox.points, oy.points)
            torch.testing.assert_close(oy.colours, ox.colours, rtol=1e-5, atol=1e-6, equal_nan=True)


def test_one_worker_serves_several_passes_one_left_early_or_failing(seq):
    """A worker kept for several passes gives each what this process does, with another observer each pass (the
    refinement's new background), after a pass left early and after one that failed, and stops when closed."""
    folder, bayes = _observer(seq, "bayes")
    _, hull = _observer(seq, "hull")
    threads = torch.get_num_threads()
    with ObservationWorker() as worker:
        for observer in (bayes, hull, bayes):
            here = list(observe_batches(folder, observer, 0, folder.num_frames, batch=2))
            _same(here, list(observe_batches(folder, observer, 0, folder.num_frames, batch=2, workers=worker)))
            left = observe_batches(folder, observer, 0, folder.num_frames, batch=1, workers=worker)
            next(left)
            left.close()  # the rest of that pass is dropped, not handed to the next
            assert torch.get_num_threads() == threads
        with pytest.raises(InputError, match=r"frame range \[0, 99\) outside"):
            list(observe_batches(folder, hull, 0, 99, workers=worker))
        _same(list(observe_batches(folder, hull, 1, 4)), list(observe_batches(folder, hull, 1, 4, workers=worker)))
        every = list(observe_batches(folder, hull, 0, folder.num_frames, batch=1))  # and every 3rd frame from 1
        _same(every[1::3], list(observe_batches(folder, hull, 1, folder.num_frames, batch=1, step=3, workers=worker)))
        assert worker.alive and _live_workers() == 1
    assert not worker.alive and _live_workers() == 0
    with pytest.raises(InputError, match="has stopped"):
        next(observe_batches(folder, hull, 0, 2, workers=worker))


def test_cached_frames_are_the_decoded_ones_and_not_decoded_again(seq, monkeypatch):
    import torchtrack.io.sequence as sequence

    fresh = SequenceFolder(seq)
    folder = SequenceFolder(seq)
    one = fresh.read_frames([2], size_wh=(160, 120)).images.numel()  # bytes of one frame in uint8
    folder.cache_frames(5 * one)
    decoded = []
    real = sequence._read_available
    monkeypatch.setattr(sequence, "_read_available", lambda src, idx: decoded.append(list(idx)) or real(src, idx))
    first = torch.cat([b.images for b in folder.iter_batches(3, 0, 6, size_wh=(160, 120))])
    C = folder.num_cameras
    assert folder.cached_bytes == 5 * one and len(decoded) == 2 * C  # two batches, every camera
    decoded.clear()
    again = torch.cat([b.images for b in folder.iter_batches(2, 0, 6, size_wh=(160, 120))])
    assert decoded == [[5]] * C  # the 6th frame did not fit the cache
    some = folder.read_frames([1, 3], size_wh=(160, 120)).images
    _, sampled = folder.sample_frames(3, 0, 5, size_wh=(160, 120))  # frames 0, 2, 4
    full = folder.read_frames([2]).images  # another size: decoded
    assert decoded == [[5]] * C + [[2]] * C
    decoded.clear()
    ref = torch.cat([b.images for b in fresh.iter_batches(6, 0, 6, size_wh=(160, 120))])
    assert torch.equal(first, ref) and torch.equal(again, ref) and torch.equal(some, ref[[1, 3]])
    assert torch.equal(sampled, ref[[0, 2, 4]].half())
    assert torch.equal(full, fresh.read_frames([2]).images)
    assert pickle.loads(pickle.dumps(folder)).cached_bytes == 0  # a worker gets the sources, not the frames
    folder.cache_frames(0)
    assert folder.cached_bytes == 0
    with pytest.raises(InputError, match="max_bytes must be >= 0"):
        folder.cache_frames(-1)
