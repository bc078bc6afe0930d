"""``quasisim export``: finished runs (of ``batch``, ``transfer``, ``bench transfer``) into one HDF5 training
set in robomimic's layout (docs/dataset.md; read it back with :mod:`quasisim.data.dataset`).

Per run: its controls are rolled out again in the MuJoCo target on the scene rebuilt from its demo (the code
path of ``quasisim evaluate``), which must reproduce the run's ``rollout.npz``; that rollout gives the
observations and, at every frame, MuJoCo's state (``mj_getState``, :data:`STATE_SPEC`). The scene goes into
the file as full-precision MJCF (:func:`quasisim.data.mjcf.exact_mjcf`): the run folder's ``scene.xml`` rounds
to 6 digits, and a replay in it drifts off the run by millimetres.
"""

from __future__ import annotations

import dataclasses
import datetime
import hashlib
import json
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from quasisim.data.controls import Controls, load_controls
from quasisim.data.dataset import FORMAT, OBS_KEYS
from quasisim.data.demo import Demo
from quasisim.data.run_demo import RunDemos
from quasisim.errors import InputError, QuasisimError
from quasisim.files import MANIFEST, atomic_path, open_npz, read_manifest
from quasisim.targets.base import pd_schedule
from quasisim.targets.mujoco_target import MujocoTarget, build_spec, dof_names
from quasisim.targets.scene import Scene

ONLY = {"strict": "strict", "20": "20deg_20cm", "any": None}  # --only -> the metrics.json success key it needs
SUCCESS_FLAGS = ("strict", "20deg_20cm")
RUN_FILES = ("controls.npz", "metrics.json", "rollout.npz", "scene.xml")
SKIP_DIRS = ("checkpoints",)
REPRODUCE_TOL = 1e-6  # m, rad: the replay here against the run's rollout.npz (bit-equal on the same machine)
STATE_SPEC = int(mujoco.mjtState.mjSTATE_FULLPHYSICS | mujoco.mjtState.mjSTATE_WARMSTART)
COMPRESSION = {"compression": "gzip", "compression_opts": 4, "shuffle": True}


@dataclass(frozen=True, eq=False)
class RunInput:
    """A finished run folder, read and checked: ``rel`` its path below the export root."""

    path: Path
    rel: str
    controls: Controls
    metrics: dict[str, Any]
    settings: dict[str, Any]
    rollout: dict[str, np.ndarray]

    @property
    def label(self) -> str:
        return self.rel if self.rel != "." else self.path.name


@dataclass
class ExportResult:
    """What an export wrote: one ``(episode, run, samples)`` per episode (the HDF5 demo group, or LeRobot's
    ``episode_<index>``), skipped runs and why, and for a LeRobot export its read-back ``check``."""

    out: Path
    episodes: list[tuple[str, str, int]] = field(default_factory=list)
    skipped: list[tuple[str, str]] = field(default_factory=list)
    seconds: float = 0.0
    check: dict[str, float] = field(default_factory=dict)

    @property
    def total(self) -> int:
        return sum(n for _, _, n in self.episodes)


# ---- finding and reading runs -------------------------------------------------------------------------


def find_runs(root: Path) -> list[Path]:
    """The finished runs (folders with ``manifest.json``) at or below ``root``, sorted; hidden folders and
    ``checkpoints`` are skipped, and a run's own subfolders are not searched."""
    if not root.is_dir():
        got = "no such folder" if not root.exists() else "a file"
        raise InputError(root, None, "a folder of finished runs (the --out of batch, transfer or bench transfer)", got)
    if (root / MANIFEST).is_file():
        return [root]
    runs: list[Path] = []
    for p in sorted(root.iterdir()):
        if p.is_dir() and not p.is_symlink() and not p.name.startswith(".") and p.name not in SKIP_DIRS:
            runs += find_runs(p)
    return runs


