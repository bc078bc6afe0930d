"""Physics curricula: sequences of quasi-physical simulator settings, shipped as YAML data."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from quasisim.config import apply_overrides, build, read_yaml
from quasisim.errors import InputError, choice_error

CURRICULA_DIR = Path(__file__).parent / "curricula"


@dataclass(frozen=True)
class SimStage:
    """One simulator of a curriculum (SI units; see :class:`quasisim.sim.types.Params`)."""

    alpha: float
    d_c: float
    k_n: float
    k_f: float
    k_d: float
    residual: bool = False


@dataclass(frozen=True)
class Curriculum:
    name: str
    stages: tuple[SimStage, ...]
    mu: float = 10.0
    path: str = ""

    @classmethod
    def from_yaml(cls, path: str | Path, overrides: dict[str, Any] | None = None) -> Curriculum:
        path = Path(path)
        data = apply_overrides(read_yaml(path), overrides)
        data["path"] = str(path)
        c = build(cls, data, path)
        if not c.stages:
            raise InputError(path, "stages", "at least one simulator", "none")
        for i, s in enumerate(c.stages):
            if not 0.0 <= s.alpha <= 1.0:
                raise InputError(path, f"stages[{i}].alpha", "a value in [0, 1]", str(s.alpha))
            if min(s.d_c, s.k_n, s.k_f, s.k_d) < 0:
                raise InputError(path, f"stages[{i}]", "non-negative d_c, k_n, k_f, k_d", str(s))
        return c

    def params_overrides(self, i: int) -> dict[str, float]:
        s = self.stages[i]
        return {"alpha": s.alpha, "d_c": s.d_c, "k_n": s.k_n, "k_f": s.k_f, "k_d": s.k_d, "mu": self.mu}


def builtin_curricula() -> list[str]:
    return sorted(p.stem for p in CURRICULA_DIR.glob("*.yaml"))


def load_curriculum(name_or_path: str | Path) -> Curriculum:
    """A built-in curriculum (``default``, ``curriculum2``, ``none``) or a YAML path."""
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml"):
        return Curriculum.from_yaml(p)
    if str(name_or_path) in builtin_curricula():
        return Curriculum.from_yaml(CURRICULA_DIR / f"{name_or_path}.yaml")
    raise choice_error("curriculum", str(name_or_path), [*builtin_curricula(), "<path/to/curriculum.yaml>"])
