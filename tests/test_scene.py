"""Table sizing from the demo: covers the object's footprint, excludes hand keypoints below the top. Hands
placed one way: a scene's placements follow the demo's hands; controls keep one base frame per hand."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from helpers import box_object
from quasisim.errors import QuasisimError
from quasisim.targets.scene import Placement, make_scene, place_hands, size_table


def _demo(joints: np.ndarray, top: float = 0.8, left: np.ndarray | None = None) -> SimpleNamespace:
    T = joints.shape[0]
    return SimpleNamespace(
        support_height=top,
        object_pos=np.tile([0.0, 0.0, top + 0.025], (T, 1)),
        object_quat=np.tile([1.0, 0, 0, 0], (T, 1)),
        right_joints=joints,
        left_joints=left,
        human_joints=joints if left is None else np.concatenate([joints, left], axis=1),
    )


def test_table_excludes_low_keypoints_and_covers_object() -> None:
    obj = box_object()
    J = np.zeros((3, 21, 3))
    J[:, :, 2] = 0.9  # above the table...
    J[0, :5] = [0.25, 0.05, 0.6]  # ...except the start of the reach: beside the table, below its top
    table, notes = size_table(_demo(J), obj, margin=0.05, clearance=0.04)
    assert not notes
    assert table.xmax <= 0.25 - 0.04 + 1e-9  # cut on the side of the low keypoints
    assert table.xmin <= -0.025 - 0.05 and table.xmax >= 0.025 + 0.05  # footprint + margin kept
    assert table.ymin <= -0.075 and table.ymax >= 0.075
    low = J.reshape(-1, 3)
    low = low[low[:, 2] < 0.79]
    assert not table.contains_xy(low[:, :2], pad=0.039).any()
    assert abs(table.top - 0.8) < 1e-12 and table.half_size[2] == 0.4


def test_keypoint_inside_footprint_is_reported() -> None:
    J = np.zeros((2, 21, 3))
    J[:, :, 2] = 0.9
    J[0, 0] = [0.01, 0.0, 0.7]  # impossible: below the top right under the object
    _, notes = size_table(_demo(J), box_object())
    assert notes and "below the table top" in notes[0]


def test_real_clips_tables(data_dir) -> None:
    from quasisim.assets.object import load_object
    from quasisim.data.demo import load_demo

    for name in ("grab_s1_banana_eat_1.npz", "grab_s1_cup_pour_1.npz", "grab_s1_flashlight_on_1.npz"):
        d = load_demo(data_dir / name)
        table, notes = size_table(d, load_object(d.object_mesh_path))
        assert not notes
        pts = d.right_joints.reshape(-1, 3)
        low = pts[pts[:, 2] < d.support_height - 0.01]
        assert len(low) > 0 and not table.contains_xy(low[:, :2]).any()


def test_table_excludes_low_keypoints_of_both_hands() -> None:
    """ARCTIC: the object starts on a small stand and either hand may pass below its top beside it."""
    obj = box_object()
    right = np.zeros((2, 21, 3))
    right[:, :, 2] = 0.9
    left = right.copy()
    left[1, 8] = [-0.2, 0.0, 0.75]  # the left hand's index tip below the top, 20 cm to the -x side
    one, _ = size_table(_demo(right), obj)
    two, notes = size_table(_demo(right, left=left), obj)
    assert one.contains_xy(np.array([-0.2, 0.0]))  # the right hand alone leaves the full footprint
    assert not notes and not two.contains_xy(np.array([-0.2, 0.0]), pad=0.039)
    assert two.contains_xy(np.array([[0.03, 0.03], [-0.03, -0.03]])).all()  # still under the object


def test_stand_when_hands_pass_under_the_object_edges() -> None:
    """Keypoints below the top within the object's footprint (ARCTIC: fingers under the edges of an object on
    a small stand): the support becomes a stand under the object's centre of mass that keeps them clear."""
    obj = box_object(extents=(0.3, 0.1, 0.05))  # 30 cm along x
    right = np.zeros((2, 21, 3))
    right[:, :, 2] = 0.9
    left = right.copy()
    right[1, 8] = [0.14, 0.0, 0.78]  # under the +x edge, 2 cm below the top
    left[1, 8] = [-0.14, 0.0, 0.78]  # under the -x edge
    table, notes = size_table(_demo(right, left=left), obj)
    assert len(notes) == 1 and "stand under the object's centre of mass" in notes[0]
    assert not table.contains_xy(np.array([[0.14, 0.0], [-0.14, 0.0]]), pad=0.039).any()
    assert table.contains_xy(np.array([[0.03, 0.03], [-0.03, -0.03]])).all()  # the 6 cm square under the COM
    one, notes_one = size_table(_demo(right), obj)  # one hand under one edge: a stand as well
    assert notes_one and not one.contains_xy(np.array([0.14, 0.0]), pad=0.039) and one.contains_xy(np.array([-0.14, 0]))


def test_make_scene_takes_one_placement_per_hand_of_the_demo() -> None:
    J = np.zeros((2, 21, 3))
    J[:, :, 2] = 0.9
    one = SimpleNamespace(**vars(_demo(J)), sides=("right",), name="one", path=None, fps=20.0)
    two = SimpleNamespace(**vars(_demo(J, left=J)), sides=("right", "left"), name="two", path=None, fps=20.0)
    right, left = SimpleNamespace(n_joints=2), SimpleNamespace(n_joints=3)
    R = np.diag([1.0, -1.0, -1.0]).astype(np.float32)
    pair = place_hands((right, left), (np.eye(3), R))
    assert [p.side for p in pair] == ["right", "left"] and pair[1].base_rot.dtype == np.float64
    sc = make_scene(two, pair, box_object())
    assert sc.hands == (right, left) and sc.sides == ("right", "left") and sc.prefixes == ("rhand/", "lhand/")
    assert np.array_equal(sc.base_rots[1], R) and sc.dof_slices == (slice(0, 8), slice(8, 17)) and sc.n_dof == 17
    assert make_scene(one, pair[:1], box_object()).prefixes == ("hand/",)
    with pytest.raises(ValueError, match="has 1 hand"):
        make_scene(one, pair, box_object())
    with pytest.raises(QuasisimError, match="handles one-hand demos only"):
        make_scene(two, pair[:1], box_object())
    with pytest.raises(ValueError, match=r"placements for hands \(right, right\)"):
        make_scene(two, (Placement(right, np.eye(3)), Placement(left, R)), box_object())
    with pytest.raises(ValueError, match="side"):
        Placement(right, np.eye(3), "middle")


def test_controls_keep_one_base_frame_per_hand_in_the_file_keys_of_v1(tmp_path) -> None:
    from quasisim.data.controls import Controls, load_controls

    R = np.diag([1.0, -1.0, -1.0])
    kw = {"hand": "shadow", "demo": "d", "method": "test", "fps": 20.0, "joint_names": ("a", "b")}
    for rots in ((np.eye(3),), (np.eye(3), R)):
        c = Controls(base_rots=rots, q_targets=np.zeros((3, 8 * len(rots))), **kw)
        path = c.save(tmp_path / f"{len(rots)}.npz")
        with np.load(path) as z:
            assert ("left_base_rot" in z.files) == (len(rots) == 2) and np.array_equal(z["base_rot"], np.eye(3))
        c = load_controls(path)
        assert c.sides == ("right", "left")[: len(rots)] and all(map(np.array_equal, c.base_rots, rots))
    with pytest.raises(ValueError, match="base frames"):
        Controls(base_rots=(), q_targets=np.zeros((3, 8)), **kw)
