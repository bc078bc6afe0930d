"""Robot hands: per-hand YAML configs and the parsed kinematic/geometric model.

Any MJCF or URDF hand is parsed by MuJoCo's compiler (which resolves defaults, includes and mesh
frames) and then copied into :class:`HandModel`, plain numpy arrays that the JAX kinematics, the
quasi-physical simulator and both target simulators (MuJoCo, PyBullet) are built from. The hand's root
body becomes the child of a floating 6-DoF base; joints of the root body itself (e.g. Shadow's wrist
joint WRJ0) and everything above it (forearm) are dropped.

A hand YAML may build its model from another one by edits (:mod:`quasisim.assets.model_edit`): a mirror
image (a left hand from a right-hand model, :mod:`quasisim.assets.mirror`) or a scaled subtree (a short
thumb); ``base:`` takes every field it does not set from another hand YAML. The format: docs/hands.md.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import os
from dataclasses import dataclass
from functools import cache, cached_property
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from quasisim.assets.mirror import mirror_spec
from quasisim.assets.model_edit import ModelEdit, canonicalize, compile_spec, read_spec, scale_subtree
from quasisim.config import apply_overrides, build, read_yaml
from quasisim.errors import InputError, QuasisimError, choice_error
from quasisim.keypoints import N_KEYPOINTS

HANDS_DIR = Path(__file__).parent / "hands"
ROBOT_PATH_ENV = "QUASISIM_ROBOT_PATH"

HINGE, SLIDE = 0, 1
GEOM_TYPES = ("plane", "hfield", "sphere", "capsule", "ellipsoid", "cylinder", "box", "mesh")
SIDES = ("right", "left")


@dataclass(frozen=True)
class KeypointSpec:
    """A robot keypoint that corresponds to one of the 21 human keypoints.

    Attributes:
        name: label.
        human: index of the human keypoint (MediaPipe order, 0..20).
        body: robot body the point is attached to (ignored when ``site`` is given).
        pos: offset in the body frame (m).
        site: take body and offset from this MJCF site instead.
        weight: weight in the retargeting objective.
        metric: used in MPJPE (the paper uses 5 fingertips + 3 wrist/palm points).
    """

    name: str
    human: int
    body: str = ""
    pos: tuple[float, float, float] = (0.0, 0.0, 0.0)
    site: str = ""
    weight: float = 1.0
    metric: bool = True


@dataclass(frozen=True)
class Gains:
    kp: float
    kv: float


@dataclass(frozen=True)
class PDConfig:
    """PD gains used in the target simulators (SI units: N/m, N s/m, N m/rad, N m s/rad)."""

    base_pos: Gains = Gains(1.0e4, 250.0)
    base_rot: Gains = Gains(500.0, 5.0)
    joint: Gains = Gains(5.0, 0.1)
    joint_damping: float = 0.1
    joint_armature: float = 1.0e-3
    joint_force_limit: float = 10.0


@dataclass(frozen=True)
class PointSetConfig:
    """How the quasi-physical point set is sampled around the collision geometry.

    Attributes:
        spacing: mean distance between neighbouring points on the surface (m).
        offset: points lie in a shell between the surface and ``offset`` outside it (m).
        seed: random seed for the sampling.
        count: a fixed number of points (None: as many as ``spacing`` gives): the surface is sampled
            at least ~25 % more densely than ``count`` needs and ``count`` of those points are drawn, so every hand
            of one topology gets a point set of one size (stage 1's human hands: one compiled program).
    """

    spacing: float = 0.006
    offset: float = 0.002
    seed: int = 0
    count: int | None = None


@dataclass(frozen=True)
class HandConfig:
    """Per-hand configuration, loaded from YAML (field by field: docs/hands.md).

    Attributes (besides the documented YAML fields): ``side``: which hand the model is once ``edits`` are
    applied; ``mirror_axis``: the axis of the model's frames normal to the plane that turns it into the
    other side (see :meth:`for_side`); ``edits``: model edits applied in order after loading ``model``;
    ``per_demo``: the hand is built from each demo (stage 1's human hand): its geometry goes to compiled
    programs as arrays (:attr:`quasisim.sim.types.Model.hand_geom`), so that demos share them.
    """

    name: str
    model: str
    root_body: str
    keypoints: tuple[KeypointSpec, ...]
    description: str = ""
    side: str = "right"
    mirror_axis: str = "x"
    edits: tuple[ModelEdit, ...] = ()
    pd: PDConfig = PDConfig()
    points: PointSetConfig = PointSetConfig()
    exclude_geoms: tuple[str, ...] = ()
    wrist_fit_human: tuple[int, ...] = (0, 5, 9, 13, 17)
    path: str = ""
    per_demo: bool = False

    @classmethod
    def from_yaml(cls, path: str | Path, overrides: dict[str, Any] | None = None) -> HandConfig:
        path = Path(path)
        data = apply_overrides(_read_hand_yaml(path), overrides)
        data["path"] = str(path.resolve())
        cfg = build(cls, data, path)
        cfg.validate()
        return cfg

    def for_side(self, side: str) -> HandConfig:
        """This hand for ``side`` (``right`` or ``left``): itself, or its mirror image named
        ``<name>-<side>`` (a trailing ``-right``/``-left`` of the name replaced)."""
        if side not in SIDES:
            raise choice_error("hand side", side, SIDES)
        if side == self.side:
            return self
        stem = self.name.removesuffix(f"-{self.side}")
        edits = (*self.edits, ModelEdit(mirror=self.mirror_axis))
        return dataclasses.replace(self, name=f"{stem}-{side}", side=side, edits=edits)

    def validate(self) -> None:
        if not self.keypoints:
            raise InputError(self.path, "keypoints", "at least one keypoint", "none")
        for i, kp in enumerate(self.keypoints):
            if not 0 <= kp.human <= 20:
                raise InputError(self.path, f"keypoints[{i}].human", "an index in 0..20", str(kp.human))
            if not (kp.body or kp.site):
                raise InputError(self.path, f"keypoints[{i}]", "a 'body' or a 'site'", "neither")
            if kp.weight < 0:
                raise InputError(self.path, f"keypoints[{i}].weight", "a non-negative weight", str(kp.weight))
        names = [k.name for k in self.keypoints]
        if len(set(names)) != len(names):
            dup = next(n for n in names if names.count(n) > 1)
            raise InputError(self.path, "keypoints", "distinct keypoint names", f"{dup!r} more than once")
        for i, kp in enumerate(self.keypoints):
            if max(abs(v) for v in kp.pos) > 0.5:
                raise InputError(
                    self.path, f"keypoints[{i}].pos", "an offset within 0.5 m of its body (metres)", str(kp.pos)
                )
        if not (0.001 <= self.points.spacing <= 0.05 and 0 <= self.points.offset <= 0.02):
            raise InputError(
                self.path, "points", "spacing in [0.001, 0.05] m and offset in [0, 0.02] m", str(self.points)
            )
        pd = self.pd
        for name, g in (("base_pos", pd.base_pos), ("base_rot", pd.base_rot), ("joint", pd.joint)):
            if not (g.kp > 0 and g.kv >= 0):
                raise InputError(self.path, f"pd.{name}", "kp > 0 and kv >= 0", f"kp {g.kp:g}, kv {g.kv:g}")
        if not (pd.joint_damping >= 0 and pd.joint_armature >= 0 and pd.joint_force_limit > 0):
            raise InputError(
                self.path, "pd", "joint_damping >= 0, joint_armature >= 0 and joint_force_limit > 0",
                f"{pd.joint_damping:g}, {pd.joint_armature:g}, {pd.joint_force_limit:g}",
            )  # fmt: skip
        if not any(k.metric for k in self.keypoints):
            raise InputError(self.path, "keypoints", "at least one keypoint with metric: true (MPJPE)", "none")
        for i in self.wrist_fit_human:
            if i not in [k.human for k in self.keypoints]:
                raise InputError(self.path, "wrist_fit_human", "human indices that have a robot keypoint", str(i))
        weights = {i: next(k.weight for k in self.keypoints if k.human == i) for i in self.wrist_fit_human}
        if sum(w > 0 for w in weights.values()) < 3:  # the rigid fit of the hand's root needs three points
            raise InputError(
                self.path, "wrist_fit_human", "at least 3 distinct indices whose keypoints have weight > 0",
                str(list(self.wrist_fit_human)),
            )  # fmt: skip
        if self.points.seed < 0:
            raise InputError(self.path, "points.seed", "a seed >= 0", str(self.points.seed))
        if self.side not in SIDES:
            raise InputError(self.path, "side", f"one of {', '.join(SIDES)}", repr(self.side))
        if self.mirror_axis not in ("x", "y", "z"):
            raise InputError(self.path, "mirror_axis", "one of x, y, z", repr(self.mirror_axis))
        for i, edit in enumerate(self.edits):
            edit.validate(self.path, f"edits[{i}]")


def apply_edits(spec: Any, edits: tuple[ModelEdit, ...], path: str | Path) -> Any:
    """Apply ``edits`` in order to ``spec`` (changed in place and returned); ``path`` names the YAML in errors."""
    for i, edit in enumerate(edits):
        canonicalize(spec, compile_spec(spec, path), path)
        if edit.mirror:
            mirror_spec(spec, edit.mirror)
        else:
            names = [b.name for b in spec.bodies]
            if edit.body not in names:
                raise InputError(path, f"edits[{i}].body", f"a body of the model ({', '.join(names[1:])})", edit.body)
            scale_subtree(spec, spec.body(edit.body), edit.scale)
    return spec


def _read_hand_yaml(path: Path, seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    """The mapping of a hand YAML with its ``base:`` resolved: the base hand's (a built-in name or a YAML
    path relative to this file) top-level fields, replaced by the ones this file sets."""
    data = read_yaml(path)
    if "base" not in data:
        return data
    base = data.pop("base")
    if not isinstance(base, str) or not base:
        raise InputError(path, "base", "a built-in hand name or the path of a hand YAML", repr(base))
    base_path = HANDS_DIR / f"{base}.yaml" if base in builtin_hands() else (path.parent / base).resolve()
    if base_path.resolve() in (path.resolve(), *seen):
        raise InputError(path, "base", "a chain of bases without a cycle", str(base_path))
    if not base_path.is_file():
        raise InputError(path, "base", f"one of {', '.join(builtin_hands())} or a hand YAML", base)
    return {**_read_hand_yaml(base_path, (*seen, path.resolve())), **data}


@dataclass(frozen=True, eq=False)
class Geom:
    """One geom of the hand in its body's frame. ``size`` follows MuJoCo's conventions."""

    name: str
    body: int
    type: str
    size: np.ndarray
    pos: np.ndarray
    quat: np.ndarray
    collision: bool
    rgba: np.ndarray
    vertices: np.ndarray | None = None
    faces: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class HandModel:
    """The parsed hand: a tree of bodies below the root, joints, geoms and keypoints (numpy, SI units).

    Body 0 is the root; its frame is the hand frame driven by the floating base. Every other body ``b``
    has ``body_parent[b] < b``, a pose relative to its parent (``body_pos``, ``body_quat``, w x y z) and
    zero or more joints applied in order, as in MuJoCo. ``source`` is the model file the hand was read
    from; the arrays are those of the model after the config's ``edits``.
    """

    config: HandConfig
    source: Path
    body_names: tuple[str, ...]
    body_parent: np.ndarray
    body_pos: np.ndarray
    body_quat: np.ndarray
    body_mass: np.ndarray
    body_ipos: np.ndarray
    body_iquat: np.ndarray
    body_inertia: np.ndarray
    joint_names: tuple[str, ...]
    joint_body: np.ndarray
    joint_type: np.ndarray
    joint_axis: np.ndarray
    joint_pos: np.ndarray
    joint_range: np.ndarray
    joint_limited: np.ndarray
    geoms: tuple[Geom, ...]
    kp_names: tuple[str, ...]
    kp_body: np.ndarray
    kp_pos: np.ndarray
    kp_human: np.ndarray
    kp_weight: np.ndarray
    kp_metric: np.ndarray

    @property
    def name(self) -> str:
        return self.config.name

    @property
    def n_bodies(self) -> int:
        return len(self.body_names)

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    @property
    def total_mass(self) -> float:
        return float(self.body_mass.sum())

    def rest_q(self) -> np.ndarray:
        """A neutral joint vector: 0 clipped into each joint's range."""
        lo, hi = self.joint_range[:, 0], self.joint_range[:, 1]
        q = np.zeros(self.n_joints)
        return np.where(self.joint_limited, np.clip(q, lo, hi), q)

    def body_joints(self, b: int) -> np.ndarray:
        return np.flatnonzero(self.joint_body == b)

    def collision_geoms(self) -> tuple[Geom, ...]:
        return tuple(g for g in self.geoms if g.collision)

    @cached_property
    def roots(self) -> np.ndarray:
        """(H,) the root bodies, one per hand (a hand set of :func:`join_hands` has several)."""
        return np.flatnonzero(self.body_parent < 0)

    @property
    def n_hands(self) -> int:
        return len(self.roots)

    @cached_property
    def body_hand(self) -> np.ndarray:
        """(B,) the hand (index into :attr:`roots`) each body belongs to."""
        hand = np.zeros(self.n_bodies, dtype=np.int32)
        hand[self.roots] = np.arange(self.n_hands)
        for b in range(self.n_bodies):
            if self.body_parent[b] >= 0:
                hand[b] = hand[self.body_parent[b]]
        return hand

    @cached_property
    def hand_joints(self) -> tuple[int, ...]:
        """Joints of each hand, in order (a hand's joints are contiguous)."""
        return tuple(int(n) for n in np.bincount(self.body_hand[self.joint_body], minlength=self.n_hands))

    def __getstate__(self) -> dict[str, Any]:
        """The fields without the cached properties: a hand pickles to the same bytes whether or not they
        have been computed (traced programs on disk are keyed by the pickle, :mod:`quasisim.tracecache`)."""
        cached = {k for k, v in vars(type(self)).items() if isinstance(v, cached_property)}
        return {k: v for k, v in vars(self).items() if k not in cached}


@cache
def join_hands(hands: tuple[HandModel, ...]) -> HandModel:
    """One hand model holding ``hands`` side by side (the bimanual quasi-physical simulator's hand).

    Bodies, joints, geoms and keypoints are concatenated in the order of ``hands``; each hand keeps its own
    root (``body_parent`` -1), so the set has one floating base per hand. Keypoint ``human`` indices of hand
    ``i`` are offset by 21 i: they index the concatenated human keypoints ``[right_joints, left_joints]``
    (:attr:`quasisim.data.demo.Demo.human_joints`). Joint names are prefixed with the hand's name. One hand
    is returned as it is. Cached: the same hands give the same object (and the same compiled programs)."""
    if len(hands) == 1:
        return hands[0]
    b0 = np.cumsum([0, *(h.n_bodies for h in hands)])[:-1]
    cat = lambda f: np.concatenate([getattr(h, f) for h in hands])  # noqa: E731
    name = " + ".join(h.name for h in hands)
    return HandModel(
        config=dataclasses.replace(hands[0].config, name=name),
        source=hands[0].source,
        body_names=tuple(f"{h.name}/{n}" for h in hands for n in h.body_names),
        body_parent=np.concatenate([np.where(h.body_parent < 0, -1, h.body_parent + o) for h, o in zip(hands, b0, strict=True)]),
        body_pos=cat("body_pos"), body_quat=cat("body_quat"), body_mass=cat("body_mass"), body_ipos=cat("body_ipos"),
        body_iquat=cat("body_iquat"), body_inertia=cat("body_inertia"),
        joint_names=tuple(f"{h.name}/{n}" for h in hands for n in h.joint_names),
        joint_body=np.concatenate([h.joint_body + o for h, o in zip(hands, b0, strict=True)]),
        joint_type=cat("joint_type"), joint_axis=cat("joint_axis"), joint_pos=cat("joint_pos"),
        joint_range=cat("joint_range"), joint_limited=cat("joint_limited"),
        geoms=tuple(dataclasses.replace(g, body=g.body + o) for h, o in zip(hands, b0, strict=True) for g in h.geoms),
        kp_names=tuple(f"{h.name}/{n}" for h in hands for n in h.kp_names),
        kp_body=np.concatenate([h.kp_body + o for h, o in zip(hands, b0, strict=True)]),
        kp_pos=cat("kp_pos"),
        kp_human=np.concatenate([h.kp_human + N_KEYPOINTS * i for i, h in enumerate(hands)]),
        kp_weight=cat("kp_weight"), kp_metric=cat("kp_metric"),
    )  # fmt: skip


# ---- loading ------------------------------------------------------------------------------------


def builtin_hands() -> list[str]:
    return sorted(p.stem for p in HANDS_DIR.glob("*.yaml"))


def resolve_hand_config(hand: str | Path, overrides: dict[str, Any] | None = None) -> HandConfig:
    """A built-in hand name (``shadow``, ``allegro``, ... : :func:`builtin_hands`) or a path to a hand YAML."""
    p = Path(hand)
    if p.suffix in (".yaml", ".yml"):
        return HandConfig.from_yaml(p, overrides)
    if str(hand) in builtin_hands():
        return HandConfig.from_yaml(HANDS_DIR / f"{hand}.yaml", overrides)
    raise choice_error("hand", str(hand), [*builtin_hands(), "<path/to/hand.yaml>"])


def resolve_model_path(cfg: HandConfig) -> Path:
    """Find the MJCF/URDF named by ``cfg.model``.

    ``gymnasium_robotics:REL`` is a file inside the installed gymnasium-robotics package; a relative
    path is looked up beside the YAML and then in each folder of ``$QUASISIM_ROBOT_PATH``.
    """
    if cfg.model.startswith("gymnasium_robotics:"):
        spec = importlib.util.find_spec("gymnasium_robotics")  # locate without importing (it prints notices)
        if spec is None or spec.origin is None:
            raise QuasisimError(
                f"hand '{cfg.name}' needs the gymnasium-robotics package (pip install gymnasium-robotics)"
            )
        p = Path(spec.origin).parent / "envs" / "assets" / cfg.model.split(":", 1)[1]
        if not p.is_file():
            raise InputError(cfg.path, "model", f"a file inside gymnasium-robotics at {p}", "no such file")
        return p
    p = Path(os.path.expandvars(cfg.model)).expanduser()
    candidates = (
        [p]
        if p.is_absolute()
        else [Path(cfg.path).parent / p]
        + [Path(d) / p for d in os.environ.get(ROBOT_PATH_ENV, "").split(os.pathsep) if d]
    )
    for c in candidates:
        if c.is_file():
            return c.resolve()
    raise InputError(
        cfg.path,
        "model",
        f"an MJCF/URDF file; looked in {', '.join(str(c) for c in candidates)} "
        f"(set ${ROBOT_PATH_ENV} to the folder that holds it)",
        "no such file",
    )


def compile_hand_model(cfg: HandConfig) -> tuple[Any, Path]:
    """The compiled MuJoCo model of ``cfg``'s hand (its ``edits`` applied) and the model file it comes from."""
    src = resolve_model_path(cfg)
    spec = read_spec(src)
    if cfg.edits:
        apply_edits(spec, cfg.edits, cfg.path)
    return compile_spec(spec, src), src


def load_hand(
    hand: str | Path | HandConfig, overrides: dict[str, Any] | None = None, side: str | None = None
) -> HandModel:
    """Load a hand by built-in name, YAML path or config; results are cached per config.

    ``side`` (``right``/``left``): the hand for that side, the mirror image of the model when the hand
    is of the other side (e.g. ``load_hand("shadow", side="left")`` is the built-in ``shadow-left``).
    """
    cfg = hand if isinstance(hand, HandConfig) else resolve_hand_config(hand, overrides)
    return _load_hand_cached(cfg if side is None else cfg.for_side(side))


@cache
def _load_hand_cached(cfg: HandConfig) -> HandModel:
    m, src = compile_hand_model(cfg)
    body_names_all = [_name(m, mujoco.mjtObj.mjOBJ_BODY, b) for b in range(m.nbody)]
    if cfg.root_body not in body_names_all:
        raise InputError(cfg.path, "root_body", f"one of the bodies {', '.join(body_names_all[1:])}", cfg.root_body)
    keep = _subtree(m, body_names_all.index(cfg.root_body))
    new_index = {old: i for i, old in enumerate(keep)}
    joints = _joints(m, keep, new_index, src)
    geoms = _geoms(m, new_index, cfg, src)
    kb, kpos = _keypoint_frames(m, cfg, src, body_names_all, new_index)
    return HandModel(
        config=cfg,
        source=src,
        body_names=tuple(body_names_all[b] for b in keep),
        body_parent=np.array([-1] + [new_index[int(m.body_parentid[b])] for b in keep[1:]]),
        body_pos=np.array([np.zeros(3)] + [m.body_pos[b] for b in keep[1:]], dtype=np.float64),
        body_quat=np.array([np.array([1.0, 0, 0, 0])] + [m.body_quat[b] for b in keep[1:]], dtype=np.float64),
        body_mass=np.array([m.body_mass[b] for b in keep], dtype=np.float64),
        body_ipos=np.array([m.body_ipos[b] for b in keep], dtype=np.float64),
        body_iquat=np.array([m.body_iquat[b] for b in keep], dtype=np.float64),
        body_inertia=np.array([m.body_inertia[b] for b in keep], dtype=np.float64),
        **joints,
        geoms=geoms,
        kp_names=tuple(k.name for k in cfg.keypoints),
        kp_body=np.array(kb),
        kp_pos=np.array(kpos, dtype=np.float64),
        kp_human=np.array([k.human for k in cfg.keypoints]),
        kp_weight=np.array([k.weight for k in cfg.keypoints], dtype=np.float64),
        kp_metric=np.array([k.metric for k in cfg.keypoints]),
    )


def _name(m: Any, obj: Any, i: int) -> str:
    return mujoco.mj_id2name(m, obj, i) or ""


def _subtree(m: Any, root: int) -> list[int]:
    """Body ids of ``root`` and its descendants, parents before children."""
    keep = [root]
    for b in range(root + 1, m.nbody):
        if m.body_parentid[b] in keep:
            keep.append(b)
    return keep


def _joints(m: Any, keep: list[int], new_index: dict[int, int], src: Path) -> dict[str, Any]:
    """The joints of the kept bodies as :class:`HandModel` fields (hinge and slide joints only)."""
    jn, jb, jt, jax_, jp, jr, jl = [], [], [], [], [], [], []
    for b in keep[1:]:
        for j in range(m.body_jntadr[b], m.body_jntadr[b] + m.body_jntnum[b]):
            t = int(m.jnt_type[j])
            name = _name(m, mujoco.mjtObj.mjOBJ_JOINT, j)
            if t not in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE):
                raise InputError(src, f"joint {name}", "hinge or slide joints", "a ball/free joint")
            if m.qpos0[m.jnt_qposadr[j]] != 0.0:
                raise InputError(src, f"joint {name}", "ref = 0", "a non-zero reference")
            jt.append(HINGE if t == mujoco.mjtJoint.mjJNT_HINGE else SLIDE)
            jn.append(name or f"joint{j}")
            jb.append(new_index[b])
            jax_.append(m.jnt_axis[j] / np.linalg.norm(m.jnt_axis[j]))
            jp.append(m.jnt_pos[j])
            jr.append(m.jnt_range[j])
            jl.append(bool(m.jnt_limited[j]))
    if not jn:
        raise InputError(src, "joints", "at least one hinge/slide joint below the root body", "none")
    return {
        "joint_names": tuple(jn), "joint_body": np.array(jb), "joint_type": np.array(jt),
        "joint_axis": np.array(jax_, dtype=np.float64), "joint_pos": np.array(jp, dtype=np.float64),
        "joint_range": np.array(jr, dtype=np.float64), "joint_limited": np.array(jl),
    }  # fmt: skip


