"""Ray-drop classifier files (``ray_drop.lidar`` back-end ``learned``; written by ``rvnoise fit ray-drop``).

Both forms take the four features of :data:`physics.ray_drop.FEATURES` in that order and give the drop probability:
- ``.json`` (schema ``rvnoise.ray_drop/1``): an :class:`~roadview_noise.physics.ray_drop.AdditiveLogistic` —
  ``features``, per feature ``knots`` and ``values`` (logit contributions, constant beyond the outer knots),
  ``intercept`` — and ``fitted_on`` (what it was fitted on, its validation scores); applied with NumPy.
- ``.onnx``: a graph with one input ``features`` (float32, [N, 4]) and one output, the drop probability ([N] or
  [N, 1]), run with onnxruntime on the CPU. ``rvnoise fit`` writes the additive model as such a graph (clip, hinge
  functions, sigmoid; needs the ``onnx`` package); any classifier on the same features exported to ONNX works.
"""

from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path

import numpy as np

from ..errors import InputError, ModelError
from ..physics.ray_drop import FEATURES, AdditiveLogistic
from .atomic import write_bytes_atomic

SCHEMA = "rvnoise.ray_drop/1"


class OnnxRayDrop:
    """A drop-probability classifier in an ONNX file (module doc)."""

    def __init__(self, path: str):
        self.path = path

    def drop_probability(self, features: np.ndarray) -> np.ndarray:
        session = _session(self.path)
        x = np.ascontiguousarray(features, dtype=np.float32)
        try:
            y = session.run(None, {session.get_inputs()[0].name: x})[0]
        except Exception as e:  # onnxruntime raises its own exception types
            raise ModelError(f"{Path(self.path).name}: the classifier failed on {x.shape} features ({e})") from None
        y = np.asarray(y, dtype=np.float64).reshape(-1)
        if len(y) != len(x):
            raise ModelError(f"{Path(self.path).name}: {len(y)} probabilities for {len(x)} rays")
        return np.clip(y, 0.0, 1.0)


@lru_cache(maxsize=4)
def _session(path: str):
    try:
        import onnxruntime as ort
    except ImportError:
        raise ModelError("an .onnx ray-drop classifier needs onnxruntime: pip install 'roadview_noise[onnx]'") from None
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    options.inter_op_num_threads = 1
    try:
        return ort.InferenceSession(path, sess_options=options, providers=["CPUExecutionProvider"])
    except Exception as e:  # onnxruntime's own exception types for unreadable or invalid models
        raise ModelError(f"{Path(path).name}: cannot load the ONNX classifier ({e})") from None


def read_model(path: str | Path) -> AdditiveLogistic | OnnxRayDrop:
    """The classifier in ``path`` (.json or .onnx); InputError naming the file and the problem."""
    p = Path(path)
    if not p.is_file():
        raise InputError("ray-drop model file not found", file=str(p))
    if p.suffix.lower() == ".onnx":
        return OnnxRayDrop(str(p.resolve()))
    stat = p.stat()
    return _read_json(str(p.resolve()), stat.st_mtime_ns, stat.st_size)


@lru_cache(maxsize=8)
def _read_json(path: str, mtime_ns: int, size: int) -> AdditiveLogistic:
    try:
        doc = json.loads(Path(path).read_text())
    except (OSError, ValueError) as e:
        raise InputError(f"cannot read the ray-drop model: {e}", file=path) from None
    if not isinstance(doc, dict) or doc.get("schema") != SCHEMA:
        raise InputError(f"not a ray-drop model (schema must be {SCHEMA!r}); write one with `rvnoise fit ray-drop`",
                         file=path)
    try:
        names = tuple(doc["features"])
        knots = tuple(np.asarray(k, dtype=np.float64) for k in doc["knots"])
        values = tuple(np.asarray(v, dtype=np.float64) for v in doc["values"])
        intercept = float(doc["intercept"])
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(f"ray-drop model: missing or malformed {e}", file=path) from None
    unknown = [n for n in names if n not in FEATURES]
    if unknown or not (len(names) == len(knots) == len(values)):
        raise InputError(f"ray-drop model: features {list(names)} (known: {list(FEATURES)}) need one knots and one "
                         f"values list each", file=path)
    for name, k, v in zip(names, knots, values):
        if k.ndim != 1 or k.shape != v.shape or len(k) < 2 or np.any(np.diff(k) <= 0) or not np.isfinite(v).all():
            raise InputError(f"ray-drop model: feature {name!r} needs ≥ 2 increasing knots and as many finite values",
                             file=path)
    return AdditiveLogistic(names, knots, values, intercept)