def finished_runs(root: Path) -> list[Path]:
    """:func:`find_runs`, or :class:`InputError` naming ``root`` when it holds no finished run."""
    paths = find_runs(root)
    if not paths:
        raise InputError(
            root, None, "finished runs below it (folders with manifest.json: batch, transfer or bench transfer outputs)",
            "none",
        )  # fmt: skip
    return paths


def _json(path: Path) -> dict[str, Any]:
    try:
        d = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise InputError(path, None, "a readable JSON object", " ".join(str(e).split())) from None
    if not isinstance(d, dict):
        raise InputError(path, None, "a JSON object", type(d).__name__)
    return d


def read_run(path: Path, root: Path) -> RunInput:
    """Run folder ``path`` (below export root ``root``) with its files checked: :class:`InputError` naming the
    file and field otherwise."""
    for name in RUN_FILES:
        if not (path / name).is_file():
            what = (
                "controls (controls.npz of transfer or batch; evaluate's folders hold no controls)"
                if name == "controls.npz"
                else "the run's outputs"
            )
            raise InputError(path / name, None, f"a finished run with {name}: {what}", "no such file")
    if read_manifest(path) is None:
        raise InputError(
            path / MANIFEST, None, "a finished run whose files match its manifest", "files missing or changed since"
        )
    metrics = _json(path / "metrics.json")
    success = metrics.get("success")
    if not isinstance(success, dict) or any(not isinstance(success.get(k), bool) for k in SUCCESS_FLAGS):
        raise InputError(
            path / "metrics.json", "success", f"true/false flags {', '.join(SUCCESS_FLAGS)}", repr(success)[:80]
        )
    with open_npz(path / "rollout.npz", "rollout", "rollout .npz file") as z:
        rollout = {k: z[k] for k in z.files}
    target = str(rollout.get("target", ""))
    if target != "mujoco":
        raise InputError(path / "rollout.npz", "target", "'mujoco' (the dataset's states are MuJoCo's)", repr(target))
    settings = _json(path / "summary.json") if (path / "summary.json").is_file() else {}
    settings = {k: v for k, v in settings.items() if k not in ("metrics", "kinematic_metrics")}
    rel = path.relative_to(root).as_posix() if path != root else "."
    return RunInput(path, rel, load_controls(path / "controls.npz"), metrics, settings, rollout)


def skip_reason(run: RunInput, only: str, min_robust: float | None) -> str | None:
    """Why ``run`` is left out (``--only``, ``--min-robust``, an unstable simulation), or None. ``--min-robust``
    applies to the robust success of ``--only``'s criterion (20deg_20cm for ``any``)."""
    m = run.metrics
    key = ONLY[only]
    if key is not None and not m["success"][key]:
        return f"not {key}"
    if m.get("unstable", False):
        return "unstable simulation"
    if min_robust is not None:
        rkey = key or "20deg_20cm"
        if run.metrics["robust"][rkey] < min_robust:
            return f"robust {rkey} {run.metrics['robust'][rkey]:.2f} < {min_robust:g}"
    return None


def check_robust(run: RunInput) -> None:
    """``--min-robust`` needs robust success in every run's metrics.json."""
    robust = run.metrics.get("robust")
    if not isinstance(robust, dict) or any(not isinstance(robust.get(k), int | float) for k in SUCCESS_FLAGS):
        raise InputError(
            run.path / "metrics.json", "robust",
            "robust success fractions for --min-robust (evaluate or transfer with --robust N, N > 0)", "missing",
        )  # fmt: skip


def select_runs(root: Path, only: str, min_robust: float | None) -> tuple[list[RunInput], list[tuple[str, str]]]:
    """The finished runs at or below ``root`` that pass the filters (``only``: a key of :data:`ONLY`;
    ``min_robust``: a minimum robust success), read and checked, and ``(label, why)`` of those left out;
    :class:`InputError` when none passes."""
    if only not in ONLY:
        raise InputError(None, "--only", f"one of {', '.join(ONLY)}", repr(only))
    runs = [read_run(p, root) for p in finished_runs(root)]
    if min_robust is not None:
        for r in runs:
            check_robust(r)
    keep, skipped = [], []
    for r in runs:
        why = skip_reason(r, only, min_robust)
        (skipped.append((r.label, why)) if why else keep.append(r))
    if not keep:
        want = f"--only {only}" + ("" if min_robust is None else f" --min-robust {min_robust:g}")
        raise InputError(root, None, f"at least one run that passes {want}",
                         f"none of {len(runs)} ({'; '.join(f'{a}: {b}' for a, b in skipped[:5])})")  # fmt: skip
    return keep, skipped


