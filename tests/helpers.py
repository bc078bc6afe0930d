"""Test helpers: a small duck-typed object asset so target tests need no SDF/CoACD work."""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from types import ModuleType, SimpleNamespace
from typing import NoReturn

import numpy as np
import pytest

UNDER_CI = os.environ.get("CI", "").strip().lower() in ("1", "true", "yes")


@contextmanager
def swapped_modules(mods: dict[str, ModuleType]) -> Iterator[None]:
    """``sys.modules`` with ``mods`` in it (stand-ins for modules a pickle names), as it was again afterwards."""
    old = {k: sys.modules.get(k) for k in mods}
    sys.modules.update(mods)
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                del sys.modules[k]
            else:
                sys.modules[k] = v


def ctrl_c_restored(argv: list[str]) -> list[str]:
    """``[python, "-m", module, *args]`` or ``[python, script, *args]`` as a command that a test can stop with
    SIGINT as Ctrl-C in a terminal would: a test run started in the background (``make test &`` in a shell
    without job control) ignores SIGINT, its children inherit that, and their Python then never raises
    KeyboardInterrupt, so the signal would go unnoticed. The command puts Python's handler back first."""
    py, first, *rest = argv
    if first == "-m":
        run, rest = f"runpy.run_module({rest[0]!r}, run_name='__main__', alter_sys=True)", rest[1:]
    else:
        run = f"sys.argv[0] = {first!r}; runpy.run_path({first!r}, run_name='__main__')"
    return [
        py,
        "-c",
        f"import runpy, signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); {run}",
        *rest,
    ]


def missing_data(reason: str) -> NoReturn:
    """A test whose shipped data (../shared: development clips, robot models) is missing: skipped on a
    developer's machine, failed under CI (``CI=true``), where a suite must not pass by skipping."""
    if UNDER_CI:
        pytest.fail(f"CI needs the shipped data: {reason}", pytrace=False)
    pytest.skip(reason)


# the stiffest analytical simulator of the default curriculum (sim 9), as default_params' contact settings
STIFF = {"alpha": 0.0, "d_c": 0.0, "k_n": 4.0e6, "k_f": 1.0e7, "k_d": 1.0e3, "mu": 10.0}


def box_object(extents: tuple[float, float, float] = (0.05, 0.05, 0.05), density: float = 500.0) -> SimpleNamespace:
    import trimesh

    m = trimesh.creation.box(extents=extents)
    m.density = density
    parts = [(np.asarray(m.vertices), np.asarray(m.faces))]
    return SimpleNamespace(
        name="box",
        vertices=np.asarray(m.vertices),
        faces=np.asarray(m.faces),
        mass=float(m.mass),
        com=np.asarray(m.center_mass),
        inertia=np.asarray(m.moment_inertia),
        convex_parts=lambda *a, **k: parts,
    )


def smooth_targets(hand, T: int, start: np.ndarray, move: np.ndarray, flex: float) -> np.ndarray:
    """PD targets (T, 6 + J) of one hand: the base from ``start`` by ``move`` (m) and every joint from 0 towards
    ``flex`` (rad, within its range), both along a smoothstep; base angles 0."""
    s = np.linspace(0, 1, T)
    s = s * s * (3 - 2 * s)
    q = np.zeros((T, 6 + hand.n_joints))
    q[:, :3] = start + s[:, None] * move
    q[:, 6:] = np.clip(s[:, None] * flex, hand.joint_range[:, 0], hand.joint_range[:, 1])
    return q


def scene_with(hand, obj=None, base_rot=None, object_pos=(0.0, 0.0, 0.825), table_top=0.8, half=0.3, fps=20.0):
    from quasisim.targets.scene import Placement, Scene, Table

    return Scene(
        placements=(Placement(hand, np.eye(3) if base_rot is None else base_rot),),
        obj=obj or box_object(),
        table=Table(-half, half, -half, half, table_top),
        object_pos0=np.asarray(object_pos, dtype=float),
        object_quat0=np.array([1.0, 0.0, 0.0, 0.0]),
        fps=fps,
    )


CHROMIUM = "/usr/bin/chromium"


def chromium_check(page, fragment: str = "") -> dict | None:
    """Load ``page`` (+ ``#fragment``) in headless Chromium and read back what the page's script wrote:
    ``duration`` of the video, the page's own ``errors``, ``console`` messages, the frame ``readout`` and
    the plots' ``cursors`` (x positions); None when Chromium is not installed."""
    import os
    import re
    import subprocess

    if not os.access(CHROMIUM, os.X_OK):
        return None
    url = page.resolve().as_uri() + (f"#{fragment}" if fragment else "")
    cmd = [
        CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--mute-audio", "--enable-logging=stderr",
        "--v=0", "--virtual-time-budget=5000", "--dump-dom", url,
    ]  # fmt: skip
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    dom = r.stdout
    m = re.search(r'data-video-duration="([^"]+)"', dom)
    return {
        "duration": float(m[1]) if m else 0.0,
        "errors": re.findall(r"<li>(.*?)</li>", re.search(r"<ul id=\"qs-errors\"[^>]*>(.*?)</ul>", dom, re.S)[1]),
        "console": [line for line in r.stderr.splitlines() if ":CONSOLE" in line],
        "readout": re.search(r'<div id="qs-readout">(.*?)</div>', dom, re.S)[1],
        "cursors": [float(x) for x in re.findall(r'<line class="cursor" x1="([^"]+)"', dom)],
    }


def cube_example(folder, n_frames: int = 20) -> tuple:
    """The bundled example ``cube_lift`` written to ``folder`` (``n_frames`` frames), its kinematic retarget
    (saved as ``folder/kinematic.npz``) and their scene: ``(path, demo, controls, scene)``."""
    from quasisim.assets.hand import load_hand
    from quasisim.data.demo import load_demo
    from quasisim.data.synthetic import write_example
    from quasisim.method.retarget import kinematic_controls
    from quasisim.targets.build import scene_for
    from quasisim.targets.scene import place_hands

    path = write_example("cube_lift", folder, n_frames=n_frames)
    demo, hand = load_demo(path), load_hand("shadow")
    controls = kinematic_controls(hand, demo, "shadow")
    controls.save(folder / "kinematic.npz")
    return path, demo, controls, scene_for(demo, place_hands((hand,), controls.base_rots))