def write_model(path: str | Path, model: AdditiveLogistic, fitted_on: dict) -> Path:
    """Write ``model`` as .json or .onnx (by the suffix), atomically."""
    p = Path(path)
    if p.suffix.lower() == ".onnx":
        data = _onnx_bytes(model, fitted_on)
    elif p.suffix.lower() == ".json":
        doc = {"schema": SCHEMA, "classifier": "additive_logistic", "features": list(model.features),
               "knots": [k.tolist() for k in model.knots], "values": [v.tolist() for v in model.values],
               "intercept": model.intercept, "fitted_on": fitted_on}
        data = (json.dumps(doc, indent=1) + "\n").encode()
    else:
        raise InputError("the model file must end in .json or .onnx", file=str(p))
    write_bytes_atomic(p, data)
    return p


def _onnx_bytes(model: AdditiveLogistic, fitted_on: dict) -> bytes:
    """The additive model as an ONNX graph: per feature, its column clipped to the knots, then
    ``values_0 + Σ_i Δslope_i · relu(x − knot_i)`` (the piecewise-linear function), summed, plus the intercept,
    through a sigmoid."""
    try:
        import onnx
        from onnx import TensorProto, helper, numpy_helper
    except ImportError:
        raise ModelError("writing an .onnx classifier needs the onnx package: pip install onnx "
                         "(or write .json)") from None
    nodes, inits, terms = [], [], []
    const = float(model.intercept)

    def init(name, array):
        inits.append(numpy_helper.from_array(np.asarray(array, dtype=np.float32), name))
        return name

    for name, k, v in zip(model.features, model.knots, model.values):
        j = FEATURES.index(name)
        slopes = np.diff(v) / np.diff(k)
        jumps = np.diff(np.concatenate([[0.0], slopes]))
        inits.append(numpy_helper.from_array(np.asarray([j], dtype=np.int64), f"{name}_index"))
        nodes.append(helper.make_node("Gather", ["features", f"{name}_index"], [f"{name}_x"], axis=1))
        nodes.append(helper.make_node("Clip", [f"{name}_x", init(f"{name}_lo", k[0]), init(f"{name}_hi", k[-1])],
                                      [f"{name}_c"]))
        nodes.append(helper.make_node("Sub", [f"{name}_c", init(f"{name}_knots", k[:-1][None, :])], [f"{name}_d"]))
        nodes.append(helper.make_node("Relu", [f"{name}_d"], [f"{name}_h"]))
        nodes.append(helper.make_node("MatMul", [f"{name}_h", init(f"{name}_jumps", jumps[:, None])], [f"{name}_g"]))
        terms.append(f"{name}_g")
        const += float(v[0])
    nodes.append(helper.make_node("Sum", terms, ["sum"]))
    nodes.append(helper.make_node("Add", ["sum", init("intercept", [[const]])], ["logit"]))
    nodes.append(helper.make_node("Sigmoid", ["logit"], ["p_drop"]))
    graph = helper.make_graph(nodes, "rvnoise_ray_drop",
                              [helper.make_tensor_value_info("features", TensorProto.FLOAT, ["N", len(FEATURES)])],
                              [helper.make_tensor_value_info("p_drop", TensorProto.FLOAT, ["N", 1])], inits)
    m = helper.make_model(graph, producer_name="rvnoise", opset_imports=[helper.make_opsetid("", 13)])
    helper.set_model_props(m, {"schema": SCHEMA, "features": json.dumps(list(FEATURES)),
                               "fitted_on": json.dumps(fitted_on)})
    onnx.checker.check_model(m)
    return m.SerializeToString()
