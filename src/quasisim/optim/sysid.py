"""The identified parameter set S (paper: object mass, inertia, linear and angular velocity damping)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from quasisim.sim.types import Params, pytree

Array = jax.Array
F32 = jnp.float32


@pytree
class SysID:
    """S in unconstrained coordinates (all scalars), so that Adam can move it freely.

    ``mass = m0 exp(log_mass)`` (kg), ``inertia = I0 exp(log_inertia)`` (kg m^2), damping rates
    ``softplus(raw)`` (1/s); ``m0``, ``I0`` are the object asset's nominal values.
    """

    log_mass: Array
    log_inertia: Array
    lin_damp_raw: Array
    ang_damp_raw: Array

    @staticmethod
    def init(lin_damp: float = 0.0, ang_damp: float = 0.0) -> SysID:
        """The nominal S: the asset's mass and inertia, (almost) no velocity damping."""

        def inv_softplus(x: float) -> float:
            x = max(x, 1e-4)
            return float(np.log(np.expm1(x)))

        return SysID(
            jnp.zeros((), F32), jnp.zeros((), F32), jnp.asarray(inv_softplus(lin_damp), F32),
            jnp.asarray(inv_softplus(ang_damp), F32),
        )  # fmt: skip

    @staticmethod
    def from_array(x: np.ndarray) -> SysID:
        """Inverse of :meth:`as_array`."""
        return SysID(*(jnp.asarray(v, F32) for v in np.asarray(x)))

    def as_array(self) -> np.ndarray:
        """(4,) the unconstrained values (for checkpoints)."""
        return np.array([float(x) for x in (self.log_mass, self.log_inertia, self.lin_damp_raw, self.ang_damp_raw)])

    def apply(self, params: Params, mass0: float, inertia0: Array) -> Params:
        """``params`` with the object's S replaced (differentiable in ``self``)."""
        return dataclasses.replace(
            params,
            obj_mass=mass0 * jnp.exp(self.log_mass),
            obj_inertia=jnp.asarray(inertia0, F32) * jnp.exp(self.log_inertia),
            obj_lin_damp=jax.nn.softplus(self.lin_damp_raw),
            obj_ang_damp=jax.nn.softplus(self.ang_damp_raw),
        )

    def describe(self, mass0: float) -> dict[str, float]:
        """S in physical units: ``mass_kg``, ``inertia_scale``, ``lin_damp``, ``ang_damp`` (1/s)."""
        return {
            "mass_kg": float(mass0 * np.exp(float(self.log_mass))),
            "inertia_scale": float(np.exp(float(self.log_inertia))),
            "lin_damp": float(jax.nn.softplus(self.lin_damp_raw)),
            "ang_damp": float(jax.nn.softplus(self.ang_damp_raw)),
        }