def _geoms(m: Any, new_index: dict[int, int], cfg: HandConfig, src: Path) -> tuple[Geom, ...]:
    """The geoms of the kept bodies (meshes with their vertices and faces), less ``cfg.exclude_geoms``."""
    geoms = []
    for g in range(m.ngeom):
        b = int(m.geom_bodyid[g])
        gname = _name(m, mujoco.mjtObj.mjOBJ_GEOM, g) or f"geom{g}"
        if b not in new_index or gname in cfg.exclude_geoms:
            continue
        gtype = GEOM_TYPES[int(m.geom_type[g])]
        verts = faces = None
        if gtype == "mesh":
            mid = int(m.geom_dataid[g])
            va, vn = m.mesh_vertadr[mid], m.mesh_vertnum[mid]
            fa, fn = m.mesh_faceadr[mid], m.mesh_facenum[mid]
            verts = np.array(m.mesh_vert[va : va + vn], dtype=np.float64)
            faces = np.array(m.mesh_face[fa : fa + fn], dtype=np.int64)
        geoms.append(
            Geom(
                name=gname, body=new_index[b], type=gtype, size=np.array(m.geom_size[g], dtype=np.float64),
                pos=np.array(m.geom_pos[g], dtype=np.float64), quat=np.array(m.geom_quat[g], dtype=np.float64),
                collision=bool(m.geom_contype[g] or m.geom_conaffinity[g]) and gtype != "plane",
                rgba=np.array(m.geom_rgba[g], dtype=np.float64), vertices=verts, faces=faces,
            )
        )  # fmt: skip
    names = {_name(m, mujoco.mjtObj.mjOBJ_GEOM, g) or f"geom{g}" for g in range(m.ngeom)}
    for i, gname in enumerate(cfg.exclude_geoms):
        if gname not in names:
            raise InputError(cfg.path, f"exclude_geoms[{i}]", f"a geom of {src.name}", repr(gname))
    if not any(g.collision for g in geoms):
        raise InputError(src, "geoms", "collision geoms below the root body", "none")
    return tuple(geoms)


