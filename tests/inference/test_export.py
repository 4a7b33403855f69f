"""ONNX export of the restore path: onnxruntime equals PyTorch on frames with holes, at any size."""

from __future__ import annotations

import numpy as np
import pytest
import torch

pytest.importorskip("onnxruntime")

from tofdenoise.inference.export import ExportError, export_graph, export_onnx, restore_graph  # noqa: E402
from tofdenoise.inference.onnx_runner import (  # noqa: E402
    OnnxModelError,
    OnnxRestorer,
    execution_providers,
    open_session,
    session_providers,
)
from tofdenoise.training.module import DepthRestorer  # noqa: E402

#: tiny networks (the sizes of tests/cli/conftest.py); DVSS's reference runs the PyTorch scan (no kernel build)
TINY = {
    "unet": {"width": 8, "stages": 2},
    "deeptof": {"channels": [8, 8, 16, 16]},
    "tofkpn": {"channels": [8, 8, 16, 16]},
    "rcf": {"width": 8, "hidden": 8, "steps": 2, "global_levels": 2},
    "restormer": {"width": 8, "blocks": [1, 1, 1, 1], "heads": [1, 1, 2, 2], "refinement_blocks": 1},
    "dvss": {"width": 8, "enc_blocks": [1], "bottleneck_blocks": 1, "d_state": 4, "scan_backend": "torch"},
}
#: parity bound of the issue: onnxruntime vs PyTorch on valid pixels, fp32
TOLERANCE_MM = 0.01


def _model(name: str) -> DepthRestorer:
    torch.manual_seed(0)
    model = DepthRestorer(
        backbone=name, backbone_kwargs=TINY[name], conditioning={"use_signal_channel": name == "rcf"}
    ).eval()
    with torch.no_grad():  # away from the zero-initialised residual head: the network's output matters
        for p in model.backbone.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return model


def _save_checkpoint(model: DepthRestorer, path):
    """``model`` as a checkpoint file of ``tofdenoise train`` (weights, hyper-parameters, the learned record)."""
    import lightning

    from tofdenoise.training.learned_guard import LEARNED_RECORD_KEY

    payload = {
        "state_dict": model.state_dict(),
        "hyper_parameters": dict(model.hparams),
        LEARNED_RECORD_KEY: {"trained_steps": 0, "best_val_mae_mm": None, "raw_val_mae_mm": None},
        "pytorch-lightning_version": lightning.__version__,
    }
    torch.save(payload, path)
    return path


def _frame(h: int, w: int, seed: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    depth = (900.0 + 2.0 * xx + 1.5 * yy + 8.0 * torch.randn(h, w, generator=gen))[None, None]
    depth[torch.rand(depth.shape, generator=gen) < 0.15] = 0.0  # scattered holes
    depth[..., h // 3 : h // 3 + 6, w // 2 : w // 2 + 9] = float("nan")  # a hole blob
    return depth, 1000.0 * torch.rand(1, 1, h, w, generator=gen)


def _max_diff(model: DepthRestorer, runner: OnnxRestorer, h: int, w: int) -> float:
    depth, amp = _frame(h, w)
    with torch.no_grad():
        ref = model.restore_mm({"noisy": depth, "amplitude": amp}, tile=None).numpy()
    out = runner.restore_mm(depth.numpy(), amp.numpy())
    valid = np.isfinite(depth.numpy()) & (depth.numpy() > 0)
    return float(np.abs(out - ref)[valid].max())


@pytest.mark.parametrize("backbone", list(TINY))
def test_onnxruntime_equals_pytorch_on_frames_with_holes_at_several_sizes(backbone, tmp_path):
    model = _model(backbone)
    path = tmp_path / f"{backbone}.onnx"
    export_graph(restore_graph(model), path)
    runner = OnnxRestorer.__new__(OnnxRestorer)  # a bare graph (no metadata): the session only
    import onnxruntime as ort

    runner.session, runner.inputs = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]), None
    runner.inputs = [i.name for i in runner.session.get_inputs()]
    runner.path = path
    for h, w in [(37, 53), (64, 80), (61, 83)]:  # odd, even and the example's own size: one graph for all
        assert _max_diff(model, runner, h, w) <= TOLERANCE_MM, (backbone, h, w)


