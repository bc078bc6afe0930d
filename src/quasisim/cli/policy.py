"""`quasisim policy`: learned tracking policies (PPO from stable-baselines3; the optional extra rl)."""

from __future__ import annotations

from pathlib import Path

import click

from quasisim.cli._common import _OVERWRITE, _RANGES, TARGET_CHOICE, _friendly, _parse_sets, _setup_runtime, main
from quasisim.errors import QuasisimError


def _need_rl() -> None:
    """A one-line error where the optional extra rl (stable-baselines3, PyTorch) is not installed."""
    import importlib.util

    if importlib.util.find_spec("stable_baselines3") is None:
        raise QuasisimError("quasisim policy needs the optional extra rl: pip install -e '.[rl]' (docs/policies.md)")


@main.group()
def policy() -> None:
    """Learned tracking policies on a clip: train (PPO), evaluate like any result, plot learning curves."""


def _split_sets(sets: tuple[str, ...]) -> tuple[dict, dict]:
    """``--set env.KEY=V`` / ``--set ppo.KEY=V`` -> (env overrides, PPO overrides)."""
    parsed = _parse_sets(sets)
    groups: dict[str, dict] = {"env": {}, "ppo": {}}
    for k, v in parsed.items():
        head, _, rest = k.partition(".")
        if head not in groups or not rest:
            raise QuasisimError(f"--set {k}: expected env.KEY (configs/track_env.yaml) or ppo.KEY (configs/ppo.yaml)")
        groups[head][rest] = v
    return groups["env"], groups["ppo"]


RESUMED = {"clip": "CLIP", "residual": "--residual", "method": "--method", "hand": "--hand", "target": "--target",
           "seed": "--seed", "algo": "--algo"}  # the options --resume takes from the stored training  # fmt: skip


def _given(ctx: click.Context) -> dict[str, object]:
    """The options of :data:`RESUMED` given on the command line (not left at their defaults): name -> value."""
    from click.core import ParameterSource

    defaults = (ParameterSource.DEFAULT, ParameterSource.DEFAULT_MAP, None)
    return {opt: ctx.params[name] for name, opt in RESUMED.items()
            if ctx.get_parameter_source(name) not in defaults and ctx.params[name] is not None}  # fmt: skip


