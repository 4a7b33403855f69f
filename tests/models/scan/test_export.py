"""The export scan equals the sequential selective scan in both forms (one loop step per position of a lane, or per
chunk of positions behind an exponent guard), in PyTorch and as an ONNX graph in onnxruntime through both exporters,
at lengths that are not a multiple of the lane count or of the chunk."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from tofdenoise.models.scan import export as export_scan
from tofdenoise.models.scan import selective_scan, selective_scan_ref
from tofdenoise.models.scan.export import (
    EXPORT_SCAN_EXP_BOUND,
    export_chunk_lanes,
    export_scan_form,
    export_scan_lanes,
    selective_scan_export,
)

FORMS = ("steps", "chunked")

BATCH, DIM, N = 2, 6, 4
LANE_ELEMS = BATCH * DIM * N  # state elements of one lane


def _inputs(length: int, groups: int = 2, seed: int = 0, batch: int = BATCH):
    g = torch.Generator().manual_seed(seed)
    return (
        torch.randn(batch, DIM, length, generator=g),
        torch.randn(batch, DIM, length, generator=g),
        -3.0 * torch.rand(DIM, N, generator=g),
        torch.randn(batch, groups, N, length, generator=g),
        torch.randn(batch, groups, N, length, generator=g),
        torch.randn(DIM, generator=g),
        torch.randn(DIM, generator=g),
    )


@pytest.mark.parametrize("form", FORMS)
@pytest.mark.parametrize(
    ("length", "lanes"),
    [(1, 1), (7, 3), (64, 5), (64, 64), (301, 1), (301, 7), (301, 16), (40, 100)],
)
def test_export_scan_equals_the_reference(length, lanes, form):
    u, delta, A, B, C, D, bias = _inputs(length)
    ref = selective_scan_ref(u, delta, A, B, C, D, bias, True)
    out = selective_scan_export(u, delta, A, B, C, D, bias, True, state_elems=lanes * LANE_ELEMS, form=form)
    assert out.shape == ref.shape
    assert torch.allclose(out, ref, atol=1e-4, rtol=1e-4), (out - ref).abs().max()


@pytest.mark.parametrize(("length", "chunk"), [(1, 16), (15, 16), (17, 16), (100, 7), (301, 1), (33, 64)])
def test_the_chunked_form_at_lengths_and_chunks_that_do_not_divide_and_batch_one(length, chunk):
    u, delta, A, B, C, D, bias = _inputs(length, batch=1, seed=length)
    ref = selective_scan_ref(u, delta, A, B, C, D, bias, True)
    for lanes in (1, 3):
        out = selective_scan_export(
            u, delta, A, B, C, D, bias, True, state_elems=lanes * DIM * N, form="chunked", chunk=chunk
        )
        assert torch.allclose(out, ref, atol=1e-4, rtol=1e-4), (lanes, (out - ref).abs().max())


def test_the_chunk_offsets_and_exponent_bound():
    """Per chunk: S - m with m the midpoint of 0 and the summed deltas' range, and the bound max |A| (S - m)."""
    dl = torch.tensor([0.5, 1.0, 0.25, 2.0, 0.0, 0.0]).reshape(2, 3, 1, 1, 1, 1, 1)  # chunks (0.5, 1, .25), (2, 0, 0)
    A = torch.tensor([[-1.0, -3.0]])
    s_mid, mid, end_mid, bound = export_scan._chunk_offsets(dl, A)
    assert torch.allclose(mid.flatten(), torch.tensor([0.875, 1.0]))  # ranges [0, 1.75] and [0, 2]
    assert torch.allclose(s_mid.flatten(), torch.tensor([-0.375, 0.625, 0.875, 1.0, 1.0, 1.0]))
    assert torch.allclose(end_mid.flatten(), torch.tensor([0.875, 1.0]))
    assert float(bound) == pytest.approx(3.0)  # |A| 3 x half of the second chunk's range 2
    negative = export_scan._chunk_offsets(-dl, A)  # deltas of either sign: the range still includes 0
    assert torch.allclose(negative[1].flatten(), torch.tensor([-0.875, -1.0])) and float(negative[3]) == 3.0


