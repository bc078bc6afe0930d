"""Run folders stay trustworthy: checkpoints carry their run's identity and are validated on load, orphan
temporary files are cleaned up, outputs are written as a set, unstable simulations are failures, controls
know their demo, earlier outputs are not overwritten silently, and a transfer killed at random points and
resumed gives bit-identical results."""

from __future__ import annotations

import dataclasses
import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from helpers import ctrl_c_restored
from quasisim.cli import main
from quasisim.files import MANIFEST, output_set, read_manifest, remove_orphans, save_npz_atomic
from quasisim.method.checkpoints import IDENTITY_KEY, Checkpoints

INFO = {"demo": "a", "demo_sha256": "0" * 16, "hand": "shadow", "stages": ["1"]}
EXPECT = {"q": (4, 3), "name": "str"}


def _arrays() -> dict[str, np.ndarray]:
    return {"q": np.arange(12.0).reshape(4, 3), "name": np.array("x")}


def _fresh(folder: Path, info: dict | None = None, resume: bool = False) -> Checkpoints:
    return Checkpoints(folder, info or INFO, resume)


# ---- checkpoints -----------------------------------------------------------------------------------------


def test_checkpoints_carry_their_run_identity(tmp_path: Path, capsys) -> None:
    ck = _fresh(tmp_path)
    ck.save("piece", **_arrays())
    assert str(np.load(tmp_path / "piece.npz")[IDENTITY_KEY]) == ck.identity("piece")
    assert _fresh(tmp_path, resume=True).load("piece", EXPECT)["q"].shape == (4, 3)
    # run.json gone and another run resumes in the folder: the piece is not reused, and that is said once
    (tmp_path / "run.json").unlink()
    other = _fresh(tmp_path, {**INFO, "demo": "b"}, resume=True)
    calls = []
    d = other.get("piece", lambda: calls.append(1) or {"q": np.zeros((4, 3)), "name": np.array("y")}, EXPECT)
    assert calls == [1] and str(d["name"]) == "y"
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and "piece.npz" in err[0] and "another run" in err[0]
    assert str(np.load(tmp_path / "piece.npz")[IDENTITY_KEY]) == other.identity("piece")


DAMAGE = {
    "truncated": lambda p: p.write_bytes(p.read_bytes()[:100]),
    "zero_bytes": lambda p: p.write_bytes(b""),
    "random_bytes": lambda p: p.write_bytes(os.urandom(500)),
    "missing_key": lambda p: save_npz_atomic(p, **{IDENTITY_KEY: np.load(p)[IDENTITY_KEY]}, name=np.array("x")),
    "wrong_shape": lambda p: save_npz_atomic(
        p, **{IDENTITY_KEY: np.load(p)[IDENTITY_KEY]}, q=np.zeros((5, 3)), name=np.array("x")
    ),
    "string_for_numbers": lambda p: save_npz_atomic(
        p, **{IDENTITY_KEY: np.load(p)[IDENTITY_KEY]}, q=np.full((4, 3), "a"), name=np.array("x")
    ),
    "no_identity_no_run_json": lambda p: (save_npz_atomic(p, **_arrays()), (p.parent / "run.json").unlink()),
}


@pytest.mark.parametrize("damage", list(DAMAGE))
def test_damaged_checkpoints_are_recomputed(tmp_path: Path, capsys, damage: str) -> None:
    _fresh(tmp_path).save("piece", **_arrays())
    DAMAGE[damage](tmp_path / "piece.npz")
    capsys.readouterr()
    ck = _fresh(tmp_path, resume=True)
    d = ck.get("piece", _arrays, EXPECT)
    np.testing.assert_array_equal(d["q"], _arrays()["q"])
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and "piece.npz" in err[0] and "recomputing" in err[0], err
    assert ck.load("piece", EXPECT) is not None  # rewritten whole


