"""A generated corpus of bad inputs (demos, meshes, controls, hand YAMLs, CLI options, output folders).

Every case runs the CLI in-process and must end with exit code 2, exactly one line on stderr that names the
file (or option), the field and what was expected, and no output written. The inputs are made in tmp_path
from the bundled synthetic example at test time; the checks run before any heavy work, so the whole corpus
takes seconds.
"""

from __future__ import annotations

import os
import shutil
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from quasisim.cli import main

DEMO, MESH, CONTROLS, HAND = "cube_lift.npz", "meshes/cube_lift.obj", "controls.npz", "hand.yaml"


@pytest.fixture(scope="module")
def base(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder with a valid demo (16 frames), its mesh, controls for it and a copy of the Shadow hand YAML."""
    import quasisim.pipeline  # noqa: F401  (JAX and the pipeline imported before the corpus runs)
    from quasisim.assets.hand import HANDS_DIR, load_hand
    from quasisim.data.controls import Controls
    from quasisim.data.demo import content_hash, load_demo
    from quasisim.data.synthetic import write_example

    d = tmp_path_factory.mktemp("bad_input_base")
    demo = load_demo(write_example("cube_lift", d, n_frames=16))
    hand = load_hand("shadow")
    Controls(
        hand="shadow",
        demo=demo.name,
        method="test",
        fps=demo.fps,
        base_rots=(np.eye(3),),
        q_targets=np.zeros((demo.n_frames, 6 + hand.n_joints)),
        joint_names=hand.joint_names,
        demo_hash=content_hash(demo),
    ).save(d / CONTROLS)
    shutil.copy(HANDS_DIR / "shadow.yaml", d / HAND)
    return d


@dataclass(frozen=True)
class Case:
    """``make(folder)`` damages a copy of the base folder; ``args`` ({d}: that folder) run; ``words`` must all
    be in the single stderr line."""

    id: str
    make: Callable[[Path], None]
    args: str
    words: tuple[str, ...]


def _npz_edit(file: str, /, **change: object) -> Callable[[Path], None]:
    """Rewrite archive ``file`` with keys changed (None: removed); object arrays are pickled by np.savez."""

    def make(d: Path) -> None:
        with np.load(d / file) as z:
            arrays = {k: z[k] for k in z.files}
        for k, v in change.items():
            if v is None:
                arrays.pop(k)
            else:
                arrays[k] = v(arrays[k]) if callable(v) else v
        os.remove(d / file)
        np.savez(d / file, **arrays)

    return make


def _write(name: str, data: bytes | str) -> Callable[[Path], None]:
    def make(d: Path) -> None:
        p = d / name
        p.unlink(missing_ok=True)
        p.write_bytes(data if isinstance(data, bytes) else data.encode())

    return make


def _mesh_scale(s: float) -> Callable[[Path], None]:
    def make(d: Path) -> None:
        import trimesh

        m = trimesh.load(d / MESH, force="mesh")
        m.apply_scale(s)
        m.export(d / MESH)

    return make


def _yaml_edit(edit: Callable[[dict], object]) -> Callable[[Path], None]:
    def make(d: Path) -> None:
        data = yaml.safe_load((d / HAND).read_text())
        edit(data)
        (d / HAND).write_text(yaml.safe_dump(data))

    return make


def _nothing(d: Path) -> None:
    pass


def _pickled(v: object) -> np.ndarray:
    a = np.empty((), dtype=object)
    a[()] = v
    return a


RANDOM = bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8))
J = lambda a: a  # noqa: E731  (the unchanged array, for readability below)


def _truncate(name: str) -> Callable[[Path], None]:
    def make(d: Path) -> None:
        data = (d / name).read_bytes()
        (d / name).write_bytes(data[: len(data) // 2])

    return make


def _zip_without_arrays(name: str) -> Callable[[Path], None]:
    def make(d: Path) -> None:
        (d / name).unlink()
        with zipfile.ZipFile(d / name, "w") as z:
            z.writestr("readme.txt", "not an array")

    return make


def _npy(name: str) -> Callable[[Path], None]:
    def make(d: Path) -> None:
        (d / name).unlink()
        with open(d / name, "wb") as f:
            np.save(f, np.zeros(3))

    return make


# ---- demos: every case runs through retarget, evaluate and transfer --------------------------------------

T = 16
DEMO_CASES: list[tuple[str, Callable[[Path], None], tuple[str, ...]]] = [
    *[
        (f"missing_{k}", _npz_edit(DEMO, **{k: None}), (k,))
        for k in (
            "format",
            "name",
            "fps",
            "right_joints",
            "object_name",
            "object_mesh",
            "object_pos",
            "object_quat",
            "support_height",
        )
    ],
    ("format_other", _npz_edit(DEMO, format=np.array("quasisim-demo-v0")), ("format", "quasisim-demo-v1")),
    ("format_number", _npz_edit(DEMO, format=np.array(1.0)), ("format", "string")),
    ("format_pickled", _npz_edit(DEMO, format=_pickled("quasisim-demo-v1")), ("format", "pickled")),
    ("name_number", _npz_edit(DEMO, name=np.array(3)), ("name", "string")),
    ("name_list", _npz_edit(DEMO, name=np.array(["a", "b"])), ("name", "0-d")),
    ("name_pickled", _npz_edit(DEMO, name=_pickled({"x": 1})), ("name", "pickled")),
    ("fps_string", _npz_edit(DEMO, fps=np.array("twenty")), ("fps", "number")),
    ("fps_zero", _npz_edit(DEMO, fps=np.array(0.0)), ("fps", "frame rate")),
    ("fps_negative", _npz_edit(DEMO, fps=np.array(-20.0)), ("fps", "frame rate")),
    ("fps_1e9", _npz_edit(DEMO, fps=np.array(1e9)), ("fps", "frame rate")),
    ("fps_nan", _npz_edit(DEMO, fps=np.array(np.nan)), ("fps", "finite")),
    ("fps_inf", _npz_edit(DEMO, fps=np.array(np.inf)), ("fps", "finite")),
    ("fps_vector", _npz_edit(DEMO, fps=np.array([20.0])), ("fps", "0-d")),
    ("fps_pickled", _npz_edit(DEMO, fps=_pickled(20.0)), ("fps", "pickled")),
    ("support_nan", _npz_edit(DEMO, support_height=np.array(np.nan)), ("support_height", "finite")),
    ("support_negative", _npz_edit(DEMO, support_height=np.array(-1.0)), ("support_height", "table-top")),
    ("support_100m", _npz_edit(DEMO, support_height=np.array(100.0)), ("support_height", "table-top")),
    ("joints_20", _npz_edit(DEMO, right_joints=lambda a: a[:, :20]), ("right_joints", "shape")),
    ("joints_2d", _npz_edit(DEMO, right_joints=lambda a: a[..., :2]), ("right_joints", "shape")),
    ("joints_flat", _npz_edit(DEMO, right_joints=lambda a: a.reshape(T, -1)), ("right_joints", "shape")),
    ("joints_strings", _npz_edit(DEMO, right_joints=lambda a: a.astype(str)), ("right_joints", "numeric")),
    ("joints_complex", _npz_edit(DEMO, right_joints=lambda a: a.astype(complex)), ("right_joints", "numeric")),
    ("joints_bool", _npz_edit(DEMO, right_joints=lambda a: a > 0), ("right_joints", "numeric")),
    ("joints_pickled", _npz_edit(DEMO, right_joints=_pickled([1, 2])), ("right_joints", "pickled")),
    (
        "joints_nan",
        _npz_edit(DEMO, right_joints=lambda a: np.where(np.arange(T)[:, None, None] == 3, np.nan, a)),
        ("right_joints", "finite", "frame 3"),
    ),
    ("joints_inf", _npz_edit(DEMO, right_joints=lambda a: a + np.inf), ("right_joints", "finite")),
    (
        "one_frame",
        _npz_edit(DEMO, right_joints=lambda a: a[:1], object_pos=lambda a: a[:1], object_quat=lambda a: a[:1]),
        ("right_joints", "2 frames"),
    ),
    (
        "joints_collapsed",
        _npz_edit(DEMO, right_joints=lambda a: np.repeat(a[:, :1], 21, axis=1)),
        ("right_joints", "human hand"),
    ),
    (
        "joints_in_cm",
        _npz_edit(DEMO, right_joints=lambda a: a.mean(1, keepdims=True) + 100 * (a - a.mean(1, keepdims=True))),
        ("right_joints", "human hand"),
    ),
    (
        "joints_tiny",
        _npz_edit(DEMO, right_joints=lambda a: a.mean(1, keepdims=True) + 0.05 * (a - a.mean(1, keepdims=True))),
        ("right_joints", "human hand"),
    ),
    (
        "joints_one_frame_collapsed",
        _npz_edit(DEMO, right_joints=lambda a: np.where(np.arange(T)[:, None, None] == 5, a[:, :1], a)),
        ("right_joints", "collapsed"),
    ),
    ("hand_100m_away", _npz_edit(DEMO, right_joints=lambda a: a + np.array([100.0, 0, 0])), ("right_joints", "+-10 m")),
    ("hand_5m_away", _npz_edit(DEMO, right_joints=lambda a: a + np.array([5.0, 0, 0])), ("object_pos", "within 1 m")),
    ("object_10m_away", _npz_edit(DEMO, object_pos=lambda a: a + np.array([0, 9.0, 0])), ("object_pos", "within 1 m")),
    (
        "joints_mirrored",
        _npz_edit(DEMO, right_joints=lambda a: a * np.array([1.0, -1.0, 1.0])),
        ("right_joints", "right hand"),
    ),
    ("joints_reordered", _npz_edit(DEMO, right_joints=lambda a: a[:, ::-1]), ("right_joints", "MediaPipe order")),
    (
        "object_in_table",
        _npz_edit(DEMO, object_pos=lambda a: a - np.array([0, 0, 0.3])),
        ("support_height", "table top"),
    ),
    ("table_far_below", _npz_edit(DEMO, support_height=np.array(0.3)), ("support_height", "table top")),
    ("object_pos_short", _npz_edit(DEMO, object_pos=lambda a: a[:-1]), ("object_pos", "same T")),
    ("object_pos_4", _npz_edit(DEMO, object_pos=lambda a: np.c_[a, a[:, :1]]), ("object_pos", "shape")),
    ("object_pos_nan", _npz_edit(DEMO, object_pos=lambda a: a * np.nan), ("object_pos", "finite")),
    ("object_pos_strings", _npz_edit(DEMO, object_pos=lambda a: a.astype(str)), ("object_pos", "numeric")),
    ("quat_half", _npz_edit(DEMO, object_quat=lambda a: a * 0.5), ("object_quat", "unit")),
    ("quat_zero", _npz_edit(DEMO, object_quat=lambda a: a * 0.0), ("object_quat", "unit")),
    ("quat_3", _npz_edit(DEMO, object_quat=lambda a: a[:, :3]), ("object_quat", "shape")),
    ("quat_nan", _npz_edit(DEMO, object_quat=lambda a: a * np.nan), ("object_quat", "finite")),
    ("extra_pickled", _npz_edit(DEMO, left_joints=_pickled([0])), ("left_joints", "pickled")),
    ("mesh_dotdot", _npz_edit(DEMO, object_mesh=np.array("../cube_lift.obj")), ("object_mesh", "meshes/")),
    ("mesh_dotdot_deep", _npz_edit(DEMO, object_mesh=np.array("../../../../etc/hostname")), ("object_mesh", "meshes/")),
    ("mesh_absolute", _npz_edit(DEMO, object_mesh=np.array("/etc/hostname")), ("object_mesh", "meshes/")),
    ("mesh_empty_name", _npz_edit(DEMO, object_mesh=np.array("")), ("object_mesh", "meshes/")),
    ("mesh_absent", _npz_edit(DEMO, object_mesh=np.array("sphere.obj")), ("object_mesh", "no such file")),
    ("mesh_folder", _npz_edit(DEMO, object_mesh=np.array(".")), ("object_mesh", "no such file")),
    ("mesh_empty_file", _write(MESH, b""), ("cube_lift.obj", "mesh")),
    ("mesh_random_bytes", _write(MESH, RANDOM), ("cube_lift.obj", "mesh")),
    ("mesh_one_triangle", _write(MESH, "v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nf 1 2 3\n"), ("cube_lift.obj", "watertight")),
    ("mesh_no_faces", _write(MESH, "v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\n"), ("cube_lift.obj", "mesh")),
    (
        "mesh_nan_vertex",
        _write(MESH, "v nan 0 0\nv 0.1 0 0\nv 0 0.1 0\nv 0 0 0.1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n"),
        ("cube_lift.obj", "mesh"),
    ),
    ("mesh_10um", _mesh_scale(10e-6 / 0.05), ("cube_lift.obj", "across")),
    ("mesh_50m", _mesh_scale(50.0 / 0.05), ("cube_lift.obj", "across")),
    (
        "mesh_1e30_m",
        _write(MESH, "v 0 0 0\nv 1e30 0 0\nv 0 1e30 0\nv 0 0 1e30\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"),
        ("cube_lift.obj", "across"),
    ),
    (
        "object_jump",
        _npz_edit(DEMO, object_pos=lambda a: np.where(np.arange(T)[:, None] == 8, a + np.float32(1.0), a)),
        ("object_pos", "15 m/s", "frame 7 to 8"),
    ),
    (
        "joints_jump",
        _npz_edit(DEMO, right_joints=lambda a: np.where(np.arange(T)[:, None, None] == 8, a + np.float32(1.0), a)),
        ("right_joints", "15 m/s"),
    ),
    ("fps_wrong_1000", _npz_edit(DEMO, fps=np.array(1000.0)), ("m/s", "wrong fps")),
    ("name_empty", _npz_edit(DEMO, name=np.array("")), ("name", "non-empty")),
    ("name_two_lines", _npz_edit(DEMO, name=np.array("cube\nlift")), ("name", "one line")),
    ("demo_empty", _write(DEMO, b""), (DEMO, "empty file")),
    ("demo_random_bytes", _write(DEMO, RANDOM), (DEMO, "not a zip archive")),
    ("demo_text", _write(DEMO, "format: quasisim-demo-v1\n"), (DEMO, "npz")),
    ("demo_truncated", _truncate(DEMO), (DEMO, "npz")),
    ("demo_npy", _npy(DEMO), (DEMO, ".npy")),
    ("demo_zip_of_text", _zip_without_arrays(DEMO), (DEMO, "format")),
]


def _demo_cases() -> list[Case]:
    commands = {
        "retarget": "retarget {d}/cube_lift.npz --out {d}/out",
        "evaluate": "evaluate {d}/cube_lift.npz {d}/controls.npz --out {d}/out",
        "transfer": "transfer {d}/cube_lift.npz --out {d}/out --no-render",
    }
    return [Case(f"{c}-demo-{i}", make, args, words) for i, make, words in DEMO_CASES for c, args in commands.items()]


# ---- controls (evaluate) ----------------------------------------------------------------------------

EVAL = "evaluate {d}/cube_lift.npz {d}/controls.npz --out {d}/out"
CONTROLS_CASES = [
    *[
        Case(f"controls-missing-{k}", _npz_edit(CONTROLS, **{k: None}), EVAL, (CONTROLS, k))
        for k in ("format", "hand", "fps", "base_rot", "q_targets", "joint_names")
    ],
    Case("controls-format", _npz_edit(CONTROLS, format=np.array("quasisim-demo-v1")), EVAL, ("format", "controls-v1")),
    Case("controls-fps-string", _npz_edit(CONTROLS, fps=np.array("abc")), EVAL, (CONTROLS, "fps", "number")),
    Case("controls-fps-pickled", _npz_edit(CONTROLS, fps=_pickled(20.0)), EVAL, (CONTROLS, "fps", "pickled")),
    Case("controls-fps-nan", _npz_edit(CONTROLS, fps=np.array(np.nan)), EVAL, (CONTROLS, "fps", "finite")),
    Case("controls-fps-zero", _npz_edit(CONTROLS, fps=np.array(0.0)), EVAL, (CONTROLS, "fps", "[1, 1000]")),
    Case("controls-fps-1e9", _npz_edit(CONTROLS, fps=np.array(1e9)), EVAL, (CONTROLS, "fps", "[1, 1000]")),
    Case("controls-fps-other", _npz_edit(CONTROLS, fps=np.array(30.0)), EVAL, (CONTROLS, "fps", "20")),
    Case("controls-q-strings", _npz_edit(CONTROLS, q_targets=lambda a: a.astype(str)), EVAL, ("q_targets", "numeric")),
    Case("controls-q-pickled", _npz_edit(CONTROLS, q_targets=_pickled([[0.0]])), EVAL, ("q_targets", "pickled")),
    Case("controls-q-nan", _npz_edit(CONTROLS, q_targets=lambda a: a * np.nan), EVAL, ("q_targets", "finite")),
    Case("controls-q-inf", _npz_edit(CONTROLS, q_targets=lambda a: a + np.inf), EVAL, ("q_targets", "finite")),
    Case("controls-q-narrow", _npz_edit(CONTROLS, q_targets=lambda a: a[:, :-1]), EVAL, ("q_targets", "shape")),
    Case("controls-q-1d", _npz_edit(CONTROLS, q_targets=lambda a: a[:, 0]), EVAL, ("q_targets", "shape")),
    Case("controls-q-one-frame", _npz_edit(CONTROLS, q_targets=lambda a: a[:1]), EVAL, ("q_targets", "T >= 2")),
    Case("controls-q-frames", _npz_edit(CONTROLS, q_targets=lambda a: a[:-2]), EVAL, ("q_targets", "16 frames")),
    Case("controls-base-rot", _npz_edit(CONTROLS, base_rot=lambda a: 2 * a), EVAL, ("base_rot", "rotation")),
    Case("controls-base-rot-mirror", _npz_edit(CONTROLS, base_rot=lambda a: -a), EVAL, ("base_rot", "rotation")),
    Case("controls-base-rot-shape", _npz_edit(CONTROLS, base_rot=lambda a: a[0]), EVAL, ("base_rot", "shape")),
    Case(
        "controls-names-2d", _npz_edit(CONTROLS, joint_names=lambda a: a.reshape(2, -1)), EVAL, ("joint_names", "1-d")
    ),
    Case(
        "controls-names-numbers",
        _npz_edit(CONTROLS, joint_names=lambda a: np.arange(len(a))),
        EVAL,
        ("joint_names", "1-d"),
    ),
    Case(
        "controls-names-duplicate",
        _npz_edit(CONTROLS, joint_names=lambda a: np.r_[a[:1], a[:-1]]),
        EVAL,
        ("joint_names", "distinct"),
    ),
    Case(
        "controls-names-other-hand",
        _npz_edit(CONTROLS, joint_names=lambda a: np.char.add("x_", a)),
        EVAL,
        ("joint_names", "shadow"),
    ),
    Case("controls-hand-unknown", _npz_edit(CONTROLS, hand=np.array("robotx")), EVAL, ("hand", "robotx", "shadow")),
    Case("controls-hand-number", _npz_edit(CONTROLS, hand=np.array(1.0)), EVAL, (CONTROLS, "hand", "string")),
    Case(
        "controls-other-demo",
        _npz_edit(CONTROLS, demo_hash=np.array("0123456789abcdef")),
        EVAL,
        (CONTROLS, "demo_hash", "--force"),
    ),
    Case("controls-empty", _write(CONTROLS, b""), EVAL, (CONTROLS, "empty file")),
    Case("controls-random", _write(CONTROLS, RANDOM), EVAL, (CONTROLS, "not a zip archive")),
    Case("controls-truncated", _truncate(CONTROLS), EVAL, (CONTROLS, "npz")),
    Case("controls-npy", _npy(CONTROLS), EVAL, (CONTROLS, ".npy")),
    Case("controls-absent", lambda d: (d / CONTROLS).unlink(), EVAL, (CONTROLS, "no such file")),
    Case(
        "controls-hand-yaml-absent",
        _npz_edit(CONTROLS, hand=np.array("/nonexistent/hand.yaml")),
        EVAL,
        (CONTROLS, "hand", "no such file"),
    ),
]

# ---- hand YAMLs (retarget --hand) ------------------------------------------------------------------------

RET = "retarget {d}/cube_lift.npz --hand {d}/hand.yaml --out {d}/out"


def _kp(i: int, **change: object) -> Callable[[dict], object]:
    return lambda y: y["keypoints"][i].update(change)


HAND_CASES = [
    Case("hand-bad-yaml", _write(HAND, "name: [unclosed\n"), RET, (HAND, "YAML")),
    Case("hand-binary", _write(HAND, RANDOM), RET, (HAND, "YAML")),
    Case("hand-list", _write(HAND, "- 1\n- 2\n"), RET, (HAND, "mapping")),
    Case("hand-empty", _write(HAND, ""), RET, (HAND, "mapping")),
    Case("hand-unknown-key", _yaml_edit(lambda y: y.update(colour="red")), RET, (HAND, "colour")),
    Case("hand-no-model", _yaml_edit(lambda y: y.pop("model")), RET, (HAND, "model")),
    Case(
        "hand-model-absent", _yaml_edit(lambda y: y.update(model="nothere.xml")), RET, (HAND, "model", "no such file")
    ),
    Case(
        "hand-model-garbage",
        lambda d: (_write("bad.xml", RANDOM)(d), _yaml_edit(lambda y: y.update(model="bad.xml"))(d)),
        RET,
        ("bad.xml", "MJCF"),
    ),
    Case("hand-root-body", _yaml_edit(lambda y: y.update(root_body="robot0:nothing")), RET, (HAND, "root_body")),
    Case("hand-no-keypoints", _yaml_edit(lambda y: y.update(keypoints=[])), RET, (HAND, "keypoints")),
    Case("hand-kp-human-25", _yaml_edit(_kp(0, human=25)), RET, (HAND, "keypoints[0].human", "0..20")),
    Case("hand-kp-human-neg", _yaml_edit(_kp(3, human=-1)), RET, (HAND, "keypoints[3].human")),
    Case("hand-kp-human-str", _yaml_edit(_kp(3, human="three")), RET, (HAND, "keypoints[3].human", "integer")),
    Case("hand-kp-weight", _yaml_edit(_kp(2, weight=-1.0)), RET, (HAND, "keypoints[2].weight")),
    Case("hand-kp-body", _yaml_edit(_kp(1, body="robot0:nobody")), RET, (HAND, "keypoints[1].body")),
    Case("hand-kp-site", _yaml_edit(_kp(4, site="robot0:nosite")), RET, (HAND, "keypoints[4].site")),
    Case("hand-kp-pos", _yaml_edit(_kp(0, pos=[0, 0])), RET, (HAND, "keypoints[0].pos", "3 values")),
    Case("hand-pd-kp-string", _yaml_edit(lambda y: y["pd"]["joint"].update(kp="stiff")), RET, (HAND, "pd.joint.kp")),
    Case("hand-spacing-zero", _yaml_edit(lambda y: y["points"].update(spacing=0.0)), RET, (HAND, "points")),
    Case("hand-wrist-fit", _yaml_edit(lambda y: y.update(wrist_fit_human=[0, 22])), RET, (HAND, "wrist_fit_human")),
    Case("hand-pd-negative", _yaml_edit(lambda y: y["pd"]["joint"].update(kp=-5.0)), RET, (HAND, "pd.joint", "kp > 0")),
    Case(
        "hand-pd-nan",
        _yaml_edit(lambda y: y["pd"]["base_pos"].update(kv=float("nan"))),
        RET,
        (HAND, "pd.base_pos.kv", "finite"),
    ),
    Case(
        "hand-force-limit",
        _yaml_edit(lambda y: y["pd"].update(joint_force_limit=0.0)),
        RET,
        (HAND, "pd", "joint_force_limit"),
    ),
    Case("hand-spacing-tiny", _yaml_edit(lambda y: y["points"].update(spacing=1e-7)), RET, (HAND, "points", "0.001")),
    Case("hand-kp-pos-far", _yaml_edit(_kp(0, pos=[100.0, 0, 0])), RET, (HAND, "keypoints[0].pos", "0.5 m")),
    Case(
        "hand-kp-duplicate",
        _yaml_edit(lambda y: y.update(keypoints=y["keypoints"] * 2)),
        RET,
        (HAND, "keypoints", "distinct"),
    ),
    Case("hand-model-passwd", _yaml_edit(lambda y: y.update(model="/etc/passwd")), RET, ("/etc/passwd", "MJCF")),
    Case("hand-unknown-name", _nothing, "retarget {d}/cube_lift.npz --hand nohand --out {d}/out", ("nohand", "shadow")),
    Case(
        "hand-wrist-fit-empty", _yaml_edit(lambda y: y.update(wrist_fit_human=[])), RET, (HAND, "wrist_fit_human", "3")
    ),
    Case(
        "hand-weights-zero",
        _yaml_edit(lambda y: [k.update(weight=0.0) for k in y["keypoints"]]),
        RET,
        (HAND, "wrist_fit_human", "weight > 0"),
    ),
    Case(
        "hand-no-metric",
        _yaml_edit(lambda y: [k.update(metric=False) for k in y["keypoints"]]),
        RET,
        (HAND, "keypoints", "metric"),
    ),
    Case("hand-seed-negative", _yaml_edit(lambda y: y["points"].update(seed=-1)), RET, (HAND, "points.seed", ">= 0")),
    Case(
        "hand-exclude-typo",
        _yaml_edit(lambda y: y.update(exclude_geoms=["robot0:V_thbse"])),
        RET,
        (HAND, "exclude_geoms[0]", "a geom of", "V_thbse"),
    ),
    Case(
        "hand-key-twice",
        lambda d: (d / HAND).write_text((d / HAND).read_text() + "\nname: other\n"),
        RET,
        (HAND, "'name' given twice"),
    ),
]

# ---- CLI options -----------------------------------------------------------------------------------------

TR = "transfer {d}/cube_lift.npz --out {d}/out "
OPTION_CASES = [
    Case("example-frames-0", _nothing, "example --out {d}/out --frames 0", ("--frames", "12")),
    Case("example-frames-neg", _nothing, "example --out {d}/out --frames -5", ("--frames",)),
    Case("example-frames-text", _nothing, "example --out {d}/out --frames many", ("--frames", "integer")),
    Case("example-name", _nothing, "example --out {d}/out --name sphere", ("sphere", "cube_lift")),
    Case("example-no-out", _nothing, "example", ("--out",)),
    Case("unknown-command", _nothing, "transmogrify", ("transmogrify",)),
    Case("retarget-no-demo", _nothing, "retarget --out {d}/out", ("DEMO",)),
    Case("evaluate-target", _nothing, EVAL + " --target gazebo", ("--target", "mujoco")),
    Case("evaluate-unknown-option", _nothing, EVAL + " --fast", ("--fast",)),
    Case("transfer-stages", _nothing, TR + "--stages 1,4", ("stage", "1, 2, 3, neural, control_vae, mpc, sample")),
    Case("transfer-stages-empty", _nothing, TR + "--stages ,", ("stage",)),
    Case("transfer-budget", _nothing, TR + "--budget huge", ("budget", "fast, paper")),
    Case("transfer-curriculum", _nothing, TR + "--curriculum soft", ("curriculum", "default")),
    Case("transfer-curriculum-file", _nothing, TR + "--curriculum {d}/none.yaml", ("none.yaml", "no such file")),
    Case("transfer-method", _nothing, TR + "--method rl", ("--method", "mpc-base")),
    Case("transfer-target", _nothing, TR + "--target gazebo", ("--target", "pybullet")),
    Case("transfer-mpc-pybullet", _nothing, TR + "--stages mpc --target pybullet", ("MuJoCo only",)),
    Case("transfer-set-syntax", _nothing, TR + "--set budgets", ("--set", "KEY=VALUE")),
    Case("transfer-set-key", _nothing, TR + "--set budgets.fast.x=1", ("budgets.fast.x",)),
    Case("transfer-set-type", _nothing, TR + "--set budgets.fast.substeps=many", ("budgets.fast.substeps", "integer")),
    Case(
        "transfer-set-soft-step", _nothing, TR + "--set budgets.fast.soft_step_scale=0.5", ("soft_step_scale", ">= 1")
    ),
    Case("transfer-set-negative-weight", _nothing, TR + "--set weights.obj_pos=-1", ("weights.obj_pos", ">= 0")),
    Case("transfer-set-nan", _nothing, TR + "--set weights.hand=.nan", ("weights.hand", "finite")),
    Case("transfer-set-inf-lr", _nothing, TR + "--set budgets.fast.sim.control_lr=.inf", ("control_lr", "finite")),
    Case("transfer-set-stage3-horizon", _nothing, TR + "--stages 3 --set stage3.horizon=0", ("stage3.horizon", ">= 1")),
    Case("transfer-set-held-out", _nothing, TR + "--stages 3 --set stage3.held_out=2", ("stage3.held_out", "(0, 1)")),
    Case("transfer-set-mpc-lr", _nothing, TR + "--stages mpc --set mpc.lr=-1", ("mpc.lr", ">= 0")),
    Case("transfer-set-samples", _nothing, TR + "--set sampling.samples=0", ("samples", "positive")),
    Case("transfer-set-mode", _nothing, TR + "--set sampling.mode=best", ("best", "predictive")),
    Case(
        "transfer-curriculum-nan",
        _write(
            "c.yaml",
            "name: c\nmu: 1.0\nstages:\n  - {alpha: 0.0, d_c: 0.0, k_n: .nan, k_f: 1.0, k_d: 1.0, residual: false}\n",
        ),
        TR + "--curriculum {d}/c.yaml",
        ("c.yaml", "stages[0].k_n", "finite"),
    ),
    Case("transfer-config-npz", _nothing, TR + "--config {d}/cube_lift.npz", ("cube_lift.npz", "YAML")),
    Case("bench-out-proc", _nothing, "bench transfer {d} --out /proc/quasisim_out", ("/proc/quasisim_out", "--out")),
    Case("transfer-config-absent", _nothing, TR + "--config {d}/cfg.yaml", ("cfg.yaml", "no such file")),
    Case("transfer-resume-overwrite", _nothing, TR + "--resume --overwrite", ("--resume", "--overwrite")),
    Case("transfer-hand", _nothing, TR + "--hand nohand", ("nohand", "allegro")),
    Case("demo-absent", _nothing, "retarget {d}/absent.npz --out {d}/out", ("absent.npz", "no such file")),
    Case("demo-device", _nothing, "retarget /dev/null --out {d}/out", ("/dev/null", "regular file")),
    Case("demo-name-too-long", _nothing, "retarget {d}/" + "y" * 300 + ".npz --out {d}/out", ("yyyy",)),
    Case("demo-folder", _nothing, "retarget {d}/meshes --out {d}/out", ("meshes", "a folder")),
    Case("transfer-set-yaml", _nothing, TR + "--set weights.hand=[1,", ("--set", "weights.hand", "YAML value")),
    Case("transfer-set-no-key", _nothing, TR + "--set =5", ("--set", "KEY=VALUE", "'=5'")),
    Case("transfer-set-soften-range", _nothing, TR + "--set mpc.soften_range=5.0", ("mpc", "soften_range < 1")),
    Case("batch-no-clips", _nothing, "batch {d}/meshes --out {d}/bout", ("meshes", "--pattern", "got none")),
    Case("batch-pattern-absolute", _nothing, "batch {d} --out {d}/bout --pattern /x/*.npz", ("--pattern", "/x/*.npz")),
    Case("batch-workers-negative", _nothing, "batch {d} --out {d}/bout --workers -1", ("--workers", "x>=0")),
    Case("batch-hand", _nothing, "batch {d} --out {d}/bout --hand nohand", ("nohand", "shadow")),
    Case("batch-curriculum", _nothing, "batch {d} --out {d}/bout --curriculum soft", ("soft", "default")),
]

# ---- convert landmarks: the base demo written as a user's files -------------------------------------------


def _landmarks(edit: Callable[[Path, np.ndarray, np.ndarray], None] | None = None) -> Callable[[Path], None]:
    """hand.csv (63 numbers per frame) and poses.csv (x y z + wxyz) from the base demo; then ``edit(d, joints,
    poses)``."""

    def make(d: Path) -> None:
        with np.load(d / DEMO) as z:
            joints = z["right_joints"].reshape(T, 63).astype(float)
            poses = np.c_[z["object_pos"], z["object_quat"]].astype(float)
        np.savetxt(d / "hand.csv", joints, delimiter=",")
        np.savetxt(d / "poses.csv", poses, delimiter=",")
        if edit is not None:
            edit(d, joints, poses)

    return make


CV = "convert landmarks {d}/hand.csv {d}/poses.csv {d}/meshes/cube_lift.obj --out {d}/conv/x.npz --fps 20 "
TET = "v 0 0 0\nv {s} 0 0\nv 0 {s} 0\nv 0 0 {s}\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"
CONVERT_CASES = [
    Case("convert-fps-negative", _landmarks(), CV + "--fps -5", ("hand.csv", "--fps", "frame rate", "-5")),
    Case("convert-support-negative", _landmarks(), CV + "--support-height -1", ("--support-height", "table-top")),
    Case(
        "convert-csv-trailing-column",
        _landmarks(lambda d, j, p: np.savetxt(d / "hand.csv", np.c_[j, np.ones(T)], delimiter=",")),
        CV,
        ("hand.csv", "63 numbers", "does not increase"),
    ),
    Case("convert-csv-binary", _landmarks(lambda d, j, p: _write("hand.csv", RANDOM)(d)), CV, ("hand.csv", "UTF-8")),
    Case(
        "convert-json-empty",
        _landmarks(lambda d, j, p: _write("hand.json", "[]")(d)),
        CV.replace("hand.csv", "hand.json"),
        ("hand.json", "no frames"),
    ),
    Case(
        "convert-npz-fps-text",
        _landmarks(lambda d, j, p: np.savez(d / "hand.npz", landmarks=j, fps=np.array("fast"))),
        CV.replace("hand.csv", "hand.npz"),
        ("hand.npz", "fps", "number"),
    ),
    Case(
        "convert-npz-pickled",
        _landmarks(lambda d, j, p: np.savez(d / "hand.npz", landmarks=j, meta=_pickled({"fps": 20}))),
        CV.replace("hand.csv", "hand.npz"),
        ("hand.npz", "meta", "pickled"),
    ),
    Case(
        "convert-pose-not-rigid",
        _landmarks(
            lambda d, j, p: np.savetxt(
                d / "poses.csv",
                [np.r_[np.c_[2 * np.eye(3), x], [[0, 0, 0, 1]]].ravel() for x in p[:, :3]],
                delimiter=",",
            )
        ),
        CV,
        ("poses.csv", "pose", "rigid"),
    ),
    Case(
        "convert-mesh-open",
        _landmarks(lambda d, j, p: _write("tri.obj", "v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nf 1 2 3\n")(d)),
        CV.replace("meshes/cube_lift.obj", "tri.obj"),
        ("tri.obj", "watertight"),
    ),
    Case(
        "convert-mesh-random",
        _landmarks(lambda d, j, p: _write("g.stl", RANDOM)(d)),
        CV.replace("meshes/cube_lift.obj", "g.stl"),
        ("g.stl", "triangle"),
    ),
    Case(
        "convert-mesh-100m",
        _landmarks(lambda d, j, p: _write("big.obj", TET.format(s=100))(d)),
        CV.replace("meshes/cube_lift.obj", "big.obj"),
        ("big.obj", "across", "--units m"),
    ),
    Case(
        "convert-out-folder",
        _landmarks(lambda d, j, p: (d / "conv" / "x.npz").mkdir(parents=True)),
        CV,
        ("x.npz", "--out", "a folder"),
    ),
    Case(
        "convert-out-exists",
        _landmarks(),
        CV.replace("conv/x.npz", "cube_lift.npz"),
        ("--out", "--overwrite", "cube_lift.npz", "meshes/cube_lift.obj"),
    ),
    Case("convert-name-folders", _landmarks(), CV + "--name ../evil", ("--name", "../evil")),
]

# ---- output folders ------------------------------------------------------------------------------------

OUT_COMMANDS = {
    "example": "example --name cube_lift --out {out}",
    "retarget": "retarget {d}/cube_lift.npz --out {out}",
    "evaluate": "evaluate {d}/cube_lift.npz {d}/controls.npz --out {out}",
    "transfer": "transfer {d}/cube_lift.npz --out {out}",
}
OUT_PLACES = {
    "is-a-file": ("{d}/controls.npz", ("controls.npz", "--out", "existing file")),
    "under-a-file": ("{d}/controls.npz/sub", ("controls.npz", "--out", "is a file")),
    "proc": ("/proc/quasisim_out", ("/proc/quasisim_out", "--out", "may write")),
    "sys": ("/sys/quasisim/out", ("/sys/quasisim/out", "--out")),
    "dev-null": ("/dev/null", ("/dev/null", "--out", "existing file")),
    "name-too-long": ("{d}/" + "x" * 300, ("xxxx", "--out")),
    "broken-link": ("{d}/link", ("link", "--out", "broken symbolic link")),
}


def _broken_link(d: Path) -> None:
    (d / "link").symlink_to(d / "nowhere" / "out")


OUT_CASES = [
    Case(f"{c}-out-{place}", _broken_link if place == "broken-link" else _nothing, args.replace("{out}", out), words)
    for c, args in OUT_COMMANDS.items()
    for place, (out, words) in OUT_PLACES.items()
]


def _earlier_outputs(names: tuple[str, ...], checkpoints: bool = False) -> Callable[[Path], None]:
    def make(d: Path) -> None:
        (d / "out").mkdir()
        for n in names:
            (d / "out" / n).write_text("earlier")

    return make


def _foreign_checkpoints(d: Path) -> None:
    """OUT/checkpoints of another program: --overwrite must not remove it."""
    (d / "out" / "checkpoints").mkdir(parents=True)
    np.savez(d / "out" / "checkpoints" / "weights.npz", w=np.zeros(3))


OVERWRITE_CASES = [
    Case(
        "example-overwrite",
        _earlier_outputs(("cube_lift.npz",)),
        "example --name cube_lift --out {d}/out",
        ("out", "--overwrite", "cube_lift.npz"),
    ),
    Case(
        "retarget-overwrite",
        _earlier_outputs(("kinematic.npz",)),
        "retarget {d}/cube_lift.npz --out {d}/out",
        ("out", "--overwrite", "kinematic.npz"),
    ),
    Case("evaluate-overwrite", _earlier_outputs(("report.html",)), EVAL, ("out", "--overwrite", "report.html")),
    Case("evaluate-overwrite-manifest", _earlier_outputs(("manifest.json",)), EVAL, ("--overwrite", "manifest.json")),
    Case("transfer-overwrite", _earlier_outputs(("metrics.json", "controls.npz")), TR, ("--overwrite", "controls.npz")),
    Case(
        "transfer-overwrite-foreign-checkpoints",
        _foreign_checkpoints,
        TR + "--overwrite",
        ("out/checkpoints", "--out", "weights.npz", "not a checkpoint of quasisim"),
    ),
]

CASES = [*_demo_cases(), *CONTROLS_CASES, *HAND_CASES, *OPTION_CASES, *CONVERT_CASES, *OUT_CASES, *OVERWRITE_CASES]


def _snapshot(d: Path) -> dict[str, bytes]:
    return {str(p.relative_to(d)): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


def test_corpus_size() -> None:
    assert len(CASES) >= 100 and len({c.id for c in CASES}) == len(CASES)


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_input(case: Case, base: Path, tmp_path: Path) -> None:
    d = tmp_path / "w"
    shutil.copytree(base, d)
    case.make(d)
    before = _snapshot(d)
    args = [a.replace("{d}", str(d)) for a in case.args.split()]
    r = CliRunner().invoke(main, args)
    lines = r.stderr.splitlines()
    assert r.exit_code == 2, (r.exit_code, r.output, r.exception)
    assert len(lines) == 1, r.stderr
    assert lines[0].startswith("error: ") and "Traceback" not in r.output
    for w in case.words:
        assert w in lines[0], (w, lines[0])
    markers = ("expect", "valid", "must be", "Invalid value", "Missing", "No such", "use --")  # what was expected
    assert any(m in lines[0] for m in markers), lines[0]
    assert _snapshot(d) == before, "the command wrote or changed files"
    assert not Path("/proc/quasisim_out").exists()


def test_input_errors_cross_process_boundaries() -> None:
    """A worker's InputError reaches the driver intact (a process pool pickles it), not as a pickling crash."""
    import pickle

    from quasisim.errors import InputError

    e = InputError("clip.npz", "object_quat", "unit quaternions", "|q| = 0.5")
    back = pickle.loads(pickle.dumps(e))
    assert type(back) is InputError and str(back) == str(e) and back.field == "object_quat"
