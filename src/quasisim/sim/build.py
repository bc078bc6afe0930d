"""Build the simulator's Model and default Params from a hand, an object asset and the table."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from quasisim import tracecache
from quasisim.assets.hand import HandModel
from quasisim.sim.kinematics import geometry_arrays
from quasisim.sim.pointset import HandPoints, sample_hand_points
from quasisim.sim.types import NETWORKS, Model, Params

F32 = jnp.float32
TABLE_POINTS = ("hull", "surface")  # SimOptions.table_points
# Changes of the simulator that move its results at the same settings (part of the identity of every run
# with a stage in it, so a run never resumes from checkpoints of another): 1 table contact at mesh surface
# samples; 2 at points of the convex hull.
SIMULATOR_REVISION = 2
CONTACT_SCALE = 1.0e-4  # see docs/simulator.md: calibration of the curriculum's stiffness units against MuJoCo


@dataclass(frozen=True)
class SimOptions:
    """Discretisation of the quasi-physical simulator.

    Attributes:
        dt: substep (s).  substeps: substeps per frame (``dt * substeps`` should equal 1 / fps).
        sdf_spacing: SDF grid spacing (m).  n_surface: object samples for table contact.
        table_points: where those samples lie: ``hull`` (the convex hull's vertices, then points on its faces;
            default) or ``surface``
            (the mesh's surface; a curved object lying on the table rocks between sparse samples).
        n_candidates: hand points examined for contact per frame (broad phase).
        point_spacing, point_offset: hand point-set sampling (m); None = the hand config's values.
    """

    dt: float
    substeps: int
    sdf_spacing: float = 0.003
    n_surface: int = 128
    table_points: str = "hull"
    n_candidates: int = 128
    point_spacing: float | None = None
    point_offset: float | None = None

    @classmethod
    def for_fps(cls, fps: float, substeps: int, **kw: Any) -> SimOptions:
        """Options whose ``substeps`` fill one frame exactly: ``dt = 1 / (fps substeps)`` (the transfer
        config's budgets choose ``substeps``; 20 at 20 fps, dt 2.5 ms, is the largest step whose object
        trajectories stay within 1 mm (median) of the dt = 0.5 ms reference, see BENCHMARKS.md)."""
        return cls(dt=1.0 / (fps * substeps), substeps=substeps, **kw)


def build_model(
    hand: HandModel, obj: Any, table: Any, opts: SimOptions, offset: np.ndarray, points: HandPoints | None = None
) -> Model:
    """``obj`` is an :class:`~quasisim.assets.object.ObjectAsset`; ``table`` a :class:`~quasisim.targets.scene.Table`;
    ``offset`` (3,) the world position of the simulator origin (e.g. the object's initial position). A hand
    built per demo (``hand.config.per_demo``) gets its geometry as array leaves (``Model.hand_geom``) and, as
    its static part, the first hand of the same topology this process built (:func:`shared_topology`)."""
    if points is None:
        points = hand_set_points((hand,), opts)
    sdf = obj.sdf(spacing=opts.sdf_spacing).as_flat()
    if opts.table_points not in TABLE_POINTS:
        raise ValueError(f"SimOptions.table_points {opts.table_points!r}; valid: {', '.join(TABLE_POINTS)}")
    sample = obj.support_points if opts.table_points == "hull" else obj.surface_points
    surf, normals = sample(opts.n_surface, seed=0)
    return Model(
        hand=shared_topology(hand) if hand.config.per_demo else hand,
        point_body=jnp.asarray(points.body, dtype=jnp.int32),
        point_local=jnp.asarray(points.local, F32),
        sdf_values=sdf.values,
        sdf_dims=sdf.dims,
        sdf_origin=sdf.origin,
        sdf_spacing=sdf.spacing,
        obj_com=jnp.asarray(obj.com, F32),
        obj_surface=jnp.asarray(surf, F32),
        obj_normals=jnp.asarray(normals, F32),
        table=jnp.asarray(
            [
                table.xmin - offset[0],
                table.xmax - offset[0],
                table.ymin - offset[1],
                table.ymax - offset[1],
                table.top - offset[2],
            ],
            F32,
        ),
        offset=jnp.asarray(offset, F32),
        hand_geom=geometry_arrays(hand) if hand.config.per_demo else None,
        dt=float(opts.dt),
        substeps=int(opts.substeps),
        n_candidates=int(min(opts.n_candidates, points.n)),
    )


# per-demo hands by topology (:func:`shared_topology`); one entry per topology for the life of the process
_SHARED_HANDS: dict[tuple[Any, ...], HandModel] = {}
# what a per-demo hand's geometry arrays (HandGeometry) and point set carry: left out of its topology
_GEOMETRY_FIELDS = frozenset(
    {"config", "source", "geoms", "body_pos", "body_quat", "body_mass", "body_ipos", "body_iquat", "body_inertia",
     "joint_axis", "joint_pos", "kp_pos"}
)  # fmt: skip


def topology(hand: HandModel) -> tuple[Any, ...]:
    """What a compiled program may read from a per-demo hand's static part (its ``Model.hand``): the names,
    the tree, the joints' types, ranges and limits, the keypoints' bodies, human indices, weights and metric
    flags, the PD settings; not its geometry (passed to the programs as ``Model.hand_geom``) nor the rest of
    its config (per-demo file paths and keypoint offsets)."""
    fields = [f.name for f in dataclasses.fields(hand) if f.name not in _GEOMETRY_FIELDS]
    val = lambda v: (v.dtype.str, v.shape, v.tobytes()) if isinstance(v, np.ndarray) else v  # noqa: E731
    return (hand.config.name, hand.config.side, hand.config.pd, *(val(getattr(hand, f)) for f in fields))


# Traced programs on disk: a per-demo hand (whose programs read its geometry from Model.hand_geom) is keyed by
# its topology, as shared_topology shares it in memory; any other hand (geometry read from Model.hand) whole.
tracecache.key_by(HandModel, lambda hand: topology(hand) if hand.config.per_demo else None)


def shared_topology(hand: HandModel) -> HandModel:
    """The first per-demo hand of ``hand``'s :func:`topology` built in this process (``hand`` itself if it is
    the first). The simulator's ``Model.hand`` is static: JAX's in-memory program cache tells models apart by
    it, so a new hand object per demo traced stage 1's programs again for every demo of a long-lived process
    (a batch worker: ~8 s per clip, BENCHMARKS.md "Stage 1 traced once per worker"). The programs read a
    per-demo hand's geometry only from ``Model.hand_geom``; ``hand``'s own geometry, which the shared object
    does not have, stays with the callers that hold ``hand`` (its point set, its kinematic fit)."""
    return _SHARED_HANDS.setdefault(topology(hand), hand)


def hand_set_points(hands: tuple[HandModel, ...], opts: SimOptions) -> HandPoints:
    """The point sets of ``hands``, each sampled on its own hand (its config's spacing, offset and seed unless
    ``opts`` sets them), concatenated with body indices of the hand set :func:`~quasisim.assets.hand.join_hands`."""
    parts, b0 = [], 0
    for hand in hands:
        cfg = hand.config.points
        pts = sample_hand_points(
            hand,
            opts.point_spacing if opts.point_spacing is not None else cfg.spacing,
            opts.point_offset if opts.point_offset is not None else cfg.offset,
            cfg.seed,
            cfg.count,
        )
        parts.append(dataclasses.replace(pts, body=pts.body + b0))
        b0 += hand.n_bodies
    if len(parts) == 1:
        return parts[0]
    return HandPoints(*(np.concatenate([getattr(p, f) for p in parts]) for f in ("body", "local", "normal")))


CONTACT_KEYS = ("alpha", "d_c", "k_n", "k_f", "k_d", "mu")


def default_params(
    model: Model, obj_mass: float, obj_inertia: np.ndarray, contact: dict[str, float], hand: HandModel | None = None,
    **overrides: Any,
) -> Params:  # fmt: skip
    """The simulator with the curriculum settings ``contact`` (:data:`CONTACT_KEYS`, e.g.
    :meth:`~quasisim.method.curriculum.Curriculum.contact`), the object's own S and the calibrated table,
    joint and point constants below; ``overrides`` replace any other leaf. ``hand``: the hand (set) the model
    was built from, whose mass its points share; by default ``model.hand``, or for a per-demo hand (whose
    ``model.hand`` may be another demo's, :func:`shared_topology`) the masses in ``model.hand_geom``."""
    missing = set(CONTACT_KEYS) - set(contact)
    if missing:
        raise KeyError(f"contact settings lack {sorted(missing)}; expected {list(CONTACT_KEYS)}")
    if hand is not None:
        hand_mass = hand.total_mass
    elif model.hand_geom is not None:
        hand_mass = float(np.sum(np.asarray(model.hand_geom.body_mass, np.float64)))
    else:
        hand_mass = model.hand.total_mass
    hand = model.hand  # joints and PD settings: the same for every hand of a topology
    J = hand.n_joints
    pd = hand.config.pd
    values: dict[str, Any] = dict(
        **{k: contact[k] for k in CONTACT_KEYS},
        contact_scale=CONTACT_SCALE,
        table_k_n=2.0e3,
        table_k_d=3.0,
        table_k_f=2.0e3,
        table_mu=1.0,
        obj_mass=obj_mass,
        obj_inertia=np.asarray(obj_inertia),
        obj_lin_damp=0.0,
        obj_ang_damp=0.0,
        gravity=np.array([0.0, 0.0, -9.81]),
        point_mass=hand_mass / max(model.n_points, 1),
        joint_damping=np.full(J, pd.joint_damping),
        joint_stiffness=np.zeros(J),
        armature=np.full(J, pd.joint_armature),
        limit_k=100.0,
        joint_kp=np.full(J, pd.joint.kp),
        joint_kv=np.full(J, pd.joint.kv),
        residual=None,
        residual_local_on=0.0,
        residual_global_on=0.0,
        control_transform=None,
    )
    unknown = set(overrides) - set(values)
    if unknown:
        raise KeyError(f"unknown simulator parameters {sorted(unknown)}; valid: {sorted(values)}")
    values.update(overrides)
    return Params(**{k: (v if k in NETWORKS else jnp.asarray(v, F32)) for k, v in values.items()})


def attach_residual(
    model: Model, params: Params, nets: Any, local_on: bool = True, global_on: bool = True
) -> tuple[Model, Params]:
    """Put residual networks (an equinox module, e.g. :class:`quasisim.sim.residual.ResidualNets`) into the
    simulator: their arrays become Params leaves (trainable), the rest static Model metadata."""
    arrays, static = eqx.partition(nets, eqx.is_array)
    model = dataclasses.replace(model, residual_static=static)
    params = params.replace(residual=arrays, residual_local_on=float(local_on), residual_global_on=float(global_on))
    return model, params


def attach_control_transform(model: Model, params: Params, ct: Any) -> tuple[Model, Params]:
    """Put a control transformation (:class:`quasisim.sim.residual.ControlTransform`) into the simulator:
    its arrays become Params leaves (trainable), the rest static Model metadata."""
    arrays, static = eqx.partition(ct, eqx.is_array)
    return dataclasses.replace(model, control_transform_static=static), params.replace(control_transform=arrays)
