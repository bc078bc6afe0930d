"""A world model fitted across clips: the stiffest quasi-physical simulator plus a learned correction of the
object's state after each frame, trained on what the target did (recorded transitions, :mod:`.transitions`).

Each frame of the fitted simulator is the quasi-physical frame followed by a correction:

    e = frame(model, params, s, u)                       (the analytical simulator, :func:`quasisim.sim.step.frame`)
    d = g(features(s, e))                                (12,) in the object frame at the frame's start, R = R(s)
    p+ = p_e + R d[0:3]    q+ = exp(R d[3:6]) q_e    v+ = v_e + R d[6:9]    w+ = w_e + R d[9:12]

(``p``: the object's centre of mass, ``q`` its orientation, ``v``/``w`` its twist; the hand is left as the
simulator moves it: its keypoints already follow the target's to 1-3 mm over 6 frames, see BENCHMARKS.md).
``g`` is a PointNet over the points where hand and object meet, in the object frame, so that it carries
across objects: the object surface samples and the hand's broad-phase points nearest to the contact region
(position relative to the region's centre, velocity relative to the object, outward normal, contact depth;
object and hand points tagged by a learned embedding), max- and mean-pooled, and a head that also sees the
object's twist, gravity and the table's height in the object frame and the simulator's own motion over the
frame. This is the paper's global residual acting on the object's state once per frame (Ajay et al.'s
residual form) rather than as a wrench held over the frame's substeps; its last layer starts at zero, so the
untrained model is exactly the analytical simulator.

Training is one-step and needs no gradient through the simulator: for every recorded frame ``k`` of a window
the simulator starts from the target's state at ``k`` (contact anchors carried over from its own previous
frame) and the correction's target is what the target did at ``k + 1`` minus what the simulator did
(:func:`teacher_forced`); Adam on the mean squared error of the 12 numbers, each divided by its spread over
the training data. Prediction rolls the corrected frames out open loop (:func:`predict`).
"""

from __future__ import annotations

import dataclasses
import functools
import io
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from quasisim.errors import InputError
from quasisim.files import check_input_file, write_atomic
from quasisim.method.transitions import ClipWindows
from quasisim.optim.objective import hand_keypoints
from quasisim.optim.trajectory import Trajectory, root_positions, root_quats, sim_controls, split_q
from quasisim.rotations import quat_conj, quat_exp, quat_log, quat_mul, quat_to_mat
from quasisim.sim.residual import nearest_points
from quasisim.sim.step import Points, frame, initial_state, object_pose, residual_input, select_candidates
from quasisim.sim.types import Control, Model, Params, State

Array = jax.Array
F32 = jnp.float32
FORMAT = "quasisim-world-model-v1"
N_FEAT = 10  # per point: position (3), velocity (3), normal (3), contact depth (1)
N_EXTRA = 22  # object twist (6), gravity (3), table height (1), simulator's motion (6) and end twist (6)


@dataclass(frozen=True)
class WorldModelConfig:
    """Sizes and training settings of the correction network (m, s).

    Attributes:
        n_object, n_hand: object surface samples and hand points the network sees (nearest to the contact
            region, within ``radius``).  embed: size of the point-type embedding.
        point_hidden: widths of the shared per-point MLP (its last entry: the pooled feature size).
        head_hidden: widths of the head.  steps, lr, batch: Adam.  per_step: sampled candidate windows kept
            per control step (the chosen one and others at random).  seed: initialisation and batches.
    """

    n_object: int = 32
    n_hand: int = 32
    radius: float = 0.08
    embed: int = 8
    point_hidden: tuple[int, ...] = (64, 128)
    head_hidden: tuple[int, ...] = (128, 64)
    steps: int = 3000
    lr: float = 1.0e-3
    batch: int = 256
    per_step: int = 4
    seed: int = 0

    def as_dict(self) -> dict[str, Any]:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()}


def _mlp(sizes: list[int], key: Array) -> list[eqx.nn.Linear]:
    keys = jax.random.split(key, len(sizes) - 1)
    return [eqx.nn.Linear(a, b, key=k) for a, b, k in zip(sizes[:-1], sizes[1:], keys, strict=True)]


def _run(layers: list[eqx.nn.Linear], x: Array) -> Array:
    for layer in layers[:-1]:
        x = jax.nn.gelu(layer(x))
    return layers[-1](x)


