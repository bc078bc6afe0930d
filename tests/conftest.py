"""Shared fixtures. Real clips and the Allegro model are read from ../shared: tests that need them are skipped
when they are absent, except under CI (``CI=true``), where a missing folder stops the run before any test and
a test that would skip for missing data fails (``helpers.missing_data``). The summary counts the skips."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("QUASISIM_DATA") or REPO.parent / "shared" / "data")
ROBOTS = Path(os.environ.get("QUASISIM_ROBOT_PATH") or REPO.parent / "shared" / "robots")
os.environ.setdefault("QUASISIM_ROBOT_PATH", str(ROBOTS))

from helpers import UNDER_CI, missing_data  # noqa: E402
from quasisim.runtime import configure, free_compiled_programs  # noqa: E402

configure()
ARCTIC_CLIP = DATA / "arctic" / "arctic_s2_box_grab_01.npz"
ALLEGRO = ROBOTS / "allegro_hand" / "allegro_hand_right.urdf"
SHIPPED = {"development clips": DATA / "manifest.json", "ARCTIC clip": ARCTIC_CLIP, "Allegro model": ALLEGRO}


def pytest_sessionstart(session: pytest.Session) -> None:
    """Under CI, a missing data or robot folder fails the run at once with one line."""
    missing = [f"{what} ({path})" for what, path in SHIPPED.items() if not path.is_file()]
    if UNDER_CI and missing:
        pytest.exit(f"CI needs ../shared beside the clone: missing {', '.join(missing)} "
                    "(set QUASISIM_DATA / QUASISIM_ROBOT_PATH)", returncode=3)  # fmt: skip


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    """The number of skipped tests and why, so that a run cannot pass by skipping unnoticed."""
    skipped = terminalreporter.stats.get("skipped", [])
    reasons: dict[str, int] = {}
    for rep in skipped:
        reason = rep.longrepr[2] if isinstance(rep.longrepr, tuple) else str(rep.longrepr)
        reasons[reason] = reasons.get(reason, 0) + 1
    terminalreporter.write_line(f"skipped tests: {len(skipped)}")
    for reason, n in sorted(reasons.items()):
        terminalreporter.write_line(f"  {n} x {reason}")


@pytest.fixture(autouse=True, scope="module")
def _free_compiled_programs():
    """Each test module's compiled programs are dropped after it: the whole suite in one process otherwise
    reaches the kernel's memory-mapping limit and XLA's next compilation aborts (see quasisim.runtime)."""
    yield
    free_compiled_programs(force=True)


@pytest.fixture(autouse=True)
def _free_compiled_programs_when_needed():
    """Within a module too, once its programs hold half the limit's mappings (a module of end-to-end tests
    that compile many programs, e.g. the soft simulators' step beside the stiffest one, crashed there)."""
    yield
    free_compiled_programs()


@pytest.fixture(scope="session")
def data_dir() -> Path:
    if not (DATA / "manifest.json").is_file():
        missing_data(f"real demonstration clips not found at {DATA} (set QUASISIM_DATA)")
    return DATA


@pytest.fixture(scope="session")
def shadow():
    from quasisim.assets.hand import load_hand

    return load_hand("shadow")


@pytest.fixture(scope="session")
def allegro():
    if not ALLEGRO.is_file():
        missing_data(f"Allegro model not found under {ROBOTS} (set QUASISIM_ROBOT_PATH)")
    from quasisim.assets.hand import load_hand

    return load_hand("allegro")


@pytest.fixture(scope="session")
def example_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The synthetic examples written once per session."""
    from quasisim.data.synthetic import write_examples

    d = tmp_path_factory.mktemp("examples")
    write_examples(d)
    return d
