"""Whole-clip programs run on the clip's frames padded to a multiple of ten (quasisim.optim.trajectory.FRAME_BUCKET):
the padded objective gives the clip's own loss and gradient, and clips of different lengths in one bucket
share one compiled program."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from helpers import STIFF


@pytest.fixture(scope="module")
def lift(tmp_path_factory: pytest.TempPathFactory):
    """The synthetic cube lift (20 frames) set up for transfer, its kinematic retarget and the stiff simulator."""
    from quasisim.data.demo import load_demo
    from quasisim.data.synthetic import write_example
    from quasisim.method.problem import kinematic_problem

    demo = load_demo(write_example("cube_lift", tmp_path_factory.mktemp("demo"), n_frames=20))
    prob, q = kinematic_problem(demo, "shadow", 5, 64)
    return prob, q, prob.params(STIFF)


def _first(ref, n: int):
    """The reference of a clip's first ``n`` frames (frames 1..n-1)."""
    cut = {k: getattr(ref, k)[: n - 1] for k in ("obj_pos", "obj_quat", "keypoints")}
    return dataclasses.replace(ref, **cut)


def test_bucket_and_pad_round_trip() -> None:
    from quasisim.optim.trajectory import Trajectory, bucket_frames, first_frames, pad_frames

    assert [bucket_frames(n) for n in (1, 10, 11, 58, 60, 61, 150)] == [10, 10, 20, 60, 60, 70, 150]
    traj = Trajectory.from_q(np.random.default_rng(0).normal(size=(13, 8)), 5)
    traj = dataclasses.replace(traj, point_force=jnp.ones_like(traj.point_force))
    padded = pad_frames(traj, 20)
    assert padded.base.shape == (20, 6) and padded.joints.shape == (20, 2) and padded.point_force.shape == (19, 5, 3)
    np.testing.assert_array_equal(padded.joints[13:], np.repeat(np.asarray(traj.joints[-1:]), 7, 0))  # targets held
    assert float(jnp.abs(padded.point_force[12:]).max()) == 0.0  # no forces after the clip's end
    back = first_frames(padded, 13)
    for a, b in zip(jax.tree.leaves(back), jax.tree.leaves(traj), strict=True):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="cannot pad a 13-frame trajectory to 12"):
        pad_frames(traj, 12)


@pytest.mark.slow  # > 20 s on 2 cores (compiles two value-and-gradient programs)
def test_padded_objective_gives_the_clips_own_loss_and_gradient(lift) -> None:
    """A 13-frame clip scored by the program of 20 frames (padded) and by an objective of exactly 13 frames:
    the same loss, terms and gradient (frames after the clip's end weigh nothing, the smoothness term
    included), and the gradient has the clip's 13 frames."""
    from quasisim.optim.objective import TrackingObjective, Weights
    from quasisim.optim.sysid import SysID

    prob, q, params = lift
    n = 13
    ref = _first(prob.reference(), n)
    padded = prob.objective(ref)
    assert padded.n_frames == 20 and float(padded.frame_w.sum()) == n - 1
    exact = TrackingObjective(**{**{f.name: getattr(padded, f.name) for f in dataclasses.fields(padded)},
                                 "ref": ref, "frame_w": jnp.ones(n - 1, jnp.float32)})  # fmt: skip
    assert exact.n_frames == n
    rng = np.random.default_rng(1)
    traj = prob.trajectory(q[:n] + rng.normal(0.0, 0.01, q[:n].shape))  # rough targets: every term non-zero
    w = Weights(1.0, 1.0, 1.0, 0.0, 1.0, 1e-4).arrays()
    (la, ta), (ga, sa) = padded.value_and_grad(traj, SysID.init(), params, w)
    (lb, tb), (gb, sb) = jax.jit(jax.value_and_grad(lambda t, s: exact(t, s, params, w), argnums=(0, 1), has_aux=True))(
        traj, SysID.init()
    )
    assert float(tb["smooth"]) > 0 and float(tb["obj_pos"]) > 0
    np.testing.assert_allclose(float(la), float(lb), rtol=1e-5)
    for k in tb:
        np.testing.assert_allclose(float(ta[k]), float(tb[k]), rtol=1e-4, atol=1e-7, err_msg=k)
    assert ga.base.shape == (n, 6) and ga.point_force.shape[0] == n - 1
    for a, b in zip(jax.tree.leaves((ga, sa)), jax.tree.leaves((gb, sb)), strict=True):
        scale = float(jnp.abs(b).max()) + 1e-12
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-3 * scale)
    v, _ = padded.value(traj, SysID.init(), params, w)  # the forward pass alone, also padded
    np.testing.assert_allclose(float(v), float(lb), rtol=1e-4)


@pytest.mark.slow  # > 20 s on 2 cores
def test_clips_of_one_bucket_share_one_program(lift) -> None:
    """Clips of 12, 15 and 20 frames run one compiled value-and-gradient program (the 20 frames')."""
    from quasisim.optim.objective import Weights, padded_value_and_grad
    from quasisim.optim.sysid import SysID

    prob, q, params = lift
    w = Weights(1.0, 1.0, 1.0, 0.0, 1e-3, 1e-4).arrays()
    seen = []
    for n in (12, 15, 20):
        obj = prob.objective(_first(prob.reference(), n))
        (loss, _), (g, _) = obj.value_and_grad(prob.trajectory(q[:n]), SysID.init(), params, w)
        assert np.isfinite(float(loss)) and g.joints.shape[0] == n
        seen.append(len(padded_value_and_grad.programs))
    assert seen[0] >= 1, "the compiled programs are recorded (QUASISIM_TRACE_CACHE must not be 0)"
    assert seen[1] == seen[0] and seen[2] == seen[0], seen
