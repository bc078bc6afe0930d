"""`quasisim export --format lerobot`: finished runs as a LeRobot dataset written and read back through the
`lerobot` package (docs/dataset.md). Marker `lerobot`: make test runs this module in .venv-lerobot (make
setup-lerobot), after the rest; the main environment runs only the test that it says how to install lerobot.

Runs are made once per module, with the kinematic method in MuJoCo: the synthetic cube lift (20 frames) here, and
a real GRAB clip by the main environment (.venv), as a user exports what it made (the clip's object is a cube,
whose principal axes LAPACK may choose differently in another numpy: the export must still reproduce the run);
then an Allegro run of the cube, which a Shadow dataset must refuse."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from helpers import UNDER_CI, missing_data

GRAB = "grab_s1_cubesmall_inspect_1"
MAIN_VENV = Path(__file__).resolve().parents[1] / ".venv" / "bin" / "quasisim"


def _cli(*args: object):
    from click.testing import CliRunner

    from quasisim.cli import main

    return CliRunner().invoke(main, [str(a) for a in args])


def _lerobot() -> None:
    try:
        import lerobot  # noqa: F401
    except ImportError:
        if UNDER_CI:
            pytest.fail("CI runs the LeRobot export's tests in .venv-lerobot (make setup-lerobot)", pytrace=False)
        pytest.skip("lerobot is not installed here: make setup-lerobot, then .venv-lerobot/bin/pytest -m lerobot")


@pytest.fixture(scope="module")
def root(tmp_path_factory) -> Path:
    """demos/ and runs/<clip>/kinematic as `bench transfer` lays them out."""
    _lerobot()
    clip = Path(os.environ.get("QUASISIM_DATA", "../shared/data")) / f"{GRAB}.npz"
    if not clip.is_file():
        missing_data(f"GRAB clip not found at {clip} (set QUASISIM_DATA)")
    root = tmp_path_factory.mktemp("lerobot")
    r = _cli("example", "--out", root / "demos", "--name", "cube_lift", "--frames", "20")
    assert r.exit_code == 0, r.output
    args = ["--method", "kinematic", "--target", "mujoco", "--no-render", "--robust", "0", "--out"]
    r = _cli("transfer", root / "demos" / "cube_lift.npz", *args, root / "runs" / "cube_lift" / "kinematic")
    assert r.exit_code == 0, r.output
    if not MAIN_VENV.is_file():
        if UNDER_CI:
            pytest.fail(f"CI makes the GRAB run with the main environment: {MAIN_VENV} not found", pytrace=False)
        pytest.skip(f"the main environment ({MAIN_VENV}) makes the GRAB run: make setup")
    cmd = [str(MAIN_VENV), "transfer", str(clip), *map(str, args), str(root / "runs" / GRAB / "kinematic")]
    p = subprocess.run(cmd, capture_output=True, text=True, check=False)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    return root


@pytest.fixture(scope="module")
def exported(root) -> tuple[Path, str]:
    """runs/ exported with one closed-loop episode per run (the cube's demo through --data, GRAB's through
    $QUASISIM_DATA)."""
    out = root / "lr"
    r = _cli("export", root / "runs", "--format", "lerobot", "--out", out, "--data", root / "demos",
             "--closed-loop", "1", "--image-size", "96", "128")  # fmt: skip
    assert r.exit_code == 0, r.output
    return out, r.output


@pytest.mark.lerobot
def test_round_trip_equals_the_runs(root, exported) -> None:
    """Loaded with LeRobotDataset, each run's episode holds the run's own rollout (rollout.npz: joints, object
    pose) and its applied PD targets (controls.npz) to float32, at the clip's fps, with its task text; each
    closed-loop episode carries its world in quasisim's episode metadata, and its frames differ from the plan's."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from quasisim.data.controls import load_controls
    from quasisim.eval.lerobot_export import episode_meta

    out, output = exported
    assert "4 episodes" in output and "vectors equal" in output, output
    ds = LeRobotDataset("quasisim/lr", root=out, video_backend="pyav")
    meta = episode_meta(out)
    assert ds.num_episodes == 4 and ds.fps == 20 and [m["episode_index"] for m in meta] == [0, 1, 2, 3]
    assert [(m["clip"], m["closed_loop"]) for m in meta] == [
        ("cube_lift", False), ("cube_lift", True), (GRAB, False), (GRAB, True)]  # fmt: skip
    cols = ds.hf_dataset.with_format("numpy")
    ep = np.asarray(cols["episode_index"])
    for i, m in enumerate(meta):
        rows = np.flatnonzero(ep == i)
        state = np.stack(cols["observation.state"][rows[0] : rows[-1] + 1])
        action = np.stack(cols["action"][rows[0] : rows[-1] + 1])
        run = root / "runs" / m["clip"] / "kinematic"
        z = np.load(run / "rollout.npz")
        q = load_controls(run / "controls.npz").q_targets
        assert len(rows) == len(q) - 1 == ds.meta.episodes["length"][i]
        if not m["closed_loop"]:
            want = np.concatenate([z["qpos"], z["object_pos"], z["object_quat"]], 1)[:-1].astype(np.float32)
            np.testing.assert_array_equal(state, want)
            np.testing.assert_array_equal(action, q[1:].astype(np.float32))
            assert m["task"] == ("lift the cube (cube_lift)" if i == 0 else f"inspect the cubesmall ({GRAB})")
            assert ds[int(rows[0])]["task"] == m["task"]
        else:
            w = m["world"]
            assert m["world_ranges"] == "robust" and m["world_index"] == 0
            assert w["object_mass"] > 0 and 0 < w["friction"] and 0.8 < w["gain_scale"] < 1.2
            np.testing.assert_allclose(state[0, -7:-4], w["object_pos0"], atol=1e-6)  # the world's start
            assert np.abs(action - q[1:].astype(np.float32)).max() > 1e-3  # the tracker's targets, not the plan's


