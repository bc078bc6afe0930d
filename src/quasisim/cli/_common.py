"""What the commands share: the root group ``main`` (every command module registers on it), the error
handling of every command, the options several commands take and their parsing."""

from __future__ import annotations

import dataclasses
import functools
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

from quasisim.errors import QuasisimError
from quasisim.method.spec import TransferSpec, parse_stages
from quasisim.targets import TARGETS

# The commands import their modules when they run (JAX, MuJoCo and PyBullet take seconds to load; `--help`
# and bad-option errors should not wait for them).

TARGET_CHOICE = click.Choice(list(TARGETS))


def _friendly(fn: Callable[..., Any]) -> Callable[..., Any]:
    """Turn quasisim's own errors into a one-line message and exit code 2 (no traceback)."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except (QuasisimError, OSError) as e:  # OSError: a path the system refuses (too long, a loop, no space)
            msg = f"{e.filename}: {e.strerror}" if isinstance(e, OSError) and e.filename and e.strerror else e
            click.echo(f"error: {' '.join(str(msg).split())}", err=True)  # one line, whatever the names hold
            sys.exit(2)

    return wrapper


INTERRUPTED = "interrupted; rerun the same command to resume"


def _interruptible(fn: Callable[..., Any]) -> Callable[..., Any]:
    """A resumable command stopped by Ctrl-C (or SIGTERM: exit 143 from :func:`_setup_runtime`'s handler,
    or a KeyboardInterrupt while Ray waits, :func:`quasisim.raycluster.sigterm_interrupts`) ends with one
    line and the shell's status for it: 130 (143), no traceback."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        from quasisim.raycluster import terminated

        try:
            return fn(*args, **kwargs)
        except KeyboardInterrupt:
            code = 143 if terminated() else 130
        except SystemExit as e:
            if e.code != 143:
                raise
            code = 143
        click.echo(INTERRUPTED, err=True)
        sys.exit(code)

    return wrapper


class _OneLineErrors(click.Group):
    """The top-level group: click's usage errors (bad or missing options) as one line on stderr, exit code 2."""

    def main(self, *args: Any, standalone_mode: bool = True, **kwargs: Any) -> Any:
        if not standalone_mode:
            return super().main(*args, standalone_mode=False, **kwargs)
        try:
            rv = super().main(*args, standalone_mode=False, **kwargs)
        except click.exceptions.NoArgsIsHelpError as e:
            click.echo(e.ctx.get_help() if e.ctx else str(e), err=True)
            sys.exit(2)
        except click.ClickException as e:
            where = f"{e.ctx.command_path}: " if getattr(e, "ctx", None) else ""
            click.echo(f"error: {where}{' '.join(e.format_message().split())} (see --help)", err=True)
            sys.exit(e.exit_code)
        except click.Abort:
            click.echo("Aborted!", err=True)
            sys.exit(1)
        sys.exit(rv if isinstance(rv, int) else 0)


def _outputs_free(out: Path, names: tuple[str, ...] = (), overwrite: bool = True) -> None:
    """Before any work: ``out`` can be written and holds none of ``names`` (unless ``overwrite``)."""
    from quasisim.files import check_out_dir, refuse_overwrite, remove_orphans

    check_out_dir(out)
    refuse_overwrite(out, names, overwrite)
    remove_orphans(out)  # what a killed atomic write left there


_OVERWRITE = click.option("--overwrite", is_flag=True, help="Replace the outputs of an earlier run in OUT.")
_CONFIG = click.option(
    "--config", "config_path", type=click.Path(path_type=Path), default=None, help="Transfer config YAML."
)


_ROBUST = click.option(
    "--robust", type=click.IntRange(0, 1000), default=None,
    help="Perturbed replays for robust success (default: n of configs/robust.yaml; 0: none).",
)  # fmt: skip
_CLOSED_LOOP = click.option(
    "--closed-loop", is_flag=True,
    help="Also replay the perturbed worlds of robust success closed loop: a tracker observes each world's state "
    "and re-plans around the result in the nominal target (configs/track.yaml; docs/transfer.md).",
)  # fmt: skip
_TRACK_SET = click.option(
    "--track-set", "track_sets", multiple=True,
    help="With --closed-loop: override a tracker setting of configs/track.yaml, e.g. --track-set every=1.",
)  # fmt: skip
_TRACKER = click.option(
    "--tracker", default="track.yaml", show_default=True,
    help="With --closed-loop: the tracker's settings, a file of configs/ (track.yaml; track_fast.yaml: a third "
    "of the time per control step) or a YAML path; --track-set overrides single settings.",
)  # fmt: skip


