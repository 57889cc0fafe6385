"""The synthetic paired benchmark: determinism, splits, file format, the headset stream, sequences."""

from __future__ import annotations

import numpy as np
import pytest
from ofera.mapping.flame_values import split_flame_values
from ofera.mapping.layouts import to_arkit51
from ofera.training.paired import SPLITS, PairedData, PairedDataError, concat, make_benchmark
from ofera.training.paired.benchmark import assign_splits
from ofera.training.paired.observe import ovr_from_arkit
from ofera.training.paired.rig import IDX
from ofera.training.paired.sequences import SequenceStyle, blink_layer, generate_weights


@pytest.fixture(scope="module")
def tiny(head):
    calls = []
    data = make_benchmark(tiny=True, head=head, progress=lambda done, total, message: calls.append((done, total)))
    data.meta["progress_calls"] = calls
    return data


def test_tiny_benchmark_shapes_and_ranges(tiny):
    t = 8 * 100  # 3 training sources x 2 subjects + 2 subjects of the held-out source, 100 frames each
    assert len(tiny) == t and tiny.fps == 30.0
    assert tiny.bs.shape == (t, 51) and tiny.bs.dtype == np.float32
    assert tiny.flame.shape == (t, 68) and tiny.flame.dtype == np.float32
    assert tiny.headset.shape == (t, 63) and tiny.rig_weights.shape == (t, 51)
    assert tiny.shape.shape == (8, 20)
    assert tiny.source_names == ("studio", "conversation", "expressive", "handheld")
    assert tiny.meta["holdout_sources"] == ["handheld"]
    for arr in (tiny.bs, tiny.headset, tiny.rig_weights):
        assert arr.min() >= 0.0 and arr.max() <= 1.0
    assert np.all(np.isfinite(tiny.flame))
    expr, rot = split_flame_values(tiny.flame)
    assert np.abs(expr).max() < 15  # a tracker's prior keeps coefficients in FLAME's usual range
    assert tiny.fit_rms.max() < 0.005  # the fit follows the rig's meshes within millimetres
    assert (np.abs(tiny.bs - tiny.rig_weights) > 1e-3).mean() > 0.5  # observations are noisy
    assert tiny.meta["progress_calls"][-1] == (8, 8)
    np.testing.assert_array_equal(tiny.frame[:100], np.arange(100))


def test_deterministic_in_the_seed(tiny, head):
    again = make_benchmark(tiny=True, head=head)
    for key in ("bs", "flame", "headset", "rig_weights", "subject", "split", "shape"):
        np.testing.assert_array_equal(getattr(again, key), getattr(tiny, key), err_msg=key)
    other = make_benchmark(frames_per_subject=30, subjects_per_source=1, seed=1, head=head)
    assert not np.allclose(other.rig_weights[:30], tiny.rig_weights[:30])


def test_splits_are_subject_disjoint(tiny):
    subject_split = {}
    for s, code in zip(tiny.subject, tiny.split):
        assert subject_split.setdefault(int(s), int(code)) == int(code)
    for name in SPLITS:
        assert tiny.subset(name).subjects.size >= 1
    for s in tiny.subjects:  # each subject belongs to one source
        assert len(np.unique(tiny.source[tiny.subject == s])) == 1
    held = tiny.source == tiny.source_names.index("handheld")  # the held-out source is test only
    assert held.any() and (tiny.split[held] == SPLITS.index("test")).all()


def test_each_source_has_its_own_estimator_and_headset():
    from ofera.training.paired.benchmark import HOLDOUT, SOURCES, source_models

    models = [source_models(0, i, src) for i, src in enumerate(SOURCES + HOLDOUT)]
    for i in range(len(models)):
        for j in range(i):
            assert not np.allclose(models[i][0]["gain"], models[j][0]["gain"])
            assert not np.allclose(models[i][1].gain, models[j][1].gain)


def test_validation_sample_digest_is_stable_and_sensitive():
    from ofera.training.paired.benchmark import SAMPLE_STEP, sample_digest, validation_sample

    sample = validation_sample(frames=10)
    assert sample["bs"].shape == (10, 51) and sample["flame"].shape == (10, 68)
    assert sample["source"] == "studio"
    same = {k: (v + 1e-9 if k in ("bs", "flame") else v) for k, v in sample.items()}
    assert sample_digest(same) == sample_digest(sample)  # rounding absorbs BLAS-sized differences
    moved = dict(sample, flame=sample["flame"] + np.where(np.arange(68) == 3, 2 * SAMPLE_STEP, 0.0))
    assert sample_digest(moved) != sample_digest(sample)


