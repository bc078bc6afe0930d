"""demo npz v1: round trip, validation errors that name file and field, CLI exit codes."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from quasisim.data.demo import FORMAT, load_demo, save_demo
from quasisim.data.synthetic import hand_keypoints
from quasisim.errors import InputError


def _write(tmp: Path, name: str = "clip", **override: object) -> Path:
    (tmp / "meshes").mkdir(parents=True, exist_ok=True)
    (tmp / "meshes" / "box.obj").write_text(
        "v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nv 0 0 0.1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"
    )
    T = 5
    q = np.tile([1.0, 0.0, 0.0, 0.0], (T, 1))
    hand = hand_keypoints(np.zeros((5, 3))) + np.array([0.0, 0.0, 0.9])  # a human hand skeleton above the object
    arrays: dict[str, object] = dict(
        format=np.array(FORMAT), source=np.array("test"), name=np.array(name), fps=np.array(20.0, np.float32),
        right_joints=np.tile(hand, (T, 1, 1)).astype(np.float32), object_name=np.array("box"),
        object_mesh=np.array("box.obj"), object_pos=np.tile([0.0, 0.0, 0.8], (T, 1)).astype(np.float32),
        object_quat=q.astype(np.float32),
        support_height=np.array(0.8, np.float32),
    )  # fmt: skip
    for k, v in override.items():
        if v is None:
            arrays.pop(k)
        else:
            arrays[k] = v
    p = tmp / f"{name}.npz"
    np.savez(p, **arrays)
    return p


def test_roundtrip(tmp_path: Path) -> None:
    d = load_demo(_write(tmp_path))
    assert d.n_frames == 5 and d.right_joints.shape == (5, 21, 3) and d.fps == 20.0
    out = tmp_path / "copy.npz"
    save_demo(d, out)
    d2 = load_demo(out)
    np.testing.assert_allclose(d2.object_quat, d.object_quat)
    assert d2.object_mesh_path == d.object_mesh_path


@pytest.mark.parametrize(
    ("override", "field", "words"),
    [
        ({"right_joints": np.zeros((5, 20, 3))}, "right_joints", "shape (T, 21, 3)"),
        ({"object_pos": np.zeros((4, 3))}, "object_pos", "same T"),
        ({"object_pos": np.full((5, 3), np.nan)}, "object_pos", "finite"),
        ({"right_joints": np.full((5, 21, 3), np.inf)}, "right_joints", "finite"),
        ({"object_quat": np.tile([0.5, 0, 0, 0], (5, 1))}, "object_quat", "unit quaternions"),
        ({"format": np.array("other-v0")}, "format", FORMAT),
        ({"object_mesh": np.array("missing.obj")}, "object_mesh", "mesh file"),
        ({"fps": None}, "fps", "present"),
        ({"fps": np.array(-1.0)}, "fps", "frame rate in [1, 1000] Hz"),
        ({"name": np.array(3.0)}, "name", "string"),
    ],
)
def test_bad_fields(tmp_path: Path, override: dict, field: str, words: str) -> None:
    p = _write(tmp_path, **override)
    with pytest.raises(InputError) as e:
        load_demo(p)
    msg = str(e.value)
    assert str(p) in msg and f"'{field}'" in msg and words in msg and "\n" not in msg


def test_too_few_frames(tmp_path: Path) -> None:
    T1 = dict(right_joints=np.zeros((1, 21, 3)), object_pos=np.zeros((1, 3)), object_quat=np.array([[1.0, 0, 0, 0]]))

    with pytest.raises(InputError, match="at least 2 frames"):
        load_demo(_write(tmp_path, **T1))


def test_not_an_npz(tmp_path: Path) -> None:
    p = tmp_path / "x.npz"
    p.write_text("hello")
    with pytest.raises(InputError, match="npz"):
        load_demo(p)
    np.save(tmp_path / "y.npy", np.zeros(3))
    shutil.move(tmp_path / "y.npy", tmp_path / "y.npz")
    with pytest.raises(InputError, match="npz"):
        load_demo(tmp_path / "y.npz")
    with pytest.raises(InputError, match="no such file"):
        load_demo(tmp_path / "absent.npz")


def test_cli_bad_input_exit_code(tmp_path: Path) -> None:
    from click.testing import CliRunner

    from quasisim.cli import main

    p = _write(tmp_path, object_quat=np.tile([0.5, 0, 0, 0], (5, 1)))
    r = CliRunner().invoke(main, ["retarget", str(p), "--out", str(tmp_path / "o")])
    assert r.exit_code == 2
    assert "object_quat" in r.output and "Traceback" not in r.output
    ok = _write(tmp_path / "ok")
    r = CliRunner().invoke(main, ["retarget", str(ok), "--hand", "nohand", "--out", str(tmp_path / "o")])
    assert r.exit_code == 2 and "nohand" in r.output and "shadow" in r.output and "Traceback" not in r.output


def test_real_clips_load(data_dir: Path) -> None:
    """Every clip the data's manifest lists is there and loads (at least the 25 60-frame development clips)."""
    import json

    listed = [c["file"] for c in json.loads((data_dir / "manifest.json").read_text())["clips"]]
    assert len([f for f in listed if not f.endswith("_long.npz")]) >= 25, listed
    for name in listed:
        d = load_demo(data_dir / name)
        assert d.n_frames >= 50
        np.testing.assert_allclose(np.linalg.norm(d.object_quat, axis=1), 1.0, atol=1e-3)


