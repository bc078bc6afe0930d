"""Robust success: a run's controls replayed in seeded, perturbed copies of its target, open or closed loop.

A trajectory planned in one simulator meets another world: a slightly heavier object, other friction, an
object a few millimetres off, softer servos, a push. :func:`robust_success` replays the same PD targets in
``n`` perturbed scenes (:func:`perturbed_scene`, ranges in ``configs/robust.yaml``, or the wider
``configs/robust_wide.yaml`` with a push mid-clip) and reports the fraction of replays that pass each success
criterion (:data:`quasisim.eval.metrics.SUCCESS_KEYS`). Open loop, the PD targets are applied as they are;
closed loop, a policy (:class:`Policy`, e.g. :class:`quasisim.method.track.Tracker`) observes each perturbed
world frame by frame and chooses the targets. Both meet the same seeded worlds, so they compare clip by clip.

The perturbations themselves (:class:`~quasisim.targets.perturb.RobustConfig`, :func:`perturbed_scene`,
:func:`push_of`, :class:`Sensor`, :func:`replay` and the metrics keys they name) are
:mod:`quasisim.targets.perturb`'s, since the method meets them too (the sampling stage's copies, the cascade's
closed-loop gate); they are imported here under the same names.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from quasisim.data.demo import Demo
from quasisim.targets.perturb import CLOSED_LOOP_SUFFIX as CLOSED_LOOP_SUFFIX
from quasisim.targets.perturb import RANGES as RANGES
from quasisim.targets.perturb import ROBUST_KEY as ROBUST_KEY
from quasisim.targets.perturb import ROBUST_PATH as ROBUST_PATH
from quasisim.targets.perturb import Policy as Policy
from quasisim.targets.perturb import RobustConfig as RobustConfig
from quasisim.targets.perturb import Sensor as Sensor
from quasisim.targets.perturb import finger_columns as finger_columns
from quasisim.targets.perturb import perturbed_scene as perturbed_scene
from quasisim.targets.perturb import push_of as push_of
from quasisim.targets.perturb import replay as replay
from quasisim.targets.perturb import replays as replays
from quasisim.targets.perturb import resolve_ranges as resolve_ranges
from quasisim.targets.perturb import world_replays
from quasisim.targets.scene import Scene

# metrics.json key of each shipped perturbation set -> what it perturbs (reports, tables)
ROBUST_SETS = {
    "robust": "object mass, friction, initial object position, PD gains; configs/robust.yaml",
    "robust_wide": "about 2x those ranges and a push on the object mid-clip; configs/robust_wide.yaml",
    "robust_sensing": "the default worlds seen through noise (2 mm, 2 deg, 0.01 rad) and one frame of latency; "
    "configs/robust_sensing.yaml",
}


def robust_success(
    demo: Demo, scene: Scene, q_targets: np.ndarray, target: str, cfg: RobustConfig,
    policy: Callable[[], Policy] | None = None,
) -> dict[str, Any]:  # fmt: skip
    """``{"n", "seed", <success key>: fraction of the n perturbed replays that pass it, "unstable": count}``
    (an unstable replay passes nothing); ``{}`` when ``cfg.n`` is 0. With ``policy`` (a function making a
    fresh :class:`Policy` per replay, built from the nominal ``scene`` only: the perturbed world is never
    handed to it) the replays are closed loop, and the result also holds ``seconds_per_replay`` and the
    policy's mean ``cost()`` per replay (``tracker``). ``failures``: per replay, its first frame over a strict
    limit, which limit and why (:class:`~quasisim.eval.replay_failures.ReplayFailure` as a dict; ``quasisim bench
    failures --replays``)."""
    from quasisim.eval.metrics import SUCCESS_KEYS, evaluate_rollout

    if cfg.n == 0:
        return {}
    passed, unstable, costs, wall = dict.fromkeys(SUCCESS_KEYS, 0), 0, [], 0.0
    why = _FailureLabeller(demo, scene, q_targets, target)
    for i, (rollout, cost, seconds) in enumerate(world_replays(scene, q_targets, target, cfg, policy)):
        wall += seconds
        if cost is not None:
            costs.append(cost)
        why.add(i, rollout)
        if rollout.instability:
            unstable += 1
            continue
        ok = evaluate_rollout(demo, rollout, None)[0]["success"]
        for k in SUCCESS_KEYS:
            passed[k] += bool(ok[k])
    out = {"n": cfg.n, "seed": cfg.seed, **{k: passed[k] / cfg.n for k in SUCCESS_KEYS}, "unstable": unstable}
    out["failures"] = why.rows
    if policy is not None:
        out["seconds_per_replay"] = wall / cfg.n
        out["tracker"] = {k: float(np.mean([c[k] for c in costs])) for k in costs[0]}
    return out


# ---- the judging settings in a run's identity (a batch's clip.json) ------------------------------------------

LEGACY_KEYS = ("name", "n", "seed")  # what a row written before the judging settings were recorded tells of them


def judged_with(cfgs: list[RobustConfig]) -> list[dict[str, Any]]:
    """The worlds a run is judged in, as its identity records them: every set with replays, its settings (the
    file's path aside)."""
    import dataclasses
    import json

    sets = [{k: v for k, v in dataclasses.asdict(c).items() if k != "path"} for c in cfgs if c.n]
    return json.loads(json.dumps(sets))


class _FailureLabeller:
    """Each replay's strict outcome and why it failed (:func:`quasisim.eval.replay_failures.replay_failure`: the first
    frame over a limit, which limit, a label), against the plan's nominal open-loop replay; hand-object contacts
    read in the nominal scene's MuJoCo model (geometry only, the same in every world; none in PyBullet)."""

    def __init__(self, demo: Demo, scene: Scene, q_targets: np.ndarray, target: str) -> None:
        from quasisim.targets import make_target

        self.demo, self.rows = demo, []
        with make_target(target, scene) as tgt:
            self.nominal = tgt.rollout(np.asarray(q_targets, np.float64))
            self.mm = getattr(tgt, "mm", None)  # MuJoCo's compiled scene (contacts), None in PyBullet

    def add(self, i: int, rollout: Any) -> None:
        from dataclasses import asdict

        from quasisim.eval.replay_failures import replay_failure

        contacts = None
        if self.mm is not None and np.isfinite(rollout.object_pos).all() and np.isfinite(rollout.qpos).all():
            from quasisim.targets.mujoco_target import hand_object_contacts

            contacts = hand_object_contacts(self.mm, rollout.qpos, rollout.object_pos, rollout.object_quat)
        self.rows.append(asdict(replay_failure(self.demo, rollout, self.nominal, contacts, i)))


def judged_in_row(metrics: dict[str, Any]) -> list[dict[str, Any]]:
    """The open-loop sets a run's metrics hold, as ``{name, n, seed}`` (a row of a folder written before the
    judging settings were part of a run's identity)."""
    return [
        {"name": k, "n": v["n"], "seed": v["seed"]}
        for k, v in metrics.items()
        if isinstance(v, dict) and {"n", "seed"} <= v.keys() and not k.endswith(CLOSED_LOOP_SUFFIX)
    ]


def judging_mismatch(identity: dict[str, Any], row: dict[str, Any], given: list[RobustConfig]) -> str | None:
    """How the judging settings ``given`` differ from those a finished run was judged with (its stored
    ``identity``, or for an identity without them its ``row``'s metrics): ``"OPTION: stored A, given B"`` naming
    the first difference, or None where there is none."""
    want = judged_with(given)
    if "judging" in identity:
        have = identity["judging"]
    else:
        have, want = judged_in_row(row.get("metrics", {})), [{k: c[k] for k in LEGACY_KEYS} for c in want]
    if have == want:
        return None
    if not have or not want:
        return f"--robust: stored {have[0]['n'] if have else 0}, given {want[0]['n'] if want else 0}"
    names = [c["name"] for c in have], [c["name"] for c in want]
    if names[0] != names[1]:
        return f"--ranges: stored {','.join(names[0])}, given {','.join(names[1])}"
    h, w = next((h, w) for h, w in zip(have, want, strict=True) if h != w)
    key = next(k for k in [*w, *h] if h.get(k) != w.get(k))
    option = "--robust" if key == "n" else f"--robust-set {key}"
    return f"{option}: stored {h.get(key)}, given {w.get(key)}" + (f" (set {w['name']})" if len(want) > 1 else "")
