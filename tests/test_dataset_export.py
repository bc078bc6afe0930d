"""`quasisim export`: finished runs into one HDF5 training set in robomimic's layout (docs/dataset.md), the
loader of quasisim.data.dataset, the replay check. Runs are made once per module: the synthetic cube lift
(20 frames, one hand) and an ARCTIC clip (two hands), both with the kinematic method in MuJoCo."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from helpers import missing_data


def _cli(*args: str):
    from click.testing import CliRunner

    from quasisim.cli import main

    return CliRunner().invoke(main, [str(a) for a in args])


def _transfer(demo: Path, out: Path, *more: str) -> Path:
    r = _cli("transfer", demo, "--method", "kinematic", "--target", "mujoco", "--out", out, "--no-render", *more)
    assert r.exit_code == 0, r.output
    return out


@pytest.fixture(scope="module")
def root(tmp_path_factory) -> Path:
    """A folder with the demos (demos/) and the runs (runs/<clip>/kinematic) as `bench transfer` lays them out."""
    from conftest import ARCTIC_CLIP

    if not ARCTIC_CLIP.is_file():
        missing_data(f"ARCTIC clip not found at {ARCTIC_CLIP} (set QUASISIM_DATA to the folder that holds arctic/)")
    root = tmp_path_factory.mktemp("export")
    r = _cli("example", "--out", root / "demos", "--name", "cube_lift", "--frames", "20")
    assert r.exit_code == 0, r.output
    _transfer(root / "demos" / "cube_lift.npz", root / "runs" / "cube_lift" / "kinematic", "--robust", "0")
    _transfer(ARCTIC_CLIP, root / "runs" / ARCTIC_CLIP.stem / "kinematic", "--robust", "1")
    return root


@pytest.fixture(scope="module")
def exported(root) -> tuple[Path, str]:
    """runs/ exported with --check (the ARCTIC demo found through $QUASISIM_DATA, the cube through --data)."""
    out = root / "train.hdf5"
    r = _cli("export", root / "runs", "--out", out, "--data", root / "demos", "--check")
    assert r.exit_code == 0, r.output
    return out, r.output


def _episodes(path: Path) -> dict:
    from quasisim.data.dataset import load_episodes

    return {ep.attrs["run"]: ep for ep in load_episodes(path)}


def test_export_replays_exactly_one_and_two_hands(root, exported) -> None:
    """Each episode's per-step actions, replayed in its own MJCF from its first state, give its stored states
    (to 1e-9; here to the bit), with one hand and with two; so does a restart from any stored state."""
    import mujoco

    from quasisim.data.dataset import REPLAY_TOL, replay_check, replay_states

    path, output = exported
    assert "check demo_0 " in output and "check demo_1 " in output and "(tolerance 1e-09): ok" in output
    devs = replay_check(path)
    assert set(devs) == {"demo_0", "demo_1"} and max(devs.values()) <= REPLAY_TOL, devs
    eps = _episodes(path)
    assert {ep.attrs["sides"] == ["right", "left"] for ep in eps.values()} == {True, False}
    for ep in eps.values():
        model = mujoco.MjModel.from_xml_string(ep.model_file)
        a = ep.attrs
        for t in (0, ep.num_samples // 2, ep.num_samples - 1):  # one frame from a stored state (warm start kept)
            got = replay_states(model, ep.states[t], ep.actions_substep[t : t + 1], ep.actions_velocity[t : t + 1],
                                np.asarray(a["pd_actuators"]), np.asarray(a["ff_actuators"]), a["state_spec"])  # fmt: skip
            want = ep.states[t + 1] if t + 1 < ep.num_samples else ep.final_state
            np.testing.assert_array_equal(got[1], want)


def test_episodes_hold_the_run(root, exported) -> None:
    """Shapes, units and attributes: observations are the run's rollout, actions its controls, the reference
    its demo; the per-step PD targets interpolate as the MuJoCo target applies them."""
    from quasisim.data.controls import load_controls
    from quasisim.data.demo import load_demo

    for rel, ep in _episodes(exported[0]).items():
        run = root / "runs" / rel
        c = load_controls(run / "controls.npz")
        z = np.load(run / "rollout.npz")
        metrics = json.loads((run / "metrics.json").read_text())
        H = len(c.base_rots)
        T, D = c.q_targets.shape
        N, n, K = T - 1, ep.attrs["substeps"], z["all_keypoints"].shape[1]
        assert ep.num_samples == N == ep.attrs["num_samples"] and D == H * 28
        shapes = {"hand_qpos": (N, D), "hand_qvel": (N, D), "pd_target": (N, D), "object_pos": (N, 3),
                  "object_quat": (N, 4), "object_linvel": (N, 3), "object_angvel": (N, 3), "robot_keypoints": (N, K, 3),
                  "ref_hand_keypoints": (N, 21 * H, 3), "ref_object_pos": (N, 3), "ref_object_quat": (N, 4)}  # fmt: skip
        assert {k: v.shape for k, v in ep.obs.items()} == shapes == {k: v.shape for k, v in ep.next_obs.items()}
        np.testing.assert_array_equal(ep.obs["hand_qpos"], z["qpos"][:-1])
        np.testing.assert_array_equal(ep.next_obs["object_pos"], z["object_pos"][1:])
        np.testing.assert_array_equal(ep.obs["robot_keypoints"], z["all_keypoints"][:-1])
        demo = load_demo(ep.attrs["demo_file"])
        np.testing.assert_array_equal(ep.obs["ref_hand_keypoints"], demo.human_joints[:-1])
        np.testing.assert_array_equal(ep.obs["ref_object_quat"], demo.object_quat[:-1])
        np.testing.assert_array_equal(ep.actions, c.q_targets[1:])
        np.testing.assert_array_equal(ep.obs["pd_target"], c.q_targets[:-1])
        s = (np.arange(n) + 1) / n
        want = (1 - s)[None, :, None] * c.q_targets[:-1, None] + s[None, :, None] * c.q_targets[1:, None]
        np.testing.assert_allclose(ep.actions_substep, want, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(ep.actions_substep[:, -1], ep.actions)
        np.testing.assert_allclose(ep.actions_velocity, np.diff(c.q_targets, axis=0) * c.fps, atol=1e-9)
        S = sum(size for _, size in ep.attrs["state_layout"])
        assert ep.states.shape == (N, S) and ep.final_state.shape == (S,) and ep.attrs["state_layout"][0] == ["time", 1]
        assert ep.rewards.shape == (N,) and not ep.rewards.any() and ep.dones.tolist() == [0] * (N - 1) + [1]
        a = ep.attrs
        assert a["metrics"] == metrics and a["success_strict"] == metrics["success"]["strict"]
        assert a["success_20deg_20cm"] == metrics["success"]["20deg_20cm"] and a["target"] == "mujoco"
        assert a["clip"] == c.demo and a["method"] == c.method and len(a["dof_names"]) == D
        assert len(a["keypoint_names"]) == K and a["fps"] == c.fps and a["dt"] == 0.002 and n == 25
        assert ("robust_strict" in a) == (H == 2)  # the ARCTIC run was made with --robust 1


def test_file_layout_for_plain_h5py(exported) -> None:
    """robomimic's layout, read with h5py alone: data/demo_N/{obs,next_obs,actions,states,rewards,dones},
    data attrs total and env_args (JSON), mask/<filter key>, the file's format and settings."""
    import h5py

    from quasisim.data.dataset import file_attrs, load_episodes

    with h5py.File(exported[0], "r") as f:
        demos = sorted(f["data"].keys())
        assert demos == ["demo_0", "demo_1"]
        total = 0
        for d in demos:
            g = f[f"data/{d}"]
            assert {"obs", "next_obs", "actions", "states", "rewards", "dones"} <= set(g.keys())
            assert g["actions"].shape[0] == g.attrs["num_samples"] == g["obs/hand_qpos"].shape[0]
            total += int(g.attrs["num_samples"])
            assert g.attrs["model_file"].startswith("<mujoco")
        assert f["data"].attrs["total"] == total
        env = json.loads(f["data"].attrs["env_args"])
        assert set(env) == {"env_name", "type", "env_kwargs"} and env["env_kwargs"]["fps"] == 20.0
        assert f.attrs["format"] == "quasisim-dataset-v1"
        assert json.loads(f.attrs["settings"])["only"] == "any"
        twenty = [n.decode() for n in f["mask/20deg_20cm"][()]]
        assert twenty == [d for d in demos if f[f"data/{d}"].attrs["success_20deg_20cm"]]
    attrs = file_attrs(exported[0])
    assert attrs["total"] == total and attrs["env_args"]["env_name"] == "quasisim-mujoco"
    assert [ep.name for ep in load_episodes(exported[0], "20deg_20cm")] == twenty