# ---- one episode ----------------------------------------------------------------------------------------


def _recorder(scene: Scene) -> MujocoTarget:
    """The MuJoCo target of ``scene`` that also keeps, at every :meth:`observe`, the observation and the state
    (a :meth:`sync` replaces the state just observed: its record is dropped, the next observation keeps it)."""

    class Recording(MujocoTarget):
        frames: list[dict[str, np.ndarray]]
        states: list[np.ndarray]

        def observe(self) -> dict[str, np.ndarray]:
            o = super().observe()
            s = np.zeros(mujoco.mj_stateSize(self.mm.model, STATE_SPEC))
            mujoco.mj_getState(self.mm.model, self.data, s, STATE_SPEC)
            self.frames.append(o)
            self.states.append(s)
            return o

        def sync(self, obs: dict[str, np.ndarray]) -> None:
            super().sync(obs)
            self.frames.pop()
            self.states.pop()

    tgt = Recording(scene)
    tgt.frames, tgt.states = [], []
    return tgt


def _reproduced(run: RunInput, rollout: Any, scene_matches: bool) -> None:
    """Refuse a run whose controls do not replay to its recorded ``rollout.npz`` here."""
    z = run.rollout
    pairs = [("object_pos", rollout.object_pos), ("object_quat", rollout.object_quat), ("qpos", rollout.qpos),
             ("all_keypoints", rollout.keypoints)]  # fmt: skip
    for key, got in pairs:
        if key not in z:
            continue
        want = np.asarray(z[key], np.float64)
        dev = np.abs(got - want).reshape(len(got), -1).max(axis=1) if got.shape == want.shape else None
        if dev is None or dev.max() > REPRODUCE_TOL:
            where = (
                f"shape {got.shape} vs {want.shape}"
                if dev is None
                else f"{dev.max():.3g} from frame {int(np.argmax(dev > REPRODUCE_TOL))}"
            )
            hint = (
                ""
                if scene_matches
                else "; its scene.xml differs from the scene rebuilt here (another quasisim, MuJoCo or numpy version?)"
            )
            raise InputError(
                run.path, None,
                f"a run whose controls replay in MuJoCo to its recorded rollout.npz (within {REPRODUCE_TOL:g})",
                f"{key} off by {where}{hint}",
            )  # fmt: skip


def record_episode(run: RunInput, demo: Demo, scene: Scene | None = None) -> dict[str, Any]:
    """The episode of ``run`` (made from ``demo``; ``scene``: its nominal scene, :func:`run_scene`, where the
    caller has it): ``obs``, ``next_obs`` (dicts), the arrays of :data:`~quasisim.data.dataset.ARRAYS` and
    ``attrs``, from a rollout of its controls in the MuJoCo target."""
    c = run.controls
    scene = scene or run_scene(run, demo)
    spec = build_spec(scene, visual=True)
    run_xml, xml6 = (run.path / "scene.xml").read_text(), spec.to_xml()
    with _recorder(scene) as tgt:
        rollout = tgt.rollout(c.q_targets)
    _reproduced(run, rollout, xml6 == run_xml)
    return _episode(run, demo, spec, tgt, c.q_targets, rollout, run.metrics, run_xml, {}, xml6)


def run_scene(run: RunInput, demo: Demo) -> Scene:
    """The nominal scene of ``run`` rebuilt from its demo (its controls checked against both)."""
    from quasisim.eval.evaluate import check_controls, hands_of
    from quasisim.targets.build import scene_for
    from quasisim.targets.scene import place_hands

    c, cpath = run.controls, run.path / "controls.npz"
    hands = hands_of(c, cpath)
    check_controls(demo, c, hands, cpath)
    return scene_for(demo, place_hands(hands, c.base_rots))