def test_export_command_and_denoise_onnx_match_the_checkpoint(tmp_path):
    from tofdenoise.cli.denoise import main as denoise_main
    from tofdenoise.cli.export import main as export_main
    from tofdenoise.data_modules.io import write_depth_png16

    model = _model("unet")
    ckpt = _save_checkpoint(model, tmp_path / "m.ckpt")
    onnx_path = tmp_path / "m.onnx"
    assert export_main([str(ckpt), "--onnx", str(onnx_path)]) == 0
    runner = OnnxRestorer(onnx_path)
    assert runner.backbone == "unet" and runner.metadata["tofdenoise_precision"] == "fp32"
    frames = tmp_path / "frames"
    depth, _ = _frame(48, 72)
    write_depth_png16(frames / "a.png", torch.nan_to_num(depth[0, 0]).numpy())
    assert denoise_main([str(frames), "--onnx", str(onnx_path), "--out", str(tmp_path / "o1"), "--npy", "--quiet"]) == 0
    assert denoise_main([str(frames), "--ckpt", str(ckpt), "--out", str(tmp_path / "o2"), "--npy", "--quiet"]) == 0
    a, b = np.load(tmp_path / "o1" / "a.npy"), np.load(tmp_path / "o2" / "a.npy")
    assert ((a > 0) == (b > 0)).all() and (a[depth[0, 0].nan_to_num().numpy() == 0] == 0).all()
    assert np.abs(a - b).max() <= TOLERANCE_MM
    # the output never replaces the checkpoint
    assert export_main([str(ckpt), "--onnx", str(ckpt)]) == 2


def _foreign_onnx(path):
    """A valid ONNX graph written by another tool (no tofdenoise_* metadata)."""
    import onnx
    from onnx import TensorProto, helper

    x, y = (helper.make_tensor_value_info(n, TensorProto.FLOAT, [1]) for n in ("x", "y"))
    graph = helper.make_graph([helper.make_node("Identity", ["x"], ["y"])], "other", [x], [y])
    onnx.save(helper.make_model(graph), str(path))
    return path


def test_export_replaces_only_an_earlier_export_never_a_checkpoint_an_image_or_a_foreign_graph(tmp_path, capsys):
    """``--onnx checkpoints/last.ckpt`` replaced a run's resume point with a graph, exit 0 (issue 41): an --onnx
    without the .onnx suffix, and an existing file that is not an export of ours, are refused (exit 2, one line
    naming the path and what was expected) and left byte for byte; an earlier export is replaced."""
    from tofdenoise.cli.export import main as export_main
    from tofdenoise.inference.export import check_onnx_output, is_onnx_export
    from tofdenoise.output_guard import OutputPathError

    ckpt = _save_checkpoint(_model("unet"), tmp_path / "m.ckpt")
    run = tmp_path / "run" / "checkpoints"
    run.mkdir(parents=True)
    last = run / "last.ckpt"
    last.write_bytes(ckpt.read_bytes())
    image = tmp_path / "view.png"
    image.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(200))
    foreign = _foreign_onnx(tmp_path / "detector.onnx")
    kept = {p: p.read_bytes() for p in (ckpt, last, image, foreign)}
    for target, names in (
        (last, [str(last), "expected a .onnx file", ".ckpt"]),
        (image, [str(image), "expected a .onnx file", ".png"]),
        (tmp_path / "model", ["model", "expected a .onnx file", "no extension"]),
        (foreign, [str(foreign), "not an ONNX export of tofdenoise"]),
    ):
        capsys.readouterr()
        assert export_main([str(ckpt), "--onnx", str(target), "--no-check"]) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and all(n in err for n in names), err
    assert {p: p.read_bytes() for p in kept} == kept
    assert not (tmp_path / "model").exists()
    assert not [p for p in tmp_path.rglob(".*") if ".tmp" in p.name]
    with pytest.raises(OutputPathError, match="not an ONNX export"):
        check_onnx_output(foreign)
    assert not is_onnx_export(last) and not is_onnx_export(image) and not is_onnx_export(foreign)

    # an earlier export of ours is replaced (the export run again, another precision)
    out = tmp_path / "m.onnx"
    assert export_main([str(ckpt), "--onnx", str(out), "--no-check"]) == 0
    assert is_onnx_export(out)
    assert export_main([str(ckpt), "--onnx", str(out), "--no-check", "--fp16"]) == 0
    assert OnnxRestorer(out).metadata["tofdenoise_precision"] == "fp16"


