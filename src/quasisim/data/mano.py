"""A small MANO hand model forward pass in numpy (Romero et al., SIGGRAPH Asia 2017), for the GRAB and ARCTIC
converters: the user's own ``MANO_RIGHT.pkl`` / ``MANO_LEFT.pkl`` (https://mano.is.tue.mpg.de; never bundled)
-> 21 hand keypoints per frame in MediaPipe order.

The official pickle holds some arrays as chumpy objects and a scipy sparse joint regressor. It is read with a
restricted unpickler (:class:`SafeUnpickler`) that reconstructs only numpy arrays, plain containers and
stand-ins for chumpy / scipy.sparse objects (their numbers become numpy arrays; neither library is imported);
any other class named in the file is refused. The same reader opens the pickled dicts inside GRAB ``.npz``
and ARCTIC ``.npy`` files (:func:`load_npy`).

The model, as in smplx's ``lbs`` (same arrays, same equations):

* shape: ``v_shaped = v_template + shapedirs . betas`` (778 x 3, 10 shape coefficients);
* joints at rest: ``J = J_regressor @ v_shaped`` (16 x 3);
* pose: axis-angle ``theta`` (16 x 3) = global orientation and 15 finger joints; the finger part is
  ``hands_mean + pose`` (``flat_hand_mean=False``, MANO's default) or ``pose`` alone (``flat_hand_mean=True``),
  where ``pose`` is 45 numbers or, with PCA, ``coeffs @ hands_components[:n]``;
* rotations ``R_k = exp([theta_k]_x)`` (Rodrigues); pose blend shapes
  ``v_posed = v_shaped + posedirs . vec(R_1..15 - I)`` (135 coefficients);
* kinematic chain (``kintree_table``): ``G_k = G_parent(k) [R_k | J_k - J_parent(k)]``, ``G_0 = [R_0 | J_0]``;
  posed joints are the translations of ``G_k``;
* linear blend skinning: ``v = sum_k w_vk G_k [I | -J_k] [v_posed; 1]``; then ``+ transl``.

Keypoints: the 16 posed joints plus 5 fingertip vertices, reordered to MediaPipe order (:data:`MANO_TO_MEDIAPIPE`).
"""

from __future__ import annotations

import io
import pickle
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from quasisim.errors import InputError, shaped_array

N_VERTS = 778
N_JOINTS = 16
N_BETAS = 10
# Fingertip vertex ids (thumb, index, middle, ring, little) on the MANO mesh: smplx's
# ``TIP_IDS["mano"]`` (vchoutas/smplx, smplx/body_models.py), the tips GRAB, ARCTIC (its 21 joints) and the
# bundled dev clips use. (manopth uses other vertices, 745, 317, 444, 556, 673.)
TIP_VERTS = (744, 320, 443, 554, 671)
# MANO joints 0-15 (wrist; index 1-3, middle 4-6, little 7-9, ring 10-12, thumb 13-15) + tips 16-20 (thumb,
# index, middle, ring, little) -> MediaPipe order (wrist; thumb, index, middle, ring, little, 4 each).
MANO_TO_MEDIAPIPE = (0, 13, 14, 15, 16, 1, 2, 3, 17, 4, 5, 6, 18, 10, 11, 12, 19, 7, 8, 9, 20)
MODEL_FILES = {"right": "MANO_RIGHT.pkl", "left": "MANO_LEFT.pkl"}


# ---- restricted unpickling ----------------------------------------------------------------------------