def record_closed_loop_episode(
    run: RunInput, demo: Demo, scene: Scene, cfg: Any, i: int, policy: Any, run_xml: str
) -> dict[str, Any]:
    """Closed-loop episode ``i`` of ``run``: the tracker ``policy()`` (:func:`quasisim.method.track.closed_loop`,
    built from the nominal ``scene``) drives robust replay ``i``'s perturbed world (``cfg``, a
    :class:`~quasisim.eval.robust.RobustConfig` without a push); the actions are the targets it applied. Checked:
    the applied targets replayed open loop in the same world reproduce the episode's states. ``run_xml``: the
    run's ``scene.xml``."""
    from quasisim.eval.evaluate import mark_stability
    from quasisim.eval.metrics import evaluate_rollout
    from quasisim.eval.robust import perturbed_scene, replay

    world = perturbed_scene(scene, cfg, i)
    q, fps = run.controls.q_targets, scene.fps
    logged = _Logged(policy(), q[0])
    with _recorder(world) as tgt:
        rollout = replay(tgt, q, logged)
    logged.inner.close()
    applied = np.array(logged.actions)
    with _recorder(world) as again:
        replay(again, applied, qd0=(q[1] - q[0]) * fps)
    dev = np.abs(np.array(again.states) - np.array(tgt.states)).max()  # type: ignore[attr-defined]
    if not dev <= REPRODUCE_TOL:
        raise QuasisimError(f"{run.path}: closed-loop episode {i} does not replay open loop in its world ({dev:.3g})")
    metrics, _ = evaluate_rollout(demo, rollout, None)
    metrics = mark_stability(metrics, rollout.instability, f"{demo.name} closed-loop episode {i}")
    spec = build_spec(world, visual=True)
    extra = {
        "closed_loop": True, "world_index": i, "world_seed": cfg.seed, "world_ranges": cfg.name,
        "world": {"object_mass": float(world.obj.mass), "friction": float(world.physics.friction),
                  "gain_scale": float(world.physics.gain_scale), "object_pos0": world.object_pos0.tolist()},
        "tracker": {k: v for k, v in dataclasses.asdict(logged.inner.opts).items() if k != "path"},
    }  # fmt: skip
    return _episode(run, demo, spec, tgt, applied, rollout, metrics, run_xml, extra)


class _Logged:
    """A policy that keeps the PD targets it applied (frame 0: the plan's first)."""

    def __init__(self, inner: Any, q0: np.ndarray) -> None:
        self.inner, self.actions = inner, [np.asarray(q0, np.float64)]

    def start(self, obs: dict[str, np.ndarray]) -> None:
        self.inner.start(obs)

    def act(self, t: int, obs: dict[str, np.ndarray]) -> np.ndarray:
        self.actions.append(np.asarray(self.inner.act(t, obs), np.float64).copy())
        return self.actions[-1]


