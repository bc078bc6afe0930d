"""Shared fixtures. Real clips and the Allegro model are read from ../shared (skipped when absent)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("QUASISIM_DATA") or REPO.parent / "shared" / "data")
ROBOTS = Path(os.environ.get("QUASISIM_ROBOT_PATH") or REPO.parent / "shared" / "robots")
os.environ.setdefault("QUASISIM_ROBOT_PATH", str(ROBOTS))

from quasisim.runtime import configure, free_compiled_programs  # noqa: E402

configure()


@pytest.fixture(autouse=True, scope="module")
def _free_compiled_programs():
    """Each test module's compiled programs are dropped after it: the whole suite in one process otherwise
    reaches the kernel's memory-mapping limit and XLA's next compilation aborts (see quasisim.runtime)."""
    yield
    free_compiled_programs(force=True)


@pytest.fixture(scope="session")
def data_dir() -> Path:
    if not (DATA / "manifest.json").is_file():
        pytest.skip(f"real demonstration clips not found at {DATA} (set QUASISIM_DATA)")
    return DATA


@pytest.fixture(scope="session")
def shadow():
    from quasisim.assets.hand import load_hand

    return load_hand("shadow")


@pytest.fixture(scope="session")
def allegro():
    if not (ROBOTS / "allegro_hand" / "allegro_hand_right.urdf").is_file():
        pytest.skip(f"Allegro model not found under {ROBOTS} (set QUASISIM_ROBOT_PATH)")
    from quasisim.assets.hand import load_hand

    return load_hand("allegro")


@pytest.fixture(scope="session")
def example_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The synthetic examples written once per session."""
    from quasisim.data.synthetic import write_examples

    d = tmp_path_factory.mktemp("examples")
    write_examples(d)
    return d