# ---- two hands: the optional left_joints -------------------------------------------------------------


def _left_of(right: np.ndarray) -> np.ndarray:
    """A left hand: the mirror image (x -> -x) of a right hand, moved 0.15 m along -x."""
    left = np.asarray(right, np.float64) * np.array([-1.0, 1.0, 1.0])
    return (left - np.array([0.15, 0.0, 0.0])).astype(np.float32)


def _right(T: int = 5) -> np.ndarray:
    return np.tile(hand_keypoints(np.zeros((5, 3))) + np.array([0.0, 0.0, 0.9]), (T, 1, 1)).astype(np.float32)


def test_left_joints_roundtrip(tmp_path: Path) -> None:
    left = _left_of(_right())
    d = load_demo(_write(tmp_path, left_joints=left))
    assert d.sides == ("right", "left") and d.human_joints.shape == (5, 42, 3)
    np.testing.assert_allclose(d.human_joints[:, 21:], left, atol=1e-6)
    save_demo(d, tmp_path / "copy.npz")
    d2 = load_demo(tmp_path / "copy.npz")
    np.testing.assert_allclose(d2.left_joints, d.left_joints)
    from quasisim.data.demo import content_hash

    one = load_demo(_write(tmp_path / "one"))
    assert one.sides == ("right",) and one.human_joints is one.right_joints
    assert content_hash(d2) == content_hash(d) != content_hash(one)
    assert d.slice(1, 4).left_joints.shape == (3, 21, 3)


@pytest.mark.parametrize(
    ("left", "words"),
    [
        (np.zeros((5, 20, 3)), "shape (T, 21, 3)"),
        (np.zeros((4, 21, 3)), "shape (5, 21, 3) (same T as right_joints)"),
        (np.full((5, 21, 3), np.nan), "finite"),
        (_right() * 100.0, "within +-10 m"),
        # the right hand's keypoints given as the left hand: a mirrored (wrong-handed) left hand
        (_right() - np.array([0.15, 0.0, 0.0], np.float32), "a left hand (thumb on the palm side"),
        (_left_of(_right()) + np.array([0.0, 0.0, 3.0], np.float32), "within 1 m of the left hand"),
    ],
)
def test_bad_left_joints(tmp_path: Path, left: np.ndarray, words: str) -> None:
    p = _write(tmp_path, left_joints=left)
    with pytest.raises(InputError) as e:
        load_demo(p)
    msg = str(e.value)
    field = "object_pos" if "within 1 m" in words else "left_joints"
    assert str(p) in msg and f"'{field}'" in msg and words in msg and "\n" not in msg


def test_mirrored_left_hand_is_named(tmp_path: Path) -> None:
    p = _write(tmp_path, left_joints=_right() - np.array([0.15, 0.0, 0.0], np.float32))
    with pytest.raises(InputError, match=r"got a right or mirrored hand in 100% of the frames"):
        load_demo(p)
