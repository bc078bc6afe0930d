"""Physics curricula: sequences of quasi-physical simulator settings, shipped as YAML data."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from quasisim.config import apply_overrides, build, read_yaml
from quasisim.errors import InputError, choice_error

CURRICULA_DIR = Path(__file__).parents[1] / "configs" / "curricula"


@dataclass(frozen=True)
class SimStage:
    """One simulator of a curriculum (SI units; see :class:`quasisim.sim.types.Params`)."""

    alpha: float
    d_c: float
    k_n: float
    k_f: float
    k_d: float
    residual: bool


@dataclass(frozen=True)
class Curriculum:
    """Simulators from soft to stiff (``configs/curricula/*.yaml``); ``mu`` is the friction coefficient of all."""

    name: str
    stages: tuple[SimStage, ...]
    mu: float
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
        if not c.rigid:
            raise InputError(path, "stages", "at least one rigid simulator (alpha 0, residual false)", "none")
        if not c.mu > 0:
            raise InputError(path, "mu", "a positive friction coefficient", str(c.mu))
        return c

    def contact(self, i: int) -> dict[str, float]:
        """Simulator ``i``'s contact settings as :class:`~quasisim.sim.types.Params` leaves."""
        s = self.stages[i]
        return {"alpha": s.alpha, "d_c": s.d_c, "k_n": s.k_n, "k_f": s.k_f, "k_d": s.k_d, "mu": self.mu}

    @property
    def relaxed(self) -> list[int]:
        """Indices of the relaxed point-set simulators (alpha > 0; stage 1)."""
        return [i for i, s in enumerate(self.stages) if s.alpha > 0 and not s.residual]

    @property
    def rigid(self) -> list[int]:
        """Indices of the analytical rigid-hand simulators (alpha = 0; stage 2), soft to stiff."""
        return [i for i, s in enumerate(self.stages) if s.alpha == 0 and not s.residual]

    @property
    def stiffest(self) -> int:
        """Index of the stiffest analytical simulator (the last rigid one): the model of MPC."""
        return self.rigid[-1]


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
