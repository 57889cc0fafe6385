"""Importers of real paired data, on files written here in the trackers' layouts."""

from __future__ import annotations

import numpy as np
import pytest
from ofera.head.rotations import axis_angle_to_matrix, matrix_to_axis_angle, matrix_to_rot6d
from ofera.mapping.flame_values import join_flame_values
from ofera.mapping.layouts import ARKIT51_NAMES, MEDIAPIPE52_NAMES
from ofera.training.paired import (
    PairedDataError,
    import_insta,
    import_metrical_tracker,
    import_vhap,
    read_blendshape_csv,
)

T = 5


@pytest.fixture(scope="module")
def truth():
    rng = np.random.default_rng(0)
    expr = rng.normal(size=(T, 100))
    rot = axis_angle_to_matrix(rng.normal(0.0, 0.2, (T, 3, 3)))  # jaw, left eye, right eye
    return {"bs": rng.uniform(0, 1, (T, 51)).astype(np.float32), "expr": expr, "rot": rot,
            "shape": rng.normal(size=300), "flame": join_flame_values(expr[:, :50], rot[:, 0], rot[:, 1], rot[:, 2])}


def write_csv(path, bs, names="mediapipe", frames=None, order_seed=1):
    """A MediaPipe-style CSV: `_neutral` first, columns in a shuffled order, a frame and a time column."""
    if names == "mediapipe":
        header = list(MEDIAPIPE52_NAMES)
        values = {n: bs[:, ARKIT51_NAMES.index(n)] for n in ARKIT51_NAMES}
        values["_neutral"] = np.full(len(bs), 0.5)
    else:
        header = [n[0].upper() + n[1:] for n in ARKIT51_NAMES] + ["TongueOut"]  # ARKit PascalCase, 52
        values = {h: bs[:, i] for i, h in enumerate(header[:51])}
        values["TongueOut"] = np.zeros(len(bs))
    header = list(np.random.default_rng(order_seed).permutation(header))
    frames = np.arange(len(bs)) if frames is None else frames
    with open(path, "w") as fh:
        fh.write("# written by a test\n")
        fh.write(",".join(["frame", "time", *header]) + "\n")
        for r in range(len(bs)):
            cells = [str(frames[r]), f"{frames[r] / 30:.4f}"] + [repr(float(values[h][r])) for h in header]
            fh.write(",".join(cells) + "\n")
    return path


def test_csv_reads_by_name_in_any_order_and_spelling(tmp_path, truth):
    for names in ("mediapipe", "arkit"):
        ids, bs = read_blendshape_csv(write_csv(tmp_path / f"{names}.csv", truth["bs"], names))
        np.testing.assert_array_equal(ids, np.arange(T))
        np.testing.assert_allclose(bs, truth["bs"], atol=1e-7)
    bad = tmp_path / "bad.csv"
    bad.write_text("frame,eyeBlinkLeft\n0,0.5\n")
    with pytest.raises(PairedDataError, match="missing blendshape columns"):
        read_blendshape_csv(bad)


