"""What DGrasp's reward reads of a target beyond an observation: each hand body's normal contact force on the
object (:meth:`quasisim.targets.base.Target.body_contact_forces`), on a real clip's held cube. The reward's terms
themselves are tested in test_envs.py (hand-made observations with known answers, and an env episode)."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from quasisim.targets import Target
from test_sampling import _inputs

TOUCHING = {"robot0:ffdistal", "robot0:thdistal"}  # the fixture's grasp: index and thumb tips pinch the cube


@pytest.fixture(scope="module")
def held(data_dir: Path):
    """12 frames of a real clip from its lift-off (clip frame 30): the hand holds the cube in two contacts (as
    test_grasp.py's fixture of the same name)."""
    from quasisim.data.demo import load_demo

    return _inputs(load_demo(data_dir / "grab_s1_cubesmall_lift.npz").slice(30, 42))


@pytest.mark.parametrize("backend", ["mujoco", "pybullet"])
def test_body_contact_forces_of_the_held_cube(held, backend) -> None:
    """Per hand body, in the hand's ``body_names`` order: the index and thumb distal phalanges press the cube
    (more than one object weight each), no other body touches it, and the bodies' forces add up to the normal
    forces of :meth:`Target.contact_forces` over every contact of the hand (to the bit's rounding)."""
    from quasisim.targets import make_target

    demo, q, scene = held
    names = [n for h in scene.hands for n in h.body_names]
    weight = scene.obj.mass * scene.physics.gravity
    with make_target(backend, scene) as tgt:
        tgt.reset(q[0], (q[1] - q[0]) * demo.fps)
        for t in range(3):
            tgt.advance(q[t], q[t + 1])
            f = tgt.body_contact_forces()
            assert f.shape == (len(names),)
            assert {names[i] for i in np.flatnonzero(f)} == TOUCHING
            assert all(f[names.index(n)] > weight for n in TOUCHING)
            np.testing.assert_allclose(f.sum(), tgt.contact_forces(64)[..., 0].sum(), rtol=1e-12)


def test_a_target_without_body_contact_forces_says_so() -> None:
    with pytest.raises(NotImplementedError, match="target stub: per-body contact forces"):
        Target.body_contact_forces(SimpleNamespace(name="stub"))  # type: ignore[arg-type]