@pytest.mark.lerobot
def test_video_frames_are_the_rendered_states(root, exported) -> None:
    """A decoded frame of the MP4 matches the scene rendered at that frame's state (PSNR above the export's
    bar) and not the scene at another frame of the same episode (the hand has moved)."""
    import torch

    from quasisim.data.controls import load_controls
    from quasisim.data.demo import load_demo
    from quasisim.eval.evaluate import hands_of
    from quasisim.eval.lerobot_export import VIDEO_PSNR, load, psnr
    from quasisim.eval.render import SideBySide
    from quasisim.targets.build import scene_for
    from quasisim.targets.scene import place_hands

    out, _ = exported
    ds = load(out)
    run = root / "runs" / GRAB / "kinematic"
    c = load_controls(run / "controls.npz")
    demo = load_demo(Path(os.environ.get("QUASISIM_DATA", "../shared/data")) / f"{GRAB}.npz")
    z = np.load(run / "rollout.npz")
    r = SideBySide(
        scene_for(demo, place_hands(hands_of(c, run / "controls.npz"), c.base_rots)), demo, width=128, height=96
    )
    start = int(np.flatnonzero(np.asarray(ds.hf_dataset.with_format("numpy")["episode_index"]) == 2)[0])
    try:
        for t, other in ((5, 55), (40, 10)):
            img = ds[start + t]["observation.images.scene"]
            got = (img.permute(1, 2, 0) * 255).round().to(torch.uint8).numpy()
            same = r.result(t, z["qpos"], z["object_pos"], z["object_quat"], show_human=False)
            moved = r.result(other, z["qpos"], z["object_pos"], z["object_quat"], show_human=False)
            assert psnr(got, same) >= VIDEO_PSNR > psnr(got, moved), (t, psnr(got, same), psnr(got, moved))
    finally:
        r.close()