def _keypoint_frames(
    m: Any, cfg: HandConfig, src: Path, body_names_all: list[str], new_index: dict[int, int]
) -> tuple[list[int], list[np.ndarray]]:
    """Each configured keypoint's body (new index) and its position in that body's frame (m)."""
    site_names = [_name(m, mujoco.mjtObj.mjOBJ_SITE, s) for s in range(m.nsite)]
    kb, kpos = [], []
    for i, kp in enumerate(cfg.keypoints):
        if kp.site:
            if kp.site not in site_names:
                raise InputError(cfg.path, f"keypoints[{i}].site", f"a site of {src.name}", kp.site)
            s = site_names.index(kp.site)
            b = int(m.site_bodyid[s])
            pos = np.array(m.site_pos[s]) + np.array(kp.pos)
        else:
            if kp.body not in body_names_all:
                raise InputError(cfg.path, f"keypoints[{i}].body", f"a body of {src.name}", kp.body)
            b = body_names_all.index(kp.body)
            pos = np.array(kp.pos, dtype=np.float64)
        if b not in new_index:
            raise InputError(
                cfg.path, f"keypoints[{i}]", f"a body below the root body {cfg.root_body}", kp.body or kp.site
            )
        kb.append(new_index[b])
        kpos.append(pos)
    return kb, kpos
