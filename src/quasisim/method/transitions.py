"""Recorded transitions as windows: the data a world model is fitted on and measured with.

``quasisim transfer --record-transitions`` keeps every window the sampling stage rolled out in the target
(format ``quasisim-transitions-v1``, ``docs/transfer.md``). :func:`load_clip` turns one such file into
:class:`ClipWindows`: ``B`` windows of ``H`` frames, each with the target's state at its start and at each of
its frames and the PD targets it applied. Two kinds of windows:

* ``final``: windows of the trajectory the run applied (``applied`` and ``run_*``), starting at every frame
  with ``H`` frames after it (any ``H``, e.g. the sampling horizon 6 and 10);
* ``sampled``: the candidate windows of the control loop (``H`` is the recorded horizon): the chosen one and
  ``per_step - 1`` others drawn at random per step (fixed seed).

:data:`HELD_OUT` is the fixed split of the 25 GRAB development clips: whole clips that a world model is never
trained on (all three clips of one object, the flashlight, and three clips of objects seen in training).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from quasisim.data.demo import load_demo
from quasisim.errors import InputError
from quasisim.files import npz_array, npz_number, npz_str, open_npz
from quasisim.method.problem import Problem, make_problem
from quasisim.method.stages.sampling import STATE_KEYS, TRANSITIONS_FORMAT
from quasisim.targets.build import demo_hands
from quasisim.targets.scene import place_hands

HELD_OUT = (
    "grab_s1_flashlight_lift",
    "grab_s1_flashlight_on_1",
    "grab_s1_flashlight_on_2",
    "grab_s1_apple_pass_1",
    "grab_s1_cup_pour_1",
    "grab_s1_mug_drink_4",
)
KINDS = ("final", "sampled")
WINDOW_ARRAYS = ("q_targets", *STATE_KEYS, "keypoints")  # the per-window arrays of ClipWindows (leading axis B)


@dataclass(frozen=True, eq=False)
class ClipWindows:
    """``B`` windows of one clip's recorded transitions (frame 0 is each window's start).

    Attributes:
        demo: the demo's name.  kind: ``final`` or ``sampled`` (module docstring).  fps: frames per second.
        prob: the clip's scene and quasi-physical simulator (hands on the recorded base frames).
        q_targets: (B, H + 1, D) PD targets.  qpos, qvel: (B, H + 1, D) the target's hands.
        obj_pos, obj_quat: (B, H + 1, 3 | 4) object frame origin (world, m) and orientation (w x y z).
        obj_vel, obj_angvel: (B, H + 1, 3) object centre-of-mass velocity and angular velocity (world).
        keypoints: (B, H + 1, K, 3) the target's metric keypoints; ``kp_index`` (K,) their indices among the
            simulator's keypoints.
    """

    demo: str
    kind: str
    fps: float
    prob: Problem
    q_targets: np.ndarray
    qpos: np.ndarray
    qvel: np.ndarray
    obj_pos: np.ndarray
    obj_quat: np.ndarray
    obj_vel: np.ndarray
    obj_angvel: np.ndarray
    keypoints: np.ndarray
    kp_index: np.ndarray

    def __len__(self) -> int:
        return len(self.q_targets)

    @property
    def horizon(self) -> int:
        return self.q_targets.shape[1] - 1

    def first(self, n: int) -> ClipWindows:
        """The first ``n`` windows."""
        return dataclasses.replace(self, **{k: getattr(self, k)[:n] for k in WINDOW_ARRAYS})

    def state(self, k: int) -> dict[str, np.ndarray]:
        """The target's state at frame ``k`` of every window (keys of ``STATE_KEYS``, leading axis B)."""
        return {key: getattr(self, key)[:, k] for key in STATE_KEYS}


def read_meta(path: Path) -> tuple[str, str, float, np.ndarray]:
    """The demo's name, the hand, the fps and the base frames (H, 3, 3) of a transitions file."""
    with open_npz(path, TRANSITIONS_FORMAT, "transitions file") as z:
        fmt = npz_str(z, "format", path) if "format" in z.files else "none"
        if fmt != TRANSITIONS_FORMAT:
            raise InputError(path, "format", repr(TRANSITIONS_FORMAT), repr(fmt))
        base = npz_array(z, "base_rots", path, ("H", 3, 3))
        return npz_str(z, "demo", path), npz_str(z, "hands", path), npz_number(z, "fps", path, 1e-3), base


def clip_problem(path: Path, data_dir: Path, substeps: int, n_candidates: int, table_points: str = "hull") -> Problem:
    """The quasi-physical simulator of a transitions file's clip (its demo read from ``data_dir``), the hands
    on the recorded base frames (``table_points``: :class:`~quasisim.sim.build.SimOptions`)."""
    demo_name, hand, _, base = read_meta(path)
    demo_path = Path(data_dir) / f"{demo_name}.npz"
    if not demo_path.is_file():
        raise InputError(demo_path, None, f"the demo of {path.name} (field 'demo' = {demo_name!r})", "no such file")
    demo = load_demo(demo_path)
    hands = place_hands(demo_hands(hand, demo.sides), list(base))
    return make_problem(demo, hands, substeps, n_candidates, table_points=table_points)