def test_each_checkpoint_is_named_by_what_determines_it() -> None:
    """A ``+mpc`` run (the bench copies its curriculum run's checkpoints) reuses the stage-1/2 pieces; the MPC
    piece depends on the stages before it and on the method."""
    from quasisim.pipeline import piece_scope as _piece_scope

    info = {"demo_content": "d", "hand": "shadow", "budget": "fast", "weights": {"w": 1.0}}
    base = {**info, "stages": ["1", "2"], "method": "ours"}
    plus = {**info, "stages": ["1", "2", "mpc"], "method": "ours", "mpc": {"horizon": 5}}
    alone = {**info, "stages": ["mpc"], "method": "mpc-base", "mpc": {"horizon": 5}}
    for name in ("kinematic", "stage1_human", "stage1_robot", "stage2_sim03"):
        assert _piece_scope(base, name) == _piece_scope(plus, name)
    assert _piece_scope(base, "stage2_sim03") != _piece_scope({**base, "stages": ["2"]}, "stage2_sim03")
    assert _piece_scope(plus, "mpc") != _piece_scope(alone, "mpc")
    assert _piece_scope({**plus, "hand": "allegro"}, "kinematic") != _piece_scope(plus, "kinematic")


def test_pieces_in_the_target_depend_on_which_target() -> None:
    """The stages that roll out or judge in the target (sample, select, mpc, 3) are named by the target too,
    the quasi-physical stages before them are not: a PyBullet run reuses a MuJoCo run's stage-1/2 checkpoints
    and never its sampling. MuJoCo runs carry no target key (their identity is as before it was added)."""
    from quasisim.pipeline import piece_scope as _piece_scope

    info = {"demo_content": "d", "hand": "shadow", "budget": "fast", "weights": {"w": 1.0}, "sampling": {"s": 1}}
    mj = {**info, "stages": ["1", "2", "sample", "select"], "method": "ours"}
    pb = {**mj, "target": "pybullet"}
    for name in ("kinematic", "stage1_human", "stage1_robot", "stage2_sim03"):
        assert _piece_scope(mj, name) == _piece_scope(pb, name), name
    for name in ("sample", "select"):
        assert _piece_scope(mj, name) != _piece_scope(pb, name), name
    assert _piece_scope({**pb, "stages": ["mpc"]}, "mpc") != _piece_scope({**mj, "stages": ["mpc"]}, "mpc")


def test_run_identity_names_a_target_other_than_mujoco(tmp_path: Path) -> None:
    from quasisim.data.demo import load_demo
    from quasisim.data.synthetic import write_example
    from quasisim.method.config import TransferConfig
    from quasisim.method.curriculum import load_curriculum
    from quasisim.method.spec import TransferSpec
    from quasisim.pipeline import identity

    path = write_example("cube_lift", tmp_path, n_frames=12)
    demo, cur, cfg = load_demo(path), load_curriculum("default"), TransferConfig.from_yaml()
    mj = identity(path, demo, TransferSpec(render=False).checked(), cur, cfg)
    pb = identity(path, demo, TransferSpec(render=False, target="pybullet").checked(), cur, cfg)
    assert "target" not in mj and pb == {**mj, "target": "pybullet"}
    # a run in the quasi-physical simulator names its revision; sample-target does not depend on it
    from quasisim.sim.build import SIMULATOR_REVISION

    st = identity(path, demo, TransferSpec(render=False, method="sample-target").checked(), cur, cfg)
    assert mj["simulator_revision"] == SIMULATOR_REVISION and "simulator_revision" not in st


def test_run_json_damage_and_legacy_checkpoints(tmp_path: Path, capsys) -> None:
    _fresh(tmp_path).save("piece", **_arrays())
    (tmp_path / "run.json").write_text("")  # empty: said once, the checkpoint's own identity decides
    assert _fresh(tmp_path, resume=True).load("piece", EXPECT) is not None
    assert "run.json: damaged" in capsys.readouterr().err
    # a checkpoint written before identities existed is trusted only under a matching run.json
    save_npz_atomic(tmp_path / "old.npz", **_arrays())
    assert _fresh(tmp_path, resume=True).load("old", EXPECT) is not None
    (tmp_path / "run.json").unlink()
    assert _fresh(tmp_path, resume=True).load("old", EXPECT) is None