class _ChumpyStandIn:
    """Takes the place of a pickled ``chumpy`` object: keeps its value (the state's ``x``) only."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.value = None

    def __setstate__(self, state: Any) -> None:
        self.value = state.get("x") if isinstance(state, dict) else None


class _SparseStandIn:
    """Takes the place of a pickled ``scipy.sparse`` matrix (csc, csr or coo): rebuilt densely in numpy."""

    fmt = "csc"

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.value = None

    def __setstate__(self, state: Any) -> None:
        self.value = _dense(state, self.fmt) if isinstance(state, dict) else None


_SPARSE = {f"{fmt}_matrix": type(f"_{fmt}StandIn", (_SparseStandIn,), {"fmt": fmt}) for fmt in ("csc", "csr", "coo")}


def _dense(s: dict[str, Any], fmt: str) -> np.ndarray | None:
    """A dense array from a scipy sparse matrix's pickled state (its ``_shape`` and index arrays)."""
    shape = tuple(int(n) for n in s.get("_shape", s.get("shape", ())))
    if len(shape) != 2:
        return None
    out = np.zeros(shape)
    if fmt == "coo":
        rows, cols = s["coords"] if "coords" in s else (s["row"], s["col"])
        np.add.at(out, (np.asarray(rows), np.asarray(cols)), np.asarray(s["data"], float))
        return out
    data, idx, ptr = (np.asarray(s[k]) for k in ("data", "indices", "indptr"))
    for i in range(len(ptr) - 1):
        lo, hi = int(ptr[i]), int(ptr[i + 1])
        if fmt == "csr":
            out[i, idx[lo:hi]] += data[lo:hi]
        else:
            out[idx[lo:hi], i] += data[lo:hi]
    return out


_NUMPY_MODULES = {
    "numpy",
    "numpy.core.multiarray",
    "numpy._core.multiarray",
    "numpy.core.numeric",
    "numpy._core.numeric",
}
_NUMPY_NAMES = {"_reconstruct", "ndarray", "dtype", "scalar", "_frombuffer", "frombuffer"}
_BUILTINS = {"set", "frozenset", "object", "slice", "complex", "bytearray"}


class SafeUnpickler(pickle.Unpickler):
    """Unpickles numpy arrays and plain containers only; chumpy and scipy.sparse objects become stand-ins
    whose ``value`` is a numpy array (see :func:`unwrap`). Any other class raises :class:`pickle.UnpicklingError`
    naming it (pickles can run code when they name a callable; this one names none but numpy's array
    reconstruction)."""

    ALLOWED = "numpy arrays (chumpy and scipy.sparse allowed)"  # what a refusal says the file may hold

    def find_class(self, module: str, name: str) -> Any:
        if module.split(".")[0] == "chumpy":
            return _ChumpyStandIn
        if module.startswith("scipy.sparse") and name in _SPARSE:
            return _SPARSE[name]
        if module == "_codecs" and name == "encode":  # bytes in protocol 0-2 pickles written by Python 3
            return _encode
        if module in ("copy_reg", "copyreg") and name == "_reconstructor":
            return _reconstructor
        if module in ("__builtin__", "builtins") and name in _BUILTINS:
            return {"set": set, "frozenset": frozenset, "object": object, "slice": slice, "complex": complex,
                    "bytearray": bytearray}[name]  # fmt: skip
        if module in _NUMPY_MODULES and name in _NUMPY_NAMES:
            if name in ("ndarray", "dtype"):
                return getattr(np, name)
            return _numpy_attr(name)
        raise pickle.UnpicklingError(f"refusing to load the class {module}.{name} (only numpy arrays are allowed)")


def _encode(text: str, encoding: str = "utf-8") -> bytes:
    return text.encode(encoding)


def _reconstructor(cls: type, base: type, state: Any) -> Any:
    """``copyreg._reconstructor`` for the classes :class:`SafeUnpickler` allows (never calls their ``__init__``)."""
    if cls not in (_ChumpyStandIn, *_SPARSE.values(), set, frozenset, object):
        raise pickle.UnpicklingError(f"refusing to reconstruct {cls!r}")
    return object.__new__(cls) if base is object else base.__new__(cls, state)


