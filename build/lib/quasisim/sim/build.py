"""Build the simulator's Model and default Params from a hand, an object asset and the table."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax.numpy as jnp
import numpy as np

from quasisim.assets.hand import HandModel
from quasisim.pointset import HandPoints, sample_hand_points
from quasisim.sim.types import Control, Model, Params

F32 = jnp.float32
DEFAULT_DT = 0.0025  # s: see docs/simulator.md and BENCHMARKS.md (step-size study)
CONTACT_SCALE = 1.0e-4  # see docs/simulator.md: calibration of the curriculum's stiffness units against MuJoCo


@dataclass(frozen=True)
class SimOptions:
    """Discretisation of the quasi-physical simulator.

    Attributes:
        dt: substep (s).  substeps: substeps per frame (``dt * substeps`` should equal 1 / fps).
        sdf_spacing: SDF grid spacing (m).  n_surface: object surface samples for table contact.
        n_candidates: hand points examined for contact per frame (broad phase).
        point_spacing, point_offset: hand point-set sampling (m); None = the hand config's values.
    """

    dt: float = 0.001
    substeps: int = 50
    sdf_spacing: float = 0.003
    n_surface: int = 128
    n_candidates: int = 128
    point_spacing: float | None = None
    point_offset: float | None = None

    @classmethod
    def for_fps(cls, fps: float, substeps: int | None = None, **kw: Any) -> SimOptions:
        """Options whose substeps fill one frame exactly; by default ``dt`` is about 2.5 ms (see BENCHMARKS.md:
        the largest step whose object trajectories stay within 1 mm (median) of the dt = 0.5 ms reference,
        and within the reference's own sensitivity to its step)."""
        n = substeps if substeps is not None else max(1, round(1.0 / (fps * DEFAULT_DT)))
        return cls(dt=1.0 / (fps * n), substeps=n, **kw)


def build_model(
    hand: HandModel, obj: Any, table: Any, opts: SimOptions, offset: np.ndarray, points: HandPoints | None = None
) -> Model:
    """``obj`` is an :class:`~quasisim.assets.object.ObjectAsset`; ``table`` a :class:`~quasisim.targets.scene.Table`;
    ``offset`` (3,) the world position of the simulator origin (e.g. the object's initial position)."""
    if points is None:
        cfg = hand.config.points
        points = sample_hand_points(
            hand,
            opts.point_spacing if opts.point_spacing is not None else cfg.spacing,
            opts.point_offset if opts.point_offset is not None else cfg.offset,
            cfg.seed,
        )
    grid = obj.sdf(spacing=opts.sdf_spacing)
    surf, normals = obj.surface_points(opts.n_surface, seed=0)
    return Model(
        hand=hand,
        point_body=np.asarray(points.body, dtype=np.int32),
        point_local=jnp.asarray(points.local, F32),
        sdf_values=jnp.asarray(grid.values, F32),
        sdf_origin=jnp.asarray(grid.origin, F32),
        sdf_spacing=jnp.asarray(grid.spacing, F32),
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
        dt=float(opts.dt),
        substeps=int(opts.substeps),
        n_candidates=int(min(opts.n_candidates, points.n)),
    )


def default_params(model: Model, obj_mass: float, obj_inertia: np.ndarray, **overrides: Any) -> Params:
    """Parameters of the stiffest analytical simulator (curriculum sim 9) with the object's own S."""
    hand = model.hand
    J = hand.n_joints
    pd = hand.config.pd
    values: dict[str, Any] = dict(
        alpha=0.0,
        d_c=0.0,
        k_n=4.0e6,
        k_f=1.0e7,
        k_d=1.0e3,
        mu=10.0,
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
        point_mass=hand.total_mass / max(model.n_points, 1),
        joint_damping=np.full(J, pd.joint_damping),
        joint_stiffness=np.zeros(J),
        armature=np.full(J, pd.joint_armature),
        limit_k=100.0,
        joint_kp=np.full(J, pd.joint.kp),
        joint_kv=np.full(J, pd.joint.kv),
        residual=None,
        residual_local_on=0.0,
        residual_global_on=0.0,
    )
    unknown = set(overrides) - set(values)
    if unknown:
        raise KeyError(f"unknown simulator parameters {sorted(unknown)}; valid: {sorted(values)}")
    values.update(overrides)
    return Params(**{k: (v if k == "residual" else jnp.asarray(v, F32)) for k, v in values.items()})


def root_velocities(root_pos: np.ndarray, root_rot: np.ndarray, fps: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame root linear (T-1, 3) and world angular (T-1, 3) velocities that move the root from
    frame t to frame t+1 in one frame time."""
    from scipy.spatial.transform import Rotation

    lin = np.diff(root_pos, axis=0) * fps
    rel = np.einsum("tij,tkj->tik", root_rot[1:], root_rot[:-1])  # R_{t+1} R_t^T
    ang = Rotation.from_matrix(rel).as_rotvec() * fps
    return lin, ang


def controls_from_trajectory(
    model: Model, root_pos: np.ndarray, root_rot: np.ndarray, q: np.ndarray, fps: float
) -> Control:
    """Controls (T-1 frames) that replay a kinematic hand trajectory: root velocities from finite
    differences, joint PD targets at the next frame with the frame-to-frame target velocity, no
    feed-forward force and no point actuation. ``root_pos`` (T, 3), ``root_rot`` (T, 3, 3), ``q`` (T, J)."""
    lin, ang = root_velocities(root_pos, root_rot, fps)
    T1 = len(lin)
    return Control(
        root_vel=jnp.asarray(lin, F32),
        root_angvel=jnp.asarray(ang, F32),
        tau=jnp.zeros((T1, q.shape[1]), F32),
        q_target=jnp.asarray(q[1:], F32),
        qd_target=jnp.asarray(np.diff(q, axis=0) * fps, F32),
        point_force=jnp.zeros((T1, model.n_points, 3), F32),
    )


def attach_residual(
    model: Model, params: Params, nets: Any, local_on: bool = True, global_on: bool = True
) -> tuple[Model, Params]:
    """Put residual networks (an equinox module, e.g. :class:`quasisim.residual.ResidualNets`) into the
    simulator: their arrays become Params leaves (trainable), the rest static Model metadata."""
    import dataclasses

    import equinox as eqx

    arrays, static = eqx.partition(nets, eqx.is_array)
    model = dataclasses.replace(model, residual_static=static)
    params = params.replace(residual=arrays, residual_local_on=float(local_on), residual_global_on=float(global_on))
    return model, params
