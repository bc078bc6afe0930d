"""Training sets of judged runs: the robomimic HDF5 layout that ``quasisim export`` writes (docs/dataset.md),
read back as episodes (:func:`load_episodes`) and replayed in MuJoCo (:func:`replay_check`).

One episode per exported run, ``N = T - 1`` samples (one per control frame that is advanced): ``obs`` at frames
``0 .. T-2``, ``next_obs`` at ``1 .. T-1``, ``actions[t]`` the PD target the frame ends at. Every array is
float64, SI units (m, rad, s), quaternions w x y z. h5py and MuJoCo load inside the functions that use them
(``import quasisim.data.dataset`` costs numpy only).
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from quasisim.errors import InputError

FORMAT = "quasisim-dataset-v1"
REPLAY_TOL = 1e-9  # max |state difference| of a replay that reproduces an episode
OBS_KEYS = (
    "hand_qpos", "hand_qvel", "pd_target", "object_pos", "object_quat", "object_linvel", "object_angvel",
    "robot_keypoints", "ref_hand_keypoints", "ref_object_pos", "ref_object_quat",
)  # fmt: skip
ARRAYS = ("actions", "actions_substep", "actions_velocity", "states", "final_state", "rewards", "dones")
JSON_ATTRS = (
    "metrics",
    "settings",
    "sides",
    "hands",
    "dof_names",
    "keypoint_names",
    "state_layout",
    "success",
    "env_args",
    "world",
    "tracker",
)


@dataclass(frozen=True, eq=False)
class Episode:
    """One exported run (N samples; D control dofs, K robot keypoints, S state numbers, n physics steps per frame).

    Attributes:
        name: the HDF5 group, ``demo_<i>``.
        obs, next_obs: :data:`OBS_KEYS` -> (N, ...) at frames ``0 .. N-1`` and ``1 .. N``.
        actions: (N, D) the PD target each frame ends at. actions_substep: (N, n, D) the PD target of each
            physics step. actions_velocity: (N, D) the fed-forward target velocity of each frame.
        states: (N, S) MuJoCo state at each frame (``attrs["state_spec"]``). final_state: (S,) after the last.
        rewards, dones: (N,) zeros; ``dones[-1] = 1``.
        attrs: the group's attributes (JSON ones decoded, numpy scalars as Python values).
    """

    name: str
    obs: dict[str, np.ndarray]
    next_obs: dict[str, np.ndarray]
    actions: np.ndarray
    actions_substep: np.ndarray
    actions_velocity: np.ndarray
    states: np.ndarray
    final_state: np.ndarray
    rewards: np.ndarray
    dones: np.ndarray
    attrs: dict[str, Any]

    @property
    def num_samples(self) -> int:
        return int(self.actions.shape[0])

    @property
    def clip(self) -> str:
        return str(self.attrs["clip"])

    @property
    def model_file(self) -> str:
        """The MJCF of the episode's scene (full precision: it compiles to the model the states come from)."""
        return str(self.attrs["model_file"])


def _value(key: str, v: Any) -> Any:
    if key in JSON_ATTRS and isinstance(v, str):
        return json.loads(v)
    if isinstance(v, bytes):
        return v.decode()
    if isinstance(v, np.generic):
        return v.item()
    return v


def _open(path: str | Path) -> Any:
    """The dataset file opened for reading; :class:`InputError` naming it when it is not one."""
    import h5py

    path = Path(path)
    if not path.is_file():
        raise InputError(path, None, "a dataset file written by quasisim export", "no such file")
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise InputError(path, None, "an HDF5 dataset written by quasisim export", f"unreadable ({e})") from None
    fmt = f.attrs.get("format")
    if fmt != FORMAT or "data" not in f:
        f.close()
        raise InputError(path, "format", f"'{FORMAT}' (and a 'data' group)", repr(fmt))
    return f


