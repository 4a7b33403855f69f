"""DVSS's selective scan on the GPU, side by side in one process (CUDA only; prints a skip line without a GPU).

Usage: python benchmarks/bench_gpu_scan.py [--baseline REV] [--json FILE] [--skip-tests] [--skip-compile]
       [--keep-defaults] [--quick] [--only SECTIONS] [--dry]

1. The SS2D scan's routes at DVSS's first level (batch 4, 320 x 320, d_inner 64, N 16): the chunked kernels and the
   sequential forward / first backward pass (``FORWARD`` / ``ADJOINT`` of ``tofdenoise.models.scan.triton``) at
   several launch settings, bf16 and float32 inputs, forward and forward + backward ms, and the largest relative
   difference of the output and every gradient from the float32 PyTorch reference (``ss2d_scan_reference``).
2. Training steps (batch 4, 320 x 320, AdamW; float32 and bf16 autocast) and 480 x 640 bf16 inference of DVSS on the
   module's defaults and on the Triton scan of git revision ``--baseline`` (its ``triton.py`` loaded under another
   module name), U-Net and the Restormer (``bench_gpu._bench_backbone``).
3. ``torch.compile`` of DVSS: first-call seconds, the bf16 step eager against compiled, and how far the compiled
   output and gradients are from eager.
4. The dt projection's forms (``tofdenoise.models.ss2d.DT_PROJECTION_FORMS``) at the first level, and a DVSS bf16
   training step with each of them as the CUDA default, and the first
   level's per-pixel products' weight gradients (a reduction over 409,600 positions) as one ``mm`` and split over
   the positions (``products``).
5. The device tests (``tests/models/scan/test_triton.py``, ``test_ops.py`` and ``tests/models/test_compile_cuda.py``,
   ``-m 'not slow'``) in a subprocess,
   with the time left (``--skip-tests`` leaves them out).
6. ``torch.profiler``'s tables of three bf16 DVSS steps: CUDA time per kernel, and per operator and input shape.

``--dry`` rehearses the whole script on the CPU at toy sizes (Triton's interpreter, ``TRITON_INTERPRET=1`` set
before the import): a GPU's minutes are not spent on a typo. Results are written as each section ends (``--json``).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
NAMES = (
    "FORWARD",
    "ADJOINT",
    "BACKWARD",
    "SEQ_BLOCK_D_MAX",
    "SEQ_NUM_WARPS",
    "SEGMENT_PROGRAMS_PER_SM",
    "SEQ_BWD_NUM_WARPS",
    "SEQ_BWD_SUB",
)
#: the route settings tried in section 1 (bf16); float32 takes the fastest of them and the chunked one. BACKWARD
#: "sequential" (the main backward pass one step at a time) applies with ADJOINT "sequential" only.
SETTINGS = (
    ("chunked", "chunked", "chunked", 64, 2, 8, 2, None),
    ("sequential", "sequential", "chunked", 64, 1, 16, 2, None),
    ("sequential", "sequential", "sequential", 64, 1, 16, 2, None),
    ("sequential", "sequential", "sequential", 64, 1, 16, 2, 8),
    ("sequential", "sequential", "sequential", 64, 1, 16, 2, 4),
    ("sequential", "sequential", "sequential", 64, 1, 8, 2, None),
    ("sequential", "sequential", "sequential", 64, 1, 8, 2, 8),
    ("sequential", "sequential", "sequential", 64, 1, 4, 2, None),
    ("sequential", "sequential", "sequential", 64, 1, 32, 2, 8),
)
DVSS = {"width": 32, "enc_blocks": [1, 1, 2], "bottleneck_blocks": 2}  # configs/backbone/dvss.yaml


class Bench:
    def __init__(self, args):
        import torch

        self.torch, self.args, self.t0 = torch, args, time.time()
        self.dev = "cpu" if args.dry else "cuda"
        self.res: dict = {"t": {}, "torch": torch.__version__, "device": "dry run" if args.dry else None}

    def save(self, section: str | None = None) -> None:
        if section:
            self.res["t"][section] = round(time.time() - self.t0, 1)
            print(f"--- {section} at {self.res['t'][section]} s", flush=True)
        if self.args.json:
            Path(self.args.json).write_text(json.dumps(self.res, indent=1))

    def time_ms(self, fn, repeats=5) -> float:
        from bench_gpu import time_ms  # benchmarks/ is on sys.path when run as a script

        return time_ms(fn, repeats, self.args.dry)

    # 1. routes
    def routes(self) -> None:
        torch = self.torch
        from tofdenoise.models.scan import ss2d_scan_reference
        from tofdenoise.models.scan import triton as st

        b, side, di, n = (1, 9, 4, 4) if self.args.dry else (4, 320, 64, 16)
        g = torch.Generator(device=self.dev).manual_seed(0)

        def randn(*shape):
            return torch.randn(*shape, device=self.dev, generator=g)

        length = side * side
        x, dts, x_dbl = randn(b, length, di), 0.5 * randn(b, length, 4 * di), randn(b, length, 4, 2 + 2 * n)
        A, D, bias = -torch.exp(0.5 * randn(4 * di, n)), randn(4 * di), randn(4 * di)
        dy = randn(b, length, di)

        def call(fn, ins):
            xd = ins[3]
            return fn(ins[0], ins[1], ins[2], xd[..., 2 : 2 + n], xd[..., 2 + n :], D, bias, side, side)

        ref_in = [t.clone().requires_grad_() for t in (x, dts, A, x_dbl)]
        ref_y = call(ss2d_scan_reference, ref_in)
        ref = [ref_y.detach(), *torch.autograd.grad(ref_y, ref_in, dy)]
        del ref_y, ref_in
        defaults = {k: getattr(st, k) for k in NAMES}
        rows = self.res.setdefault("routes", [])

        def run(dtype, settings):
            ins = [(t.to(dtype) if i != 2 else t).clone().requires_grad_() for i, t in enumerate((x, dts, A, x_dbl))]
            for setting in settings:
                for k, v in zip(NAMES, setting):
                    setattr(st, k, v)
                row = dict(zip(NAMES, setting), dtype=str(dtype).replace("torch.", ""))
                try:
                    y = call(st.ss2d_scan_triton, ins)
                    got = [y, *torch.autograd.grad(y, ins, dy.to(dtype))]
                    row["max_rel_err"] = max(
                        float(((a.float() - r).abs().max() / r.abs().max()).item()) for a, r in zip(got, ref)
                    )
                    row["fwd_ms"] = self.time_ms(lambda: call(st.ss2d_scan_triton, ins))
                    row["fwd_bwd_ms"] = self.time_ms(
                        lambda: torch.autograd.grad(call(st.ss2d_scan_triton, ins), ins, dy.to(dtype))
                    )
                except Exception:  # report and go on with the next setting
                    row["error"] = traceback.format_exc()[-1500:]
                rows.append(row)
                print(json.dumps(row), flush=True)
                self.save()

        try:
            run(torch.bfloat16, SETTINGS)
            ok = [r for r in rows if "fwd_bwd_ms" in r and r["max_rel_err"] < 5e-2]
            best = min(ok, key=lambda r: r["fwd_bwd_ms"]) if ok else None
            fp32 = [SETTINGS[0]] + ([tuple(best[k] for k in NAMES)] if best else [])
            run(torch.float32, fp32)
        finally:
            for k, v in defaults.items():
                setattr(st, k, v)
        self.res["fastest_bf16"] = best
        if best and not self.args.keep_defaults:  # the later sections run on the fastest setting
            for k in NAMES:
                setattr(st, k, best[k])
            self.res["later_sections_route"] = {k: best[k] for k in NAMES}
            print(f"later sections run on {self.res['later_sections_route']}", flush=True)

    # 2. backbones
    def backbones(self) -> None:
        import bench_gpu

        from tofdenoise.models.scan import triton as st

        previous = _load_baseline(self.args.baseline) if self.args.baseline else None

        def kernel_names(module) -> tuple[str, ...]:
            """What to swap for SS2D to run on ``module``'s kernels for a whole case (forward and backward). Since
            the scan became a custom operator, ``ss2d_scan_triton`` calls ``torch.ops.tofdenoise.ss2d_scan``, whose
            implementation calls this tree's ``ss2d_forward`` / ``ss2d_backward``: those are swapped (swapping
            ``ss2d_scan_triton`` alone would run this tree's kernels under the baseline's name); a revision from
            before the operator brings its own ``ss2d_scan_triton``."""
            return ("ss2d_forward", "ss2d_backward") if hasattr(module, "ss2d_forward") else ("ss2d_scan_triton",)

        cases = [("dvss", DVSS, "this tree", None)]
        if previous is not None:
            cases.append(("dvss", DVSS, f"Triton scan of {self.args.baseline}", previous))
        cases += [("unet", {}, None, None), ("restormer", {}, None, None)]
        rows = self.res.setdefault("backbones", [])
        for name, kwargs, label, module in cases:
            ours = {k: getattr(st, k) for k in kernel_names(module)} if module is not None else {}
            for k in ours:
                setattr(st, k, getattr(module, k))
            try:
                row = {**bench_gpu._bench_backbone(name, kwargs, 320, False), "scan": label}
            except Exception:
                row = {"backbone": name, "scan": label, "error": traceback.format_exc()[-1500:]}
            finally:
                for k, v in ours.items():
                    setattr(st, k, v)
            rows.append(row)
            print(json.dumps(row), flush=True)
            self.save()
            self.torch.cuda.empty_cache()

    # 3. torch.compile
    def compile(self) -> None:
        torch = self.torch
        from tofdenoise.models.common import draw_zero_parameters, execution_distances
        from tofdenoise.models.registry import build_backbone

        out: dict = {}
        self.res["compile"] = out
        torch.manual_seed(0)
        # the zero-initialised head drawn: else only the head's gradient is compared
        net = draw_zero_parameters(build_backbone("dvss", in_channels=1, **DVSS)).to(self.dev)
        compiled = torch.compile(net)
        size = 32 if self.args.dry else 320
        x = torch.randn(4, 1, size, size, device=self.dev)
        runs = {}
        for label, model in (("eager", net), ("compiled", compiled)):
            net.zero_grad(set_to_none=True)
            t = time.time()
            with torch.autocast(self.dev, dtype=torch.bfloat16):
                y = model(x)
            y.float().square().mean().backward()
            if not self.args.dry:
                torch.cuda.synchronize()
            out[f"{label}_first_call_s"] = round(time.time() - t, 1)
            runs[label] = (y.detach().float(), {n: p.grad.detach().float().clone() for n, p in net.named_parameters()})
        # the tests' measure (models.common.execution_distances): each gradient against its own largest magnitude,
        # floored at 1e-3 of the network's largest gradient
        errs = execution_distances(runs["eager"], runs["compiled"])
        out["max_rel_diff_output"] = errs.pop("output")
        worst = sorted(errs, key=errs.get, reverse=True)[:3]
        out["max_rel_diff_grads"] = errs[worst[0]]
        out["worst_grads"] = {n: errs[n] for n in worst}
        opt = torch.optim.AdamW(net.parameters(), 2e-4)
        for label, model in (("eager", net), ("compiled", compiled)):

            def step(model=model):
                opt.zero_grad(set_to_none=True)
                with torch.autocast(self.dev, dtype=torch.bfloat16):
                    y = model(x)
                y.float().abs().mean().backward()
                opt.step()

            out[f"{label}_bf16_ms_step"] = self.time_ms(step, 10)
        print(json.dumps(out), flush=True)

    # 4. the dt projection's forms
    def dt_forms(self) -> None:
        """SS2D's dt projection at DVSS's first level (batch 4, 320 x 320: 409,600 positions, 4 directions,
        dt_rank 2, 64 channels) under bf16 autocast, forward + backward, in each form of
        ``tofdenoise.models.ss2d.DT_PROJECTION_FORMS`` (the profile's table by operator and input shape tells
        which products the 3.4 ms CUTLASS kernel of 2026-11-27 belongs to)."""
        torch = self.torch
        from tofdenoise.models.ss2d import DT_PROJECTION_FORMS, dt_projection

        m, k, r, d = (36, 4, 2, 8) if self.args.dry else (4 * 320 * 320, 4, 2, 64)
        g = torch.Generator(device=self.dev).manual_seed(0)
        # bf16, as SS2D's x_proj output under autocast
        x_dbl = torch.randn(m, k, r + 32, device=self.dev, generator=g).bfloat16().requires_grad_()
        weight = (0.5 * torch.randn(k, d, r, device=self.dev, generator=g)).requires_grad_()
        dout = torch.randn(m, k, d, device=self.dev, generator=g)
        out: dict = {}
        self.res["dt_forms"] = out
        ref = None
        for form in DT_PROJECTION_FORMS:

            def fwd_bwd(form=form):
                with torch.autocast(self.dev, dtype=torch.bfloat16):
                    y = dt_projection(x_dbl[..., :r], weight, form=form)
                return y, torch.autograd.grad(y, [x_dbl, weight], dout.to(y.dtype))

            y, grads = fwd_bwd()
            got = [y.detach().float(), *(t.float() for t in grads)]
            ref = ref or got
            out[form] = {
                "out_dtype": str(y.dtype).replace("torch.", ""),
                "fwd_bwd_ms": self.time_ms(lambda: fwd_bwd()),
                "max_rel_diff_from_bmm": max(
                    float((a - b).abs().max() / b.abs().max().clamp_min(1e-12)) for a, b in zip(got, ref)
                ),
            }
            print(form, json.dumps(out[form]), flush=True)
        self._dvss_step_per_dt_form(out)

    def _dvss_step_per_dt_form(self, out: dict) -> None:
        """A DVSS bf16 training step (batch 4, 320 x 320, AdamW; toy sizes with ``--dry``) with each dt projection
        form as the CUDA default (``ss2d.DT_PROJECTION_CUDA``, set for the step and restored), side by side."""
        torch = self.torch
        from tofdenoise.models import ss2d
        from tofdenoise.models.registry import build_backbone

        side, cfg = (16, {"width": 8, "enc_blocks": [1, 1], "bottleneck_blocks": 1}) if self.args.dry else (320, DVSS)
        net = build_backbone("dvss", in_channels=1, **cfg).to(self.dev)
        opt = torch.optim.AdamW(net.parameters(), 2e-4)
        x = torch.randn(4, 1, side, side, device=self.dev)

        def step():
            opt.zero_grad(set_to_none=True)
            with torch.autocast(self.dev, dtype=torch.bfloat16):
                y = net(x)
            y.float().abs().mean().backward()
            opt.step()

        default = ss2d.DT_PROJECTION_CUDA
        try:
            for form in ss2d.DT_PROJECTION_FORMS:
                ss2d.DT_PROJECTION_CUDA = form
                step()  # the first call of a form outside the timing
                out[form]["dvss_bf16_ms_step"] = self.time_ms(step, 10)
                print(form, "DVSS bf16 step ms", round(out[form]["dvss_bf16_ms_step"], 2), flush=True)
        finally:
            ss2d.DT_PROJECTION_CUDA = default

    # 4b. the per-pixel products' weight gradients
    def products(self) -> None:
        """The weight gradient of each per-pixel product at DVSS's first level (409,600 positions of batch 4 at 320 x
        320; in -> out channels of in_proj, x_proj stacked over the 4 directions, out_proj and the block's fusion),
        bf16 as under autocast: ``dW = dY^T X``, a reduction over all positions into a small matrix, as autograd
        computes it (one ``mm``: the 3.4 ms CUTLASS kernel of 2026-11-27's profile is most likely one of these) and
        split over the positions by hand (``bmm`` of ``chunks`` slices, then a float32 sum of the partial matrices).
        Each row: ms of each form and the split form's largest relative difference from the ``mm``'s."""
        torch = self.torch
        m = 4 * 6 * 6 if self.args.dry else 4 * 320 * 320
        shapes = {"in_proj": (32, 128), "x_proj": (64, 136), "out_proj": (64, 32), "fusion": (96, 32)}
        g = torch.Generator(device=self.dev).manual_seed(0)
        out: dict = {}
        self.res["products"] = out
        for name, (c_in, c_out) in shapes.items():
            x = torch.randn(m, c_in, device=self.dev, generator=g).bfloat16()
            dy = torch.randn(m, c_out, device=self.dev, generator=g).bfloat16()
            row: dict = {"positions": m, "in": c_in, "out": c_out}

            def mm(x=x, dy=dy):
                return dy.t() @ x

            row["mm_ms"] = self.time_ms(mm)
            ref = mm().float()
            for chunks in (16, 64, 256):
                if m % chunks:
                    continue

                def split(x=x, dy=dy, chunks=chunks):
                    xs, dys = x.view(chunks, m // chunks, c_in), dy.view(chunks, m // chunks, c_out)
                    return torch.bmm(dys.transpose(1, 2), xs).float().sum(0)

                row[f"split{chunks}_ms"] = self.time_ms(split)
                row[f"split{chunks}_max_rel_diff"] = float(
                    (split() - ref).abs().max() / ref.abs().max().clamp_min(1e-12)
                )
            out[name] = row
            print(name, json.dumps(row), flush=True)

    # 5. device tests
    def tests(self, budget_s: float) -> None:
        scan = ["tests/models/scan/test_triton.py", "tests/models/scan/test_ops.py"]
        tests = [*scan, "tests/models/test_compile_cuda.py"]
        cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-m", "not slow", *tests]
        env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
        try:
            done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=budget_s, env=env)
            self.res["tests"] = done.stdout[-4000:] + done.stderr[-1000:]
        except subprocess.TimeoutExpired as exc:
            self.res["tests"] = f"stopped after {budget_s:.0f} s: " + (exc.stdout or b"")[-4000:].decode(
                errors="replace"
            )
        print(self.res["tests"][-1500:], flush=True)

    # 6. profile
    def profile(self) -> None:
        torch = self.torch
        from tofdenoise.models.registry import build_backbone

        net = build_backbone("dvss", in_channels=1, **DVSS).cuda()
        opt = torch.optim.AdamW(net.parameters(), 2e-4)
        x = torch.randn(4, 1, 320, 320, device="cuda")

        def step():
            opt.zero_grad(set_to_none=True)
            with torch.autocast("cuda", dtype=torch.bfloat16):
                y = net(x)
            y.float().abs().mean().backward()
            opt.step()

        for _ in range(3):
            step()
        torch.cuda.synchronize()
        activities = [torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA]
        with torch.profiler.profile(activities=activities, record_shapes=True) as prof:
            for _ in range(3):
                step()
            torch.cuda.synchronize()
        self.res["profile_3_steps"] = prof.key_averages().table(sort_by="self_cuda_time_total", row_limit=15)
        self.res["profile_by_shape"] = prof.key_averages(group_by_input_shape=True).table(
            sort_by="cuda_time_total", row_limit=25
        )
        print(self.res["profile_3_steps"], self.res["profile_by_shape"], sep="\n", flush=True)


def _load_baseline(rev: str):
    """The Triton scan module of git revision ``rev``, imported as ``tofdenoise.models.scan._baseline_triton`` (its
    relative imports resolve in today's package)."""
    source = subprocess.run(
        ["git", "show", f"{rev}:src/tofdenoise/models/scan/triton.py"], cwd=ROOT, capture_output=True, text=True
    )
    if source.returncode != 0:
        raise SystemExit(f"bench_gpu_scan: --baseline {rev}: {source.stderr.strip()}")
    path = Path(tempfile.mkdtemp()) / "baseline_triton.py"
    path.write_text(source.stdout)
    spec = importlib.util.spec_from_file_location("tofdenoise.models.scan._baseline_triton", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--baseline", default=None, help="a git revision whose Triton scan DVSS also runs on")
    p.add_argument("--json", default=None, help="write the results to this JSON file (after every section)")
    p.add_argument("--skip-tests", action="store_true", help="leave the device tests out")
    p.add_argument("--budget-s", type=float, default=440.0, help="seconds the whole run may take (tests get the rest)")
    p.add_argument(
        "--keep-defaults", action="store_true", help="run sections 2-5 on the module's defaults, not the fastest route"
    )
    p.add_argument("--skip-compile", action="store_true", help="leave section 3 (torch.compile) out")
    p.add_argument("--dry", action="store_true", help="rehearse on the CPU at toy sizes in Triton's interpreter")
    p.add_argument("--quick", action="store_true", help="three route settings, no device tests (make bench --quick)")
    p.add_argument(
        "--only",
        default=None,
        help="comma-separated sections to run, of routes, backbones, compile, dt_forms, products, tests, profile "
        "(default all)",
    )
    args = p.parse_args(argv)
    if args.dry:
        os.environ["TRITON_INTERPRET"] = "1"
    sys.path[:0] = [str(ROOT / "src"), str(ROOT / "benchmarks")]
    import torch

    if not args.dry and not torch.cuda.is_available():
        print("bench_gpu_scan: skipped (no CUDA device)")
        return 0
    torch.backends.cuda.matmul.allow_tf32 = False
    torch.backends.cudnn.allow_tf32 = False
    if args.quick:
        global SETTINGS
        SETTINGS = SETTINGS[:1] + SETTINGS[-2:]
        args.skip_tests = True
    bench = Bench(args)
    if not args.dry:
        bench.res["device"] = torch.cuda.get_device_name()
    sections = [("routes", bench.routes)]
    if not args.dry:
        sections.append(("backbones", bench.backbones))
    if not args.skip_compile:
        sections.append(("compile", bench.compile))
    sections.append(("dt_forms", bench.dt_forms))
    sections.append(("products", bench.products))
    only = None if args.only is None else set(args.only.split(","))
    if only is not None:
        unknown = only - {"routes", "backbones", "compile", "dt_forms", "products", "tests", "profile"}
        if unknown:
            p.error(f"--only: unknown section(s) {sorted(unknown)}")
        sections = [(name, fn) for name, fn in sections if name in only]
        args.skip_tests = args.skip_tests or "tests" not in only
    for name, fn in sections:
        try:
            fn()
        except Exception:
            bench.res[f"{name}_error"] = traceback.format_exc()[-2500:]
            print(bench.res[f"{name}_error"], flush=True)
        bench.save(name)
    if not args.skip_tests and not args.dry:
        bench.tests(max(30.0, args.budget_s - (time.time() - bench.t0)))
        bench.save("tests")
    if not args.dry and time.time() - bench.t0 < args.budget_s and (only is None or "profile" in only):
        try:
            bench.profile()
        except Exception:
            bench.res["profile_error"] = traceback.format_exc()[-1500:]
        bench.save("profile")
    return 0


if __name__ == "__main__":
    sys.exit(main())
