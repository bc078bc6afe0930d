"""Command line interface: ``quasisim --help``.

The root group ``main`` is in _common (every command module registers its commands on it); importing the command
modules here registers them all."""

from __future__ import annotations

from quasisim.cli import bench, convert, policy, results, run  # noqa: F401  (they register the commands)
from quasisim.cli._common import main

__all__ = ["main"]
