"""``quasisim export --format lerobot``: finished runs as a LeRobot dataset (the v3 layout of the ``lerobot``
package: parquet frames, one MP4 per camera, metadata), written through lerobot's own ``LeRobotDataset`` API
(docs/dataset.md, "LeRobot").

The episodes are the robomimic export's (:func:`quasisim.eval.dataset_export.run_episodes`): each run's controls
rolled out again in MuJoCo and checked against the run's ``rollout.npz``, and with ``closed_loop`` N the tracker
driving N perturbed worlds. Per frame ``t = 0 .. N-1`` of an episode (float32, SI units):

- ``observation.state`` (D + 7): the hands' joints (bases included, :func:`~quasisim.targets.mujoco_target.dof_names`
  order), then the object's position (m) and quaternion (w x y z);
- ``observation.velocity`` (D + 6): the joints' velocities, then the object's linear and angular velocity;
- ``action`` (D): the PD target frame ``t`` ends at (the one applied: the plan's, or the tracker's);
- ``observation.images.<camera>``: the MuJoCo scene at that state, rendered offscreen;
- the task text: ``"<action> the <object> (<clip>)"``.

lerobot keeps no free-form metadata per episode, so the world's parameters, the clip, the run and its metrics go
to ``meta/quasisim_episodes.jsonl`` beside lerobot's own files (one JSON object per episode, in episode order).
lerobot, torch and the video codec load only here (``make setup-lerobot``).
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from quasisim.data.demo import Demo
from quasisim.data.run_demo import RunDemos
from quasisim.errors import InputError, QuasisimError
from quasisim.eval.dataset_export import ExportResult, check_replace, run_episodes, run_scene, select_runs

CAMERA = "scene"
SIDECAR = "meta/quasisim_episodes.jsonl"
VIDEO_PSNR = 30.0  # dB: a decoded frame against the one rendered (lossy video; a wrong frame is far below)
STATE_TOL = 0.0  # the vectors read back against those written (both float32: equal)
INSTALL = "make setup-lerobot (a separate environment, .venv-lerobot: lerobot pins torch < 2.11; docs/dataset.md)"


def require_lerobot() -> Any:
    """The ``lerobot.datasets.lerobot_dataset`` module, or :class:`QuasisimError` saying how to install it."""
    try:
        from lerobot.datasets import lerobot_dataset
    except ImportError as e:
        raise QuasisimError(f"--format lerobot needs the lerobot package ({e}); install it with {INSTALL}") from None
    return lerobot_dataset


def task_text(demo: Demo) -> str:
    """``"<action> the <object> (<clip>)"``: the action is the word after the object's name in the clip's name
    (GRAB's ``s1_apple_eat_1`` -> eat, ARCTIC's ``s5_laptop_grab_01`` -> grab), else "manipulate"."""
    m = re.search(rf"(?:^|_){re.escape(demo.object_name)}_([a-z]+)", demo.name)
    return f"{m.group(1) if m else 'manipulate'} the {demo.object_name} ({demo.name})"


def features(ep: dict[str, Any], size: tuple[int, int]) -> dict[str, dict[str, Any]]:
    """lerobot's feature specification of episode ``ep`` (a :func:`run_episodes` dict), images ``size`` (H, W)."""
    names = list(ep["attrs"]["dof_names"])
    if ep["obs"]["hand_qpos"].shape[1] != len(names) or ep["actions"].shape[1] != len(names):
        raise QuasisimError(f"{ep['attrs']['run']}: joints, actions and dof names differ in number")
    obj = ["object_x", "object_y", "object_z", "object_qw", "object_qx", "object_qy", "object_qz"]
    vel = [f"{n}_vel" for n in names] + [f"object_v{a}" for a in "xyz"] + [f"object_w{a}" for a in "xyz"]
    return {
        "observation.state": {"dtype": "float32", "shape": (len(names) + 7,), "names": names + obj},
        "observation.velocity": {"dtype": "float32", "shape": (len(vel),), "names": vel},
        "action": {"dtype": "float32", "shape": (len(names),), "names": names},
        f"observation.images.{CAMERA}": {"dtype": "video", "shape": (*size, 3), "names": ["height", "width", "channels"]},
    }  # fmt: skip