def test_the_guard_takes_the_step_loops_where_the_chunks_exponents_would_overflow():
    """Large deltas (|A| x half a chunk's summed delta far above the bound): without the guard the chunked loops
    overflow float32; with it the scan is the step loops' result exactly, equal to the reference."""
    u, delta, A, B, C, D, bias = _inputs(301)
    delta = 40.0 * delta.abs() + 1.0  # no softplus: summed delta of a chunk of 16 about 500, |A| up to 3
    args = (u, delta, A, B, C, 5 * LANE_ELEMS)
    ref = selective_scan_ref(u, delta, A, B, C)
    steps = export_scan._lane_scan(*args)
    assert torch.allclose(steps, ref, atol=1e-4, rtol=1e-4)
    unguarded = export_scan._chunk_scan(*args, 16, float("inf"))
    assert not torch.isfinite(unguarded).all() or not torch.allclose(unguarded, ref, atol=1e-3, rtol=1e-3)
    assert torch.equal(export_scan._chunk_scan(*args, 16, EXPORT_SCAN_EXP_BOUND), steps)
    # within the bound the chunked loops run: their result, not the step loops'
    small = (u, 0.01 * delta, A, B, C, 5 * LANE_ELEMS)
    chunked = export_scan._chunk_scan(*small, 16, EXPORT_SCAN_EXP_BOUND)
    assert not torch.equal(chunked, export_scan._lane_scan(*small))
    assert torch.equal(chunked, export_scan._chunk_scan(*small, 16, float("inf")))
    assert torch.allclose(chunked, selective_scan_ref(*small[:5]), atol=1e-4, rtol=1e-4)


def test_the_dispatcher_route_and_one_group_of_b_and_c():
    u, delta, A, B, C, D, bias = _inputs(45, groups=1)
    ref = selective_scan_ref(u, delta, A, B[:, 0], C[:, 0], D, bias, True)
    routed = selective_scan(u, delta, A, B[:, 0], C[:, 0], D, bias, True, backend="export")
    assert torch.allclose(routed, ref, atol=1e-4)
    no_skip = selective_scan_export(u, delta.abs(), A, B, C)  # no D, no bias, no softplus
    assert torch.allclose(no_skip, selective_scan_ref(u, delta.abs(), A, B, C), atol=1e-4)


def test_the_form_is_one_setting_and_a_bad_one_is_an_error():
    u, delta, A, B, C, D, bias = _inputs(45)
    budget = export_scan.EXPORT_SCAN_STATE_ELEMS
    default = selective_scan_export(u, delta.abs(), A, B, C)
    chunked_ref = export_scan._chunk_scan(u, delta.abs(), A, B, C, budget, 16, EXPORT_SCAN_EXP_BOUND)
    steps_ref = export_scan._lane_scan(u, delta.abs(), A, B, C, budget)
    assert torch.equal(default, steps_ref if export_scan.EXPORT_SCAN_FORM == "steps" else chunked_ref)
    for form, ref in (("chunked", chunked_ref), ("steps", steps_ref)):
        with export_scan_form(form):
            assert torch.equal(selective_scan_export(u, delta.abs(), A, B, C), ref)
            assert torch.equal(selective_scan_export(u, delta.abs(), A, B, C, form="steps"), steps_ref)  # told
    assert not torch.equal(chunked_ref, steps_ref)  # the two forms differ in rounding: the checks above can tell
    assert export_scan._FORM is None  # restored after the block
    with pytest.raises(ValueError, match="export scan form 'loop'; expected one of steps, chunked"):
        with export_scan_form("loop"):
            pass
    with pytest.raises(ValueError, match="form 'loop'; expected one of steps, chunked"):
        selective_scan_export(u, delta, A, B, C, form="loop")
    with pytest.raises(ValueError, match="chunk must be >= 1"):
        selective_scan_export(u, delta, A, B, C, chunk=0)


def test_lanes_grow_with_the_length_only_up_to_the_state_budget():
    assert export_scan_lanes(4096, 307200, 1 << 18) == 64  # DVSS's first level at 480 x 640: 64 lanes
    assert export_scan_lanes(4096, 4800, 1 << 18) == 64
    assert export_scan_lanes(4096, 10, 1 << 18) == 10  # shorter than the budget: one position per lane
    assert export_scan_lanes(1 << 20, 307200, 1 << 18) == 1  # a lane larger than the budget: one lane
    assert export_chunk_lanes(4096, 307200, 1 << 18, 16) == 64
    assert export_chunk_lanes(4096, 40, 1 << 18, 16) == 3  # at most one lane per chunk of the sequence
    with pytest.raises(ValueError, match="state_elems must be >= 1"):
        selective_scan_export(*_inputs(5)[:5], state_elems=0)