def test_orphans_do_not_block_a_fresh_run(tmp_path: Path) -> None:
    ck = tmp_path / "checkpoints"
    ck.mkdir()
    (ck / ".kinematic.npz.k2j3h4ab.tmp.npz").write_bytes(b"half")  # as tempfile names them: 8 random characters
    (tmp_path / ".metrics.json.x1yz_789.tmp.json").write_bytes(b"{")
    (tmp_path / ".outputs.abc45678.tmp").mkdir()
    Checkpoints(ck, INFO, resume=False)  # no "holds checkpoints of an earlier run"
    assert not list(ck.glob(".*"))
    assert len(remove_orphans(tmp_path)) == 2 and not list(tmp_path.glob(".*"))


def test_orphans_are_only_what_quasisim_names_so(tmp_path: Path) -> None:
    """remove_orphans takes only the names quasisim's own atomic writes give (``.NAME.<8 random>.tmp[.ext]``
    files, ``.outputs.<8 random>.tmp`` staging folders): another program's hidden ``*.tmp`` files and folders in
    an output folder stay."""
    mine = [".mydata.tmp", ".notes.tmp", ".build.tmp.d", ".a.b.tmp", ".cache.abcd1234.tmp"]
    for n in mine[:3]:
        (tmp_path / n).mkdir()
        (tmp_path / n / "keep.txt").write_text("mine")
    for n in mine[3:]:
        (tmp_path / n).mkdir() if n.startswith(".cache") else (tmp_path / n).write_text("mine")
    ours = [".metrics.json.abcd1234.tmp.json", ".outputs.ab_d1234.tmp", ".write-probe.zz99zz99.tmp"]
    (tmp_path / ours[0]).write_text("{")
    (tmp_path / ours[1]).mkdir()
    (tmp_path / ours[2]).write_text("")
    assert sorted(p.name for p in remove_orphans(tmp_path)) == sorted(ours)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(mine)
    assert all((tmp_path / n / "keep.txt").read_text() == "mine" for n in mine[:3])


def test_overwrite_never_removes_a_checkpoints_folder_quasisim_did_not_write(tmp_path: Path) -> None:
    """--overwrite removes a checkpoints folder only where every file in it is quasisim's (run.json, pieces that
    carry their run identity): another program's .npz files there are refused, naming the folder, the file and
    --out, and left as they were."""
    from quasisim.errors import InputError

    ck = tmp_path / "checkpoints"
    ck.mkdir()
    np.savez(ck / "weights.npz", w=np.zeros(3))
    (ck / "notes.txt").write_text("mine")
    with pytest.raises(InputError, match="--out") as e:
        Checkpoints(ck, INFO, resume=False, overwrite=True)
    assert str(ck) in str(e.value) and "notes.txt" in str(e.value)
    assert sorted(p.name for p in ck.iterdir()) == ["notes.txt", "weights.npz"]
    (ck / "notes.txt").unlink()
    with pytest.raises(InputError, match=r"weights\.npz"):  # an .npz without quasisim's run identity
        Checkpoints(ck, INFO, resume=False, overwrite=True)
    assert (ck / "weights.npz").is_file()
    (ck / "weights.npz").unlink()
    _fresh(ck).save("piece", **_arrays())  # quasisim's own: removed
    Checkpoints(ck, INFO, resume=False, overwrite=True)
    assert sorted(p.name for p in ck.iterdir()) == ["run.json"]


def test_overwrite_starts_afresh(tmp_path: Path) -> None:
    _fresh(tmp_path).save("piece", **_arrays())
    with pytest.raises(Exception, match="--overwrite"):
        _fresh(tmp_path)
    Checkpoints(tmp_path, INFO, resume=False, overwrite=True)
    assert not (tmp_path / "piece.npz").exists()


# ---- output sets -----------------------------------------------------------------------------------------


def _write_set(out: Path, tag: str, fail: bool = False, extra: str = "") -> None:
    with output_set(out) as stage:
        (stage / "metrics.json").write_text(tag)
        if fail:
            raise KeyboardInterrupt
        (stage / "report.html").write_text(tag)
        if extra:
            (stage / extra).write_text(tag)