def _episode(
    run: RunInput, demo: Demo, spec: Any, rec: MujocoTarget, q: np.ndarray, rollout: Any, metrics: dict[str, Any],
    run_xml: str, extra: dict[str, Any], xml: str | None = None,
) -> dict[str, Any]:  # fmt: skip
    """An episode's arrays and attributes from the recorder ``rec`` (:func:`_recorder`) that ran the PD targets
    ``q`` (T, D) in its scene, built from ``spec`` (``xml``: its ``to_xml()`` where the caller has it)."""
    from quasisim.data.mjcf import exact_mjcf

    scene, mm, n, model = rec.scene, rec.mm, rec.substeps, spec.compile()
    frames, states = rec.frames, np.array(rec.states)  # type: ignore[attr-defined]
    if (model.nq, model.nv, model.na, model.nu) != (mm.model.nq, mm.model.nv, mm.model.na, mm.model.nu):
        raise QuasisimError(f"{run.path}: the exported scene's layout differs from the target's model")
    fps = scene.fps
    substep, velocity = pd_schedule(q[:-1], q[1:], n, fps)
    per_frame = {
        "hand_qpos": rollout.qpos, "hand_qvel": np.array([f["qvel"] for f in frames]), "pd_target": q,
        "object_pos": rollout.object_pos, "object_quat": rollout.object_quat,
        "object_linvel": np.array([f["obj_vel"] for f in frames]),
        "object_angvel": np.array([f["obj_angvel"] for f in frames]), "robot_keypoints": rollout.keypoints,
        "ref_hand_keypoints": demo.human_joints, "ref_object_pos": demo.object_pos, "ref_object_quat": demo.object_quat,
    }  # fmt: skip
    N = len(q) - 1
    attrs = _episode_attrs(run, demo, scene, model, mm, n, exact_mjcf(spec, model, xml), run_xml, N, metrics)
    return {
        "obs": {k: per_frame[k][:-1] for k in OBS_KEYS},
        "next_obs": {k: per_frame[k][1:] for k in OBS_KEYS},
        "actions": q[1:], "actions_substep": substep, "actions_velocity": velocity,
        "states": states[:-1], "final_state": states[-1],
        "rewards": np.zeros(N), "dones": (np.arange(N) == N - 1).astype(np.int64),
        "attrs": attrs | extra,
    }  # fmt: skip


def run_episodes(run: RunInput, demo: Demo, closed_loop: int, scene: Scene | None = None) -> Any:
    """``run``'s episode, then its ``closed_loop`` closed-loop episodes (a generator: one in memory at a time);
    ``scene``: the run's nominal scene (:func:`run_scene`) where the caller has it."""
    scene = scene or run_scene(run, demo)
    yield record_episode(run, demo, scene)
    if closed_loop:
        from quasisim.eval.robust import replays
        from quasisim.method.track import closed_loop as tracker

        policy = tracker()(demo, scene, run.controls.q_targets, "mujoco")
        cfg, run_xml = replays(closed_loop), (run.path / "scene.xml").read_text()
        for i in range(closed_loop):
            yield record_closed_loop_episode(run, demo, scene, cfg, i, policy, run_xml)


def _state_layout(model: Any) -> list[list[Any]]:
    """``[name, size]`` of each part of a :data:`STATE_SPEC` state vector, in order (parts of size 0 left out)."""
    out, bit = [], 1
    while bit <= STATE_SPEC:
        if STATE_SPEC & bit and mujoco.mj_stateSize(model, bit):
            out.append([mujoco.mjtState(bit).name.removeprefix("mjSTATE_").lower(), mujoco.mj_stateSize(model, bit)])
        bit <<= 1
    return out


def _episode_attrs(
    run: RunInput, demo: Demo, scene: Scene, model: Any, mm: Any, n: int, xml: str, run_xml: str, N: int,
    m: dict[str, Any],
) -> dict[str, Any]:  # fmt: skip
    """The attributes of an episode's group (docs/dataset.md); ``m``: the episode's metrics."""
    c = run.controls
    names = dof_names(scene)
    pd = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, f"pd/{j}") for j in names]
    ff = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, f"ff/{j}") for j in names]
    if pd != mm.pd_act.tolist() or ff != mm.ff_act.tolist():
        raise QuasisimError(f"{run.path}: the exported scene's actuators differ from the target's")
    robust = m.get("robust") or {}
    attrs: dict[str, Any] = {
        "num_samples": N, "clip": demo.name, "run": run.rel, "hand": c.hand, "hands": [h.name for h in scene.hands],
        "sides": list(scene.sides), "method": c.method, "target": "mujoco", "metrics": m, "settings": run.settings,
        "closed_loop": False,
        "success": m["success"], **{f"success_{k}": bool(m["success"][k]) for k in SUCCESS_FLAGS},
        **{f"robust_{k}": float(robust[k]) for k in SUCCESS_FLAGS if k in robust},
        "unstable": bool(m.get("unstable", False)), "fps": float(scene.fps), "dt": float(model.opt.timestep),
        "substeps": n, "demo_hash": c.demo_hash, "demo_file": str(demo.path or ""), "model_file": xml,
        "scene_xml_sha256": hashlib.sha256(run_xml.encode()).hexdigest(), "dof_names": names,
        "keypoint_names": [p + k for h, p in zip(scene.hands, scene.prefixes, strict=True) for k in h.kp_names],
        "kp_human": scene.kp_human.astype(np.int64), "kp_metric": scene.kp_metric.astype(bool),
        "pd_actuators": np.array(pd, np.int64), "ff_actuators": np.array(ff, np.int64),
        "hand_qpos_adr": mm.hand_qpos.astype(np.int64), "hand_dof_adr": mm.hand_dof.astype(np.int64),
        "object_qpos_adr": int(mm.obj_qpos), "object_dof_adr": int(mm.obj_dof),
        "state_spec": STATE_SPEC, "state_layout": _state_layout(model),
    }  # fmt: skip
    return attrs


