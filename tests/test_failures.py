"""The strict-failure analysis (:mod:`quasisim.eval.failures`, ``quasisim bench failures``): the hidden-rotation
measure against shapes with known symmetries, and each label on a real run's outputs whose object motion is
edited into a known failure (a pass, a quarter turn of a cube, a drop, an object never touched)."""

from __future__ import annotations

import shutil
import subprocess
import sys

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from quasisim.eval.failures import SYMMETRIC_MM, analyse, classify, finished_runs, rotation_distance


def _wxyz(rotvec: list[float]) -> np.ndarray:
    x, y, z, w = Rotation.from_rotvec(rotvec).as_quat()
    return np.array([w, x, y, z])


@pytest.mark.parametrize(
    ("mesh", "rotvec", "hidden"),
    [
        (trimesh.creation.box(extents=(0.05, 0.05, 0.05)), [0, 0, np.pi / 2], True),  # a cube's quarter turn
        (trimesh.creation.box(extents=(0.05, 0.05, 0.05)), [0, 0, np.radians(35)], False),
        (trimesh.creation.cylinder(radius=0.03, height=0.1, sections=128), [0, 0, 1.3], True),  # about its axis
        (trimesh.creation.cylinder(radius=0.03, height=0.1, sections=128), [1.3, 0, 0], False),
    ],
)
def test_a_rotation_is_hidden_exactly_when_it_is_a_symmetry_of_the_shape(mesh, rotvec, hidden) -> None:
    pts = mesh.sample(400)
    q0 = _wxyz([0.3, -0.2, 0.1])  # any common start pose
    q1 = (Rotation.from_quat(np.r_[q0[1:], q0[0]]) * Rotation.from_rotvec(rotvec)).as_quat()
    d = rotation_distance(mesh, pts, q0, np.r_[q1[3], q1[:3]])
    assert (d < SYMMETRIC_MM) == hidden, d


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """The bundled example (cube, 24 frames) and its kinematic replay's run folder."""
    from quasisim.data.synthetic import write_example

    root = tmp_path_factory.mktemp("failures")
    demo = write_example("cube_lift", root / "data", n_frames=24)
    out = root / "runs" / "kinematic"
    cmd = [sys.executable, "-m", "quasisim.cli", "transfer", str(demo), "--method", "kinematic", "--out", str(out),
           "--no-render", "--robust", "0"]  # fmt: skip
    res = subprocess.run(cmd, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    return demo, out


def _edited(run, tmp_path, pos_fn, quat_fn, sample=None):
    """A copy of the run whose object poses (rollout and exported trajectory alike) are those of the demo
    changed by ``pos_fn`` (T, 3) -> (T, 3) and ``quat_fn`` (T, 4) -> (T, 4); ``sample``: arrays of a sampling
    checkpoint to give it."""
    from quasisim.data.demo import load_demo

    demo_path, src = run
    demo = load_demo(demo_path)
    dst = tmp_path / "runs" / "edited"
    shutil.copytree(src, dst)
    pos, quat = pos_fn(demo.object_pos.copy()), quat_fn(demo.object_quat.copy())
    with np.load(dst / "rollout.npz") as z:
        r = dict(z)
    np.savez(dst / "rollout.npz", **{**r, "object_pos": pos, "object_quat": quat})
    with np.load(dst / "trajectory.npz") as z:
        t = dict(z)
    t["qpos"][:, -7:-4], t["qpos"][:, -4:] = pos, quat  # the object's free joint comes last
    np.savez(dst / "trajectory.npz", **t)
    if sample is not None:
        (dst / "checkpoints").mkdir(exist_ok=True)
        np.savez(dst / "checkpoints" / "sample.npz", **sample)
    mesh = trimesh.creation.box(extents=(0.05, 0.05, 0.05))
    return classify(demo, dst, "edited", mesh, mesh.sample(400))


def test_each_label_on_a_run_edited_into_a_known_failure(run, tmp_path) -> None:
    same = _edited(run, tmp_path / "a", lambda p: p, lambda q: q)
    assert same.label == "pass" and same.frame == -1 and same.failing_frames == 0

    def quarter_turn(q):
        r = Rotation.from_quat(q[:, [1, 2, 3, 0]]) * Rotation.from_rotvec([0, 0, np.pi / 2])
        return r.as_quat()[:, [3, 0, 1, 2]]

    turned = _edited(run, tmp_path / "b", lambda p: p, quarter_turn)
    assert turned.label == "symmetric" and turned.frame == 0 and turned.over == "rotation"
    assert turned.failing_frames == 24 and abs(turned.max_rot_deg - 90) < 1e-3

    def dropped(p):
        p[14:, 2] -= np.linspace(0.01, 0.3, 10)  # falls away from the hand from frame 14
        return p

    drop = _edited(run, tmp_path / "c", dropped, lambda q: q)
    assert drop.label == "drop" and drop.over == "translation" and drop.frame >= 14

    away = _edited(run, tmp_path / "d", lambda p: p + np.array([0.0, 0.4, 0.0]), lambda q: q)  # 40 cm off, untouched
    assert away.label == "never grasped" and away.frame == 0 and away.contacts == 0


def test_a_failure_reports_the_sampling_stages_back_ups(run, tmp_path) -> None:
    """The back-ups recorded in the run's sampling checkpoint (frame left from, frame gone back to) show in the
    failure and its table row; a run without a sampling stage has none to report."""
    from quasisim.eval.failures import markdown

    def dropped(p):
        p[14:, 2] -= np.linspace(0.01, 0.3, 10)
        return p

    plain = _edited(run, tmp_path / "a", dropped, lambda q: q)
    assert plain.backups is None and plain.backed_up_from is None and "| - |" in markdown([plain])
    ck = {"backups": np.array(3), "backup_frames": np.array([[16, 11], [15, 10], [17, 12]])}
    sampled = _edited(run, tmp_path / "b", dropped, lambda q: q, sample=ck)
    assert sampled.label == "drop" and sampled.backups == 3 and sampled.backed_up_from == (15, 17)
    assert "| 3 (15-17) |" in markdown([sampled])


def test_the_command_finds_the_runs_and_tabulates_them(run, tmp_path) -> None:
    demo_path, src = run
    assert finished_runs(src.parent) == [src]
    (failures,) = analyse(src.parent, demo_path.parent)
    assert failures.method == "kinematic" and failures.clip == demo_path.stem
    cmd = [sys.executable, "-m", "quasisim.cli", "bench", "failures", str(src.parent), "--data", str(demo_path.parent),
           "--out", str(tmp_path)]  # fmt: skip
    res = subprocess.run(cmd, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    md = (tmp_path / "failures.md").read_text()
    assert "| kinematic | 1 |" in md and (tmp_path / "failures.json").is_file()
    empty = subprocess.run([*cmd[:5], str(tmp_path), "--data", str(demo_path.parent)], capture_output=True, text=True)
    assert empty.returncode != 0 and "no finished runs" in empty.stderr and "Traceback" not in empty.stderr
