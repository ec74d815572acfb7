"""Fixtures of the depth tests: a tiny monocular depth model in ONNX format, built with the onnx package."""

from __future__ import annotations

from pathlib import Path

import pytest


def _tiny_depth_model(path: Path, *, weights=(20.0, 10.0, 5.0), bias=2.0, fixed_hw=None) -> Path:
    """A 1×1 convolution: depth = 20 R + 10 G + 5 B + 2 on the normalised input, shape (1, 1, H, W)."""
    onnx = pytest.importorskip("onnx")
    from onnx import TensorProto, helper

    hw = list(fixed_hw) if fixed_hw else ["H", "W"]
    x = helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, *hw])
    y = helper.make_tensor_value_info("depth", TensorProto.FLOAT, [1, 1, *hw])
    w = helper.make_tensor("w", TensorProto.FLOAT, [1, 3, 1, 1], list(weights))
    b = helper.make_tensor("b", TensorProto.FLOAT, [1], [bias])
    graph = helper.make_graph([helper.make_node("Conv", ["image", "w", "b"], ["depth"])], "tiny", [x], [y], [w, b])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


@pytest.fixture
def tiny_depth_model():
    """``build(path, *, weights, bias, fixed_hw) -> path`` of a tiny ONNX depth model (skips without onnx)."""
    return _tiny_depth_model