def test_execution_providers_follow_the_device_and_what_onnxruntime_has():
    cpu_only = ["AzureExecutionProvider", "CPUExecutionProvider"]
    gpu = ["TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider"]
    assert execution_providers("auto", cpu_only) == ["CPUExecutionProvider"]
    assert execution_providers("auto", gpu) == ["CUDAExecutionProvider", "CPUExecutionProvider"]
    assert execution_providers("cpu", gpu) == ["CPUExecutionProvider"]
    assert execution_providers("tensorrt", gpu) == gpu
    # TensorRT falls back to CUDA, then to the CPU, node by node: only what is installed is asked for
    assert execution_providers("tensorrt", ["TensorrtExecutionProvider", "CPUExecutionProvider"]) == [
        "TensorrtExecutionProvider",
        "CPUExecutionProvider",
    ]
    with pytest.raises(ValueError, match="no CUDAExecutionProvider .*install onnxruntime-gpu"):
        execution_providers("cuda", cpu_only)
    with pytest.raises(ValueError, match="auto, cpu, cuda or tensorrt, got 'npu'"):
        execution_providers("npu", gpu)
    # float32 graphs compute in float32 on the GPU too: TF32 off
    assert session_providers(execution_providers("cuda", gpu)) == [
        ("CUDAExecutionProvider", {"use_tf32": "0"}),
        "CPUExecutionProvider",
    ]
    assert session_providers(execution_providers("cpu", gpu)) == ["CPUExecutionProvider"]


def test_denoise_onnx_on_a_device_the_installed_onnxruntime_lacks_is_an_error(tmp_path, capsys):
    import onnxruntime as ort

    from tofdenoise.cli.denoise import main as denoise_main
    from tofdenoise.data_modules.io import write_depth_png16

    if "CUDAExecutionProvider" in ort.get_available_providers():
        pytest.skip("this onnxruntime has the CUDA provider")
    path = tmp_path / "m.onnx"
    export_graph(restore_graph(_model("unet")), path)
    frames = tmp_path / "frames"
    write_depth_png16(frames / "a.png", torch.nan_to_num(_frame(16, 16)[0][0, 0]).numpy())
    out = tmp_path / "o"
    assert denoise_main([str(frames), "--onnx", str(path), "--device", "cuda", "--out", str(out), "--quiet"]) == 2
    assert "no CUDAExecutionProvider" in capsys.readouterr().err and not out.exists()


def test_a_cuda_provider_that_does_not_start_is_an_error_unless_auto(tmp_path, monkeypatch):
    """onnxruntime-gpu whose CUDA libraries do not load falls back to the CPU with a log line only: --device cuda
    says so in one line, auto runs on the CPU with a warning."""
    import onnxruntime as ort

    from tofdenoise.inference.export import export_onnx

    path = tmp_path / "m.onnx"
    export_onnx(_save_checkpoint(_model("unet"), tmp_path / "m.ckpt"), path)
    real_session = ort.InferenceSession

    def session_without_cuda(model_path, options=None, providers=None):  # what a failed CUDA start leaves
        assert providers[0] == ("CUDAExecutionProvider", {"use_tf32": "0"})
        return real_session(model_path, options, providers=["CPUExecutionProvider"])

    monkeypatch.setattr(ort, "get_available_providers", lambda: ["CUDAExecutionProvider", "CPUExecutionProvider"])
    monkeypatch.setattr(ort, "preload_dlls", lambda *a, **k: None, raising=False)
    monkeypatch.setattr(ort, "InferenceSession", session_without_cuda)
    with pytest.raises(OnnxModelError, match="could not start its CUDAExecutionProvider .*--device cpu"):
        OnnxRestorer(path, device="cuda")
    with pytest.warns(RuntimeWarning, match="running on CPUExecutionProvider"):
        runner = OnnxRestorer(path, device="auto")
    assert runner.device == "cpu" and runner.backbone == "unet"