class Correction(eqx.Module):
    """``g`` of the module docstring: point-type embedding, per-point MLP, max- and mean-pool, head (12 outputs,
    multiplied by ``out_scale``; inputs of the head divided by ``extra_scale``; both fixed from the data)."""

    embed: Array
    point: list[eqx.nn.Linear]
    head: list[eqx.nn.Linear]
    extra_scale: Array
    out_scale: Array

    def __init__(self, cfg: WorldModelConfig, extra_scale: Array, out_scale: Array) -> None:
        k1, k2, k3 = jax.random.split(jax.random.PRNGKey(cfg.seed), 3)
        self.embed = 0.1 * jax.random.normal(k1, (2, cfg.embed))
        self.point = _mlp([cfg.embed + N_FEAT, *cfg.point_hidden], k2)
        head = _mlp([2 * cfg.point_hidden[-1] + N_EXTRA, *cfg.head_hidden, 12], k3)
        last = head[-1]
        head[-1] = eqx.tree_at(
            lambda l: (l.weight, l.bias), last, (jnp.zeros_like(last.weight), jnp.zeros_like(last.bias))
        )
        self.head = head
        self.extra_scale = jnp.asarray(extra_scale, F32)
        self.out_scale = jnp.asarray(out_scale, F32)

    def normalized(self, feats: Array, kinds: Array, mask: Array, extra: Array) -> Array:
        """The head's raw output (12,) (the correction divided by ``out_scale``)."""
        x = jnp.concatenate([self.embed[kinds], feats], axis=-1)
        h = jax.vmap(lambda p: _run(self.point, p))(x)
        m = mask[:, None]
        hmax = jnp.where(jnp.any(mask), jnp.max(jnp.where(m, h, -1e9), axis=0), 0.0)
        hmean = jnp.sum(jnp.where(m, h, 0.0), axis=0) / jnp.maximum(jnp.sum(mask), 1)
        e = extra / jax.lax.stop_gradient(self.extra_scale)
        return _run(self.head, jnp.concatenate([hmax, hmean, e]))

    def __call__(self, feats: Array, kinds: Array, mask: Array, extra: Array) -> Array:
        return self.normalized(feats, kinds, mask, extra) * jax.lax.stop_gradient(self.out_scale)


class Features(eqx.Module):
    """What ``g`` sees of one frame: points (P, N_FEAT), their kinds (P,) 0 object / 1 hand, mask (P,), extra
    (N_EXTRA,)."""

    feats: Array
    kinds: Array
    mask: Array
    extra: Array


def features(model: Model, params: Params, s: State, e: State, cfg: WorldModelConfig, fps: float) -> Features:
    """:class:`Features` of the frame from ``s`` to the simulator's ``e`` (module docstring), object frame."""
    idx = select_candidates(model, params, s)
    pts = Points(jnp.asarray(model.point_body)[idx], model.point_local[idx])
    sub = dataclasses.replace(s, delta=s.delta[idx], delta_vel=s.delta_vel[idx])
    x, R = residual_input(model, params, s, pts, sub)
    w = jnp.maximum(x.depth, 0.0)
    center = jnp.where(jnp.sum(w) > 0, jnp.sum(w[:, None] * x.contact_pt, 0) / (jnp.sum(w) + 1e-12), 0.0)
    oi, om = nearest_points(x.obj_pts, center, min(cfg.n_object, len(x.obj_pts)), cfg.radius)
    hi, hm = nearest_points(x.hand_pts, center, min(cfg.n_hand, len(x.hand_pts)), cfg.radius)
    fo = jnp.concatenate([x.obj_pts[oi] - center, x.obj_vel[oi], x.obj_nrm[oi], jnp.zeros((len(oi), 1))], -1)
    fh = jnp.concatenate([x.hand_pts[hi] - center, x.hand_vel[hi], x.contact_nrm[hi], x.depth[hi, None]], -1)
    kinds = jnp.concatenate([jnp.zeros(len(oi), jnp.int32), jnp.ones(len(hi), jnp.int32)])
    to_obj = lambda v: R.T @ v  # noqa: E731
    g = params.gravity / jnp.maximum(jnp.linalg.norm(params.gravity), 1e-6)
    table_h = model.table[4] - s.obj_pos[2]
    moved = quat_log(quat_mul(e.obj_quat, quat_conj(s.obj_quat)))
    extra = jnp.concatenate([
        to_obj(s.obj_vel), to_obj(s.obj_angvel), to_obj(g), table_h[None], to_obj(e.obj_pos - s.obj_pos) * fps,
        to_obj(moved) * fps, to_obj(e.obj_vel), to_obj(e.obj_angvel),
    ])  # fmt: skip
    return Features(jnp.concatenate([fo, fh]), kinds, jnp.concatenate([om, hm]), extra)


