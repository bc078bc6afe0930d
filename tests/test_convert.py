"""`quasisim convert landmarks`: the bundled example written out as a user's files (other units, another up
axis, each file format) converts back to the same clip; bad inputs are named."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from quasisim.cli import main
from quasisim.data.convert import UP_AXES, ConvertOptions, convert_landmarks
from quasisim.data.demo import load_demo
from quasisim.data.synthetic import make_example
from quasisim.errors import InputError, QuasisimError
from quasisim.rotations import np_quat_to_mat

T = 20


@pytest.fixture(scope="module")
def example():
    return make_example("cube_lift", n_frames=T)


def _user_files(example, d: Path, up: str = "y", scale: float = 1000.0) -> dict[str, Path]:
    """The example as a user might have it: mm, ``up`` axis up, every file format."""
    demo, mesh = example
    to_user = UP_AXES[up].T  # world (z up) -> the user's frame
    joints = demo.right_joints @ to_user.T * scale
    pos = demo.object_pos @ to_user.T * scale
    rot = to_user @ np_quat_to_mat(demo.object_quat)
    from quasisim.rotations import np_mat_to_quat

    q = np_mat_to_quat(rot)
    d.mkdir(parents=True, exist_ok=True)
    frame = np.arange(T)[:, None]
    lines = ["frame," + ",".join(f"{a}{i}" for i in range(21) for a in "xyz")]
    lines += [",".join(f"{v:.9g}" for v in row) for row in np.hstack([frame, joints.reshape(T, 63)])]
    (d / "hand.csv").write_text("\n".join(lines) + "\n")
    pts = [[{"x": float(x), "y": float(y), "z": float(z)} for x, y, z in f] for f in joints]
    (d / "hand.json").write_text(json.dumps({"fps": demo.fps, "frames": pts}))
    np.savez(d / "hand.npz", landmarks=joints, fps=demo.fps, confidence=np.ones((T, 21)))
    poses = [{"pos": list(p), "quat": list(qq[[1, 2, 3, 0]])} for p, qq in zip(pos, q, strict=True)]
    (d / "poses.json").write_text(json.dumps(poses))  # xyzw
    mats = np.tile(np.eye(4), (T, 1, 1))
    mats[:, :3, :3], mats[:, :3, 3] = rot, pos
    np.savetxt(d / "poses.csv", mats.reshape(T, 16), delimiter=",")
    np.savez(d / "poses.npz", object_pos=pos, object_quat=q)
    m = mesh.copy()
    m.apply_scale(scale)
    m.export(d / "cube.stl")
    return {"csv": d / "hand.csv", "json": d / "hand.json", "npz": d / "hand.npz", "mesh": d / "cube.stl",
            "poses_json": d / "poses.json", "poses_csv": d / "poses.csv", "poses_npz": d / "poses.npz"}  # fmt: skip


def _same_clip(got, demo, mesh) -> None:
    np.testing.assert_allclose(got.right_joints, demo.right_joints, atol=2e-6)
    np.testing.assert_allclose(got.object_pos, demo.object_pos, atol=2e-6)
    dots = np.abs(np.sum(got.object_quat * demo.object_quat, axis=1))
    np.testing.assert_allclose(dots, 1.0, atol=1e-5)
    assert got.fps == demo.fps and got.support_height == pytest.approx(demo.support_height, abs=1e-5)
    import trimesh

    v = np.asarray(trimesh.load(got.object_mesh_path, force="mesh").vertices)
    assert np.abs(np.sort(v, axis=0) - np.sort(np.asarray(mesh.vertices), axis=0)).max() < 1e-6


@pytest.mark.parametrize(
    ("hand", "poses", "order"),
    [("csv", "poses_csv", "wxyz"), ("json", "poses_json", "xyzw"), ("npz", "poses_npz", "wxyz")],
)
def test_formats_units_and_up_axis_round_trip(example, tmp_path: Path, hand: str, poses: str, order: str) -> None:
    f = _user_files(example, tmp_path / "in")
    opts = ConvertOptions(units="mm", up="y", quat_order=order, fps=20.0 if hand == "csv" else None)
    out = convert_landmarks(f[hand], f[poses], f["mesh"], tmp_path / "out" / "mine.npz", opts)
    got = load_demo(out)  # a valid quasisim-demo-v1 clip with its mesh in meshes/
    assert got.name == "mine" and got.object_mesh_path.parent == (tmp_path / "out" / "meshes").resolve()
    _same_clip(got, *example)


def test_cli_and_bad_inputs_are_named(example, tmp_path: Path) -> None:
    f = _user_files(example, tmp_path / "in", up="-x", scale=100.0)
    args = [
        "convert",
        "landmarks",
        str(f["csv"]),
        str(f["poses_npz"]),
        str(f["mesh"]),
        "--out",
        str(tmp_path / "o.npz"),
    ]
    r = CliRunner().invoke(main, [*args, "--units", "cm", "--up", "-x", "--fps", "20"])
    assert r.exit_code == 0, r.output
    _same_clip(load_demo(tmp_path / "o.npz"), *example)
    r = CliRunner().invoke(main, [*args, "--units", "mm", "--fps", "20"])  # 10x too small a hand
    assert r.exit_code == 2 and "hand.csv" in r.output and "--units" in r.output and "got 0.931 cm" in r.output
    r = CliRunner().invoke(main, [*args, "--units", "cm", "--up", "w"])
    assert r.exit_code == 2 and "valid options" in r.output and "-y" in r.output
    with pytest.raises(InputError, match="frame rate"):  # a CSV has no fps
        convert_landmarks(f["csv"], f["poses_npz"], f["mesh"], tmp_path / "p.npz", ConvertOptions(units="cm", up="-x"))
    short = tmp_path / "short.csv"
    short.write_text("\n".join(f["csv"].read_text().splitlines()[:5]))
    with pytest.raises(InputError, match=r"poses\.npz.*expected 4 frames"):
        convert_landmarks(short, f["poses_npz"], f["mesh"], tmp_path / "p.npz", ConvertOptions("cm", "-x", fps=20.0))
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps([[1.0, 2.0]] * 3))
    with pytest.raises(QuasisimError, match="63 numbers per frame"):
        convert_landmarks(bad, f["poses_npz"], f["mesh"], tmp_path / "p.npz", ConvertOptions(fps=20.0))