def _fake_run(src: Path, dst: Path, **metrics) -> Path:
    """A copy of run ``src`` whose metrics.json is changed (success flags, robust, unstable) and re-manifested."""
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("checkpoints"))
    m = json.loads((dst / "metrics.json").read_text())
    m["success"].update(metrics.pop("success", {}))
    m.update(metrics)
    (dst / "metrics.json").write_text(json.dumps(m))
    _remanifest(dst)
    return dst


def _remanifest(run: Path) -> None:
    from quasisim.files import MANIFEST, file_sha256

    files = json.loads((run / MANIFEST).read_text())["files"]
    (run / MANIFEST).write_text(json.dumps({"files": {n: file_sha256(run / n) for n in files}}))


@pytest.fixture(scope="module")
def fake_runs(root, tmp_path_factory) -> Path:
    """Four copies of the cube run with made-up outcomes (the filters read metrics.json only)."""
    src, out = root / "runs" / "cube_lift" / "kinematic", tmp_path_factory.mktemp("fake")
    yes = {"strict": True, "20deg_20cm": True}
    _fake_run(src, out / "a", success=yes, robust={"strict": 0.9, "20deg_20cm": 1.0})
    _fake_run(src, out / "b", success={"20deg_20cm": True}, robust={"strict": 0.0, "20deg_20cm": 0.4})
    _fake_run(src, out / "c", robust={"strict": 0.0, "20deg_20cm": 0.0})
    _fake_run(src, out / "d", success=yes, unstable=True, robust={"strict": 1.0, "20deg_20cm": 1.0})
    return out