def episode_names(f: Any, filter_key: str | None = None) -> list[str]:
    """The demo groups of open file ``f`` in index order (``demo_0, demo_1, ...``), or those of ``mask/<filter_key>``."""
    if filter_key is None:
        names = list(f["data"].keys())
    else:
        if f"mask/{filter_key}" not in f:
            keys = ", ".join(f["mask"].keys()) if "mask" in f else "none"
            raise InputError(f.filename, "mask", f"a filter key of the file ({keys})", repr(filter_key))
        names = [n.decode() if isinstance(n, bytes) else str(n) for n in f[f"mask/{filter_key}"][()]]
    return sorted(names, key=lambda n: int(n.split("_")[-1]))


def read_episode(f: Any, name: str) -> Episode:
    """Episode ``name`` (``demo_<i>``) of open file ``f``."""
    g = f[f"data/{name}"]
    arrays = {k: np.asarray(g[k][()]) for k in ARRAYS}
    return Episode(
        name=name,
        obs={k: np.asarray(v[()]) for k, v in g["obs"].items()},
        next_obs={k: np.asarray(v[()]) for k, v in g["next_obs"].items()},
        attrs={k: _value(k, v) for k, v in g.attrs.items()},
        **arrays,
    )


def load_episodes(path: str | Path, filter_key: str | None = None) -> Iterator[Episode]:
    """The episodes of dataset ``path`` one at a time (all, or those of ``mask/<filter_key>``, e.g. ``strict``)."""
    with _open(path) as f:
        for name in episode_names(f, filter_key):
            yield read_episode(f, name)


def file_attrs(path: str | Path) -> dict[str, Any]:
    """The file's own attributes (``format``, ``settings``, versions) and ``data``'s (``total``, ``env_args``)."""
    with _open(path) as f:
        out = {k: _value(k, v) for k, v in f.attrs.items()}
        out.update({k: _value(k, v) for k, v in f["data"].attrs.items()})
    return out


# ---- replay ------------------------------------------------------------------------------------------


def replay_states(
    model: Any, state0: np.ndarray, substep: np.ndarray, velocity: np.ndarray, pd_act: np.ndarray,
    ff_act: np.ndarray, spec: int,
) -> np.ndarray:  # fmt: skip
    """(N + 1, S) the states of a replay in ``model`` from ``state0`` (``mj_getState`` layout ``spec``): per frame
    ``t`` the feed-forward actuators ``ff_act`` get ``velocity[t]`` (D,), then for each physics step ``k`` the PD
    actuators ``pd_act`` get ``substep[t, k]`` (D,) and MuJoCo steps once (as the MuJoCo target advances)."""
    import mujoco

    data = mujoco.MjData(model)
    mujoco.mj_setState(model, data, np.asarray(state0, np.float64), spec)
    out = np.zeros((len(substep) + 1, len(state0)))
    mujoco.mj_getState(model, data, out[0], spec)
    for t in range(len(substep)):
        data.ctrl[ff_act] = velocity[t]
        for pd in substep[t]:
            data.ctrl[pd_act] = pd
            mujoco.mj_step(model, data)
        mujoco.mj_getState(model, data, out[t + 1], spec)
    return out


def replay_episode(ep: Episode) -> np.ndarray:
    """(N + 1,) max |difference| between the stored states (and the final one) and a replay of the episode's
    per-step actions in its own MJCF from its first state."""
    import mujoco

    model = mujoco.MjModel.from_xml_string(ep.model_file)
    a = ep.attrs
    got = replay_states(model, ep.states[0], ep.actions_substep, ep.actions_velocity,
                        np.asarray(a["pd_actuators"]), np.asarray(a["ff_actuators"]), int(a["state_spec"]))  # fmt: skip
    want = np.concatenate([ep.states, ep.final_state[None]])
    return np.abs(got - want).max(axis=1)


def replay_check(path: str | Path) -> dict[str, float]:
    """Per episode (``demo_<i>``) of dataset ``path``, the max state deviation of its replay
    (:func:`replay_episode`); an exact file gives 0 everywhere (:data:`REPLAY_TOL`)."""
    return {ep.name: float(replay_episode(ep).max()) for ep in load_episodes(path)}
