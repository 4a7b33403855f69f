"""The export scan (two loops over lanes of the sequence) equals the sequential selective scan, in PyTorch and as
an ONNX graph in onnxruntime, at lengths that are not a multiple of the lane count."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from tofdenoise.models.scan import selective_scan, selective_scan_ref
from tofdenoise.models.scan.export import export_scan_lanes, selective_scan_export

BATCH, DIM, N = 2, 6, 4
LANE_ELEMS = BATCH * DIM * N  # state elements of one lane


def _inputs(length: int, groups: int = 2, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    return (
        torch.randn(BATCH, DIM, length, generator=g),
        torch.randn(BATCH, DIM, length, generator=g),
        -3.0 * torch.rand(DIM, N, generator=g),
        torch.randn(BATCH, groups, N, length, generator=g),
        torch.randn(BATCH, groups, N, length, generator=g),
        torch.randn(DIM, generator=g),
        torch.randn(DIM, generator=g),
    )


@pytest.mark.parametrize(
    ("length", "lanes"),
    [(1, 1), (7, 3), (64, 5), (64, 64), (301, 1), (301, 7), (301, 16), (40, 100)],
)
def test_export_scan_equals_the_reference(length, lanes):
    u, delta, A, B, C, D, bias = _inputs(length)
    ref = selective_scan_ref(u, delta, A, B, C, D, bias, True)
    out = selective_scan_export(u, delta, A, B, C, D, bias, True, state_elems=lanes * LANE_ELEMS)
    assert out.shape == ref.shape
    assert torch.allclose(out, ref, atol=1e-4, rtol=1e-4), (out - ref).abs().max()


def test_the_dispatcher_route_and_one_group_of_b_and_c():
    u, delta, A, B, C, D, bias = _inputs(45, groups=1)
    ref = selective_scan_ref(u, delta, A, B[:, 0], C[:, 0], D, bias, True)
    routed = selective_scan(u, delta, A, B[:, 0], C[:, 0], D, bias, True, backend="export")
    assert torch.allclose(routed, ref, atol=1e-4)
    no_skip = selective_scan_export(u, delta.abs(), A, B, C)  # no D, no bias, no softplus
    assert torch.allclose(no_skip, selective_scan_ref(u, delta.abs(), A, B, C), atol=1e-4)


def test_lanes_grow_with_the_length_only_up_to_the_state_budget():
    assert export_scan_lanes(4096, 307200, 1 << 18) == 64  # DVSS's first level at 480 x 640: 64 lanes
    assert export_scan_lanes(4096, 4800, 1 << 18) == 64
    assert export_scan_lanes(4096, 10, 1 << 18) == 10  # shorter than the budget: one position per lane
    assert export_scan_lanes(1 << 20, 307200, 1 << 18) == 1  # a lane larger than the budget: one lane
    with pytest.raises(ValueError, match="state_elems must be >= 1"):
        selective_scan_export(*_inputs(5)[:5], state_elems=0)


class _ScanModule(torch.nn.Module):
    """The export scan of the tests' A, D and bias over 5 lanes, as a module of (u, delta, B, C) to export."""

    def __init__(self, A, D, bias):
        super().__init__()
        self.A, self.D, self.bias = A, D, bias

    def forward(self, u, delta, B, C):
        return selective_scan_export(u, delta, self.A, B, C, self.D, self.bias, True, state_elems=5 * LANE_ELEMS)


def _assert_equal_to_the_reference_at_any_length(proto, A, D, bias) -> None:
    """The scan graph ``proto`` (inputs u, delta, B, C in that order) in onnxruntime equals the reference scan
    within 1e-4 at lengths below, at and around multiples of the 5 lanes of the tests."""
    import onnxruntime as ort

    session = ort.InferenceSession(proto.SerializeToString(), providers=["CPUExecutionProvider"])
    names = [i.name for i in session.get_inputs()]
    for length in (1, 4, 5, 37, 64, 301):  # fewer positions than lanes, multiples of 5 and not
        u, delta, _, B, C, _, _ = _inputs(length, seed=length)
        ref = selective_scan_ref(u, delta, A, B, C, D, bias, True).numpy()
        out = session.run(None, dict(zip(names, (t.numpy() for t in (u, delta, B, C)))))[0]
        assert out.shape == ref.shape and np.abs(out - ref).max() <= 1e-4, length


def test_onnxruntime_runs_the_scan_at_any_length_with_loops_and_scan_outputs(tmp_path):
    pytest.importorskip("onnxruntime")
    import onnx

    from tofdenoise.inference.onnx_loops import sequences_to_scan_outputs

    u, delta, A, B, C, D, bias = _inputs(37)
    scan = _ScanModule(A, D, bias)

    names = ["u", "delta", "B", "C"]
    path = tmp_path / "scan.onnx"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            scan,
            (u, delta, B, C),
            str(path),
            dynamo=False,
            input_names=names,
            output_names=["y"],
            dynamic_axes={"u": {2: "L"}, "delta": {2: "L"}, "B": {3: "L"}, "C": {3: "L"}},
            opset_version=18,
        )
    proto = onnx.load(str(path))
    assert sequences_to_scan_outputs(proto.graph) == 1  # the emitting loop's per-step outputs
    ops = [node.op_type for node in proto.graph.node]
    body_ops = [n.op_type for node in proto.graph.node for a in node.attribute if a.type == a.GRAPH for n in a.g.node]
    assert ops.count("Loop") == 3 and "SequenceInsert" not in body_ops  # two position loops, one carry
    _assert_equal_to_the_reference_at_any_length(proto, A, D, bias)


def test_the_dynamo_exporter_gets_scan_operators_that_run_at_any_length(tmp_path):
    """torch.export would unroll the scripted loops at the example's length; under it the scan takes the ``scan``
    operator route (ONNX ``Scan``, K lanes whatever L), equal to the reference at every length."""
    pytest.importorskip("onnxruntime")

    u, delta, A, B, C, D, bias = _inputs(37)
    scan = _ScanModule(A, D, bias)

    length = torch.export.Dim("L")
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")
        program = torch.onnx.export(
            scan.eval(),
            (u, delta, B, C),
            dynamo=True,
            dynamic_shapes=({2: length}, {2: length}, {3: length}, {3: length}),
            opset_version=18,
            verbose=False,
        )
    proto = program.model_proto
    ops = [node.op_type for node in proto.graph.node]
    assert ops.count("Scan") == 2 and "Loop" not in ops  # the two position loops, not unrolled
    _assert_equal_to_the_reference_at_any_length(proto, A, D, bias)