# ---- replacing --out ---------------------------------------------------------------------------------------


def check_replace(
    out: Path, inputs: Sequence[Path], overwrite: bool, new: str, what: str, why_not: Callable[[Path], str | None]
) -> None:
    """Refuse (:class:`InputError` naming ``out`` and ``--out``) an existing ``out`` that is or holds one of
    ``inputs``, that ``overwrite`` is not given for, or that is not ``what`` quasisim export wrote (``why_not``:
    why a path is not, or None); a new ``out`` passes. ``new``: what a new ``out`` is ("a new file")."""
    out = Path(out)
    if not out.exists() and not out.is_symlink():
        return
    own = f"{what} that quasisim export wrote"
    o = Path(os.path.realpath(out))
    for p in inputs:
        q = Path(os.path.realpath(p))
        if q == o or o in q.parents:
            got = f"{'the input' if q == o else 'a folder holding the input'} {p}"
            raise InputError(out, "--out", f"{new} or {own}, not an input or a folder holding one", got)
    if not overwrite:
        raise InputError(out, "--out", f"{new} (pass --overwrite to replace {own})", "an existing path")
    why = why_not(out)
    if why is not None:
        raise InputError(out, "--out", f"{own}, to replace with --overwrite", why)


def not_a_dataset(path: Path) -> str | None:
    """Why ``path`` is not an HDF5 dataset file that quasisim export wrote (its ``format``), or None."""
    import h5py

    if path.is_symlink() or not path.is_file():
        return "a symbolic link" if path.is_symlink() else "a folder" if path.is_dir() else "not a regular file"
    try:
        with h5py.File(path, "r") as f:
            fmt, data = f.attrs.get("format"), "data" in f
    except OSError:
        return "a file that is not HDF5"
    return None if fmt == FORMAT and data else f"an HDF5 file of format {fmt!r}"


def check_out(out: Path, inputs: Sequence[Path], overwrite: bool) -> None:
    """Refuse ``--out`` unless it is a new file, or (``overwrite``) an HDF5 dataset that quasisim export wrote
    and not one of ``inputs`` (:func:`check_replace`)."""
    check_replace(out, inputs, overwrite, "a new file", "an HDF5 dataset", not_a_dataset)


# ---- the file ----------------------------------------------------------------------------------------------


def _attr(v: Any) -> Any:
    """An attribute value as HDF5 holds it: dicts and lists as JSON text."""
    return json.dumps(v) if isinstance(v, dict | list) else v


def _write_episode(g: Any, ep: dict[str, Any]) -> None:
    for part in ("obs", "next_obs"):
        for k, a in ep[part].items():
            g.create_dataset(f"{part}/{k}", data=np.asarray(a, np.float64), **COMPRESSION)
    for k in ("actions", "actions_substep", "actions_velocity", "states", "rewards"):
        g.create_dataset(k, data=np.asarray(ep[k], np.float64), **COMPRESSION)
    g.create_dataset("final_state", data=np.asarray(ep["final_state"], np.float64))
    g.create_dataset("dones", data=ep["dones"])
    for k, v in ep["attrs"].items():
        g.attrs[k] = _attr(v)