def frame_arrays(ep: dict[str, Any]) -> dict[str, np.ndarray]:
    """The per-frame vectors of episode ``ep`` (N, ...), float32, as :func:`features` names them."""
    o = ep["obs"]
    return {
        "observation.state": np.concatenate([o["hand_qpos"], o["object_pos"], o["object_quat"]], 1).astype(np.float32),
        "observation.velocity": np.concatenate([o["hand_qvel"], o["object_linvel"], o["object_angvel"]], 1).astype(
            np.float32
        ),
        "action": np.asarray(ep["actions"], np.float32),
    }


def render_episode(renderer: Any, ep: dict[str, Any]) -> np.ndarray:
    """(N, H, W, 3) uint8: the robot and the object at each observed frame of ``ep`` (no human skeleton),
    through ``renderer`` (a :class:`~quasisim.eval.render.SideBySide` of the run's scene)."""
    o = ep["obs"]
    q, p, r = o["hand_qpos"], o["object_pos"], o["object_quat"]
    return np.stack([renderer.result(t, q, p, r, show_human=False) for t in range(len(q))])


def _meta(ep: dict[str, Any], index: int, task: str) -> dict[str, Any]:
    a = ep["attrs"]
    keep = ("clip", "run", "hand", "hands", "sides", "method", "closed_loop", "world_index", "world_seed",
            "world_ranges", "world", "tracker", "fps", "dt", "substeps", "demo_hash")  # fmt: skip
    return {"episode_index": index, "task": task, **{k: a[k] for k in keep if k in a},
            "metrics": {k: a["metrics"][k] for k in ("success", "robust", "unstable") if k in a["metrics"]}}  # fmt: skip


def not_a_dataset(path: Path) -> str | None:
    """Why ``path`` is not a LeRobot dataset folder that quasisim export wrote (lerobot's ``meta/info.json`` and
    quasisim's :data:`SIDECAR`), or None."""
    if path.is_symlink() or not path.is_dir():
        return "a symbolic link" if path.is_symlink() else "a file"
    missing = [n for n in ("meta/info.json", SIDECAR) if not (path / n).is_file()]
    return f"a folder without {' and '.join(missing)}" if missing else None


def check_out(out: Path, inputs: Sequence[Path], overwrite: bool) -> None:
    """Refuse ``--out`` unless it is a new folder, or (``overwrite``) a LeRobot dataset that quasisim export
    wrote and that neither is nor holds one of ``inputs`` (:func:`~quasisim.eval.dataset_export.check_replace`)."""
    what = f"a LeRobot dataset folder (meta/info.json, {SIDECAR})"
    check_replace(out, inputs, overwrite, "a new folder", what, not_a_dataset)


