"""Rotation helpers that work on numpy and JAX arrays alike (quaternions are w, x, y, z)."""

from __future__ import annotations

from typing import Any

import jax.numpy as jnp
import numpy as np
from scipy.spatial.transform import Rotation

Array = jnp.ndarray


def _quat_matrix(q: Array, xp: Any) -> Array:
    """(..., 4) w, x, y, z -> (..., 3, 3) with the array module ``xp`` (numpy or jax.numpy)."""
    q = q / xp.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    r = xp.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    )  # fmt: skip
    return r.reshape((*q.shape[:-1], 3, 3))


def quat_to_mat(q: Array) -> Array:
    """(..., 4) unit quaternion (w, x, y, z) -> (..., 3, 3) rotation matrix (JAX)."""
    return _quat_matrix(q, jnp)


def quat_mul(a: Array, b: Array) -> Array:
    """Hamilton product a * b of (..., 4) quaternions."""
    aw, ax, ay, az = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bw, bx, by, bz = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return jnp.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def quat_conj(q: Array) -> Array:
    return q * jnp.array([1.0, -1.0, -1.0, -1.0])


def axis_angle_to_mat(axis: Array, angle: Array) -> Array:
    """Rodrigues: unit ``axis`` (..., 3), ``angle`` (...) in rad -> (..., 3, 3)."""
    x, y, z = axis[..., 0], axis[..., 1], axis[..., 2]
    c, s = jnp.cos(angle), jnp.sin(angle)
    C = 1 - c
    r = jnp.stack(
        [
            c + x * x * C, x * y * C - z * s, x * z * C + y * s,
            y * x * C + z * s, c + y * y * C, y * z * C - x * s,
            z * x * C - y * s, z * y * C + x * s, c + z * z * C,
        ],
        axis=-1,
    )  # fmt: skip
    return r.reshape((*jnp.shape(angle), 3, 3))


def quat_log(q: Array) -> Array:
    """Rotation vector (..., 3) of unit quaternions (..., 4), shortest arc; smooth at the identity."""
    q = q * jnp.where(q[..., :1] < 0, -1.0, 1.0)
    v = q[..., 1:]
    s2 = jnp.sum(v * v, axis=-1, keepdims=True)
    s = jnp.sqrt(jnp.maximum(s2, 1e-20))
    angle = 2.0 * jnp.arctan2(s, q[..., :1])
    scale = jnp.where(s2 > 1e-12, angle / s, 2.0 / jnp.maximum(q[..., :1], 1e-6))
    return v * scale


def quat_exp(v: Array) -> Array:
    """Unit quaternion (..., 4) w x y z of rotation vectors (..., 3) (inverse of :func:`quat_log`); smooth at 0."""
    a2 = jnp.sum(v * v, axis=-1, keepdims=True)
    a = jnp.sqrt(jnp.maximum(a2, 1e-20))
    s = jnp.where(a2 > 1e-12, jnp.sin(0.5 * a) / a, 0.5 - a2 / 48.0)
    return jnp.concatenate([jnp.cos(0.5 * a), v * s], axis=-1)


def skew(v: Array) -> Array:
    """(..., 3) -> (..., 3, 3) cross-product matrix: skew(a) @ b == cross(a, b)."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    o = jnp.zeros_like(x)
    return jnp.stack([o, -z, y, z, o, -x, -y, x, o], axis=-1).reshape((*v.shape[:-1], 3, 3))


def euler_xyz_to_mat(e: Array) -> Array:
    """Intrinsic x-y-z Euler angles (..., 3) -> Rx(a) @ Ry(b) @ Rz(c)."""
    ex = jnp.array([1.0, 0.0, 0.0])
    ey = jnp.array([0.0, 1.0, 0.0])
    ez = jnp.array([0.0, 0.0, 1.0])
    return axis_angle_to_mat(ex, e[..., 0]) @ axis_angle_to_mat(ey, e[..., 1]) @ axis_angle_to_mat(ez, e[..., 2])


# ---- numpy-only helpers -------------------------------------------------------------------------


def np_quat_to_mat(q: np.ndarray) -> np.ndarray:
    """(..., 4) w, x, y, z -> (..., 3, 3), numpy float64 (safe to call while JAX traces)."""
    return _quat_matrix(np.asarray(q, dtype=np.float64), np)


def np_mat_to_quat(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) -> (..., 4) w, x, y, z with w >= 0."""
    shp = R.shape[:-2]
    xyzw = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat()
    q = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    return q.reshape((*shp, 4))


def np_mat_to_euler_xyz(R: np.ndarray) -> np.ndarray:
    """Inverse of :func:`euler_xyz_to_mat` (intrinsic x-y-z), numpy."""
    shp = R.shape[:-2]
    e = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_euler("XYZ")
    return e.reshape((*shp, 3))


def quat_angle_deg(q_ref: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Angle (deg) of q_ref^-1 q for (..., 4) unit quaternions; sign-invariant."""
    d = np.abs(np.sum(np.asarray(q_ref) * np.asarray(q), axis=-1))
    d = d / (np.linalg.norm(q_ref, axis=-1) * np.linalg.norm(q, axis=-1))
    return np.degrees(2.0 * np.arccos(np.clip(d, 0.0, 1.0)))


def chordal_mean_rotation(R: np.ndarray) -> np.ndarray:
    """Rotation closest (Frobenius) to the mean of (N, 3, 3) rotations."""
    M = R.mean(axis=0)
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def kabsch(src: np.ndarray, dst: np.ndarray, w: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Weighted rigid fit: R, t minimising sum w_i |R src_i + t - dst_i|^2. Shapes (N, 3)."""
    w = np.ones(len(src)) if w is None else np.asarray(w, dtype=np.float64)
    w = w / w.sum()
    cs, cd = w @ src, w @ dst
    H = ((src - cs) * w[:, None]).T @ (dst - cd)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, cd - R @ cs


def sign_continuous(q: np.ndarray) -> np.ndarray:
    """(T, 4) quaternions with signs flipped so that dot(q[t], q[t-1]) >= 0 and q[0].w >= 0."""
    q = np.array(q, dtype=np.float64)
    if q[0, 0] < 0:
        q[0] *= -1
    for t in range(1, len(q)):
        if np.dot(q[t], q[t - 1]) < 0:
            q[t] *= -1
    return q