def _track_overrides(tracker: str, track_sets: tuple[str, ...]) -> dict[str, Any]:
    """``--tracker`` and ``--track-set`` as overrides of ``configs/track.yaml`` (only the settings that differ
    from it), validated."""
    import dataclasses

    from quasisim.method.track import TrackOptions

    def plain(o: Any) -> dict[str, Any]:
        return {k: v for k, v in dataclasses.asdict(o).items() if k != "path"}

    chosen, base = plain(TrackOptions.preset(tracker)), plain(TrackOptions.from_yaml())
    out = {k: list(v) if isinstance(v, tuple) else v for k, v in chosen.items() if v != base[k]}
    out |= _parse_sets(track_sets)
    TrackOptions.from_yaml(None, out)  # a bad setting fails here, before anything runs
    return out


_RANGES = click.option(
    "--ranges", default="default", show_default=True,
    help="Perturbation sets of robust success, comma-separated: default (configs/robust.yaml), wide "
    "(configs/robust_wide.yaml: about 2x the ranges and a push on the object mid-clip), sensing "
    "(configs/robust_sensing.yaml: the default worlds, seen closed loop through pose noise and one frame of latency), "
    "or the path of a YAML file of your own with the keys of configs/robust.yaml.",
)  # fmt: skip
_ROBUST_SET = click.option(
    "--robust-set", "robust_sets", multiple=True,
    help="Override a setting of every perturbation set of --ranges (the keys of configs/robust.yaml), e.g. "
    "--robust-set seed=7 (other worlds; never those the method chose its plans in, whatever the seed) or "
    "--robust-set mass=0.3; --robust N sets the number of replays.",
)  # fmt: skip


def _ranges(text: str) -> tuple[str, ...]:
    """``--ranges`` as a tuple of sets, each one of :data:`quasisim.eval.robust.RANGES` or the absolute path of
    a YAML file (:func:`quasisim.eval.robust.resolve_ranges`)."""
    from quasisim.eval.robust import resolve_ranges

    names = tuple(dict.fromkeys(x.strip() for x in text.split(",") if x.strip()))
    if not names:
        resolve_ranges("")  # the error listing the options
    return tuple(resolve_ranges(n) for n in names)


_LEAD_CLIP = click.option(
    "--lead-clip/--no-lead-clip", default=True, show_default=True,
    help="A local batch of several workers runs its first clip alone on every core first, so that its programs "
    "compile once on all cores; a resumed batch never does (docs/batch.md).",
)  # fmt: skip


def _summary(title: str, runs: dict[str, dict[str, Any]], report: Path) -> None:
    """The human summary that ends ``evaluate`` and ``transfer`` (strict first; metrics.json has the numbers)."""
    from quasisim.eval.summary import summary_lines

    click.echo("\n" + "\n".join(summary_lines(title, runs, report if report.is_file() else None)))


def _setup_runtime() -> None:
    """Environment and JAX settings of every command (before MuJoCo or JAX load); SIGTERM ends the command
    like Ctrl-C, so atomic writes remove their temporary files."""
    import signal

    from quasisim.runtime import configure

    configure()
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(128 + signum))


@click.group(cls=_OneLineErrors, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="quasisim")
def main() -> None:
    """quasisim: turn human hand-object demonstrations into robot-hand controls that work in MuJoCo/PyBullet."""


def _parse_sets(sets: tuple[str, ...], option: str = "--set") -> dict[str, Any]:
    """``--set a.b=1.5`` options (or another ``option`` of the same form) -> {"a.b": 1.5} (values parsed as
    YAML scalars)."""
    import yaml

    out: dict[str, Any] = {}
    ex = "budgets.fast.sim.control_steps=20" if option == "--set" else "seed=7"
    for s in sets:
        if "=" not in s:
            raise QuasisimError(f"{option} expects KEY=VALUE (e.g. {ex}), got {s!r}")
        k, v = s.split("=", 1)
        if not k.strip():
            raise QuasisimError(f"{option} expects KEY=VALUE with a key (e.g. {ex}), got {s!r}")
        try:
            out[k.strip()] = yaml.safe_load(v)
        except yaml.YAMLError as e:
            problem = " ".join(str(getattr(e, "problem", "") or e).split())
            raise QuasisimError(
                f"{option} {k.strip()}: expected a YAML value (e.g. 2.0, true, [1, 2]), got {v!r} ({problem})"
            ) from None
    return out