@pytest.mark.lerobot
def test_refuses_other_hand_and_leaves_nothing(root, tmp_path) -> None:
    """A batch that mixes a Shadow and an Allegro run is refused, naming the run and the joints, and no
    dataset folder (or temporary one) is left behind."""
    runs = tmp_path / "runs"
    shutil.copytree(root / "runs" / "cube_lift" / "kinematic", runs / "cube_lift" / "a_shadow")
    r = _cli("transfer", root / "demos" / "cube_lift.npz", "--hand", "allegro", "--method", "kinematic", "--target",
             "mujoco", "--out", runs / "cube_lift" / "b_allegro", "--no-render", "--robust", "0")  # fmt: skip
    assert r.exit_code == 0, r.output
    out = tmp_path / "lr"
    r = _cli("export", runs, "--format", "lerobot", "--out", out, "--data", root / "demos")
    assert r.exit_code != 0 and "b_allegro" in r.output and "joints" in r.output, r.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["runs"]


@pytest.mark.lerobot
def test_read_back_check_catches_changes_and_keeps_nothing(root, exported, tmp_path, monkeypatch) -> None:
    """The read-back check refuses a vector one float32 step off and a frame of another moment; an export
    whose check fails leaves no dataset folder."""
    import torch

    from quasisim.errors import QuasisimError
    from quasisim.eval import lerobot_export as le

    out, _ = exported
    ds = le.load(out)
    cols = ds.hf_dataset.with_format("numpy")
    rows = np.flatnonzero(np.asarray(cols["episode_index"]) == 0)
    arrays = {k: np.stack(cols[k][rows[0] : rows[-1] + 1]) for k in ("observation.state", "action")}

    def frame(t: int) -> np.ndarray:
        return (ds[int(rows[t])]["observation.images.scene"].permute(1, 2, 0) * 255).round().to(torch.uint8).numpy()

    good = [(arrays, {0: frame(0), 18: frame(18)})] + [({}, {})] * 3
    assert le.verify(ds, good)["max_vector_difference"] == 0.0
    bumped = {**arrays, "action": arrays["action"].copy()}
    bumped["action"][3, 2] = np.nextafter(bumped["action"][3, 2], np.float32(10))
    with pytest.raises(QuasisimError, match="vectors differ"):
        le.verify(ds, [(bumped, {}), *good[1:]])
    with pytest.raises(QuasisimError, match="PSNR"):
        le.verify(ds, [(arrays, {0: frame(18)}), *good[1:]])

    def fail(*a: object) -> None:
        raise QuasisimError("read back differs")

    monkeypatch.setattr(le, "verify", fail)
    r = _cli("export", root / "runs" / "cube_lift", "--format", "lerobot", "--out", tmp_path / "lr", "--data",
             root / "demos", "--image-size", "96", "128")  # fmt: skip
    assert r.exit_code != 0 and "read back differs" in r.output, r.output
    assert list(tmp_path.iterdir()) == []


def test_without_lerobot_says_how_to_install(tmp_path) -> None:
    """In an environment without lerobot (the main one), the export stops with one line naming the set-up."""
    try:
        import lerobot  # noqa: F401

        pytest.skip("lerobot is installed here")
    except ImportError:
        pass
    from quasisim.errors import QuasisimError
    from quasisim.eval.lerobot_export import require_lerobot

    with pytest.raises(QuasisimError, match="make setup-lerobot"):
        require_lerobot()
    r = _cli("export", tmp_path, "--format", "lerobot", "--out", tmp_path / "lr")
    assert r.exit_code != 0 and "make setup-lerobot" in r.output, r.output
    assert not (tmp_path / "lr").exists()


def test_task_text_from_clip_names() -> None:
    from types import SimpleNamespace

    from quasisim.eval.lerobot_export import task_text

    def t(name: str, obj: str) -> str:
        return task_text(SimpleNamespace(name=name, object_name=obj))  # type: ignore[arg-type]

    assert t("grab_s1_mug_drink_3", "mug") == "drink the mug (grab_s1_mug_drink_3)"
    assert t("arctic_s5_laptop_grab_01", "laptop") == "grab the laptop (arctic_s5_laptop_grab_01)"
    assert t("cube_lift", "cube") == "lift the cube (cube_lift)"
    assert t("my_clip", "cube") == "manipulate the cube (my_clip)"
    assert t("s2_apple_pass_1", "apple") == "pass the apple (s2_apple_pass_1)"  # the object's name starts it
    assert t("x", "y") == "manipulate the y (x)"  # no action word: "manipulate"


