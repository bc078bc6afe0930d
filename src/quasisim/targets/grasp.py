"""How much a grasp's contacts have left before they slip: friction-cone slack (numpy only).

A contact ``c`` between a hand and the object presses with normal force ``f_n,c`` (N) and carries the
tangential force ``f_t,c`` (N, two components); Coulomb friction with coefficient ``mu`` holds it while
``|f_t,c| <= mu f_n,c``, the friction cone of radius ``mu f_n,c``. A grasp that holds only at the cone's rim
slips in a world with a little less friction (or a heavier object, or fingers that press less). The margin the
sampler plans for (``sampling.grasp_weight``): each contact should carry its load inside a cone shrunk by the
fraction ``margin``; what exceeds that shrunken cone, summed over the contacts, is

    slack_excess = sum_c max(0, |f_t,c| - (1 - margin) mu f_n,c)

in units of the object's weight ``m g`` (0: every contact holds with the margin; a grasp whose contacts sit at
the rim carries ``margin x`` its load beyond it). A contact set is stored as its cone radii and loads in object
weights, ``(..., C, 2)`` = ``(mu f_n, |f_t|) / (m g)`` (:func:`cone_loads`): the world's friction and the
object's weight are in it, so a perturbed world's contacts are weighed in that world.
"""

from __future__ import annotations

import numpy as np


def cone_loads(force: np.ndarray, friction: float, weight: float) -> np.ndarray:
    """(..., C, 2) each contact's friction-cone radius ``mu f_n`` and tangential load ``|f_t|``, in units of
    the object's weight ``weight`` (N, ``m g``), from contact forces ``force`` (..., C, 3) in the contact frame
    (normal, tangential 1, tangential 2; N; an empty slot all zeros) and the friction coefficient ``friction``."""
    force = np.asarray(force, np.float64)
    if not weight > 0:
        raise ValueError(f"cone_loads: the object's weight must be > 0 N, got {weight!r}")
    radius = friction * np.abs(force[..., 0])  # pressing; a sensor may report it with the pair's sign
    load = np.linalg.norm(force[..., 1:3], axis=-1)
    return np.stack([radius, load], axis=-1) / weight


def slack_excess(cones: np.ndarray, margin: float) -> np.ndarray:
    """(...,) ``sum_c max(0, |f_t,c| - (1 - margin) mu f_n,c)`` over the contacts of ``cones`` (..., C, 2)
    (:func:`cone_loads`, object weights): the load the contacts carry beyond cones shrunk by ``margin`` in
    [0, 1) (0: beyond the cones themselves, which Coulomb friction never lets a contact do)."""
    if not 0.0 <= margin < 1.0:
        raise ValueError(f"slack_excess: the margin must be in [0, 1), got {margin!r}")
    cones = np.asarray(cones, np.float64)
    return np.sum(np.maximum(cones[..., 1] - (1.0 - margin) * cones[..., 0], 0.0), axis=-1)


def strongest(force: np.ndarray, slots: int) -> np.ndarray:
    """(slots, 3) the ``slots`` contact forces of ``force`` (M, 3) with the largest norm, largest first, zero
    rows where there are fewer (the layout of MuJoCo's contact sensor with ``reduce="maxforce"``)."""
    force = np.asarray(force, np.float64).reshape(-1, 3)
    order = np.argsort(-np.linalg.norm(force, axis=1), kind="stable")[:slots]
    out = np.zeros((slots, 3))
    out[: len(order)] = force[order]
    return out