_SPEC = TransferSpec()  # the defaults of `quasisim transfer`'s options


def _ablation_flags(f: Any) -> Any:
    """Stage 3's ablation flags (each removes networks from what stage 3 trains)."""
    for name, what in (
        ("--no-control-transform", "the control transformation"),
        ("--no-local-residual", "the local residual network (the global one stays)"),
        ("--no-residual", "the residual networks (local and global)"),
    ):
        f = click.option(name, is_flag=True, help=f"Stage 3 without {what}.")(f)
    return f


def _stages(text: str | None) -> tuple[str, ...] | None:
    """``--stages``: None where not given (the method's own stages)."""
    return None if text is None else parse_stages(text)


# ---- option stacks shared by transfer, batch, bench transfer and evaluate -----------------------------------


def _bundle(name: str, build: Callable[..., Any], *options: Callable[[Any], Any]) -> Callable[[Any], Any]:
    """A decorator adding ``options`` (click options, shown in this order) to a command, whose function then
    gets one argument ``name`` = ``build(**the options' values)`` instead of one per option."""

    def decorate(f: Callable[..., Any]) -> Callable[..., Any]:
        @functools.wraps(f)
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            mine = {k: kwargs.pop(k) for k in keys}
            return _friendly(lambda: f(*args, **kwargs, **{name: build(**mine)}))()  # build's errors: one line

        before = len(getattr(wrapper, "__click_params__", []))
        for option in reversed(options):
            wrapper = option(wrapper)
        keys = [p.name for p in wrapper.__click_params__[before:]]  # type: ignore[attr-defined]
        return wrapper

    return decorate


@dataclasses.dataclass(frozen=True)
class Judging:
    """How a command judges its results beyond the nominal replay: ``robust`` replays per perturbation set of
    ``ranges`` (names or YAML paths) with the ``robust_set`` overrides, also ``closed_loop`` with the tracker
    settings ``track`` (overrides of configs/track.yaml)."""

    robust: int | None = None
    closed_loop: bool = False
    ranges: tuple[str, ...] = ("default",)
    robust_set: tuple[tuple[str, Any], ...] = ()
    track: dict[str, Any] = dataclasses.field(default_factory=dict)

    def configs(self) -> list[Any]:
        """The :class:`~quasisim.targets.perturb.RobustConfig` of each set."""
        return self.on(TransferSpec()).robust_configs()

    def on(self, spec: TransferSpec) -> TransferSpec:
        """``spec`` judged this way."""
        return dataclasses.replace(
            spec, robust=self.robust, closed_loop=self.closed_loop, ranges=self.ranges, robust_set=self.robust_set
        )


def _judging(
    robust: Callable[[Any], Any] = _ROBUST,
    closed_loop: Callable[[Any], Any] | None = _CLOSED_LOOP,
    tracker: bool = False,
) -> Callable[[Any], Any]:
    """``--robust``, ``--closed-loop`` (unless None), ``--tracker`` and ``--track-set`` (with ``tracker``),
    ``--ranges`` and ``--robust-set`` as one argument ``judging`` (:class:`Judging`, validated)."""

    def build(
        robust: int | None, ranges: str, robust_sets: tuple[str, ...], closed_loop: bool = False,
        tracker: str = "track.yaml", track_sets: tuple[str, ...] = (),
    ) -> Judging:  # fmt: skip
        over = tuple(sorted(_parse_sets(robust_sets, "--robust-set").items()))
        judging = Judging(robust, closed_loop, _ranges(ranges), over)
        sets = judging.configs()  # bad sets or overrides fail here
        if closed_loop and not any(c.n for c in sets):
            raise QuasisimError("--closed-loop replays the perturbed worlds of robust success: add --robust N (N > 0)")
        return dataclasses.replace(judging, track=_track_overrides(tracker, track_sets) if closed_loop else {})

    loop = (closed_loop, *((_TRACKER, _TRACK_SET) if tracker else ())) if closed_loop else ()
    return _bundle("judging", build, robust, *loop, _RANGES, _ROBUST_SET)


