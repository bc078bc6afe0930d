"""Building the scene of a demo: its object, its robot hands, the hands placed on their base frames.

Every command that judges controls or sets up a transfer builds its scene here (:func:`scene_for`): the
evaluation, the method's problem (:func:`quasisim.method.problem.make_problem`), the benchmarks.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from quasisim.assets.hand import HandModel, load_hand
from quasisim.assets.object import DEFAULT_DENSITY, ObjectAsset, load_object
from quasisim.data.demo import Demo
from quasisim.targets.scene import PhysicsOptions, Placement, Scene, make_scene


def load_object_for(demo: Demo, density: float | None = None, mass: float | None = None) -> ObjectAsset:
    """The demo's object mesh as an asset (``density`` in kg/m^3, default :data:`DEFAULT_DENSITY`; or a
    given ``mass`` in kg)."""
    return load_object(demo.object_mesh_path, name=demo.object_name, density=density or DEFAULT_DENSITY, mass=mass)


def demo_hands(hand: str | Path, sides: tuple[str, ...]) -> tuple[HandModel, ...]:
    """The robot hands for a demo with hands ``sides``: one hand, ``hand`` as it is; two hands, ``hand`` as a
    right hand and its left version (:meth:`~quasisim.assets.hand.HandConfig.for_side`, a mirror image)."""
    if tuple(sides) == ("right",):
        return (load_hand(hand),)
    return tuple(load_hand(hand, side=s) for s in sides)


def scene_for(
    demo: Demo, placements: Sequence[Placement], obj: ObjectAsset | None = None, physics: PhysicsOptions | None = None
) -> Scene:
    """The scene of ``demo`` with its robot hands ``placements`` (one per hand of the demo, right then left;
    :func:`~quasisim.targets.scene.make_scene`), loading the demo's object if ``obj`` is not given."""
    return make_scene(demo, placements, obj if obj is not None else load_object_for(demo), physics)