@pytest.mark.parametrize(
    ("flags", "kept"),
    [((), "abc"), (("--only", "strict"), "a"), (("--only", "20"), "ab"), (("--min-robust", "0.5"), "a"),
     (("--only", "20", "--min-robust", "0.3"), "ab"), (("--only", "strict", "--min-robust", "0.95"), "")],
)  # fmt: skip
def test_filters(root, fake_runs, tmp_path, flags, kept) -> None:
    """--only strict|20|any and --min-robust (robust success of --only's criterion; 20deg_20cm for any);
    unstable runs never; nothing left is an error."""
    out = tmp_path / "f.hdf5"
    r = _cli("export", fake_runs, "--out", out, "--data", root / "demos", *flags)
    if not kept:
        assert r.exit_code == 2 and "expected at least one run that passes --only strict --min-robust 0.95" in r.output
        assert not out.exists()
        return
    assert r.exit_code == 0, r.output
    assert [ep.attrs["run"] for ep in _episodes(out).values()] == list(kept)
    assert "d (unstable simulation)" in r.output


def test_min_robust_needs_robust_success(root, tmp_path) -> None:
    r = _cli("export", root / "runs", "--out", tmp_path / "x.hdf5", "--data", root / "demos", "--min-robust", "0.5")
    assert r.exit_code == 2 and len(r.output.strip().splitlines()) == 1, r.output
    assert "cube_lift/kinematic/metrics.json: field 'robust': expected robust success" in r.output


def test_bad_inputs_one_line(root, tmp_path, monkeypatch) -> None:
    """No finished run, a run without controls, changed files, no demo, a bad --out: one line each, naming
    the folder or file, the field and what was expected."""
    (tmp_path / "empty" / "sub").mkdir(parents=True)
    cases = [
        (tmp_path / "empty", tmp_path / "o.hdf5", "empty: expected finished runs below it", ()),
        (tmp_path / "nope", tmp_path / "o.hdf5", "nope: expected a folder of finished runs", ()),
        (root / "runs", tmp_path / "o.npz", "o.npz: option '--out': expected a file name ending in .hdf5", ()),
    ]
    src = root / "runs" / "cube_lift" / "kinematic"
    shutil.copytree(src, tmp_path / "noctl" / "run")
    (tmp_path / "noctl" / "run" / "controls.npz").unlink()
    cases.append(
        (tmp_path / "noctl", tmp_path / "o.hdf5", "run/controls.npz: expected a finished run with controls.npz", ())
    )
    shutil.copytree(src, tmp_path / "changed" / "run")
    (tmp_path / "changed" / "run" / "metrics.json").write_text("{}")
    cases.append(
        (tmp_path / "changed", tmp_path / "o.hdf5", "run/manifest.json: expected a finished run whose files match", ())
    )
    monkeypatch.setenv("QUASISIM_DATA", str(tmp_path / "empty"))
    cases.append(
        (
            root / "runs" / "cube_lift",
            tmp_path / "o.hdf5",
            "controls.npz: field 'demo': expected the demo 'cube_lift'",
            (),
        )
    )
    for batch, out, said, more in cases:
        r = _cli("export", batch, "--out", out, *more)
        assert r.exit_code == 2 and len(r.output.strip().splitlines()) == 1, r.output
        assert said in r.output and r.output.startswith("error: "), r.output
        assert not out.exists()