def test_metrical_tracker_round_trip(tmp_path, truth):
    torch = pytest.importorskip("torch")
    folder = tmp_path / "checkpoint"
    folder.mkdir()
    for t in range(T):
        frame = {
            "flame": {"exp": truth["expr"][t:t + 1].astype(np.float32),
                      "shape": truth["shape"][None].astype(np.float32),
                      "jaw": matrix_to_rot6d(truth["rot"][t, 0])[None].astype(np.float32),
                      "eyes": np.concatenate([matrix_to_rot6d(truth["rot"][t, 1]),
                                              matrix_to_rot6d(truth["rot"][t, 2])])[None].astype(np.float32),
                      "eyelids": np.zeros((1, 2), np.float32)},
            "camera": {"R": torch.eye(3)[None], "t": torch.zeros(1, 3)},
            "img_size": np.array([512, 512]), "frame_id": t,
        }
        torch.save(frame, folder / f"{t:05d}.frame")
    data = import_metrical_tracker(write_csv(tmp_path / "bs.csv", truth["bs"]), folder, fps=25.0, subject=2,
                                   split="test")
    assert len(data) == T and data.fps == 25.0
    np.testing.assert_allclose(data.flame, truth["flame"], atol=1e-5)
    np.testing.assert_allclose(data.bs, truth["bs"], atol=1e-7)
    assert data.shape.shape == (3, 300) and np.allclose(data.shape[2], truth["shape"], atol=1e-6)
    assert set(data.subject.tolist()) == {2} and set(data.split_names.tolist()) == {"test"}

    # Misaligned: a frame missing on the tracker side.
    (folder / "00003.frame").unlink()
    with pytest.raises(PairedDataError, match="misaligned.*CSV 5 frames.*4 frames"):
        import_metrical_tracker(tmp_path / "bs.csv", folder)
    # A pickle that would run code is refused (weights only).
    torch.save({"flame": {"exp": Evil()}}, folder / "00003.frame")
    with pytest.raises(PairedDataError, match="weights only"):
        import_metrical_tracker(tmp_path / "bs.csv", folder)
    with pytest.raises(PairedDataError, match="no such folder"):
        import_metrical_tracker(tmp_path / "bs.csv", tmp_path / "nowhere")


class Evil:
    def __reduce__(self):
        return (print, ("this must not run",))


def test_vhap_round_trip_and_errors(tmp_path, truth):
    aa = matrix_to_axis_angle(truth["rot"])
    path = tmp_path / "flame_param.npz"
    np.savez(path, expr=truth["expr"], jaw_pose=aa[:, 0], eyes_pose=aa[:, 1:].reshape(T, 6), shape=truth["shape"],
             rotation=np.zeros((T, 3)), neck_pose=np.zeros((T, 3)), translation=np.zeros((T, 3)))
    data = import_vhap(write_csv(tmp_path / "bs.csv", truth["bs"]), path)
    np.testing.assert_allclose(data.flame, truth["flame"], atol=1e-6)
    np.testing.assert_allclose(data.shape[0], truth["shape"], atol=1e-6)
    with pytest.raises(PairedDataError, match="misaligned"):
        import_vhap(write_csv(tmp_path / "long.csv", np.zeros((T + 2, 51))), path)
    np.savez(tmp_path / "broken.npz", expr=truth["expr"], jaw_pose=aa[:, 0])
    with pytest.raises(PairedDataError, match="missing arrays.*eyes_pose"):
        import_vhap(tmp_path / "bs.csv", tmp_path / "broken.npz")


def test_insta_round_trip_with_and_without_rotations(tmp_path, truth):
    root = tmp_path / "insta"
    for part in ("exp", "jaw", "eyes"):
        (root / "flame" / part).mkdir(parents=True)
    for t in range(T):
        name = f"{t:05d}.txt"
        np.savetxt(root / "flame" / "exp" / name, truth["expr"][t])
        np.savetxt(root / "flame" / "jaw" / name, matrix_to_rot6d(truth["rot"][t, 0]))
        np.savetxt(root / "flame" / "eyes" / name, matrix_to_axis_angle(truth["rot"][t, 1:]).reshape(-1))
    csv = write_csv(tmp_path / "bs.csv", truth["bs"])
    data = import_insta(csv, root)
    np.testing.assert_allclose(data.flame, truth["flame"], atol=1e-9)
    for part in ("jaw", "eyes"):
        for f in (root / "flame" / part).iterdir():
            f.unlink()
        (root / "flame" / part).rmdir()
    data = import_insta(csv, root)
    np.testing.assert_allclose(data.flame[:, :50], truth["flame"][:, :50], atol=1e-9)
    np.testing.assert_allclose(data.flame[:, 50:56], np.tile([1.0, 0, 0, 0, 1.0, 0], (T, 1)))
    assert "identity" in data.meta["jaw_rotation"]
    (root / "flame" / "exp" / "00004.txt").unlink()
    with pytest.raises(PairedDataError, match="misaligned"):
        import_insta(csv, root)
    with pytest.raises(PairedDataError, match="no flame/exp folder"):
        import_insta(csv, tmp_path)
