"""A minimal ONNX writer for tests (the ``onnx`` package is not a dependency): protobuf encoded by hand.

``constant_detections_model`` builds a real network that OpenCV's dnn module runs: its output is a fixed detection
table plus the mean of the input image added to the score column, so a test can tell that the image went through it.
"""

from __future__ import annotations

import numpy as np


def _varint(value: int) -> bytes:
    out = bytearray()
    while True:
        byte = value & 0x7F
        value >>= 7
        if value:
            out.append(byte | 0x80)
        else:
            out.append(byte)
            return bytes(out)


def _field(number: int, payload) -> bytes:
    if isinstance(payload, int):
        return _varint(number << 3) + _varint(payload)
    if isinstance(payload, str):
        payload = payload.encode()
    return _varint((number << 3) | 2) + _varint(len(payload)) + payload


def _tensor(name: str, array: np.ndarray) -> bytes:
    array = np.ascontiguousarray(array, np.float32)
    return b"".join(_field(1, int(d)) for d in array.shape) + _field(2, 1) + _field(8, name) + _field(9, array.tobytes())


def _value_info(name: str, shape) -> bytes:
    dims = b"".join(_field(1, _field(1, int(d))) for d in shape)
    return _field(1, name) + _field(2, _field(1, _field(1, 1) + _field(2, dims)))


def _node(op: str, inputs, outputs, name: str) -> bytes:
    return (b"".join(_field(1, x) for x in inputs) + b"".join(_field(2, x) for x in outputs)
            + _field(3, name) + _field(4, op))


def constant_detections_model(table: np.ndarray, input_hw: tuple[int, int], score_column: int) -> bytes:
    """ONNX bytes: out = table + mean(input) * onehot(score_column); input (1, 3, H, W) float."""
    table = np.asarray(table, np.float32)
    weights = np.zeros_like(table)
    weights[..., score_column] = 1.0
    graph = (_field(1, _node("ReduceMean", ["data"], ["mean"], "mean"))
             + _field(1, _node("Mul", ["mean", "weights"], ["bias"], "mul"))
             + _field(1, _node("Add", ["table", "bias"], ["out"], "add"))
             + _field(2, "semloc_test") + _field(5, _tensor("table", table)) + _field(5, _tensor("weights", weights))
             + _field(11, _value_info("data", (1, 3) + tuple(input_hw))) + _field(12, _value_info("out", table.shape)))
    return _field(1, 7) + _field(2, "semloc-tests") + _field(7, graph) + _field(8, _field(1, "") + _field(2, 13))