def apply_correction(s: State, e: State, d: Array) -> State:
    """``e`` with the object's state corrected by ``d`` (12,) given in the object frame of ``s``."""
    R = quat_to_mat(s.obj_quat)
    q = quat_mul(quat_exp(R @ d[3:6]), e.obj_quat)
    return dataclasses.replace(
        e, obj_pos=e.obj_pos + R @ d[0:3], obj_quat=q / jnp.linalg.norm(q), obj_vel=e.obj_vel + R @ d[6:9],
        obj_angvel=e.obj_angvel + R @ d[9:12],
    )  # fmt: skip


def correction_target(s: State, e: State, truth: State) -> Array:
    """The ``d`` (12,) that turns the simulator's ``e`` into the target's ``truth`` (object frame of ``s``)."""
    R = quat_to_mat(s.obj_quat)
    rot = quat_log(quat_mul(truth.obj_quat, quat_conj(e.obj_quat)))
    return jnp.concatenate([R.T @ (truth.obj_pos - e.obj_pos), R.T @ rot, R.T @ (truth.obj_vel - e.obj_vel),
                            R.T @ (truth.obj_angvel - e.obj_angvel)])  # fmt: skip


def corrected_frame(
    model: Model, params: Params, net: Correction | None, cfg: WorldModelConfig, s: State, c: Control, fps: float
) -> State:
    """One frame of the fitted simulator (module docstring); ``net`` None: the analytical frame alone."""
    e = frame(model, params, s, c)
    if net is None:
        return e
    f = features(model, params, s, e, cfg, fps)
    return apply_correction(s, e, net(f.feats, f.kinds, f.mask, f.extra))


def observed(model: Model, base_quat: Array, qpos: Array, qvel: Array, obj: tuple[Array, Array, Array, Array]) -> State:
    """The simulator state of a target's state (traceable; contacts start fresh): hands ``qpos``, ``qvel``
    (D,), object frame origin, orientation, centre-of-mass velocity and angular velocity ``obj``."""
    hj = model.hand.hand_joints
    base, joints = split_q(qpos, hj)
    s = initial_state(
        model, root_positions(base[None])[0], root_quats(base[None], base_quat)[0], joints, obj[0], obj[1]
    )
    return dataclasses.replace(s, qd=split_q(qvel, hj)[1].astype(F32), obj_vel=obj[2].astype(F32),
                               obj_angvel=obj[3].astype(F32))  # fmt: skip


@dataclass(frozen=True, eq=False)
class Batch:
    """A clip's windows as simulator inputs: start states and frame states (B, H + 1) of the target, controls
    (B, H) and the target's metric keypoints (B, H + 1, K, 3)."""

    states: State
    controls: Control
    keypoints: Array


def batch(w: ClipWindows) -> Batch:
    """:class:`Batch` of all windows of ``w``."""
    model, bq = w.prob.model, jnp.asarray(w.prob.base_quat, F32)
    f = lambda x: jnp.asarray(x, F32)  # noqa: E731
    obs = jax.vmap(jax.vmap(lambda *a: observed(model, bq, a[0], a[1], a[2:])))
    states = obs(f(w.qpos), f(w.qvel), f(w.obj_pos), f(w.obj_quat), f(w.obj_vel), f(w.obj_angvel))
    trajs = [Trajectory.from_q(q, model.n_points, model.hand.hand_joints) for q in w.q_targets]
    ctrls = [sim_controls(t, bq, w.fps) for t in trajs]
    controls = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *ctrls)
    return Batch(states, controls, f(w.keypoints))


def _chunks(n: int, size: int) -> list[np.ndarray]:
    """Index chunks of one size (the last padded with its final index), so that one program serves all."""
    return [np.minimum(np.arange(i, i + size), n - 1) for i in range(0, n, size)]