@policy.command("train")
@click.argument("clip", type=click.Path(path_type=Path))
@click.option("--algo", type=click.Choice(["ppo"]), default="ppo", show_default=True, help="RL algorithm.")
@click.option(
    "--residual",
    "residual",
    type=click.Path(path_type=Path),
    default=None,
    help="Our result (run folder or controls.npz): train a residual on its PD targets (ours+residual). "
    "Without it: a DGrasp baseline (--method), PPO from scratch on the measured pose.",
)
@click.option(
    "--method",
    type=click.Choice(["dgrasp-tracking", "dgrasp-base", "dgrasp-tracking-curriculum"]),
    default=None,
    help="Without --residual: dgrasp-tracking (default; the kinematic retarget observed at every frame), "
    "dgrasp-base (the first grasp frame's grasp, then only the root guided along the object's path) or "
    "dgrasp-tracking-curriculum (dgrasp-tracking trained first in each analytical simulator of the physics "
    "curriculum, ppo.curriculum_stage_steps each, then in the target).",
)
@click.option("--hand", default="shadow", show_default=True, help="Robot hand without --residual.")
@click.option("--target", type=TARGET_CHOICE, default="mujoco", show_default=True)
@click.option("--steps", type=click.IntRange(1), default=200_000, show_default=True, help="Env steps in all.")
@click.option("--out", "out", type=click.Path(path_type=Path), required=True, help="Training folder.")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option(
    "--set",
    "sets",
    multiple=True,
    help="Override a setting: env.KEY=V (configs/track_env.yaml), ppo.KEY=V (configs/ppo.yaml). Not with "
    "--resume, which continues with the stored settings.",
)
@click.option(
    "--resume", is_flag=True, help="Continue the training in OUT from its last checkpoint, with its settings."
)
@click.option("--progress/--no-progress", default=True, show_default=True, help="A progress bar.")
@_OVERWRITE
@_friendly
def policy_train(
    clip: Path, algo: str, residual: Path | None, method: str | None, hand: str, target: str, steps: int, out: Path,
    seed: int, sets: tuple[str, ...], resume: bool, progress: bool, overwrite: bool,
) -> None:  # fmt: skip
    """Train a tracking policy for CLIP in OUT (setup.json, checkpoints, logs/, policy.zip, training.json)."""
    _need_rl()
    _setup_runtime()
    from quasisim.files import check_out_dir, run_lock
    from quasisim.policy.train import SETUP, TrainSetup, check_owned, check_resume, prepare, train

    if method is not None and residual is not None:
        raise QuasisimError(f"--method {method} with --residual: a residual policy is ours+residual; "
                            "the DGrasp baselines train from scratch (no --residual)")  # fmt: skip
    if resume and sets:
        raise QuasisimError(f"--set with --resume: a resumed training continues with the stored settings "
                            f"({out / SETUP}); to change them, start again with --overwrite")  # fmt: skip
    check_out_dir(out)
    if not resume:
        env_o, ppo_o = _split_sets(sets)
        check_owned(out)  # a folder of something else: refused, nothing in it touched
        if (out / SETUP).exists() and not overwrite:
            raise QuasisimError(f"{out} holds a training already: --resume to continue it, --overwrite to restart")
    with run_lock(out, f"policy train {clip}"):
        if resume:
            setup = TrainSetup.read(out)
            check_resume(out, setup, _given(click.get_current_context()))
        else:  # validated first, then the previous training (its best model and validation too) replaced
            setup = prepare(clip, out, residual, hand, target, seed, env_o, ppo_o, method or "dgrasp-tracking")
        click.echo(f"{setup.method} on {Path(setup.clip).stem} in {setup.target}: up to {steps} env steps")
        info = train(out, steps, resume=resume, progress=progress)
    click.echo(f"wrote {out / 'policy.zip'}: {info['env_steps']} env steps in {info['wall_s']:.0f} s")


@policy.command("evaluate")
@click.argument("folder", type=click.Path(path_type=Path))
@click.option("--out", "out", type=click.Path(path_type=Path), required=True, help="Output folder.")
@click.option(
    "--robust",
    type=click.IntRange(0, 1000),
    default=8,
    show_default=True,
    help="Perturbed worlds (the seeded worlds of robust success; 0: none).",
)
@click.option("--render/--no-render", default=False, show_default=True, help="Render the report's video.")
@click.option("--model", "which", type=click.Choice(["best", "final"]), default="best", show_default=True,
              help="best: the model that did best in validation (best.zip); final: the last one (policy.zip).")  # fmt: skip
@_RANGES
@_OVERWRITE
@_friendly
def policy_evaluate(
    folder: Path, out: Path, robust: int, render: bool, which: str, ranges: str, overwrite: bool
) -> None:  # fmt: skip
    """Replay the policy trained in FOLDER in its target: metrics.json (nominal and robust), report.html."""
    _need_rl()
    _setup_runtime()
    from quasisim.cli._common import _outputs_free, _ranges, _summary
    from quasisim.eval.evaluate import OUTPUTS
    from quasisim.files import MANIFEST
    from quasisim.policy.evaluate import evaluate_policy

    names = _ranges(ranges)
    if len(names) != 1:
        raise QuasisimError("quasisim policy evaluate: one perturbation set per run (--ranges default or wide)")
    _outputs_free(out, (*OUTPUTS, MANIFEST), overwrite)
    ev = evaluate_policy(folder, out, robust, names[0], render=render, progress=True, which=which)
    label = ev.metrics["policy"]["method"]
    _summary(f"{ev.scene.obj.name}: {label}", {label: ev.metrics}, out / "report.html")


@policy.command("curves")
@click.argument("folders", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--out", "out", type=click.Path(path_type=Path), required=True, help="Figure (.png or .svg).")
@_friendly
def policy_curves(folders: tuple[Path, ...], out: Path) -> None:
    """The learning curves of training FOLDERS in one figure."""
    from quasisim.policy.curves import plot_curves

    click.echo(f"wrote {plot_curves(list(folders), out)}")