@pytest.mark.gpu
def test_onnxruntime_cuda_provider_equals_pytorch(tmp_path):
    import onnxruntime as ort

    if "CUDAExecutionProvider" not in ort.get_available_providers():
        pytest.skip("needs onnxruntime-gpu (onnxruntime's CUDA execution provider)")
    model = _model("unet")
    path = tmp_path / "m.onnx"
    export_graph(restore_graph(model), path)
    runner = OnnxRestorer.__new__(OnnxRestorer)
    runner.session, runner.path, runner.inputs = open_session(path, None, "cuda"), path, ["depth_mm"]
    assert runner.session.get_providers()[0] == "CUDAExecutionProvider"
    assert _max_diff(model, runner, 45, 67) <= TOLERANCE_MM


def test_fp16_graph_runs_on_the_cpu(tmp_path):
    model = _model("unet")
    path = tmp_path / "h.onnx"
    export_graph(restore_graph(model, fp16=True), path)
    runner = OnnxRestorer.__new__(OnnxRestorer)
    import onnxruntime as ort

    runner.session, runner.path = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]), path
    runner.inputs = ["depth_mm"]
    # float16 network (11 significant bits on values of order 1 x 100 mm): within 1 mm of float32, not 0.01
    assert _max_diff(model, runner, 45, 67) < 1.0


#: reductions that add their inputs up (ReduceMax/Min cannot overflow)
_SUMMING = {"ReduceMean", "ReduceSum", "ReduceL1", "ReduceL2", "ReduceSumSquare", "ReduceLogSumExp"}


def _fp16_spatial_sums(path) -> list[str]:
    """Summing reductions of a float16 tensor over a spatial axis (2 or 3 of a rank-4 tensor) in the graph at
    ``path``: their sum over a frame's pixels overflows float16 (65504) on onnxruntime's CUDA provider at full size
    (measured: DVSS's channel attention at 480 x 640 gave NaN, CHANGELOG.md)."""
    import onnx
    from onnx import TensorProto, numpy_helper, shape_inference

    graph = shape_inference.infer_shapes(onnx.load(str(path))).graph
    info = {v.name: v.type.tensor_type for v in [*graph.value_info, *graph.input, *graph.output]}
    consts = {n.output[0]: numpy_helper.to_array(n.attribute[0].t) for n in graph.node if n.op_type == "Constant"}
    found = []
    for node in graph.node:
        if node.op_type not in _SUMMING:
            continue
        tensor = info.get(node.input[0])
        if tensor is None or tensor.elem_type != TensorProto.FLOAT16:
            continue
        rank = len(tensor.shape.dim)
        axes = [a.ints for a in node.attribute if a.name == "axes"]
        axes = list(axes[0]) if axes else (consts[node.input[1]].tolist() if len(node.input) > 1 else range(rank))
        if rank == 4 and {int(a) % rank for a in axes} & {2, 3}:
            found.append(f"{node.op_type} {node.name}")
    return found


@pytest.mark.parametrize("backbone", list(TINY))
def test_fp16_graph_sums_over_pixels_in_float32(backbone, tmp_path):
    path = tmp_path / "h.onnx"
    export_graph(restore_graph(_model(backbone), fp16=True), path)
    assert _fp16_spatial_sums(path) == []


def test_bad_files_and_settings_are_one_line_errors(tmp_path):
    bad = tmp_path / "x.onnx"
    bad.write_bytes(b"not onnx")
    with pytest.raises(OnnxModelError, match=f"ONNX model {bad} could not be loaded"):
        OnnxRestorer(bad)
    with pytest.raises(OnnxModelError, match="does not exist"):
        OnnxRestorer(tmp_path / "none.onnx")
    with pytest.raises(ExportError, match="scan form 'loop'; expected one of steps, chunked"):
        export_onnx(bad, tmp_path / "y.onnx", scan_form="loop")
    with pytest.raises(ExportError, match="conditioning.centering 'image' cannot be exported"):
        restore_graph(DepthRestorer(backbone="unet", backbone_kwargs=TINY["unet"], conditioning={"centering": "image"}))


def _ops(graph) -> list[str]:
    """Operator types of ``graph`` and of the graphs nested in its nodes, at any depth."""
    ops = []
    for node in graph.node:
        ops.append(node.op_type)
        ops += [op for attr in node.attribute if attr.type == attr.GRAPH for op in _ops(attr.g)]
    return ops