@contextlib.contextmanager
def _atomic_dir(out: Path, overwrite: bool, inputs: Sequence[Path] = ()) -> Iterator[Path]:
    """A fresh path beside ``out`` (not created: lerobot creates it) moved onto ``out`` on success; on failure
    it is removed and ``out`` left as it was. An existing ``out`` is replaced only as :func:`check_out` allows,
    checked before the block and again after it (``inputs`` may grow in it)."""
    check_out(out, inputs, overwrite)
    tmp = out.parent / f".{out.name}.tmp-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        yield tmp
        check_out(out, inputs, overwrite)
        if out.exists():
            old = out.parent / f".{out.name}.old-{os.getpid()}"
            os.replace(out, old)
            try:
                os.replace(tmp, out)
            except OSError:
                os.replace(old, out)
                raise
            shutil.rmtree(old)
        else:
            os.replace(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def export_lerobot(
    root: Path, out: Path, only: str = "any", min_robust: float | None = None, data_dirs: tuple[Path, ...] = (),
    closed_loop: int = 0, size: tuple[int, int] = (240, 320), repo_id: str | None = None, overwrite: bool = False,
    progress: bool = True,
) -> ExportResult:  # fmt: skip
    """Write the finished runs at or below ``root`` that pass the filters (as :func:`~quasisim.eval.dataset_export.
    export_dataset`) to the LeRobot dataset folder ``out``, atomically (a failure leaves no folder): one episode
    per run, then ``closed_loop`` closed-loop episodes per run; images ``size`` (H, W) pixels; ``repo_id``: the
    dataset's name in its metadata (default ``quasisim/<out's name>``). Every episode must share the fps and the
    joints of the first (a batch of one hand model and one number of hands)."""
    from tqdm import tqdm

    from quasisim.eval.render import SideBySide

    ld = require_lerobot()
    os.environ.setdefault("SVT_LOG", "1")  # the AV1 encoder's banner: errors only
    t0 = time.perf_counter()
    root, out = Path(root), Path(out)
    keep, skipped = select_runs(root, only, min_robust)
    res = ExportResult(out, skipped=skipped)
    demos, meta, ds, spec, expected = RunDemos(tuple(data_dirs), root), [], None, None, []
    inputs = [root, *map(Path, data_dirs)]  # and each run's demo file, as found
    bar = tqdm(total=len(keep), desc="export", unit="run", disable=None if progress else True, leave=False)
    with bar, _atomic_dir(out, overwrite, inputs) as tmp:
        for r in keep:
            bar.set_postfix_str(r.label)
            demo = demos.find(r.path)
            inputs += [Path(demo.path)] if demo.path else []
            scene = run_scene(r, demo)
            renderer = SideBySide(scene, demo, width=size[1], height=size[0])
            try:
                for ep in run_episodes(r, demo, closed_loop, scene):
                    if ds is None:
                        spec = features(ep, size)
                        ds = ld.LeRobotDataset.create(
                            repo_id or f"quasisim/{out.name}", fps=_fps(demo, r.label), features=spec, root=tmp,
                            robot_type=str(ep["attrs"]["hand"]), use_videos=True,
                        )  # fmt: skip
                    _check_same(ep, demo, spec, ds.fps, r.label)
                    task = task_text(demo)
                    arrays, images = frame_arrays(ep), render_episode(renderer, ep)
                    for t in range(len(images)):
                        ds.add_frame({**{k: v[t] for k, v in arrays.items()},
                                      f"observation.images.{CAMERA}": images[t], "task": task})  # fmt: skip
                    ds.save_episode()
                    meta.append(_meta(ep, len(res.episodes), task))
                    n = len(images)
                    expected.append((arrays, {t: images[t] for t in sorted({0, n // 2, n - 1})}))
                    res.episodes.append((f"episode_{len(res.episodes)}", r.label, n))
            finally:
                renderer.close()
            bar.update(1)
        assert ds is not None
        ds.finalize()
        with contextlib.suppress(OSError):  # lerobot's frame images, encoded into the videos by now
            (tmp / "images" / f"observation.images.{CAMERA}").rmdir()
            (tmp / "images").rmdir()
        (tmp / SIDECAR).write_text("".join(json.dumps(m) + "\n" for m in meta))
        res.check = verify(load(out, tmp), expected)
    res.seconds = time.perf_counter() - t0
    return res


def _fps(demo: Demo, label: str) -> int:
    if abs(demo.fps - round(demo.fps)) > 1e-9:
        raise InputError(demo.path, "fps", "a whole number of frames per second (lerobot stores fps as an integer)",
                         f"{demo.fps:g} (run {label})")  # fmt: skip
    return round(demo.fps)


def _check_same(ep: dict[str, Any], demo: Demo, spec: Any, fps: int, label: str) -> None:
    """Refuse an episode whose fps or joints differ from the dataset's (lerobot: one shape per feature)."""
    if _fps(demo, label) != fps:
        raise InputError(demo.path, "fps", f"{fps} like the dataset's first episode (one fps per dataset)",
                         f"{demo.fps:g} (run {label}; export such runs to another dataset)")  # fmt: skip
    names = spec["action"]["names"]
    if list(ep["attrs"]["dof_names"]) != names:
        raise InputError(None, "run", f"runs of one hand model and one number of hands ({len(names)} joints, like "
                         "the dataset's first episode)", f"{label} with {len(ep['attrs']['dof_names'])} joints")  # fmt: skip


# ---- reading back -----------------------------------------------------------------------------------------


def load(out: Path, root: Path | None = None) -> Any:
    """The dataset folder ``out`` (files at ``root``, default ``out``) through lerobot's ``LeRobotDataset``:
    local files only, videos decoded with PyAV."""
    ld = require_lerobot()
    root = Path(root or out)
    if not (root / "meta" / "info.json").is_file():
        raise InputError(root, None, "a LeRobot dataset folder (meta/info.json) written by quasisim export", "none")
    return ld.LeRobotDataset(f"quasisim/{Path(out).name}", root=root, video_backend="pyav")


def episode_meta(out: Path) -> list[dict[str, Any]]:
    """The per-episode records of ``meta/quasisim_episodes.jsonl``, in episode order."""
    path = Path(out) / SIDECAR
    if not path.is_file():
        raise InputError(path, None, "quasisim's per-episode metadata of a LeRobot export", "no such file")
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """Peak signal-to-noise ratio (dB) of two uint8 images (inf when equal)."""
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(255.0**2 / mse)


def verify(ds: Any, expected: list[tuple[dict[str, np.ndarray], dict[int, np.ndarray]]]) -> dict[str, float]:
    """Compare the dataset ``ds`` (loaded with :func:`load`) with what was written: per episode ``i`` its
    vectors ``expected[i][0]`` (:func:`frame_arrays`) and a few rendered frames ``expected[i][1]`` (frame ->
    image). Returns the largest vector difference and the lowest frame PSNR (dB); :class:`QuasisimError` when
    the episode count, a length, a vector (beyond float32 rounding) or a frame (below :data:`VIDEO_PSNR`)
    differs."""
    import torch

    if ds.num_episodes != len(expected):
        raise QuasisimError(f"{ds.root}: {ds.num_episodes} episodes read back, {len(expected)} written")
    cols = ds.hf_dataset.with_format("numpy")
    ep_col, worst, low = np.asarray(cols["episode_index"]), 0.0, float("inf")
    for i, (arrays, frames) in enumerate(expected):
        rows = np.flatnonzero(ep_col == i)
        for key, want in arrays.items():
            got = np.stack(cols[key][rows[0] : rows[-1] + 1]) if len(rows) else np.zeros((0,))
            if got.shape != want.shape:
                raise QuasisimError(f"{ds.root}: episode {i} {key} read back {got.shape}, written {want.shape}")
            worst = max(worst, float(np.abs(got - want).max() / max(1.0, np.abs(want).max())))
        for t, img in frames.items():
            item = ds[int(rows[t])]
            dec = item[f"observation.images.{CAMERA}"]
            dec = (dec.permute(1, 2, 0) * 255).round().to(torch.uint8).numpy() if hasattr(dec, "permute") else dec
            low = min(low, psnr(dec, img))
    if not worst <= STATE_TOL or not low >= VIDEO_PSNR:
        raise QuasisimError(f"{ds.root}: read back through LeRobotDataset, the vectors differ by {worst:.3g} "
                            f"(<= {STATE_TOL:g} wanted) and the frames' PSNR is {low:.1f} dB (>= {VIDEO_PSNR:g} wanted)")  # fmt: skip
    return {"max_vector_difference": worst, "min_frame_psnr_db": low}