def _batch_meta(root: Path) -> dict[str, Any]:
    """``batch.json`` of the export root without its rows (the batch's settings), or {}."""
    b = root / "batch.json"
    return {k: v for k, v in _json(b).items() if k not in ("rows", "failures")} if b.is_file() else {}


def _root_attrs(
    root: Path, only: str, min_robust: float | None, fps: list[float], dts: list[float], closed_loop: int
) -> dict[str, Any]:
    from quasisim import __version__

    env_kwargs = {"target": "mujoco", "scene": "per episode: attribute model_file (MJCF)",
                  "actions": "PD position targets (docs/dataset.md)"}  # fmt: skip
    if len(set(fps)) == 1:
        env_kwargs["fps"] = fps[0]
    if len(set(dts)) == 1:
        env_kwargs["dt"] = dts[0]
    return {
        "file": {
            "format": FORMAT, "quasisim_version": __version__, "mujoco_version": mujoco.__version__,
            "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"), "source": str(root),
            "settings": {"only": only, "min_robust": min_robust, "closed_loop": closed_loop, "batch": _batch_meta(root)},
        },
        "data": {"env_args": {"env_name": "quasisim-mujoco", "type": None, "env_kwargs": env_kwargs}},
    }  # fmt: skip


def export_dataset(
    root: Path, out: Path, only: str = "any", min_robust: float | None = None, data_dirs: tuple[Path, ...] = (),
    progress: bool = True, closed_loop: int = 0,
) -> ExportResult:  # fmt: skip
    """Write the finished runs at or below ``root`` that pass the filters (``only``: a key of :data:`ONLY`;
    ``min_robust``: a minimum robust success) to the HDF5 file ``out``, atomically (a failure leaves no file).
    ``closed_loop``: per run, also that many closed-loop episodes in the perturbed worlds of robust success
    (``configs/robust.yaml``'s ranges, replays 0..N-1; :func:`record_closed_loop_episode`)."""
    import h5py
    from tqdm import tqdm

    t0 = time.perf_counter()
    root = Path(root)
    keep, skipped = select_runs(root, only, min_robust)
    res = ExportResult(Path(out), skipped=skipped)
    demos = RunDemos(tuple(data_dirs), root)
    fps, dts = [], []
    bar = tqdm(total=len(keep), desc="export", unit="run", disable=None if progress else True, leave=False)
    with bar, atomic_path(out) as tmp, h5py.File(tmp, "w", libver="v108") as f:
        data, mask = f.create_group("data"), {k: [] for k in (*SUCCESS_FLAGS, "closed_loop")}
        for r in keep:
            bar.set_postfix_str(r.label)
            for ep in run_episodes(r, demos.find(r.path), closed_loop):
                name = f"demo_{len(res.episodes)}"
                _write_episode(data.create_group(name), ep)
                res.episodes.append((name, r.label, ep["attrs"]["num_samples"]))
                fps.append(ep["attrs"]["fps"])
                dts.append(ep["attrs"]["dt"])
                for k in SUCCESS_FLAGS:
                    if ep["attrs"][f"success_{k}"]:
                        mask[k].append(name)
                if ep["attrs"]["closed_loop"]:
                    mask["closed_loop"].append(name)
            bar.update(1)
        for k, names in mask.items():
            f.create_dataset(f"mask/{k}", data=np.array(names, dtype="S"))
        attrs = _root_attrs(root, only, min_robust, fps, dts, closed_loop)
        for k, v in attrs["file"].items():
            f.attrs[k] = _attr(v)
        data.attrs["total"] = res.total
        data.attrs["env_args"] = _attr(attrs["data"]["env_args"])
    res.seconds = time.perf_counter() - t0
    return res
