"""`quasisim convert`: bring your own data in (landmarks, GRAB, ARCTIC, TACO, OakInk2)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

from quasisim.cli._common import _friendly, main


@main.group()
def convert() -> None:
    """Bring your own data in: write a quasisim-demo-v1 clip (docs/demo_format.md)."""


@convert.command("landmarks")
@click.argument("landmarks", type=click.Path(path_type=Path))
@click.argument("poses", type=click.Path(path_type=Path))
@click.argument("mesh", type=click.Path(path_type=Path))
@click.option("--out", "out", type=click.Path(path_type=Path), required=True, help="Demo .npz to write.")
@click.option("--units", default="m", show_default=True, help="Length unit of all three inputs: m, cm or mm.")
@click.option("--up", default="z", show_default=True, help="The inputs' up axis: z, y, -y, x, -x or -z.")
@click.option("--quat-order", default="wxyz", show_default=True, help="Quaternion order in POSES: wxyz or xyzw.")
@click.option("--fps", type=float, default=None, help="Frame rate (default: the landmark file's 'fps').")
@click.option(
    "--support-height", type=float, help="Table top z (m, z up; default: the object's lowest point at frame 0)."
)
@click.option("--key", default=None, help="Landmark array in an .npz (default: the only (T, 21, 3) or (T, 63) one).")
@click.option("--name", default=None, help="Clip name (default: OUT's file name).")
@click.option("--overwrite", is_flag=True, help="Replace OUT and its mesh in meshes/ when they exist.")
@_friendly
def convert_landmarks(
    landmarks: Path, poses: Path, mesh: Path, out: Path, units: str, up: str, quat_order: str, fps: float | None,
    support_height: float | None, key: str | None, name: str | None, overwrite: bool,
) -> None:  # fmt: skip
    """21 hand LANDMARKS per frame (MediaPipe order; .npz, .csv or .json), the object's POSES per frame
    (position + quaternion, or 4x4) and its MESH (object frame) -> OUT (demo npz) and meshes/ beside it.
    File layouts: docs/demo_format.md."""
    from quasisim.data import convert as cv

    opts = cv.ConvertOptions(units, up, quat_order, fps, support_height, key, name)
    click.echo(str(cv.convert_landmarks(landmarks, poses, mesh, out, opts, overwrite)))


def _raw_options(fn: Callable[..., Any]) -> Callable[..., Any]:
    """The options `convert grab` and `convert arctic` share."""
    for opt in reversed((
        click.option("--mano-dir", type=click.Path(path_type=Path), required=True,
                     help="Folder with your MANO_RIGHT.pkl / MANO_LEFT.pkl (or its mano/ subfolder); https://mano.is.tue.mpg.de."),
        click.option("--out", "out", type=click.Path(path_type=Path), required=True, help="Demo .npz to write."),
        click.option("--fps", type=float, default=20.0, show_default=True, help="Clip frame rate (0: the source rate)."),
        click.option("--start", type=int, default=0, show_default=True, help="Source frame of clip frame 0."),
        click.option("--frames", type=int, default=None, help="Clip frames (default: to the end of the sequence)."),
        click.option("--name", default=None, help="Clip name (default: OUT's file name)."),
    )):  # fmt: skip
        fn = opt(fn)
    return fn


@convert.command("grab")
@click.argument("seq", type=click.Path(path_type=Path))
@click.option("--grab-root", type=click.Path(path_type=Path), default=None,
              help="Folder holding grab/ and tools/ (default: three levels above SEQ).")  # fmt: skip
@click.option("--left", is_flag=True, help="Also write the left hand as left_joints (needs MANO_LEFT.pkl).")
@_raw_options
@_friendly
def convert_grab(
    seq: Path, grab_root: Path | None, left: bool, mano_dir: Path, out: Path, fps: float, start: int,
    frames: int | None, name: str | None,
) -> None:  # fmt: skip
    """A GRAB sequence (grab/<subject>/<object>_<intent>.npz) -> OUT (demo npz, right hand) and meshes/ beside
    it. docs/demo_format.md, "From GRAB / ARCTIC"."""
    from quasisim.data import convert_raw as cr

    opts = cr.RawOptions(fps=fps or None, start=start, frames=frames, name=name, left=left)
    click.echo(str(cr.convert_grab(seq, mano_dir, out, grab_root, opts)))


@convert.command("arctic")
@click.argument("seq", type=click.Path(path_type=Path))
@click.option("--arctic-root", type=click.Path(path_type=Path), default=None,
              help="Folder holding raw_seqs/ and meta/ (default: three levels above SEQ).")  # fmt: skip
@click.option("--source-fps", type=float, default=30.0, show_default=True, help="ARCTIC's frame rate.")
@_raw_options
@_friendly
def convert_arctic(
    seq: Path, arctic_root: Path | None, source_fps: float, mano_dir: Path, out: Path, fps: float, start: int,
    frames: int | None, name: str | None,
) -> None:  # fmt: skip
    """An ARCTIC raw sequence (raw_seqs/<subject>/<seq>.mano.npy and .object.npy) -> OUT (demo npz, both
    hands) and a rigid mesh (hinge at the clip's median angle) in meshes/. docs/demo_format.md."""
    from quasisim.data import convert_raw as cr

    opts = cr.RawOptions(fps=fps or None, start=start, frames=frames, name=name, source_fps=source_fps)
    click.echo(str(cr.convert_arctic(seq, mano_dir, out, arctic_root, opts)))


@convert.command("taco")
@click.argument("seq", type=click.Path(path_type=Path))
@click.option("--mano-dir", type=click.Path(path_type=Path), required=True,
              help="Folder holding MANO_RIGHT.pkl (your own download of MANO).")  # fmt: skip
@click.option("--out", type=click.Path(path_type=Path), required=True, help="Demo file to write (.npz).")
@click.option(
    "--taco-root",
    type=click.Path(path_type=Path),
    default=None,
    help="Folder holding Hand_Poses/, Object_Poses/ and the object models (default: found above SEQ).",
)
@click.option(
    "--object-models",
    type=click.Path(path_type=Path),
    default=None,
    help="Folder holding <id>_cm.obj (default: TACO_ROOT/Object_Models).",
)
@click.option("--fps", type=float, default=0.0, show_default=True, help="Output frame rate (0: TACO's own).")
@click.option("--source-fps", type=float, default=30.0, show_default=True, help="TACO's frame rate.")
@click.option(
    "--start", type=int, default=None, help="Source frame of clip frame 0 (default: 1.5 s before the tool first moves)."
)
@click.option("--frames", type=int, default=150, show_default=True, help="Clip frames at most (the paper's 150).")
@click.option("--up", type=click.Choice(["x", "y", "z"]), default="z", show_default=True, help="TACO's up axis.")
@click.option("--name", default=None, help="Clip name (default: OUT's file name).")
@_friendly
def convert_taco(
    seq: Path, mano_dir: Path, out: Path, taco_root: Path | None, object_models: Path | None, fps: float,
    source_fps: float, start: int | None, frames: int, up: str, name: str | None,
) -> None:  # fmt: skip
    """A TACO sequence (Hand_Poses/<triplet>/<sequence> or Object_Poses/...) -> OUT (demo npz: the right hand
    and its tool, the first approach-and-act segment) and the tool's mesh in metres in meshes/.
    docs/demo_format.md, "From TACO"."""
    from quasisim.data import convert_taco as ct

    opts = ct.TacoOptions(fps=fps or None, start=start, frames=frames, name=name, source_fps=source_fps, up=up)
    click.echo(str(ct.convert_taco(seq, mano_dir, out, taco_root, object_models, opts)))


def _frame_range(ctx: click.Context, param: click.Parameter, value: str | None) -> tuple[int, int] | None:
    """``--range BEGIN:END`` -> (BEGIN, END)."""
    if value is None:
        return None
    try:
        b, e = (int(x) for x in value.split(":"))
    except ValueError:
        raise click.BadParameter(f"expected BEGIN:END (mocap frame ids, END excluded), got {value!r}") from None
    return b, e


@convert.command("oakink2")
@click.argument("seq", type=click.Path(path_type=Path))
@click.option("--mano-dir", type=click.Path(path_type=Path), default=None,
              help="Folder holding MANO_RIGHT.pkl and MANO_LEFT.pkl (your own download of MANO).")  # fmt: skip
@click.option("--out", type=click.Path(path_type=Path), default=None, help="Demo file to write (.npz).")
@click.option(
    "--oakink2-root",
    type=click.Path(path_type=Path),
    default=None,
    help="Folder holding anno_preview/, program/ and object_*/ (default: two levels above SEQ's pickle).",
)
@click.option(
    "--object-dir",
    type=click.Path(path_type=Path),
    default=None,
    help="The align_ds folder of <obj_id>/ meshes (default: OAKINK2_ROOT/object_repair/align_ds, object_raw/...).",
)
@click.option(
    "--segment", default=None, help="Primitive-task segment: its index or name, e.g. 3 or pour:00 (default 0)."
)
@click.option("--range", "frame_range", default=None, callback=_frame_range,
              help="Mocap frames BEGIN:END (END excluded) instead of a segment.")  # fmt: skip
@click.option("--hands", type=click.Choice(["right", "left", "both"]), default=None,
              help="Hands to write (default: the segment's; the left alone is written mirrored).")  # fmt: skip
@click.option("--object", "object_id", default=None, help="Object id (default: the segment's main object).")
@click.option("--fps", type=float, default=20.0, show_default=True, help="Clip frame rate (0: OakInk2's 120).")
@click.option("--source-fps", type=float, default=120.0, show_default=True, help="OakInk2's mocap rate.")
@click.option("--frames", type=int, default=None, help="Clip frames at most (default: to the segment's end).")
@click.option("--up", type=click.Choice(["y", "z", "-y", "x", "-x", "-z"]), default="y", show_default=True,
              help="OakInk2's up axis.")  # fmt: skip
@click.option("--table-height", type=float, default=0.8, show_default=True,
              help="Height (m) of the object's lowest point at clip frame 0: the table top.")  # fmt: skip
@click.option("--name", default=None, help="Clip name (default: OUT's file name).")
@click.option("--list-segments", is_flag=True, help="List the sequence's segments and exit.")
@_friendly
def convert_oakink2(
    seq: Path, mano_dir: Path | None, out: Path | None, oakink2_root: Path | None, object_dir: Path | None,
    segment: str | None, frame_range: tuple[int, int] | None, hands: str | None, object_id: str | None, fps: float,
    source_fps: float, frames: int | None, up: str, table_height: float, name: str | None, list_segments: bool,
) -> None:  # fmt: skip
    """An OakInk2 sequence (anno_preview/<scene>++<seq>.pkl, or its key with --oakink2-root) -> OUT (demo npz:
    one primitive-task segment, its hands and its object) and the object's mesh in meshes/.
    docs/demo_format.md, "From OakInk2"."""
    from quasisim.data import convert_oakink2 as co

    if list_segments:
        for seg in co.read_segments(co.find_sequence(seq, oakink2_root)):
            objs = ", ".join(seg.objects())
            click.echo(
                f"{seg.describe()} {seg.interaction_mode} objects: {objs}" + (f" - {seg.desc}" if seg.desc else "")
            )
        return
    if mano_dir is None or out is None:
        raise click.UsageError("--mano-dir and --out are required (unless --list-segments)")
    which: int | str | None = int(segment) if segment is not None and segment.isdigit() else segment
    opts = co.OakInk2Options(
        segment=which,
        frame_range=frame_range,
        hands=hands,
        object_id=object_id,
        fps=fps or None,
        frames=frames,
        name=name,
        source_fps=source_fps,
        up=up,
        table_height=table_height,
    )
    click.echo(str(co.convert_oakink2(seq, mano_dir, out, oakink2_root, object_dir, opts)))
