"""Open-loop prediction of the quasi-physical simulator from MuJoCo's recorded states (stage 3's measure)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest


@pytest.mark.slow
def test_prediction_error_against_mujoco(tmp_path: Path) -> None:
    from quasisim.assets.hand import load_hand
    from quasisim.data.demo import load_demo
    from quasisim.data.synthetic import write_example
    from quasisim.method.curriculum import load_curriculum
    from quasisim.method.problem import make_problem
    from quasisim.method.replay import collect, prediction_errors, split_starts, windows
    from quasisim.method.retarget import retarget
    from quasisim.targets.scene import Placement

    demo = load_demo(write_example("cube_lift", tmp_path, n_frames=16))
    hand = load_hand("shadow")
    rt = retarget(hand, demo)
    prob = make_problem(demo, (Placement(hand, rt.base_rot),), substeps=20, n_candidates=128)
    model, bq = prob.model, prob.base_quat
    cur = load_curriculum("default")
    stiff, soft = prob.params(cur.contact(8)), prob.params(cur.contact(1))
    buf = collect(prob.scene, [rt.q], demo.fps)
    assert buf.q_targets.shape == (1, demo.n_frames, 6 + hand.n_joints) and buf.keypoints.shape[:2] == (1, 16)
    np.testing.assert_allclose(buf.obj_pos[0, 0], demo.object_pos[0], atol=1e-9)  # at rest at the start
    w = windows(model, buf, [(0, t) for t in range(demo.n_frames - 3)], 3, bq)
    s, f = (prediction_errors(model, p, w, demo.fps, bq) for p in (stiff, soft))
    assert s.n_windows == demo.n_frames - 3 and s.obj_pos_cm.shape == (3,) and s.n_diverged == 0
    # the hand follows the same PD targets in both: keypoints agree within millimetres after one frame
    assert s.keypoints_mm[0] < 5.0
    # the stiffest simulator is the closest to MuJoCo; with d_c = 10 cm the object is pushed from afar
    assert s.obj_pos_cm[-1] < 0.5 * f.obj_pos_cm[-1]
    assert np.all(np.diff(f.obj_pos_cm) > 0)  # errors accumulate over the horizon

    # while the hand approaches, the object rests on the table in both simulators
    early = prediction_errors(model, stiff, windows(model, buf, [(0, t) for t in range(3)], 3, bq), demo.fps, bq)
    assert early.obj_pos_cm[-1] < 0.05 and early.obj_rot_deg[-1] < 0.5

    with pytest.raises(ValueError, match="20-frame window"):
        windows(model, buf, [(0, 0)], 20, bq)
    # held-out windows start after every training window has ended
    train, test = split_starts(2, 60, 10, 0.3)
    assert max(t for _, t in train) + 10 <= min(t for _, t in test) and max(t for _, t in test) == 49
