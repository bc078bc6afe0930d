"""Why a perturbed replay fails (:func:`quasisim.eval.failures.replay_failure`): each label on hand-made runs whose
object and hand motions are known (a demo that rests for 5 frames, then lifts the object 10 cm), and the contact
count of a recorded run read in MuJoCo."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from quasisim.eval.replay_failures import REPLAY_LABELS, label_counts, replay_failure

T, LIFT = 20, 5
KP = np.array([[0.0, 0.0, 0.0], [0.02, 0.0, 0.0], [0.0, 0.03, 0.0], [0.0, 0.0, 0.04]])  # hand keypoints about its wrist


def _demo():
    z = np.where(np.arange(T) < LIFT, 0.0, 0.1 * (np.arange(T) - LIFT) / (T - LIFT))
    pos = np.stack([np.zeros(T), np.zeros(T), 0.8 + z], 1)
    return SimpleNamespace(object_pos=pos, object_quat=np.tile([1.0, 0, 0, 0], (T, 1)))


def _run(obj_pos, obj_quat=None, hand_shift=None):
    """A rollout: the object at ``obj_pos``, the hand's keypoints 5 cm beside the demo's object, shifted by
    ``hand_shift`` (T, 3)."""
    demo = _demo()
    shift = np.zeros((T, 3)) if hand_shift is None else hand_shift
    kp = demo.object_pos[:, None] + np.array([0.05, 0, 0]) + KP[None] + shift[:, None]
    quat = np.tile([1.0, 0, 0, 0], (T, 1)) if obj_quat is None else obj_quat
    return SimpleNamespace(object_pos=obj_pos, object_quat=quat, robot_keypoints=kp)


def _after(t0, v):
    """(T, 3): 0 before frame t0, ``v`` (3,) from it."""
    return (np.arange(T) >= t0)[:, None] * np.asarray(v, float)


def _turned(t0, deg):
    r = Rotation.from_rotvec([0, 0, np.radians(deg)]).as_quat()
    q = np.tile([1.0, 0, 0, 0], (T, 1))
    q[t0:] = [r[3], r[0], r[1], r[2]]
    return q


HELD = np.full(T, 4)


@pytest.mark.parametrize(
    ("name", "run", "contacts", "label", "frame", "over"),
    [
        ("as the demo", lambda d: _run(d.object_pos), HELD, "pass", -1, ""),
        (
            "knocked before the lift",
            lambda d: _run(d.object_pos + _after(3, [0.03, 0, 0])),
            HELD,
            "pushed off",
            3,
            "translation",
        ),
        (
            "falls out of the hand",
            lambda d: _run(d.object_pos - _after(12, [0, 0, 0.05])),
            np.where(np.arange(T) >= 13, 0, 4),
            "drop",
            12,
            "translation",
        ),
        (
            "left behind, not below",
            lambda d: _run(d.object_pos + _after(12, [0.03, 0, 0])),
            np.where(np.arange(T) >= 12, 0, 4),
            "lost contact",
            12,
            "translation",
        ),
        (
            "held, the hand off course",
            lambda d: _run(d.object_pos + _after(10, [0.03, 0, 0]), hand_shift=_after(10, [0.03, 0, 0])),
            HELD,
            "carried off",
            10,
            "translation",
        ),
        ("turned in the hand", lambda d: _run(d.object_pos, _turned(10, 40)), HELD, "rotated in grasp", 10, "rotation"),
        (
            "slides in the hand",
            lambda d: _run(d.object_pos + _after(10, [0, 0.03, 0])),
            HELD,
            "slip in grasp",
            10,
            "translation",
        ),
    ],
)
def test_each_label_on_a_known_failure(name, run, contacts, label, frame, over) -> None:
    demo = _demo()
    f = replay_failure(demo, run(demo), _run(demo.object_pos), contacts, replay=3)
    assert (f.label, f.frame, f.over, f.replay) == (label, frame, over, 3), name


def test_without_contacts_a_drop_is_told_by_the_hand_frame_alone() -> None:
    demo = _demo()
    f = replay_failure(demo, _run(demo.object_pos - _after(12, [0, 0, 0.05])), _run(demo.object_pos), None, 0)
    assert f.label == "slip in grasp"  # no contact information: never "drop" or "lost contact"


def test_an_unstable_replay_fails_at_its_first_nan_frame() -> None:
    demo = _demo()
    pos = demo.object_pos.copy()
    pos[7:] = np.nan
    assert replay_failure(demo, _run(pos), _run(demo.object_pos), HELD, 0).frame == 7


def test_label_counts_cover_every_label() -> None:
    rows = [{"label": "pass"}, {"label": "drop"}, {"label": "drop"}]
    c = label_counts(rows)
    assert set(c) == {"pass", *REPLAY_LABELS} and c["drop"] == 2 and c["pass"] == 1 and sum(c.values()) == 3


def test_a_failure_after_the_demo_put_the_object_back_is_not_a_push_on_the_approach() -> None:
    demo = _demo()
    demo.object_pos[-3:] = demo.object_pos[0]  # the demo sets the object back where it started
    run = _run(demo.object_pos + _after(T - 2, [0, 0.03, 0]))
    f = replay_failure(demo, run, _run(demo.object_pos), HELD, 0)
    assert (f.frame, f.label) == (T - 2, "slip in grasp")


def test_bench_failures_replays_reads_the_closed_loop_caches_of_the_set_and_tracker(tmp_path) -> None:
    """``bench failures --replays``: the caches of the asked set and tracker only (another tracker's, an older
    cache without labels: "not recorded"), per clip and loop, and the label counts; none found: one line, exit 2."""
    import json

    from click.testing import CliRunner

    from quasisim.bench.closed_loop import _track_dict
    from quasisim.cli import main
    from quasisim.method.track import TrackOptions

    track = json.loads(json.dumps(_track_dict(TrackOptions.from_yaml())))
    other = {**track, "samples": 32}
    rows = [{"replay": 0, "label": "pass", "frame": -1, "over": ""},
            {"replay": 1, "label": "drop", "frame": 31, "over": "translation"}]  # fmt: skip

    def cache(clip, name, tr, metrics):
        d = tmp_path / clip / "cascade"
        d.mkdir(parents=True, exist_ok=True)
        settings = {"sets": {"default": {"name": "robust"}}, "track": tr, "target": "mujoco"}
        (d / f"robust_closed_loop-{name}.json").write_text(json.dumps({"settings": settings, "metrics": metrics}))

    cache("a", "1", track, {"robust": {"failures": rows}, "robust_closed_loop": {"failures": rows[:1] * 2}})
    cache("a", "2", other, {"robust": {"failures": rows[1:] * 2}, "robust_closed_loop": {"failures": rows[1:] * 2}})
    cache("b", "3", track, {"robust": {}, "robust_closed_loop": {}})
    res = CliRunner().invoke(main, ["bench", "failures", str(tmp_path), "--replays"])
    assert res.exit_code == 0, res.output
    assert "| a | cascade | 1 pass, 1 drop (f 31) | 2 pass |" in res.output
    assert "| b | cascade | not recorded | not recorded |" in res.output
    assert "| open | 2 | 1 | 0 | 1 |" in res.output and "| closed | 2 | 2 | 0 | 0 |" in res.output
    assert (tmp_path / "replay_failures.md").is_file()
    res = CliRunner().invoke(main, ["bench", "failures", str(tmp_path), "--replays", "--ranges", "wide"])
    assert res.exit_code == 2 and "expected closed-loop caches" in res.output