_HAND_HELP = "Built-in hand (shadow, shadow-left, shadow-short-thumb, allegro) or a hand YAML (docs/hands.md)."
_HAND = click.option("--hand", default=_SPEC.hand, show_default=True, help=_HAND_HELP)
_TARGET = click.option(
    "--target", type=TARGET_CHOICE, default=_SPEC.target, show_default=True, help="Simulator that judges the result."
)
_BUDGET = click.option(
    "--budget", default=_SPEC.budget, show_default=True, help="Step budget from the config: fast or paper."
)


def _spec_options(render: bool, render_help: str) -> Callable[[Any], Any]:
    """What to run, as one argument ``spec`` (:class:`TransferSpec`, not yet checked): ``--hand``,
    ``--target``, ``--curriculum``, ``--stages``, ``--method``, ``--budget``, ``--render`` (default ``render``)
    and stage 3's ablation flags."""
    from quasisim.method.registry import METHODS as REGISTERED
    from quasisim.method.spec import DEFAULT_METHOD, FULL_STAGES, METHODS, networks_from_flags

    def build(
        hand: str, target: str, curriculum: str, stages: str | None, method: str | None, budget: str, render: bool,
        no_residual: bool, no_local_residual: bool, no_control_transform: bool,
    ) -> TransferSpec:  # fmt: skip
        nets = networks_from_flags(no_residual, no_local_residual, no_control_transform)
        return TransferSpec(hand, target, curriculum, _stages(stages), budget, method, render, networks=nets)

    return _bundle(
        "spec",
        build,
        _HAND,
        _TARGET,
        click.option(
            "--curriculum",
            default=_SPEC.curriculum,
            show_default=True,
            help="short (4 analytical simulators), default (the paper's 8), curriculum2, none or a YAML path.",
        ),
        click.option(
            "--stages",
            default=None,
            help="Stages of method ours (given alone, they imply --method ours; default "
            f"{','.join(FULL_STAGES)}): quick: sampling in the target that ends the run where it passes strict "
            "success, 1: point dynamics, 2: contact curriculum, mpc: closed-loop MPC in MuJoCo with the "
            "quasi-physical model, sample: sampling MPC in the target, select: keep the best trajectory seen, "
            "judged in the target.",
        ),
        click.option(
            "--method",
            type=click.Choice(METHODS),
            default=None,
            help=f"Default {DEFAULT_METHOD} (ours where --stages is given). "
            + "; ".join(f"{name}: {m.summary}" for name, m in REGISTERED.items())
            + ".",
        ),
        _BUDGET,
        click.option("--render/--no-render", default=render, show_default=True, help=render_help),
        _ablation_flags,
    )


@dataclasses.dataclass(frozen=True)
class Clips:
    """The clips of a batch (``--clips``, ``--pattern``) and how it runs (``--ray``, ``--workers``, ``--set``,
    ``--record-transitions``, ``--lead-clip``)."""

    names: tuple[str, ...]
    pattern: str
    ray_address: str | None
    workers: int
    overrides: dict[str, Any]
    record: bool
    lead_clip: bool


def _clips_options(ray_help: str, set_help: str) -> Callable[[Any], Any]:
    """A batch's clips and how it runs, as one argument ``clips`` (:class:`Clips`)."""

    def build(
        clip_names: str, pattern: str, ray_address: str | None, workers: int, sets: tuple[str, ...], record: bool,
        lead_clip: bool,
    ) -> Clips:  # fmt: skip
        names = tuple(c.strip() for c in clip_names.split(",") if c.strip())
        return Clips(names, pattern, ray_address, workers, _parse_sets(sets), record, lead_clip)

    return _bundle(
        "clips",
        build,
        click.option(
            "--clips", "clip_names", default="", help="Comma-separated clip names (default: every clip of --pattern)."
        ),
        click.option(
            "--pattern",
            default="*.npz",
            show_default=True,
            help="Clips of DATA_DIR (glob); *_long.npz skipped unless named.",
        ),
        click.option("--ray", "ray_address", default=None, help=ray_help),
        click.option(
            "--workers",
            default=0,
            show_default=True,
            type=click.IntRange(0, None),
            help="Clips at once (0: one per core).",
        ),
        click.option("--set", "sets", multiple=True, help=set_help),
        click.option(
            "--record-transitions",
            "record",
            is_flag=True,
            help="Each clip's folder keeps what its sampling stage rolled out in the target (transitions/; "
            "docs/transfer.md). Clips finished before are not redone: use a new OUT.",
        ),
        _LEAD_CLIP,
    )