def _take(tree: Any, idx: np.ndarray) -> Any:
    return jax.tree_util.tree_map(lambda x: x[jnp.asarray(idx)], tree)


@functools.partial(jax.jit, static_argnames=("cfg", "fps"))
def _teacher_forced(model: Model, params: Params, states: State, controls: Control, cfg: WorldModelConfig,
                    fps: float) -> tuple[Features, Array]:  # fmt: skip
    def window(st: State, ctrl: Control) -> tuple[Features, Array]:
        def body(prev: State, k: Array) -> tuple[State, tuple[Features, Array]]:
            s = jax.tree_util.tree_map(lambda x: x[k], st)
            s = dataclasses.replace(s, anchor=prev.anchor, in_contact=prev.in_contact,
                                    table_anchor=prev.table_anchor, table_contact=prev.table_contact)  # fmt: skip
            e = frame(model, params, s, jax.tree_util.tree_map(lambda x: x[k], ctrl))
            truth = jax.tree_util.tree_map(lambda x: x[k + 1], st)
            return e, (features(model, params, s, e, cfg, fps), correction_target(s, e, truth))

        s0 = jax.tree_util.tree_map(lambda x: x[0], st)
        _, out = jax.lax.scan(body, s0, jnp.arange(ctrl.q_target.shape[0]))
        return out

    return jax.vmap(window)(states, controls)


def teacher_forced(
    params: Params, w: ClipWindows, cfg: WorldModelConfig, chunk: int = 16
) -> tuple[Features, np.ndarray]:
    """Training pairs of every frame of every window of ``w``: the :class:`Features` (B H, ...) and the
    correction targets (B H, 12) (module docstring), as numpy arrays."""
    b, n = batch(w), len(w)
    outs = [_teacher_forced(w.prob.model, params, _take(b.states, i), _take(b.controls, i), cfg, w.fps)
            for i in _chunks(n, min(chunk, n))]  # fmt: skip
    flat = lambda x: np.concatenate([np.asarray(o) for o in x])[:n].reshape(n * w.horizon, *x[0].shape[2:])  # noqa: E731
    f = Features(*(flat([getattr(o[0], k) for o in outs]) for k in ("feats", "kinds", "mask", "extra")))
    return f, flat([o[1] for o in outs])


@functools.partial(jax.jit, static_argnames=("cfg", "fps"))
def _predict(model: Model, params: Params, net: Correction | None, s0: State, controls: Control,
             cfg: WorldModelConfig, fps: float) -> tuple[Array, Array, Array]:  # fmt: skip
    def window(s: State, ctrl: Control) -> tuple[Array, Array, Array]:
        def body(s: State, c: Control) -> tuple[State, State]:
            s = corrected_frame(model, params, net, cfg, s, c, fps)
            return s, s

        _, states = jax.lax.scan(body, s, ctrl)
        pos, quat = object_pose(model, states)
        return pos, quat, hand_keypoints(model, states)

    return jax.vmap(window)(s0, controls)


def predict(params: Params, net: Correction | None, w: ClipWindows, cfg: WorldModelConfig,
            chunk: int = 16, prepared: Batch | None = None) -> dict[str, np.ndarray]:  # fmt: skip
    """Open-loop predictions of every window of ``w`` from the target's start state under its PD targets:
    object frame origin (B, H, 3), orientation (B, H, 4) and metric keypoints (B, H, K, 3); ``prepared``:
    ``batch(w)`` when the caller predicts the same windows several times."""
    b, n = prepared or batch(w), len(w)
    s0 = jax.tree_util.tree_map(lambda x: x[:, 0], b.states)
    outs = [_predict(w.prob.model, params, net, _take(s0, i), _take(b.controls, i), cfg, w.fps)
            for i in _chunks(n, min(chunk, n))]  # fmt: skip
    pos, quat, kp = (np.concatenate([np.asarray(o[k], np.float64) for o in outs])[:n] for k in range(3))
    return {"obj_pos": pos, "obj_quat": quat, "keypoints": kp[:, :, w.kp_index]}


# ---- training ------------------------------------------------------------------------------------


