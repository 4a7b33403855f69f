"""The rewrite of a loop's sequence of per-step outputs into scan outputs: same values, no sequence left; other
uses of a sequence are left alone."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

ort = pytest.importorskip("onnxruntime")
onnx = pytest.importorskip("onnx")

from tofdenoise.inference.onnx_loops import sequences_to_scan_outputs  # noqa: E402


def _stacked(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    h = torch.zeros_like(x[0])
    ys: list[torch.Tensor] = []
    for t in range(x.size(0)):
        h = 0.5 * h + x[t]
        ys.append(h.sum(0))
    return torch.stack(ys, 0), h


def _read_back(x: torch.Tensor) -> torch.Tensor:
    ys: list[torch.Tensor] = [x[0]]
    for t in range(x.size(0)):
        ys.append(ys[-1] + x[t])  # the body reads the sequence: it must stay one
    return torch.stack(ys, 0)


def _export(fn, tmp_path) -> onnx.ModelProto:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scripted = torch.jit.script(fn)

        class Module(torch.nn.Module):
            def forward(self, x):
                return scripted(x)

        path = tmp_path / "m.onnx"
        torch.onnx.export(
            Module(), (torch.randn(3, 2, 4),), str(path), dynamo=False, input_names=["x"], dynamic_axes={"x": {0: "T"}}
        )
    return onnx.load(str(path))


def _ops(graph: onnx.GraphProto) -> list[str]:
    """Operator types of ``graph`` and of the graphs nested in its nodes."""
    ops = []
    for node in graph.node:
        ops.append(node.op_type)
        ops += [op for attr in node.attribute if attr.type == onnx.AttributeProto.GRAPH for op in _ops(attr.g)]
    return ops


def _run(proto: onnx.ModelProto, x: np.ndarray) -> list[np.ndarray]:
    return ort.InferenceSession(proto.SerializeToString(), providers=["CPUExecutionProvider"]).run(None, {"x": x})


def test_the_stacked_sequence_becomes_a_scan_output_with_the_same_values(tmp_path):
    proto = _export(_stacked, tmp_path)
    x = np.random.default_rng(0).standard_normal((9, 2, 4)).astype(np.float32)
    before = _run(proto, x)
    assert "SequenceInsert" in _ops(proto.graph)
    assert sequences_to_scan_outputs(proto.graph) == 1
    onnx.checker.check_model(proto, full_check=True)
    assert not {"SequenceInsert", "SequenceEmpty", "ConcatFromSequence"} & set(_ops(proto.graph))
    after = _run(proto, x)
    ref = _stacked(torch.from_numpy(x))
    for a, b, r in zip(before, after, ref):
        assert a.shape == b.shape == tuple(r.shape)
        assert np.abs(a - b).max() == 0.0 and np.abs(b - r.numpy()).max() < 1e-5


def test_a_sequence_the_loop_reads_is_left_alone(tmp_path):
    proto = _export(_read_back, tmp_path)
    text = str(proto.graph)
    assert sequences_to_scan_outputs(proto.graph) == 0
    assert str(proto.graph) == text