def test_full_size_split_is_8_1_1_per_source():
    codes = assign_splits(10, 0, np.random.default_rng(0))
    assert np.bincount(codes, minlength=3).tolist() == [8, 1, 1]


def test_save_load_round_trip(tiny, tmp_path):
    path = tmp_path / "paired.npz"
    tiny.save(path)
    with np.load(path, allow_pickle=False) as z:  # no object arrays: loads without pickle
        assert "bs" in z.files
    back = PairedData.load(path)
    for key in ("bs", "flame", "subject", "source", "split", "frame", "headset", "rig_weights", "fit_rms", "shape"):
        np.testing.assert_array_equal(getattr(back, key), getattr(tiny, key), err_msg=key)
    assert back.fps == tiny.fps and back.source_names == tiny.source_names
    assert back.split_names[0] in SPLITS
    with pytest.raises(PairedDataError, match="no such"):
        PairedData.load(tmp_path / "missing.npz")
    np.savez(tmp_path / "other.npz", x=np.zeros(3))
    with pytest.raises(PairedDataError, match="not an OFERA paired-data file"):
        PairedData.load(tmp_path / "other.npz")


def test_select_and_concat(tiny):
    test = tiny.subset("test")
    assert set(test.split.tolist()) == {SPLITS.index("test")}
    both = concat([tiny, tiny])
    n = len(tiny.shape)
    assert len(both) == 2 * len(tiny) and len(both.shape) == 2 * n
    assert set(both.subject[len(tiny):].tolist()) == set((tiny.subject + n).tolist())
    with pytest.raises(PairedDataError, match="shape"):
        PairedData(bs=np.zeros((3, 50)), flame=np.zeros((3, 68)), subject=np.zeros(3), source=np.zeros(3),
                   split=np.zeros(3), frame=np.arange(3))


def test_headset_through_metas_mapping_is_a_distorted_truth(tiny):
    meta = to_arkit51("ovr63", tiny.headset)
    truth = tiny.rig_weights
    err = np.abs(meta - truth)
    assert err.mean() > 0.02  # what BDA must correct
    assert np.median([np.corrcoef(meta[:, k], truth[:, k])[0, 1] for k in range(51)
                      if truth[:, k].std() > 0.02]) > 0.8  # but it is the same face


def test_ovr_inversion_is_a_right_inverse_of_metas_mapping():
    rng = np.random.default_rng(0)
    w = rng.uniform(0.0, 0.45, (50, 51))
    for side in ("Left", "Right"):  # where Meta's sums allow it: shares it cannot split apart
        smile = w[:, IDX[f"mouthSmile{side}"]]
        w[:, IDX[f"cheekSquint{side}"]] = np.maximum(w[:, IDX[f"cheekSquint{side}"]], smile)
        w[:, IDX[f"eyeSquint{side}"]] = np.maximum(w[:, IDX[f"eyeSquint{side}"]], 0.25 * smile)
    w[:, IDX["mouthFunnel"]] = np.maximum(w[:, IDX["mouthFunnel"]], w[:, IDX["mouthPucker"]])
    np.testing.assert_allclose(to_arkit51("ovr63", ovr_from_arkit(w).astype(np.float32)), w, atol=1e-6)


def test_sequences_resemble_captures():
    rng = np.random.default_rng(3)
    fps, minutes = 30.0, 4.0
    blinks = blink_layer(rng, int(minutes * 60 * fps), fps, SequenceStyle(blink_rate=15.0))[:, IDX["eyeBlinkLeft"]]
    closed = blinks > 0.5
    onsets = np.count_nonzero(closed[1:] & ~closed[:-1])
    assert 8 * minutes <= onsets <= 24 * minutes  # about 15 a minute
    runs = np.diff(np.flatnonzero(np.diff(np.concatenate([[0], closed.astype(int), [0]]))))[::2]
    assert runs.max() <= 5  # 100-150 ms blinks: a few frames at 30 fps
    w = generate_weights(np.random.default_rng(4), 1800, fps)
    assert w.shape == (1800, 51) and w.min() >= 0.0 and w.max() <= 1.0
    assert np.all(w[:, IDX["mouthClose"]] <= w[:, IDX["jawOpen"]] + 1e-12)
    assert np.corrcoef(w[:, IDX["mouthSmileLeft"]], w[:, IDX["cheekSquintLeft"]])[0, 1] > 0.3  # co-activation
    assert (w.max(axis=0) > 0.1).all()  # every shape occurs
    assert np.abs(np.diff(w[:, IDX["jawOpen"]])).mean() < 0.05  # smooth, not white noise