def test_outputs_are_written_as_a_set(tmp_path: Path) -> None:
    _write_set(tmp_path, "old")
    assert set(read_manifest(tmp_path)) == {"metrics.json", "report.html"}
    with pytest.raises(KeyboardInterrupt):  # killed while rendering: the old set stays whole
        _write_set(tmp_path, "new", fail=True)
    assert {p.name for p in tmp_path.iterdir()} == {"metrics.json", "report.html", MANIFEST}
    assert (tmp_path / "metrics.json").read_text() == "old" and read_manifest(tmp_path) is not None
    _write_set(tmp_path, "new")
    assert (tmp_path / "report.html").read_text() == "new" and read_manifest(tmp_path) is not None
    (tmp_path / "metrics.json").write_text("mixed")  # a reader can tell a mixed or unfinished set
    assert read_manifest(tmp_path) is None
    _write_set(tmp_path, "a", extra="rollout.npz")
    _write_set(tmp_path, "b")  # a file of the earlier set that the new set lacks goes with it
    assert set(read_manifest(tmp_path)) == {"metrics.json", "report.html"} and not (tmp_path / "rollout.npz").exists()


def test_an_earlier_set_removes_only_its_own_unchanged_files(tmp_path: Path) -> None:
    """The files an earlier manifest lists go with it only where they still hold what it recorded (their
    sha256): a file edited since, or listed by a manifest.json of another program, stays."""
    from quasisim.files import file_sha256

    _write_set(tmp_path, "a", extra="rollout.npz")
    (tmp_path / "rollout.npz").write_text("edited by hand")
    _write_set(tmp_path, "b")
    assert (tmp_path / "rollout.npz").read_text() == "edited by hand"
    other = tmp_path / "other"
    other.mkdir()
    (other / "data.csv").write_text("mine")
    (other / "notes.txt").write_text("mine")
    (other / MANIFEST).write_text(json.dumps({"files": ["data.csv"]}))  # another program's list of its files
    _write_set(other, "x")
    (other / MANIFEST).write_text(json.dumps({"files": {"notes.txt": "sha256:" + file_sha256(other / "notes.txt")}}))
    _write_set(other, "y")
    assert (other / "data.csv").read_text() == "mine" and (other / "notes.txt").read_text() == "mine"
    assert set(read_manifest(other)) == {"metrics.json", "report.html"}


def test_sigkill_while_writing_leaves_the_earlier_set(tmp_path: Path) -> None:
    _write_set(tmp_path, "old")
    code = (
        "import os, signal, sys\nfrom pathlib import Path\nfrom quasisim.files import output_set\n"
        "with output_set(Path(sys.argv[1])) as s:\n    (s / 'metrics.json').write_text('new')\n"
        "    os.kill(os.getpid(), signal.SIGKILL)\n"
    )
    r = subprocess.run([sys.executable, "-c", code, str(tmp_path)], env={**os.environ}, check=False)
    assert r.returncode == -signal.SIGKILL
    assert (tmp_path / "metrics.json").read_text() == "old" and read_manifest(tmp_path) is not None
    _write_set(tmp_path, "new")  # the next writer removes the orphan staging folder
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


# ---- the CLI on the synthetic example --------------------------------------------------------------------


