"""MJCF with every number at full precision.

``MjSpec.to_xml`` prints numbers with 6 significant digits: a model reloaded from that text differs from the
compiled one (body and geom poses, inertias, joint axes, mesh vertices in the 7th digit), and a clip replayed
in it drifts off the original run by millimetres. :func:`exact_mjcf` rewrites the numbers of that text from
the spec itself (``repr`` of each double, 9 digits of each float32 mesh vertex) and checks that the text
compiles to the very same model (:func:`same_model`: ``mj_saveModel`` bytes equal).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from typing import Any

import numpy as np

from quasisim.errors import QuasisimError

# per MJCF element: XML attribute -> the spec element's field (the numbers to_xml rounds)
FIELDS: dict[str, dict[str, str]] = {
    "option": {"timestep": "timestep", "gravity": "gravity", "impratio": "impratio"},
    "body": {"pos": "pos", "quat": "quat"},
    "inertial": {"pos": "ipos", "quat": "iquat", "mass": "mass", "diaginertia": "inertia"},
    "joint": {"pos": "pos", "axis": "axis", "range": "range", "armature": "armature", "damping": "damping"},
    "geom": {"size": "size", "pos": "pos", "quat": "quat", "rgba": "rgba", "friction": "friction"},
    "site": {"size": "size", "pos": "pos", "quat": "quat", "rgba": "rgba"},
    "mesh": {"vertex": "uservert"},
    "general": {"gainprm": "gainprm", "biasprm": "biasprm", "forcerange": "forcerange", "ctrlrange": "ctrlrange"},
    "light": {"pos": "pos", "dir": "dir", "diffuse": "diffuse"},
    "texture": {"rgb1": "rgb1", "rgb2": "rgb2"},
}
NAMED = {"body": "body", "geom": "geom", "joint": "joint", "site": "site", "mesh": "mesh", "texture": "texture",
         "general": "actuator"}  # fmt: skip
FLOAT32 = {"mesh"}  # fields stored as float32 in the spec (9 significant digits restore them exactly)
ROUNDING = 1e-5  # relative: a number of to_xml's text and the spec field it is rewritten from agree this well


def exact_mjcf(spec: Any, model: Any, text: str | None = None) -> str:
    """The MJCF text of ``spec`` (compiled: ``model = spec.compile()``; ``text``: its ``to_xml()`` where the
    caller has it) with full-precision numbers; raises :class:`QuasisimError` when the text does not compile
    to ``model`` exactly."""
    import mujoco

    root = ET.fromstring(spec.to_xml() if text is None else text)
    lights = iter(spec.lights)
    for child in root:
        _patch(child, spec, lights, None)
    text = ET.tostring(root, encoding="unicode")
    if not same_model(mujoco.MjModel.from_xml_string(text), model):
        raise QuasisimError("full-precision MJCF: the text does not compile to the spec's model (an MJCF field "
                            "to_xml rounds is missing from quasisim.data.mjcf.FIELDS)")  # fmt: skip
    return text


def same_model(a: Any, b: Any) -> bool:
    """Whether two compiled models are the same to the bit (their ``mj_saveModel`` bytes)."""
    return bool(np.array_equal(model_bytes(a), model_bytes(b)))


def model_bytes(model: Any) -> np.ndarray:
    """``mj_saveModel`` of ``model`` as bytes (uint8)."""
    import mujoco

    buf = np.zeros(mujoco.mj_sizeModel(model), np.uint8)
    mujoco.mj_saveModel(model, None, buf)
    return buf


def _patch(el: ET.Element, spec: Any, lights: Any, body: Any) -> None:
    """Rewrite the numbers of ``el`` (and below) from the matching spec element (``body``: the enclosing one)."""
    obj = _spec_element(el, spec, lights, body)
    if obj is not None:
        for attr, field in FIELDS.get(el.tag, {}).items():
            value = getattr(obj, field)
            if attr in el.attrib:
                el.set(attr, _numbers(el.get(attr, ""), value, el.tag in FLOAT32, el, attr))
            elif _negative_zero(value):  # left out as equal to the default, but -0.0 there
                el.set(attr, _numbers("", value, el.tag in FLOAT32, el, attr))
    for child in el:
        _patch(child, spec, lights, obj if el.tag == "body" else body)


def _spec_element(el: ET.Element, spec: Any, lights: Any, body: Any) -> Any:
    """The spec element that ``el`` was written from, or None (elements without rounded numbers)."""
    if el.tag == "option":
        return spec.option
    if el.tag == "inertial":
        return body
    if el.tag == "light":
        return next(lights)
    name = el.get("name")
    if el.tag in NAMED and name:
        return getattr(spec, NAMED[el.tag])(name)
    return None


def _numbers(text: str, value: Any, float32: bool, el: ET.Element, attr: str) -> str:
    """``value`` (the spec field) at full precision, as long as the text's vector or longer (trailing values
    that to_xml left out are written too); checks the text's rounded numbers against it."""
    v = _vector(value, float32)
    toks = text.split()
    if len(toks) > len(v) or any(
        abs(float(t) - x) > ROUNDING * max(1.0, abs(x)) for t, x in zip(toks, v, strict=False)
    ):
        raise QuasisimError(f"full-precision MJCF: <{el.tag} name={el.get('name')!r}> {attr}={text[:60]!r} is not "
                            f"the spec's {v[:4].tolist()}")  # fmt: skip
    return " ".join(format(x, ".9g") for x in v) if float32 else " ".join(repr(float(x)) for x in v)


def _vector(value: Any, float32: bool) -> np.ndarray:
    """A spec field (a number, a numpy array or a MuJoCo vector) as a 1-d array."""
    return np.atleast_1d(
        np.asarray(list(value) if not np.isscalar(value) else value, np.float32 if float32 else np.float64)
    )


def _negative_zero(value: Any) -> bool:
    v = _vector(value, False)
    return bool((np.signbit(v) & (v == 0)).any())