def _numpy_attr(name: str) -> Any:
    """numpy's array reconstruction helpers, wherever this numpy version keeps them."""
    try:
        from numpy._core import multiarray, numeric
    except ImportError:  # numpy < 2
        from numpy.core import multiarray, numeric  # type: ignore[no-redef]
    for mod in (multiarray, numeric, np):
        if hasattr(mod, name):
            return getattr(mod, name)
    raise pickle.UnpicklingError(f"numpy has no {name}")


def unwrap(obj: Any) -> Any:
    """Replace stand-ins by their numpy values, recursively in dicts, lists and tuples."""
    if isinstance(obj, _ChumpyStandIn | _SparseStandIn):
        return unwrap(obj.value)
    if isinstance(obj, dict):
        return {(k.decode("latin1") if isinstance(k, bytes) else k): unwrap(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return type(obj)(unwrap(v) for v in obj)
    if isinstance(obj, np.ndarray) and obj.dtype == object and obj.ndim == 0:
        return unwrap(obj.item())
    return obj


def safe_load_pickle(f: BinaryIO, path: str | Path, unpickler: type[SafeUnpickler] = SafeUnpickler) -> Any:
    """Unpickle ``f`` with :class:`SafeUnpickler` (or a subclass allowing a few more classes, as TACO's torch
    tensors); any failure is an :class:`InputError` naming ``path``."""
    try:
        return unwrap(unpickler(f, encoding="latin1").load())
    except pickle.UnpicklingError as e:
        raise InputError(path, None, f"a pickle of {unpickler.ALLOWED}", str(e)) from None
    except Exception as e:  # truncated or corrupt: EOFError, ValueError, TypeError, ...
        raise InputError(path, None, "a readable pickle file", f"{type(e).__name__}: {str(e)[:100]}") from None


def load_npy(f: BinaryIO, path: str | Path) -> Any:
    """Read one ``.npy`` stream: a numeric array as is, an object array (a pickled dict, as GRAB and ARCTIC
    write them) through :class:`SafeUnpickler`, with 0-d object arrays unwrapped to their item."""
    try:
        version = np.lib.format.read_magic(f)
        reader = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
        _, _, dtype = reader(f)
    except ValueError as e:
        raise InputError(path, None, "a .npy array file", str(e)[:100]) from None
    if dtype.hasobject:
        return safe_load_pickle(f, path)
    f.seek(0)
    return np.lib.format.read_array(f, allow_pickle=False)


def load_npz_member(path: Path, key: str) -> Any:
    """Member ``key`` of an ``.npz`` file read with :func:`load_npy`; :class:`InputError` if it is missing."""
    try:
        with zipfile.ZipFile(path) as z:
            names = [n.removesuffix(".npy") for n in z.namelist()]
            if key not in names:
                raise InputError(path, key, "a member of this name", f"missing (keys: {', '.join(names)})")
            data = z.read(f"{key}.npy")
    except (zipfile.BadZipFile, OSError) as e:
        raise InputError(path, None, "an .npz archive", str(e)[:100]) from None
    return load_npy(io.BytesIO(data), f"{path}:{key}")


# ---- the model ----------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ManoModel:
    """The arrays of a MANO pickle (float64). ``parents[0] == -1``; ``hands_components`` rows are PCA
    components of the 45 finger pose numbers."""

    v_template: np.ndarray  # (V, 3)
    shapedirs: np.ndarray  # (V, 3, 10)
    posedirs: np.ndarray  # (V, 3, 135)
    j_regressor: np.ndarray  # (16, V)
    weights: np.ndarray  # (V, 16)
    parents: np.ndarray  # (16,)
    hands_components: np.ndarray  # (45, 45)
    hands_mean: np.ndarray  # (45,)
    path: Path


def find_model(mano_dir: str | Path, side: str) -> Path:
    """``MANO_RIGHT.pkl`` / ``MANO_LEFT.pkl`` in ``mano_dir`` or its ``mano/`` subfolder (smplx's layout), or
    ``mano_dir`` itself when it is that file."""
    d = Path(mano_dir)
    name = MODEL_FILES[side]
    if d.is_file() and d.name.upper() == name.upper():
        return d
    for p in (d / name, d / "mano" / name, d / "models" / name):
        if p.is_file():
            return p
    raise InputError(
        d / name, "--mano-dir", f"the MANO model file {name} (download it from https://mano.is.tue.mpg.de)",
        "no such file",
    )  # fmt: skip


def _field(raw: dict[str, Any], path: Path, key: str, shape: tuple[int | None, ...]) -> np.ndarray:
    if key not in raw or raw[key] is None:
        raise InputError(path, key, "a MANO model array of this name", f"missing (keys: {', '.join(sorted(raw))})")
    return shaped_array(raw[key], path, key, shape, "N")


def load_mano(path: str | Path) -> ManoModel:
    """Read a MANO model pickle (see the module docstring on its safety); :class:`InputError` on a missing or
    foreign file, a missing array or a wrong shape."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, None, "a MANO model file (MANO_RIGHT.pkl or MANO_LEFT.pkl)", "no such file")
    with open(path, "rb") as f:
        raw = safe_load_pickle(f, path)
    if not isinstance(raw, dict):
        raise InputError(path, None, "a MANO model (a pickled dict of arrays)", type(raw).__name__)
    v = _field(raw, path, "v_template", (None, 3))
    n = len(v)
    kintree = _field(raw, path, "kintree_table", (2, N_JOINTS))
    parents = kintree[0].astype(np.int64)
    parents[0] = -1  # stored as 2**32 - 1
    if np.any(parents[1:] < 0) or np.any(parents[1:] >= np.arange(1, N_JOINTS)):
        raise InputError(path, "kintree_table", "parents listed before their children", str(parents.tolist()))
    comps = raw.get("hands_components")
    return ManoModel(
        v_template=v,
        shapedirs=_field(raw, path, "shapedirs", (n, 3, N_BETAS)),
        posedirs=_field(raw, path, "posedirs", (n, 3, (N_JOINTS - 1) * 9)),
        j_regressor=_field(raw, path, "J_regressor", (N_JOINTS, n)),
        weights=_field(raw, path, "weights", (n, N_JOINTS)),
        parents=parents,
        hands_components=np.eye(45) if comps is None else _field(raw, path, "hands_components", (None, 45)),
        hands_mean=np.zeros(45) if raw.get("hands_mean") is None else _field(raw, path, "hands_mean", (45,)),
        path=path,
    )


def rodrigues(aa: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of axis-angle vectors (..., 3):
    ``R = I + sin(t) K + (1 - cos(t)) K^2``, ``K = [k]_x``, ``k = aa / t``, ``t = |aa|``."""
    t = np.linalg.norm(aa, axis=-1, keepdims=True)
    k = aa / np.maximum(t, 1e-12)
    x, y, z = k[..., 0], k[..., 1], k[..., 2]
    zero = np.zeros_like(x)
    K = np.stack([zero, -z, y, z, zero, -x, -y, x, zero], axis=-1).reshape(*aa.shape[:-1], 3, 3)
    s, c = np.sin(t)[..., None], np.cos(t)[..., None]
    return np.eye(3) + s * K + (1 - c) * (K @ K)


def full_pose(
    model: ManoModel, global_orient: np.ndarray, hand_pose: np.ndarray, flat_hand_mean: bool = False
) -> np.ndarray:
    """(T, 16, 3) axis-angle of all joints. ``hand_pose`` (T, 45) is the finger pose itself, or (T, n < 45)
    PCA coefficients of ``hands_components[:n]``; ``hands_mean`` is added unless ``flat_hand_mean``."""
    hand_pose = np.asarray(hand_pose, dtype=np.float64)
    n = hand_pose.shape[-1]
    fingers = hand_pose if n == 45 else hand_pose @ model.hands_components[:n]
    if not flat_hand_mean:
        fingers = fingers + model.hands_mean
    return np.concatenate([np.asarray(global_orient, np.float64)[:, None], fingers.reshape(-1, 15, 3)], axis=1)


def forward(
    model: ManoModel,
    pose: np.ndarray,
    betas: np.ndarray | None = None,
    transl: np.ndarray | None = None,
    v_template: np.ndarray | None = None,
    vertex_ids: tuple[int, ...] | np.ndarray | None = TIP_VERTS,
) -> tuple[np.ndarray, np.ndarray]:
    """Posed joints (T, 16, 3) and vertices (T, len(vertex_ids), 3; all vertices for ``None``) for the
    axis-angle ``pose`` (T, 16, 3) (:func:`full_pose`), shape ``betas`` (10,) or (T, 10) (None: zero) and
    ``transl`` (T, 3); ``v_template`` replaces the model's template (a subject's personal hand, as GRAB's)."""
    T = len(pose)
    template = model.v_template if v_template is None else np.asarray(v_template, dtype=np.float64)
    b = np.zeros((T, N_BETAS)) if betas is None else np.broadcast_to(np.asarray(betas, np.float64), (T, N_BETAS))
    v_shaped = template[None] + np.einsum("vcb,tb->tvc", model.shapedirs, b)  # (T, V, 3)
    J = np.einsum("jv,tvc->tjc", model.j_regressor, v_shaped)  # (T, 16, 3)
    R = rodrigues(np.asarray(pose, dtype=np.float64))  # (T, 16, 3, 3)
    G = np.zeros((T, N_JOINTS, 4, 4))
    G[:, :, 3, 3] = 1.0
    G[:, 0, :3, :3], G[:, 0, :3, 3] = R[:, 0], J[:, 0]
    for k in range(1, N_JOINTS):
        p = model.parents[k]
        local = np.zeros((T, 4, 4))
        local[:, :3, :3], local[:, :3, 3], local[:, 3, 3] = R[:, k], J[:, k] - J[:, p], 1.0
        G[:, k] = G[:, p] @ local
    joints = G[:, :, :3, 3].copy()
    ids = np.arange(len(template)) if vertex_ids is None else np.asarray(vertex_ids)
    feat = (R[:, 1:] - np.eye(3)).reshape(T, -1)  # (T, 135)
    v_posed = v_shaped[:, ids] + np.einsum("vcp,tp->tvc", model.posedirs[ids], feat)
    A = G.copy()  # G_k [I | -J_k]: moves the rest joint to the origin first
    A[:, :, :3, 3] -= np.einsum("tkij,tkj->tki", G[:, :, :3, :3], J)
    Tv = np.einsum("vk,tkij->tvij", model.weights[ids], A)  # (T, n, 4, 4)
    verts = np.einsum("tvij,tvj->tvi", Tv[:, :, :3, :3], v_posed) + Tv[:, :, :3, 3]
    if transl is not None:
        tr = np.asarray(transl, dtype=np.float64)[:, None]
        joints, verts = joints + tr, verts + tr
    return joints, verts


def keypoints(
    model: ManoModel,
    global_orient: np.ndarray,
    hand_pose: np.ndarray,
    transl: np.ndarray,
    betas: np.ndarray | None = None,
    flat_hand_mean: bool = False,
    v_template: np.ndarray | None = None,
) -> np.ndarray:
    """(T, 21, 3) keypoints in MediaPipe order (16 MANO joints + the :data:`TIP_VERTS` vertices), in the units
    of the model and ``transl`` (metres for the official files)."""
    pose = full_pose(model, global_orient, hand_pose, flat_hand_mean)
    joints, tips = forward(model, pose, betas, transl, v_template, TIP_VERTS)
    return np.concatenate([joints, tips], axis=1)[:, list(MANO_TO_MEDIAPIPE)]