@pytest.fixture(scope="module")
def clip(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A 16-frame cube_lift, a 16-frame cylinder clip and kinematic controls for the cube."""
    d = tmp_path_factory.mktemp("rundir")
    r = CliRunner()
    for name in ("cube_lift", "cylinder_lift_turn"):
        assert r.invoke(main, ["example", "--out", str(d), "--name", name, "--frames", "16"]).exit_code == 0
    assert r.invoke(main, ["retarget", str(d / "cube_lift.npz"), "--out", str(d / "k")]).exit_code == 0
    return {"cube": d / "cube_lift.npz", "cyl": d / "cylinder_lift_turn.npz", "controls": d / "k" / "kinematic.npz"}


def test_unstable_simulations_are_failures(clip: dict[str, Path], tmp_path: Path, capsys) -> None:
    from quasisim.assets.hand import load_hand
    from quasisim.data.controls import load_controls
    from quasisim.data.demo import load_demo
    from quasisim.eval.evaluate import evaluate_controls
    from quasisim.targets.build import scene_for
    from quasisim.targets.scene import PhysicsOptions, place_hands

    demo, c = load_demo(clip["cube"]), load_controls(clip["controls"])
    calm = evaluate_controls(demo, c, "mujoco", None, render=False)
    assert calm.metrics["unstable"] is False and calm.rollout.instability == ""
    # MuJoCo's own warning (a 50 ms step): flagged, every success flag false, said in metrics and report
    scene = scene_for(demo, place_hands((load_hand(c.hand),), c.base_rots), physics=PhysicsOptions(mujoco_dt=0.05))
    ev = evaluate_controls(demo, c, "mujoco", tmp_path / "mj", render=False, scene=scene)
    assert "BADQACC" in ev.rollout.instability
    m = json.loads((tmp_path / "mj" / "metrics.json").read_text())
    assert m["unstable"] is True and not any(m["success"].values())
    assert "UNSTABLE simulation" in (tmp_path / "mj" / "report.html").read_text()
    assert "unstable simulation" in capsys.readouterr().err
    # an energy blow-up (the hand teleported 2 m in one frame) in both targets
    q = c.q_targets.copy()
    q[8:, 0] += 2.0
    for target in ("mujoco", "pybullet"):
        ev = evaluate_controls(demo, dataclasses.replace(c, q_targets=q), target, None, render=False)
        assert "energy blow-up" in ev.rollout.instability and ev.metrics["unstable"] is True
        assert not any(ev.metrics["success"].values())


def test_rollout_instability_checks() -> None:
    from quasisim.targets import TargetRollout

    T = 5
    base = dict(
        target="x", qpos=np.zeros((T, 8)), object_pos=np.zeros((T, 3)), object_quat=np.tile([1.0, 0, 0, 0], (T, 1)),
        keypoints=np.zeros((T, 2, 3)), kp_human=np.arange(2), kp_metric=np.ones(2, bool), dt=0.002, substeps=25,
        wall_s=0.0,
    )  # fmt: skip
    assert TargetRollout(**base).instability == ""
    nan = np.zeros((T, 8))
    nan[3, 2] = np.nan
    assert "NaN" in TargetRollout(**{**base, "qpos": nan}).instability
    fly = np.zeros((T, 3))
    fly[4, 2] = 1.0  # 1 m in 50 ms
    assert "object speed" in TargetRollout(**{**base, "object_pos": fly}).instability
    assert "BADQACC x2" in TargetRollout(**base, extras={"sim_warnings": {"BADQACC": 2}}).instability


def test_controls_know_their_demo(clip: dict[str, Path], tmp_path: Path) -> None:
    from quasisim.data.controls import load_controls
    from quasisim.data.demo import content_hash, load_demo

    assert load_controls(clip["controls"]).demo_hash == content_hash(load_demo(clip["cube"]))
    # the same demo content rewritten (another file, new zip timestamps) has the same hash
    r = CliRunner().invoke(main, ["example", "--out", str(tmp_path / "again"), "--name", "cube_lift", "--frames", "16"])
    assert r.exit_code == 0 and content_hash(load_demo(tmp_path / "again" / "cube_lift.npz")) == content_hash(
        load_demo(clip["cube"])
    )
    # cube controls for the cylinder clip (same frames, same hand): refused, then replayed with --force
    args = ["evaluate", str(clip["cyl"]), str(clip["controls"]), "--no-render", "--out", str(tmp_path / "e")]
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 2 and "demo_hash" in r.stderr and not (tmp_path / "e").exists()
    r = CliRunner().invoke(main, [*args, "--force"])
    assert r.exit_code == 0 and "replayed anyway" in r.stderr and read_manifest(tmp_path / "e") is not None


def test_overwrite_only_when_asked(clip: dict[str, Path], tmp_path: Path) -> None:
    args = ["evaluate", str(clip["cube"]), str(clip["controls"]), "--no-render", "--out", str(tmp_path)]
    assert CliRunner().invoke(main, args).exit_code == 0
    before = (tmp_path / MANIFEST).read_bytes()
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 2 and "--overwrite" in r.stderr and (tmp_path / MANIFEST).read_bytes() == before
    assert CliRunner().invoke(main, [*args, "--overwrite"]).exit_code == 0
    r = CliRunner().invoke(main, ["example", "--out", str(tmp_path), "--name", "cube_lift", "--frames", "16"])
    assert r.exit_code == 0  # a folder without an example demo in it is fine


def _lock_of(pid: int) -> str:
    import socket

    return json.dumps(
        {"pid": pid, "host": socket.gethostname(), "since": "2026-11-26 06:00:00", "command": "transfer x"}
    )


def test_a_folder_being_written_is_refused_and_a_stale_lock_is_taken_over(
    clip: dict[str, Path], tmp_path: Path
) -> None:
    """One run per folder: a second run on an --out that a live process is writing is refused with one line
    naming that process, before any work; a lock whose process has ended is taken over; the lock is gone after
    the run."""
    from quasisim.files import LOCK

    out = tmp_path / "run"
    out.mkdir()
    holder = subprocess.Popen(["sleep", "60"])
    try:
        (out / LOCK).write_text(_lock_of(holder.pid))
        for cmd in (
            ["evaluate", str(clip["cube"]), str(clip["controls"]), "--no-render", "--out", str(out)],
            ["transfer", str(clip["cube"]), "--method", "kinematic", "--no-render", "--out", str(out)],
            ["retarget", str(clip["cube"]), "--out", str(out)],
        ):
            r = CliRunner().invoke(main, cmd)
            assert r.exit_code != 0, cmd
            line = r.stderr.strip()
            assert "\n" not in line and f"process {holder.pid}" in line and "another quasisim run (transfer x)" in line
            assert sorted(p.name for p in out.iterdir()) == [LOCK]  # nothing written
    finally:
        holder.kill()
        holder.wait()
    # the holder is gone: its lock is stale and the next run takes it over
    r = CliRunner().invoke(
        main, ["evaluate", str(clip["cube"]), str(clip["controls"]), "--no-render", "--out", str(out)]
    )
    assert r.exit_code == 0, r.output
    assert (out / MANIFEST).is_file() and not (out / LOCK).exists()
    # a folder made only for the lock is removed again when the run leaves it empty
    from quasisim.files import run_lock

    with run_lock(tmp_path / "a" / "b"):
        assert (tmp_path / "a" / "b" / LOCK).is_file()
    assert not (tmp_path / "a" / "b").exists()


def test_a_full_disk_while_writing_outputs_ends_cleanly(
    clip: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """No space left while the outputs are written (injected ENOSPC): one line naming the file, exit code not 0,
    no manifest and no temporary files; a later run in the same folder works."""
    import errno

    import quasisim.files as files

    real = files.np.savez_compressed

    def full(*a, **k) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    out = tmp_path / "out"
    args = ["evaluate", str(clip["cube"]), str(clip["controls"]), "--no-render", "--out", str(out)]
    monkeypatch.setattr(files.np, "savez_compressed", full)
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 2 and r.stderr.count("\n") == 1, r.output
    assert r.stderr.startswith(f"error: {out}") and "No space left on device" in r.stderr and ".npz" in r.stderr
    assert not (out / MANIFEST).exists() and not [q for q in out.rglob(".*")]
    monkeypatch.setattr(files.np, "savez_compressed", real)
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 0, r.output
    assert read_manifest(out) is not None


def test_long_clips_warn_with_an_estimate(capsys) -> None:
    from types import SimpleNamespace

    from quasisim.data.demo import LONG_CLIP, warn_long_clip

    warn_long_clip(SimpleNamespace(name="c", n_frames=LONG_CLIP), 1.0, 1.0, "x")
    assert capsys.readouterr().err == ""
    warn_long_clip(SimpleNamespace(name="c", n_frames=10_000), 0.36, 0.4, "transfer")
    err = capsys.readouterr().err.splitlines()
    # BASE + T * per frame: (15 s + 3600 s) / 60 and (600 MB + 4000 MB) / 1024
    assert len(err) == 1 and "10000 frames" in err[0] and "60 min" in err[0] and "4.5 GB" in err[0]
    warn_long_clip(SimpleNamespace(name="c", n_frames=1600), 0.01, 0.1, "retargeting")
    assert "about 0.5 min and 0.7 GB" in capsys.readouterr().err  # under 10 min: one decimal


# ---- transfer: another demo's checkpoints, and kills at random points -----------------------------------

FAST = ["--method", "sample-target", "--set", "sampling.samples=6", "--set", "sampling.horizon=3"]


def test_resume_without_run_json_never_reuses_another_demos_checkpoints(clip: dict[str, Path], tmp_path: Path) -> None:
    from quasisim.method.compare import compare_runs

    r = CliRunner()
    base = ["transfer", *FAST, "--no-render", "--out"]
    assert r.invoke(main, [*base, str(tmp_path / "cube"), str(clip["cube"])]).exit_code == 0
    assert r.invoke(main, [*base, str(tmp_path / "cyl"), str(clip["cyl"])]).exit_code == 0
    # the cube run's checkpoints under a folder without run.json, resumed for the cylinder
    (tmp_path / "mixed").mkdir()
    os.rename(tmp_path / "cube" / "checkpoints", tmp_path / "mixed" / "checkpoints")
    (tmp_path / "mixed" / "checkpoints" / "run.json").unlink()
    res = r.invoke(main, [*base, str(tmp_path / "mixed"), str(clip["cyl"]), "--resume"])
    assert res.exit_code == 0, res.output
    assert res.stderr.count("made by another run") == 2  # kinematic.npz and sample.npz
    n, diffs = compare_runs(tmp_path / "cyl", tmp_path / "mixed")
    assert n >= 4 and diffs == []
    # a folder with outputs and no checkpoints is refused, --overwrite replaces it
    res = r.invoke(main, [*base, str(tmp_path / "cube"), str(clip["cube"])])
    assert res.exit_code == 2 and "--overwrite" in res.stderr
    assert r.invoke(main, [*base, str(tmp_path / "cube"), str(clip["cube"]), "--overwrite"]).exit_code == 0


def _transfer(demo: Path, out: Path, *extra: str) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "quasisim.cli", "transfer", str(demo), *FAST, "--no-render", "--out", str(out)]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    return subprocess.Popen(ctrl_c_restored([*cmd, *extra]), env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


@pytest.mark.slow
def test_killed_or_interrupted_then_resumed_is_bit_identical(clip: dict[str, Path], tmp_path: Path) -> None:
    """A short transfer (sample-target, 16 frames) killed with SIGKILL at random moments, or stopped by SIGTERM
    or SIGINT, resumed until it finishes: every array (controls, rollout, checkpoints) and metrics.json equal
    an uninterrupted run's."""
    from quasisim.method.compare import compare_runs

    t0 = time.perf_counter()
    ref = _transfer(clip["cube"], tmp_path / "ref")
    assert ref.wait() == 0, ref.stderr.read().decode()
    t_ref = time.perf_counter() - t0
    rng = random.Random(int(os.environ.get("QUASISIM_CRASH_SEED", "0")))
    kills = 0
    for k in range(3):
        out, extra = tmp_path / f"run{k}", ()
        for _ in range(2):  # up to two kills per run, then let it finish
            p = _transfer(clip["cube"], out, *extra)
            time.sleep(rng.uniform(0.2, 0.9) * t_ref)  # a rerun is faster than the reference (compiled programs cached)
            if p.poll() is None:
                p.send_signal(signal.SIGKILL)
                kills += 1
            p.wait()
            extra = ("--resume",) if (out / "checkpoints").is_dir() else ("--overwrite",)
        p = _transfer(clip["cube"], out, *extra)
        assert p.wait() == 0, p.stderr.read().decode()
        n, diffs = compare_runs(tmp_path / "ref", out)
        assert diffs == [] and n >= 4, diffs
        assert read_manifest(out) is not None and not [q for q in out.rglob(".*")]
    assert kills >= 2  # the kills did land
    # SIGTERM (a scheduler) and SIGINT (Ctrl-C): the command ends at once, its temporary files and its run lock
    # go with it, and --resume finishes bit-identical to the uninterrupted run
    for sig in (signal.SIGTERM, signal.SIGINT):
        out = tmp_path / sig.name
        p = _transfer(clip["cube"], out)
        time.sleep(0.7 * t_ref)
        p.send_signal(sig)
        assert p.wait() in (0, 1, 128 + sig, -sig), sig.name
        assert not [q for q in out.rglob(".*")], sig.name
        extra = ("--resume",) if (out / "checkpoints").is_dir() else ("--overwrite",)
        p = _transfer(clip["cube"], out, *extra)
        assert p.wait() == 0, p.stderr.read().decode()
        n, diffs = compare_runs(tmp_path / "ref", out)
        assert diffs == [] and n >= 4, (sig.name, diffs)