class _ScanModule(torch.nn.Module):
    """The export scan of the tests' A, D and bias over 5 lanes, as a module of (u, delta, B, C) to export."""

    def __init__(self, A, D, bias, form):
        super().__init__()
        self.A, self.D, self.bias, self.form = A, D, bias, form

    def forward(self, u, delta, B, C):
        return selective_scan_export(
            u, delta, self.A, B, C, self.D, self.bias, True, state_elems=5 * LANE_ELEMS, form=self.form
        )


def _ops(graph) -> list[str]:
    """Operator types of ``graph`` and of the graphs nested in its nodes, at any depth."""
    ops = []
    for node in graph.node:
        ops.append(node.op_type)
        ops += [op for attr in node.attribute if attr.type == attr.GRAPH for op in _ops(attr.g)]
    return ops


def _assert_equal_to_the_reference_at_any_length(proto, A, D, bias) -> None:
    """The scan graph ``proto`` (inputs u, delta, B, C in that order) in onnxruntime equals the reference scan
    within 1e-4 (relative, for the large outputs of large deltas) at lengths below, at and around multiples of the 5
    lanes of the tests and of the chunk, with deltas that pass the chunked form's exponent guard and ones that fail
    it (the step loops then run)."""
    import onnxruntime as ort

    session = ort.InferenceSession(proto.SerializeToString(), providers=["CPUExecutionProvider"])
    names = [i.name for i in session.get_inputs()]
    for length in (1, 4, 5, 37, 64, 301):  # fewer positions than lanes, multiples of 5 and not
        u, delta, _, B, C, _, _ = _inputs(length, seed=length)
        for shift in (0.0, 60.0):  # softplus(delta + 60): |A| x a chunk's half sum about 1400, the guard fails
            ref = selective_scan_ref(u, delta + shift, A, B, C, D, bias, True).numpy()
            out = session.run(None, dict(zip(names, (t.numpy() for t in (u, delta + shift, B, C)))))[0]
            err = np.abs(out - ref) / (1.0 + np.abs(ref))
            assert out.shape == ref.shape and err.max() <= 1e-4, (length, shift)


@pytest.mark.parametrize("form", FORMS)
def test_onnxruntime_runs_the_scan_at_any_length_with_loops_and_scan_outputs(tmp_path, form):
    pytest.importorskip("onnxruntime")
    import onnx

    from tofdenoise.inference.onnx_loops import sequences_to_scan_outputs

    u, delta, A, B, C, D, bias = _inputs(37)
    scan = _ScanModule(A, D, bias, form)

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
    # the emitting loops' per-step outputs (the chunked form's and its fallback's)
    assert sequences_to_scan_outputs(proto.graph) == (2 if form == "chunked" else 1)
    ops = _ops(proto.graph)
    assert "SequenceInsert" not in ops
    if form == "chunked":  # the guard and, inside it, two chunk loops, a carry and the three loops of the steps
        assert ops.count("If") == 2 and ops.count("Loop") == 6 and ops.count("CumSum") == 2
    else:
        assert ops.count("Loop") == 3 and "If" not in ops  # two position loops, one carry
    _assert_equal_to_the_reference_at_any_length(proto, A, D, bias)


@pytest.mark.parametrize("form", FORMS)
def test_the_dynamo_exporter_gets_scan_operators_that_run_at_any_length(tmp_path, form):
    """torch.export would unroll the scripted loops at the example's length; under it the scan takes the ``scan``
    operator route (ONNX ``Scan``, K lanes whatever L), and the chunked form's guard a ``cond`` (ONNX ``If``),
    equal to the reference at every length."""
    pytest.importorskip("onnxruntime")

    u, delta, A, B, C, D, bias = _inputs(37)
    scan = _ScanModule(A, D, bias, form)

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
    ops = _ops(proto.graph)
    assert "Loop" not in ops  # not unrolled
    if form == "chunked":  # two chunk loops and the steps' two position loops, under one If
        assert ops.count("Scan") == 4 and ops.count("If") == 1
    else:
        assert ops.count("Scan") == 2 and "If" not in ops
    _assert_equal_to_the_reference_at_any_length(proto, A, D, bias)
