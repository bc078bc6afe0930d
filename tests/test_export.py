"""Export of a result for MuJoCo's tools: scene.xml (standalone) and qpos (T, nq) in its layout; `view`."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest

from helpers import box_object, scene_with
from quasisim.errors import QuasisimError
from quasisim.eval.export import export_mujoco, load_export, view
from quasisim.targets import make_target


@pytest.fixture(scope="module")
def exported(shadow, tmp_path_factory: pytest.TempPathFactory):
    from scipy.spatial.transform import Rotation

    base_rot = Rotation.from_euler("y", 90, degrees=True).as_matrix()
    sc = scene_with(shadow, obj=box_object(density=200.0), base_rot=base_rot)
    T = 12
    q = np.zeros((T, 6 + shadow.n_joints))
    q[:, 0] = np.linspace(-0.2, 0.1, T)  # the palm sweeps through the box: the object moves too
    q[:, 2] = 0.84
    q[:, 6:] = np.clip(0.3, *shadow.joint_range.T)
    r = make_target("mujoco", sc).rollout(q)
    out = tmp_path_factory.mktemp("export")
    return sc, r, out, export_mujoco(sc, r, out)


def test_scene_and_qpos_reproduce_the_rollout(exported) -> None:
    sc, r, out, (scene_path, traj_path) = exported
    assert scene_path == out / "scene.xml" and traj_path == out / "trajectory.npz"
    model, qpos, fps = load_export(out)  # loads from the XML file alone (meshes inline)
    assert qpos.shape == (len(r.qpos), model.nq) and model.nq == 6 + sc.hands[0].n_joints + 7 and fps == sc.fps
    assert np.linalg.norm(r.object_pos[-1] - r.object_pos[0]) > 0.01  # a trajectory worth checking
    data = mujoco.MjData(model)
    site = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, f"hand/kp/{n}") for n in sc.hands[0].kp_names]
    body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "object")
    for t in range(len(qpos)):
        data.qpos[:] = qpos[t]
        mujoco.mj_kinematics(model, data)
        np.testing.assert_allclose(data.site_xpos[site], r.keypoints[t], atol=1e-5)
        np.testing.assert_allclose(data.xpos[body], r.object_pos[t], atol=1e-5)
        q = r.object_quat[t] * np.sign(np.dot(r.object_quat[t], data.xquat[body]))  # q and -q: one rotation
        np.testing.assert_allclose(data.xquat[body], q, atol=1e-5)


def test_view_without_a_display_says_so(exported, monkeypatch) -> None:
    out = exported[2]
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr("sys.platform", "linux")
    with pytest.raises(QuasisimError, match=r"no display.*scene\.xml"):
        view(out)
    with pytest.raises(QuasisimError, match=r"trajectory\.npz"):
        view(Path(out) / "missing")