def test_overwrite_replaces_only_a_dataset_quasisim_wrote(root, tmp_path) -> None:
    """--overwrite replaces an HDF5 dataset that quasisim export wrote; any other file (HDF5 or not) or a
    folder at --out is refused with one line naming it and --out, and left as it was."""
    import h5py

    run, more = root / "runs" / "cube_lift", ("--data", root / "demos", "--overwrite")
    text = tmp_path / "notes.hdf5"
    text.write_text("not a dataset")
    folder = tmp_path / "folder.hdf5"
    (folder / "keep").mkdir(parents=True)
    plain = tmp_path / "plain.h5"
    with h5py.File(plain, "w") as f:
        f.attrs["owner"] = "someone else"
    for out in (text, folder, plain):
        r = _cli("export", run, "--out", out, *more)
        assert r.exit_code == 2 and len(r.output.strip().splitlines()) == 1, r.output
        assert f"{out}: option '--out': expected" in r.output and "quasisim export wrote" in r.output, r.output
    assert text.read_text() == "not a dataset" and (folder / "keep").is_dir()
    with h5py.File(plain) as f:
        assert dict(f.attrs) == {"owner": "someone else"}
    ours = tmp_path / "ours.hdf5"
    for flags in ((), ("--overwrite",)):
        r = _cli("export", run, "--out", ours, "--data", root / "demos", *flags)
        assert r.exit_code == 0, r.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["folder.hdf5", "notes.hdf5", "ours.hdf5", "plain.h5"]


def test_unreproduced_run_is_refused_and_no_partial_file(root, tmp_path) -> None:
    """A run whose rollout.npz the replay here does not reproduce is refused, naming its folder; the file being
    written is removed (nothing partial, no temporary file left)."""
    runs = tmp_path / "runs"
    shutil.copytree(root / "runs" / "cube_lift" / "kinematic", runs / "a_good")
    bad = runs / "b_bad"
    shutil.copytree(root / "runs" / "cube_lift" / "kinematic", bad)
    z = dict(np.load(bad / "rollout.npz"))
    z["object_pos"][5, 2] += 1e-3
    np.savez_compressed(bad / "rollout.npz", **z)
    _remanifest(bad)
    out = tmp_path / "out" / "t.hdf5"
    r = _cli("export", runs, "--out", out, "--data", root / "demos")
    assert r.exit_code == 2, r.output
    assert f"{bad}: expected a run whose controls replay in MuJoCo to its recorded rollout.npz" in r.output
    assert "object_pos off by 0.001 from frame 5" in r.output
    assert not out.exists() and list(out.parent.iterdir()) == []


def test_import_stays_light() -> None:
    code = "import sys, quasisim.data.dataset; sys.exit(bool({'h5py', 'mujoco', 'jax'} & set(sys.modules)))"
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


def test_closed_loop_episodes_are_marked_and_replay_exactly(root, tmp_path) -> None:
    """``--closed-loop 2``: after each run's episode, two episodes of the tracker in robust replays 0 and 1's
    perturbed worlds, each replaying in its own MJCF (the perturbed world's) to its stored states, marked with
    its world's parameters, holding the targets the tracker applied."""
    import h5py
    import mujoco

    from quasisim.data.controls import load_controls
    from quasisim.data.dataset import REPLAY_TOL, load_episodes, replay_check
    from quasisim.eval.robust import replays

    out = tmp_path / "cl.hdf5"
    run = root / "runs" / "cube_lift" / "kinematic"
    r = _cli("export", run, "--out", out, "--data", root / "demos", "--closed-loop", "2")
    assert r.exit_code == 0, r.output
    eps = list(load_episodes(out))
    assert [ep.attrs["closed_loop"] for ep in eps] == [False, True, True]
    devs = replay_check(out)
    assert max(devs.values()) <= REPLAY_TOL, devs

    def object_mass(ep) -> float:
        m = mujoco.MjModel.from_xml_string(ep.model_file)
        return float(m.body_mass[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "object")])

    cfg, m0 = replays(2), object_mass(eps[0])
    plan = load_controls(run / "controls.npz").q_targets
    for i, ep in enumerate(eps[1:]):
        u = np.random.default_rng([cfg.seed, i]).uniform(-1.0, 1.0, size=5)
        assert ep.attrs["world_index"] == i and ep.attrs["world_ranges"] == "robust"
        assert ep.attrs["world"]["object_mass"] == pytest.approx(m0 * (1 + cfg.mass * u[0]))
        assert object_mass(ep) == pytest.approx(ep.attrs["world"]["object_mass"])  # the MJCF is the world's
        assert ep.attrs["tracker"]["every"] >= 1 and ep.actions.shape == eps[0].actions.shape
        assert np.abs(ep.actions - plan[1:]).max() > 1e-4  # the tracker's targets (shifted at least)
    with h5py.File(out) as f:
        assert sorted(f["mask/closed_loop"][:].astype(str).tolist()) == ["demo_1", "demo_2"]
