"""Robot pose files made elsewhere (4x4 matrices, position + quaternion, UR pose vectors) and their
pairing with images: every form read to the matrix scipy builds, every bad input one clear error
naming the file (and line or entry), never a NaN."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from brave6d.core.errors import DataError
from brave6d.calibration import (
    PoseFileError,
    PoseFormat,
    list_images,
    pair_images_with_poses,
    read_pose_collection,
    read_pose_file,
)

# An independent reference pose: built with scipy only.
ROT = Rotation.from_euler("xyz", [20.0, -35.0, 110.0], degrees=True)
POS = np.array([0.41, -0.27, 0.63])
TRUTH = np.eye(4)
TRUTH[:3, :3], TRUTH[:3, 3] = ROT.as_matrix(), POS
QX, QY, QZ, QW = ROT.as_quat()  # scipy: scalar last
ROTVEC = ROT.as_rotvec()


def _write(path, text: str):
    path.write_text(text)
    return path


@pytest.mark.parametrize("name, text, fmt", [
    ("m.txt", "\n".join(" ".join(f"{v:.12g}" for v in row) for row in TRUTH), PoseFormat()),
    ("m1.txt", ",".join(f"{v:.12g}" for v in TRUTH.ravel()), PoseFormat()),
    ("m.json", json.dumps({"matrix": TRUTH.tolist()}), PoseFormat()),
    ("m.yaml", "pose: " + json.dumps(TRUTH[:3].tolist()), PoseFormat()),
    ("ric.yaml", f"x: {POS[0]}\ny: {POS[1]}\nz: {POS[2]}\nqx: {QX}\nqy: {QY}\nqz: {QZ}\nqw: {QW}\n", PoseFormat()),
    ("ros.yaml", f"position: {{x: {POS[0]}, y: {POS[1]}, z: {POS[2]}}}\n"
                 f"orientation: {{x: {QX}, y: {QY}, z: {QZ}, w: {QW}}}\n", PoseFormat()),
    ("tf.json", json.dumps({"translation": POS.tolist(), "rotation": {"x": QX, "y": QY, "z": QZ, "w": QW}}),
     PoseFormat()),
    ("xyzw.txt", " ".join(map(str, [*POS, QX, QY, QZ, QW])), PoseFormat(quaternion_order="xyzw")),
    ("wxyz.json", json.dumps([*POS, QW, QX, QY, QZ]), PoseFormat(quaternion_order="wxyz")),
    ("ur.txt", " ".join(map(str, [*POS, *ROTVEC])), PoseFormat(kind="ur")),
    ("ur.yaml", f"x: {POS[0]}\ny: {POS[1]}\nz: {POS[2]}\nrx: {ROTVEC[0]}\nry: {ROTVEC[1]}\nrz: {ROTVEC[2]}\n",
     PoseFormat(kind="ur")),
    ("mm.txt", " ".join(map(str, [*(POS * 1000), *ROTVEC])), PoseFormat(kind="ur", unit="mm")),
])
def test_every_form_reads_to_the_same_pose(tmp_path, name, text, fmt) -> None:
    T = read_pose_file(_write(tmp_path / name, text), fmt)
    assert np.allclose(T, TRUTH, atol=1e-9)


def test_npy_single_and_stacked(tmp_path) -> None:
    np.save(tmp_path / "one.npy", TRUTH)
    assert np.allclose(read_pose_file(tmp_path / "one.npy"), TRUTH)
    np.save(tmp_path / "many.npy", np.stack([TRUTH, np.eye(4), TRUTH]))
    poses = read_pose_collection(tmp_path / "many.npy")
    assert isinstance(poses, list) and len(poses) == 3 and np.allclose(poses[1], np.eye(4))
    np.save(tmp_path / "rows.npy", np.array([[*POS, *ROTVEC]] * 2))
    assert len(read_pose_collection(tmp_path / "rows.npy", PoseFormat(kind="ur"))) == 2


def test_collections_in_order_or_by_name(tmp_path) -> None:
    rows = "x y z rx ry rz\n" + "\n".join(" ".join(map(str, [*POS, *ROTVEC])) for _ in range(3))
    listed = read_pose_collection(_write(tmp_path / "p.csv", rows), PoseFormat(kind="ur"))
    assert isinstance(listed, list) and len(listed) == 3
    named = read_pose_collection(_write(tmp_path / "n.txt", "a 1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1\nb " +
                                        " ".join(f"{v:.15g}" for v in TRUTH.ravel())))
    assert isinstance(named, dict) and set(named) == {"a", "b"} and np.allclose(named["b"], TRUTH)
    mapping = read_pose_collection(_write(tmp_path / "m.yaml", "img1: " + json.dumps(TRUTH.tolist()) + "\n"
                                          "img2: " + json.dumps(np.eye(4).tolist()) + "\n"))
    assert isinstance(mapping, dict) and np.allclose(mapping["img1"], TRUTH)


def test_a_matrix_rounded_as_printed_files_are_is_projected_onto_the_nearest_rotation(tmp_path) -> None:
    rounded = np.round(TRUTH, 6)
    rounded[:3, 0] *= 1.000001  # a column norm of 1.000001, as instant-ngp's files carry
    assert np.abs(rounded[:3, :3].T @ rounded[:3, :3] - np.eye(3)).max() > 1e-6  # above the strict check's 1e-6
    T = read_pose_file(_write(tmp_path / "p.txt", " ".join(f"{v:.6f}" for v in rounded.ravel())))
    np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12)
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(T, TRUTH, atol=1e-5)


@pytest.mark.parametrize("text, fmt, message", [
    (" ".join(map(str, [*POS, QX, QY, QZ, QW])), PoseFormat(), "in which order is the quaternion"),
    (" ".join(map(str, [*POS, *ROTVEC])), PoseFormat(), "6 numbers are ambiguous"),
    (" ".join(map(str, [*POS, 0.5, 0.5, 0.5, 0.9])), PoseFormat(quaternion_order="xyzw"), "has norm 1.2"),
    (" ".join(map(str, [*POS, 0, 0, 0, 0])), PoseFormat(quaternion_order="xyzw"), "has norm 0"),
    ("1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1 5", PoseFormat(), "17 numbers"),
    ("1 0 0 nan 0 1 0 0 0 0 1 0 0 0 0 1", PoseFormat(), "contains NaN or inf"),
    (" ".join(map(str, (np.diag([2.0, 1, 1, 1])).ravel())), PoseFormat(), "not orthonormal"),
    (" ".join(map(str, (np.diag([-1.0, 1, 1, 1])).ravel())), PoseFormat(), "reflection"),
    ("hello world", PoseFormat(), "no numbers"),
    ("1 2 3\nfoo bar", PoseFormat(), ":2: not a row of numbers"),
])
def test_bad_files_are_named_with_the_cause(tmp_path, text, fmt, message) -> None:
    path = _write(tmp_path / "bad_pose.txt", text)
    with pytest.raises(PoseFileError, match=message) as info:
        read_pose_file(path, fmt)
    assert str(path) in str(info.value)


def test_bad_json_yaml_and_npy_are_named(tmp_path) -> None:
    for name, text, message in [("a.json", "{", "not valid JSON"), ("b.yaml", "x: [1, 2", "invalid YAML"),
                                ("c.yaml", "x: 1\nx: 2\n", "duplicate key"),
                                ("u.yaml", "x: 1\ny: 2\nz: 3\nrx: 0\nry: 0\nrz: 0\n", "rx ry rz are ambiguous"),
                                ("d.json", json.dumps({"x": 1, "y": 2, "z": 3, "qx": 0, "qy": 0, "qz": 0, "qw": "NaN"}),
                                 "expected numbers|NaN"),
                                ("e.json", json.dumps({"frame": "base"}), "entry 'frame': expected numbers")]:
        with pytest.raises(PoseFileError, match=message) as info:
            read_pose_file(_write(tmp_path / name, text))
        assert name in str(info.value)
    (tmp_path / "f.npy").write_bytes(b"not numpy")
    with pytest.raises(PoseFileError, match="f.npy: not a NumPy array file"):
        read_pose_file(tmp_path / "f.npy")
    with pytest.raises(PoseFileError, match="file not found"):
        read_pose_file(tmp_path / "missing.txt")


@given(values=st.lists(st.one_of(st.floats(allow_nan=True, allow_infinity=True, width=64),
                                 st.floats(-2.0, 2.0)), min_size=0, max_size=18),
       kind=st.sampled_from(["auto", "matrix", "quaternion", "ur"]), order=st.sampled_from([None, "xyzw", "wxyz"]))
@settings(max_examples=200, deadline=None)
def test_any_numbers_give_a_rigid_finite_pose_or_a_named_error(tmp_path_factory, values, kind, order) -> None:
    path = tmp_path_factory.mktemp("p") / "pose.txt"
    path.write_text(" ".join(repr(v) for v in values))
    try:
        T = read_pose_file(path, PoseFormat(kind=kind, quaternion_order=order))
    except PoseFileError as exc:
        assert str(path) in str(exc)
        return
    assert T.shape == (4, 4) and np.all(np.isfinite(T))
    assert np.allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-9) and np.linalg.det(T[:3, :3]) > 0


@given(q=st.tuples(*[st.floats(-1.0, 1.0)] * 4), scale=st.floats(0.9, 1.1))
@settings(max_examples=100, deadline=None)
def test_quaternions_near_unit_are_normalised_others_refused(tmp_path_factory, q, scale) -> None:
    qv = np.asarray(q)
    if np.linalg.norm(qv) < 1e-3 or abs(abs(scale - 1.0) - 1e-3) < 1e-9:
        return  # no rotation, or on the tolerance itself
    qv = [float(v) for v in qv / np.linalg.norm(qv) * scale]
    path = tmp_path_factory.mktemp("q") / "q.yaml"
    path.write_text(f"x: 0\ny: 0\nz: 0\nqx: {qv[0]!r}\nqy: {qv[1]!r}\nqz: {qv[2]!r}\nqw: {qv[3]!r}\n")
    if abs(scale - 1.0) > 1e-3:
        with pytest.raises(PoseFileError, match="not a unit quaternion"):
            read_pose_file(path)
        return
    T = read_pose_file(path)
    assert np.allclose(T[:3, :3], Rotation.from_quat(qv).as_matrix(), atol=1e-6)  # scipy normalises too


# ----------------------------------------------------------------------------- pairing
def _images(folder, names):
    folder.mkdir(parents=True, exist_ok=True)
    for n in names:
        (folder / n).write_bytes(b"")
    return folder


def test_natural_order_and_stem_matching(tmp_path) -> None:
    images = _images(tmp_path / "img", ["10.png", "2.png", "1.png"])
    assert [p.name for p in list_images(images)] == ["1.png", "2.png", "10.png"]
    poses = tmp_path / "poses"
    poses.mkdir()
    for k, stem in enumerate(["1", "2", "10"]):
        T = TRUTH.copy()
        T[0, 3] = k
        (poses / f"{stem}.json").write_text(json.dumps(T.tolist()))
    paired = pair_images_with_poses(images, poses)
    assert paired.matching == "stem" and "by file stem" in paired.description
    assert [T[0, 3] for T in paired.poses] == [0.0, 1.0, 2.0]
    ordered = pair_images_with_poses(images, poses, match="order")
    assert ordered.matching == "order" and "sorted order" in ordered.description


def test_one_file_of_poses_pairs_by_order_and_counts_must_match(tmp_path) -> None:
    images = _images(tmp_path / "img", [f"view{k}.jpg" for k in range(3)])
    row = " ".join(map(str, [*POS, *ROTVEC]))
    f = _write(tmp_path / "poses.txt", "\n".join([row] * 3))
    paired = pair_images_with_poses(images, f, PoseFormat(kind="ur"))
    assert paired.matching == "order" and len(paired.poses) == 3
    f2 = _write(tmp_path / "poses2.txt", "\n".join([row] * 4))
    with pytest.raises(DataError, match=r"poses2.txt: 4 poses but 3 images"):
        pair_images_with_poses(images, f2, PoseFormat(kind="ur"))
    with pytest.raises(DataError, match="not named; pair them by sorted order"):
        pair_images_with_poses(images, f, PoseFormat(kind="ur"), match="stem")


def test_stem_mismatch_lists_both_sides(tmp_path) -> None:
    images = _images(tmp_path / "img", ["a.png", "b.png", "c.png"])
    poses = tmp_path / "poses"
    poses.mkdir()
    for stem in ("a", "b", "d"):
        (poses / f"{stem}.txt").write_text(" ".join(map(str, TRUTH.ravel())))
    with pytest.raises(DataError, match=r"images without a pose: c.png; poses without an image: d.*--match order"):
        pair_images_with_poses(images, poses)


def test_nan_in_one_pose_file_names_that_file(tmp_path) -> None:
    images = _images(tmp_path / "img", ["0.png", "1.png"])
    poses = tmp_path / "poses"
    poses.mkdir()
    (poses / "0.yaml").write_text(f"x: 0\ny: 0\nz: 0\nqx: 0\nqy: 0\nqz: 0\nqw: 1\n")
    (poses / "1.yaml").write_text(f"x: .nan\ny: 0\nz: 0\nqx: 0\nqy: 0\nqz: 0\nqw: 1\n")
    with pytest.raises(PoseFileError, match=r"poses/1.yaml: contains NaN"):
        pair_images_with_poses(images, poses)


def test_millimetres_given_as_metres_are_caught(tmp_path) -> None:
    images = _images(tmp_path / "img", ["0.png"])
    f = _write(tmp_path / "p.txt", " ".join(map(str, [410.0, -270.0, 630.0, *ROTVEC])))
    with pytest.raises(DataError, match=r"0.png is 798.7 m from the robot base.*--pose-unit mm"):
        pair_images_with_poses(images, f, PoseFormat(kind="ur"))
    paired = pair_images_with_poses(images, f, PoseFormat(kind="ur", unit="mm"))
    assert math.isclose(float(np.linalg.norm(paired.poses[0][:3, 3])), float(np.linalg.norm(POS)), rel_tol=1e-9)