def _quasisim_lerobot(path: Path) -> Path:
    """A folder laid out as a LeRobot dataset that quasisim export wrote (meta/info.json, its episodes file)."""
    (path / "meta").mkdir(parents=True)
    (path / "meta" / "info.json").write_text("{}")
    (path / "meta" / "quasisim_episodes.jsonl").write_text("")
    return path


def test_overwrite_replaces_only_a_lerobot_export_without_inputs(tmp_path) -> None:
    """--overwrite replaces a LeRobot dataset folder that quasisim wrote; a folder of anything else, or a
    dataset folder that holds or is an input, is refused (naming it and --out) and left as it was."""
    from quasisim.errors import InputError
    from quasisim.eval.lerobot_export import _atomic_dir

    def write(tmp: Path) -> None:
        _quasisim_lerobot(tmp)
        (tmp / "new").write_text("")

    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "keep.txt").write_text("x")
    with pytest.raises(InputError, match=r"mine: option '--out': expected a LeRobot dataset folder"):
        with _atomic_dir(mine, True) as tmp:
            write(tmp)
    assert [p.name for p in mine.iterdir()] == ["keep.txt"] and list(tmp_path.iterdir()) == [mine]
    old = _quasisim_lerobot(tmp_path / "old")
    (old / "runs").mkdir()
    for inputs in ((old / "runs",), (old,)):
        with pytest.raises(InputError, match=r"old: option '--out': expected .*not an input"):
            with _atomic_dir(old, True, inputs) as tmp:
                write(tmp)
        assert sorted(p.name for p in old.iterdir()) == ["meta", "runs"]
    with _atomic_dir(old, True, (tmp_path / "mine",)) as tmp:
        write(tmp)
    assert sorted(p.name for p in old.iterdir()) == ["meta", "new"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine", "old"]


def test_export_never_replaces_its_input(tmp_path) -> None:
    """`export RUNS --format lerobot --out D --overwrite` with D the runs' folder or one above it: one line
    naming D and --out, exit 2, before any work (the environment without lerobot refuses it too)."""
    run = tmp_path / "runs" / "a"
    run.mkdir(parents=True)
    (run / "manifest.json").write_text("{}")
    for out in (tmp_path, tmp_path / "runs"):
        r = _cli("export", tmp_path / "runs", "--format", "lerobot", "--out", out, "--overwrite")
        assert r.exit_code == 2 and len(r.output.strip().splitlines()) == 1, r.output
        assert f"{out}: option '--out': expected" in r.output and "not an input" in r.output, r.output
    assert (run / "manifest.json").is_file()


def test_bench_export_without_finished_runs(tmp_path) -> None:
    """`bench export` on a folder with no finished run: one line naming it, exit 2."""
    (tmp_path / "empty" / "sub").mkdir(parents=True)
    r = _cli("bench", "export", tmp_path / "empty")
    assert r.exit_code == 2 and len(r.output.strip().splitlines()) == 1, r.output
    assert f"{tmp_path / 'empty'}: expected finished runs below it" in r.output, r.output


@pytest.mark.lerobot
def test_overwrite_keeps_the_runs(root, tmp_path) -> None:
    """--overwrite never replaces the folder that holds the runs being exported (the runs stay), and does
    replace a LeRobot dataset it wrote before."""
    runs = tmp_path / "runs"
    shutil.copytree(root / "runs" / "cube_lift", runs / "cube_lift")
    more = ("--format", "lerobot", "--data", root / "demos", "--image-size", "96", "128", "--overwrite")
    r = _cli("export", runs, "--out", tmp_path, *more)
    assert r.exit_code == 2 and f"{tmp_path}: option '--out'" in r.output, r.output
    assert (runs / "cube_lift" / "kinematic" / "manifest.json").is_file()
    for _ in range(2):
        r = _cli("export", runs, "--out", tmp_path / "lr", *more)
        assert r.exit_code == 0 and "1 episodes" in r.output, r.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["lr", "runs"]