@pytest.mark.parametrize("scan_form", ["chunked", "steps"])
def test_dvss_graph_scans_in_loops_with_scan_outputs_not_sequences(tmp_path, scan_form):
    import onnx

    model = _model("dvss")
    path = tmp_path / "dvss.onnx"
    export_graph(restore_graph(model), path, scan_form=scan_form)
    graph = onnx.load(str(path)).graph
    layers = sum(type(m).__name__ == "SS2D" for m in model.backbone.modules())
    ops = _ops(graph)
    assert layers == 3 and not {"SequenceEmpty", "SequenceInsert", "ConcatFromSequence"} & set(ops)
    if scan_form == "steps":  # per SS2D layer: two loops over the positions of a lane, one carry across lanes
        assert ops.count("Loop") == 3 * layers and "If" not in ops
    else:  # per layer: the exponent guard's If, the chunked form's three loops and the step loops' three
        assert ops.count("Loop") == 6 * layers and ops.count("If") == 2 * layers
        runner = OnnxRestorer.__new__(OnnxRestorer)
        import onnxruntime as ort

        runner.session, runner.path = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]), path
        runner.inputs = ["depth_mm"]
        assert _max_diff(model, runner, 45, 67) <= TOLERANCE_MM


def test_an_unknown_exporter_is_refused_before_any_export(tmp_path, capsys):
    from tofdenoise.cli.export import main as export_main

    ckpt = _save_checkpoint(_model("unet"), tmp_path / "u.ckpt")
    assert export_main([str(ckpt), "--onnx", str(tmp_path / "x.onnx"), "--exporter", "jit"]) == 2
    assert "exporter 'jit'; expected one of torchscript, dynamo" in capsys.readouterr().err
    assert not (tmp_path / "x.onnx").exists()


@pytest.mark.slow
def test_the_dynamo_exporter_route_gives_a_dvss_graph_that_runs_at_any_size(tmp_path, capsys):
    """``--exporter dynamo`` (torch.export): DVSS's scans become ONNX ``Scan`` nodes, not loops unrolled at the
    example's size, and the graph equals PyTorch at sizes other than the example's. ``slow``: torch's exporter takes
    about 2.5 min for this tiny DVSS on the 2-core CI machine (65 s for a tiny U-Net); the scans' own dynamo export
    runs in the default suite (tests/models/scan/test_export.py)."""
    import onnx

    from tofdenoise.cli.export import main as export_main

    model = _model("dvss")
    ckpt = _save_checkpoint(model, tmp_path / "d.ckpt")
    path = tmp_path / "d.onnx"
    assert export_main([str(ckpt), "--onnx", str(path), "--exporter", "dynamo"]) == 0
    assert "dynamo exporter" in capsys.readouterr().err
    graph = onnx.load(str(path)).graph
    ops = _ops(graph)
    layers = sum(type(m).__name__ == "SS2D" for m in model.backbone.modules())
    assert ops.count("Scan") == 2 * layers and "Loop" not in ops  # the default (step) form: two loops per layer
    runner = OnnxRestorer(path)
    assert runner.metadata["tofdenoise_exporter"] == "dynamo"
    assert runner.metadata["tofdenoise_export_scan"] == "steps"
    for h, w in [(37, 53), (64, 80)]:
        assert _max_diff(model, runner, h, w) <= TOLERANCE_MM, (h, w)


def test_the_export_carries_the_depths_the_checkpoint_was_trained_on(tmp_path, restorer_ckpt):
    from tofdenoise.training.depth_range import DEPTH_RANGE_KEY, TrainingDepthRange

    old = tmp_path / "old.onnx"
    export_onnx(restorer_ckpt, old)
    assert OnnxRestorer(old).training_depth_range_mm is None  # a checkpoint without the record
    trained = TrainingDepthRange()
    depths = torch.linspace(300, 2400, 4096).reshape(1, 1, 64, 64)
    trained.update(depths, torch.ones_like(depths))
    content = torch.load(restorer_ckpt, map_location="cpu", weights_only=True)
    content[DEPTH_RANGE_KEY] = trained.record()
    torch.save(content, tmp_path / "ranged.ckpt")
    out = tmp_path / "ranged.onnx"
    export_onnx(tmp_path / "ranged.ckpt", out)
    assert OnnxRestorer(out).training_depth_range_mm == pytest.approx(trained.range_mm)