def init_correction(cfg: WorldModelConfig, extra: np.ndarray, target: np.ndarray) -> Correction:
    """A zero correction whose input and output scales are the spreads (robust: 1.4826 MAD, floored) of the
    training data's head inputs ``extra`` (n, N_EXTRA) and targets (n, 12)."""

    def spread(x: np.ndarray, floor: float) -> np.ndarray:
        mad = 1.4826 * np.median(np.abs(x - np.median(x, 0)), 0)
        return np.maximum(np.maximum(mad, x.std(0) * 0.1), floor)

    return Correction(cfg, spread(extra, 1e-4), spread(target, 1e-6))


def train(net: Correction, data: Features, target: np.ndarray, cfg: WorldModelConfig,
          progress: Any = None) -> tuple[Correction, list[float]]:  # fmt: skip
    """Adam (``cfg.steps``, ``cfg.lr`` with cosine decay, ``cfg.batch``) on the mean squared normalized error
    of the corrections of ``data`` against ``target``; returns the network and the loss every 100 steps."""
    opt = optax.adam(optax.cosine_decay_schedule(cfg.lr, max(cfg.steps, 1), alpha=0.05))
    params, static = eqx.partition(net, eqx.is_array)
    state = opt.init(params)
    d = {k: jnp.asarray(getattr(data, k)) for k in ("feats", "kinds", "mask", "extra")}
    y = jnp.asarray(target, F32)

    @jax.jit
    def step(params: Any, state: Any, idx: Array) -> tuple[Any, Any, Array]:
        def loss(p: Any) -> Array:
            m = eqx.combine(p, static)
            out = jax.vmap(m.normalized)(d["feats"][idx], d["kinds"][idx], d["mask"][idx], d["extra"][idx])
            return jnp.mean((out - y[idx] / m.out_scale) ** 2)

        v, g = jax.value_and_grad(loss)(params)
        upd, state = opt.update(g, state, params)
        return optax.apply_updates(params, upd), state, v

    rng = np.random.default_rng(cfg.seed)
    losses, run = [], []
    for i in range(cfg.steps):
        params, state, v = step(params, state, rng.integers(0, len(y), min(cfg.batch, len(y))))
        run.append(float(v))
        if (i + 1) % 100 == 0 or i + 1 == cfg.steps:
            losses.append(float(np.mean(run)))
            run = []
            if progress is not None:
                progress(i + 1, losses[-1])
    return eqx.combine(params, static), losses


# ---- the file ------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class WorldModel:
    """A fitted world model: the correction network, its settings and what it was trained on (``info``:
    hand, simulator settings, training and held-out clips, losses; JSON)."""

    net: Correction
    cfg: WorldModelConfig
    info: dict[str, Any]

    def save(self, path: Path) -> Path:
        """One file: a JSON header line, then the network's arrays (equinox serialisation); written atomically."""
        head = json.dumps({"format": FORMAT, "config": self.cfg.as_dict(), **self.info}, sort_keys=True)

        def write(tmp: Path) -> None:
            with open(tmp, "wb") as f:
                f.write(head.encode() + b"\n")
                eqx.tree_serialise_leaves(f, self.net)

        return write_atomic(path, write)

    @staticmethod
    def load(path: Path) -> WorldModel:
        """Read a file written by :meth:`save`; :class:`InputError` naming the file when it is not one."""
        path = Path(path)
        check_input_file(path, "world model file")
        raw = path.read_bytes()
        line, _, body = raw.partition(b"\n")
        try:
            info = json.loads(line.decode())
            fmt = info.pop("format", None)
        except (UnicodeDecodeError, json.JSONDecodeError, AttributeError):
            info, fmt = {}, None
        if fmt != FORMAT:
            raise InputError(path, "format", f"a {FORMAT} file (quasisim fit)", repr(fmt) if fmt else "another file")
        try:
            cfg_d = info.pop("config")
            cfg = WorldModelConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in cfg_d.items()})
        except (KeyError, TypeError, AttributeError) as e:
            raise InputError(path, "config", "the settings of WorldModelConfig", " ".join(str(e).split())) from None
        skeleton = Correction(cfg, np.ones(N_EXTRA), np.ones(12))
        try:
            net = eqx.tree_deserialise_leaves(io.BytesIO(body), skeleton)
        except (RuntimeError, ValueError, EOFError, OSError) as e:
            raise InputError(path, None, "a complete world model file", f"damaged network arrays ({e})") from None
        return WorldModel(net, cfg, info)