def load_clip(path: Path, prob: Problem, kind: str, horizon: int = 0, per_step: int = 4, seed: int = 0) -> ClipWindows:
    """The windows of ``kind`` (:data:`KINDS`) of the transitions file ``path`` (module docstring);
    ``horizon``: frames per ``final`` window (0: the recorded horizon)."""
    if kind not in KINDS:
        raise ValueError(f"unknown kind {kind!r}; valid: {', '.join(KINDS)}")
    with open_npz(path, TRANSITIONS_FORMAT, "transitions file") as z:
        S, N, H1, _d = npz_array(z, "windows", path, ("S", "N", "H+1", "D")).shape
        arr = {
            k: np.asarray(z[k]) for k in z.files if k.startswith(("start_", "run_")) or k in (*STATE_KEYS, "keypoints")
        }
        arr |= {k: np.asarray(z[k]) for k in ("windows", "chosen", "applied", "kp_metric_index")}
    kp_index = arr["kp_metric_index"].astype(np.int64)
    if kind == "final":
        H = horizon or H1 - 1
        T = len(arr["applied"])
        if T <= H:
            raise InputError(path, "applied", f"more than {H} frames for {H}-frame windows", f"{T} frames")
        idx = np.arange(T - H)[:, None] + np.arange(H + 1)[None]  # (B, H + 1) frames of each window
        run = {k: arr[f"run_{k}"][idx] for k in STATE_KEYS}
        kp = arr["run_keypoints"][:, kp_index][idx]
        return ClipWindows(
            str(prob.demo.name), kind, float(prob.demo.fps), prob, arr["applied"][idx], **run, keypoints=kp,
            kp_index=kp_index,
        )  # fmt: skip
    rng = np.random.default_rng(seed)
    picks = []
    for s in range(S):
        c = int(arr["chosen"][s]) if arr["chosen"][s] >= 0 else 0
        others = np.setdiff1d(np.arange(N), [c])
        picks += [(s, c)] + [(s, int(n)) for n in rng.choice(others, min(per_step - 1, len(others)), replace=False)]
    s_i, n_i = (np.array(x) for x in zip(*picks, strict=True))
    return _candidates(arr, prob, s_i, n_i)


@dataclass(frozen=True)
class Steps:
    """The control loop's steps of a transitions file (``S`` steps, ``N`` candidates each).

    Attributes:
        frames: (S,) the frame each step planned from (the window covers ``frames + 1 .. frames + H``).
        costs: (S, N) every candidate's window cost, measured in the target.  chosen: (S,) the applied
            candidate (-1: none, mppi).  n_frames: frames of the clip (the applied trajectory's length).
    """

    frames: np.ndarray
    costs: np.ndarray
    chosen: np.ndarray
    n_frames: int


def load_candidates(path: Path, prob: Problem) -> tuple[ClipWindows, Steps]:
    """Every candidate window of every step of the transitions file ``path``, step by step (window
    ``s N + n`` is candidate ``n`` of step ``s``), and the steps' frames, costs and choices."""
    with open_npz(path, TRANSITIONS_FORMAT, "transitions file") as z:
        S, N, _h1, _d = npz_array(z, "windows", path, ("S", "N", "H+1", "D")).shape
        arr = {k: np.asarray(z[k]) for k in z.files}
    start = np.concatenate([arr[f"start_{k}"].reshape(S, -1) for k in ("qpos", "obj_pos", "obj_quat")], axis=1)
    frames = arr["frame"].astype(np.int64) if "frame" in arr else step_frames(start)
    s_i, n_i = np.repeat(np.arange(S), N), np.tile(np.arange(N), S)
    steps = Steps(frames, arr["costs"].astype(np.float64), arr["chosen"].astype(np.int64), len(arr["applied"]))
    return _candidates(arr, prob, s_i, n_i), steps


def step_frames(start: np.ndarray) -> np.ndarray:
    """(S,) the frame each step planned from, for files recorded before the frame was kept: ``start`` (S, F)
    is the target's state each step started from. A step plans the frame after its predecessor's, except
    after a back-up, which restores the exact state an earlier step started from (and so its frame)."""
    frames = np.zeros(len(start), np.int64)
    for s in range(1, len(start)):
        same = [p for p in range(s) if np.array_equal(start[p], start[s])]
        frames[s] = frames[same[-1]] if same else frames[s - 1] + 1
    return frames


def _candidates(arr: dict[str, np.ndarray], prob: Problem, s_i: np.ndarray, n_i: np.ndarray) -> ClipWindows:
    """The sampled windows ``(s_i, n_i)`` (steps, candidates) of a transitions file's arrays ``arr``."""
    kp_index = arr["kp_metric_index"].astype(np.int64)

    def series(key: str, start: np.ndarray) -> np.ndarray:
        return np.concatenate([start[:, None], arr[key][s_i, n_i]], axis=1)

    states = {k: series(k, arr[f"start_{k}"][s_i]) for k in STATE_KEYS if k != "qvel"}
    states["qvel"] = series("qvel", arr["start_qvel"][s_i, n_i])
    # where each step started (files made before back-ups recorded it: the applied run's frame of the step)
    start_kp = arr["start_keypoints"] if "start_keypoints" in arr else arr["run_keypoints"]
    kp = series("keypoints", start_kp[:, kp_index][s_i])
    return ClipWindows(
        str(prob.demo.name), "sampled", float(prob.demo.fps), prob, arr["windows"][s_i, n_i], **states,
        keypoints=kp, kp_index=kp_index,
    )  # fmt: skip


def transition_files(folder: Path) -> list[Path]:
    """Every transitions file under ``folder`` (``<clip>/<run>/transitions/<demo>.<method>.npz``), sorted;
    hidden folders (a batch's ``.work``) are skipped."""
    root = Path(folder)
    files = sorted(
        f for f in root.rglob("transitions/*.npz") if not any(p.startswith(".") for p in f.relative_to(root).parts)
    )
    if not files:
        raise InputError(folder, None, "a folder holding recorded transitions (*/transitions/*.npz)", "none found")
    return files
