"""mamba-ssm's CUDA selective scan beside this project's Triton scan, in one process (CUDA only).

Usage: python benchmarks/bench_mamba_scan.py --src MAMBA_REPO [--arch 90] [--build-dir DIR] [--json FILE] [--dry]
                                             [--build-only]

``MAMBA_REPO`` is a checkout of https://github.com/state-spaces/mamba (its ``csrc/selective_scan``; nothing of it
is part of this project). The GPU machine cannot download, so the checkout travels with the command.

1. Builds mamba-ssm's ``selective_scan_cuda`` extension from that source with ``torch.utils.cpp_extension.load``
   (ninja, as many jobs as CPU cores) for one architecture only (``--arch``; mamba-ssm's own build compiles about
   ten), with mamba-ssm's nvcc flags; the build's seconds and, when it fails, the tail of its log are recorded.
   ``--build-only`` stops there, so that the build can run beside other work and the timings later on an idle GPU
   (a second call with the same ``--build-dir`` finds the build up to date and only loads it).
2. At DVSS's first level (batch 4, 4 directions x 64 channels = 256, L = 320 x 320, N 16, one B/C group per
   direction, delta_bias and softplus, D): forward and forward + backward ms with bf16 and float32 inputs of
   - mamba-ssm's kernels (called through its extension's ``fwd`` / ``bwd``, in an autograd Function of this file),
   - this project's Triton kernels on the same (batch, dim, L) tensors (``selective_scan_triton``),
   - this project's SS2D route (``ss2d_scan_triton``: the same work with the four directions read in place from
     channels-last activations; mamba-ssm and the plain route need the cross-scan copies besides, not timed here),
   and the largest relative difference of each output and gradient from the float32 PyTorch scan
   (``selective_scan_chunked``) on the plain inputs.

``--dry`` rehearses on the CPU at toy sizes: a stand-in for the extension (the PyTorch scan behind the same
``fwd`` / ``bwd`` calls) and the Triton interpreter, so a GPU sitting is not lost to a typo. Results are written
after each part (``--json``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import traceback
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SOURCES = (
    "selective_scan.cpp",
    "selective_scan_fwd_fp32.cu",
    "selective_scan_fwd_fp16.cu",
    "selective_scan_fwd_bf16.cu",
    "selective_scan_bwd_fp32_real.cu",
    "selective_scan_bwd_fp32_complex.cu",
    "selective_scan_bwd_fp16_real.cu",
    "selective_scan_bwd_fp16_complex.cu",
    "selective_scan_bwd_bf16_real.cu",
    "selective_scan_bwd_bf16_complex.cu",
)
#: mamba-ssm's nvcc flags (its setup.py), less the architecture list
NVCC_FLAGS = (
    "-O3",
    "-std=c++17",
    "-U__CUDA_NO_HALF_OPERATORS__",
    "-U__CUDA_NO_HALF_CONVERSIONS__",
    "-U__CUDA_NO_BFLOAT16_OPERATORS__",
    "-U__CUDA_NO_BFLOAT16_CONVERSIONS__",
    "-U__CUDA_NO_BFLOAT162_OPERATORS__",
    "-U__CUDA_NO_BFLOAT162_CONVERSIONS__",
    "--expt-relaxed-constexpr",
    "--expt-extended-lambda",
    "--use_fast_math",
    "-lineinfo",
)


def build_extension(src: Path, arch: int, build_dir: Path, log):
    """mamba-ssm's ``selective_scan_cuda`` compiled from ``src`` (a mamba checkout or its csrc/selective_scan) for
    sm_``arch``; returns the module."""
    from torch.utils.cpp_extension import load

    csrc = src / "csrc" / "selective_scan" if (src / "csrc").is_dir() else src
    missing = [s for s in SOURCES if not (csrc / s).is_file()]
    if missing:
        raise SystemExit(f"bench_mamba_scan: {csrc} lacks {', '.join(missing)} (expected mamba's csrc/selective_scan)")
    build_dir.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("MAX_JOBS", str(os.cpu_count() or 1))
    flags = [*NVCC_FLAGS, "-gencode", f"arch=compute_{arch},code=sm_{arch}", f"--threads={os.cpu_count() or 1}"]
    log(f"building selective_scan_cuda for sm_{arch} in {build_dir} ({os.environ['MAX_JOBS']} jobs)")
    return load(
        name="selective_scan_cuda",
        sources=[str(csrc / s) for s in SOURCES],
        extra_cflags=["-O3", "-std=c++17"],
        extra_cuda_cflags=flags,
        extra_include_paths=[str(csrc)],
        build_directory=str(build_dir),
        verbose=True,
    )


class StandInExtension:
    """``--dry``: the PyTorch scan behind the extension's ``fwd`` / ``bwd`` calls (same arguments and results)."""

    @staticmethod
    def fwd(u, delta, A, B, C, D, z, delta_bias, delta_softplus):
        import torch

        from tofdenoise.models.scan.reference import selective_scan_chunked

        with torch.no_grad():
            out = selective_scan_chunked(u, delta, A, B, C, D, delta_bias, delta_softplus)
        return [out, torch.empty(0)]

    @staticmethod
    def bwd(u, delta, A, B, C, D, z, delta_bias, dout, x, out, dz, delta_softplus, recompute_out_z):
        import torch

        from tofdenoise.models.scan.reference import selective_scan_chunked

        ins = [t.detach().clone().requires_grad_() for t in (u, delta, A, B, C, D, delta_bias)]
        with torch.enable_grad():
            y = selective_scan_chunked(*ins, delta_softplus)
            grads = torch.autograd.grad(y, ins, dout)
        return list(grads)


def mamba_scan(ext):
    """An autograd Function over the extension's ``fwd`` / ``bwd`` (D and delta_bias given, no z): ``fn(u, delta,
    A, B, C, D, delta_bias, softplus)``."""
    import torch

    class MambaScan(torch.autograd.Function):
        @staticmethod
        def forward(ctx, u, delta, A, B, C, D, delta_bias, softplus):
            out, x = ext.fwd(u, delta, A, B, C, D, None, delta_bias, softplus)[:2]
            ctx.save_for_backward(u, delta, A, B, C, D, delta_bias, x)
            ctx.softplus = softplus
            return out

        @staticmethod
        def backward(ctx, dout):
            u, delta, A, B, C, D, delta_bias, x = ctx.saved_tensors
            grads = ext.bwd(
                u, delta, A, B, C, D, None, delta_bias, dout.contiguous(), x, None, None, ctx.softplus, False
            )
            du, ddelta, dA, dB, dC, dD, dbias = grads[:7]
            return du, ddelta, dA, dB, dC, dD, dbias, None

    return MambaScan.apply


class Bench:
    def __init__(self, args):
        import torch

        self.torch, self.args, self.t0 = torch, args, time.time()
        self.dev = "cpu" if args.dry else "cuda"
        self.res: dict = {"torch": torch.__version__, "device": "dry run" if args.dry else torch.cuda.get_device_name()}

    def log(self, msg: str) -> None:
        print(f"[{time.time() - self.t0:6.1f} s] {msg}", flush=True)

    def save(self) -> None:
        if self.args.json:
            Path(self.args.json).write_text(json.dumps(self.res, indent=1))

    def time_ms(self, fn, repeats: int = 5) -> float:
        from bench_gpu import time_ms  # benchmarks/ is on sys.path when run as a script

        return time_ms(fn, repeats, self.args.dry)

    def build(self):
        if self.args.dry:
            self.res["build"] = {"stand_in": True}
            self.save()
            return StandInExtension()
        t = time.time()
        try:
            ext = build_extension(Path(self.args.src), self.args.arch, Path(self.args.build_dir), self.log)
        except BaseException:  # noqa: BLE001 - record why the build failed, then stop
            self.res["build"] = {"ok": False, "s": round(time.time() - t, 1), "error": traceback.format_exc()[-3000:]}
            self.save()
            raise
        self.res["build"] = {"ok": True, "s": round(time.time() - t, 1), "arch": self.args.arch}
        self.log(f"built in {self.res['build']['s']} s")
        self.save()
        return ext

    def compare(self, ext) -> None:
        torch = self.torch
        from tofdenoise.models.scan.reference import selective_scan_chunked
        from tofdenoise.models.scan.triton import selective_scan_triton, ss2d_scan_triton

        b, side, di, n = (1, 6, 4, 4) if self.args.dry else (4, 320, 64, 16)
        k, length = 4, side * side
        dim = k * di
        g = torch.Generator(device=self.dev).manual_seed(0)

        def randn(*shape, scale=1.0):
            return scale * torch.randn(*shape, device=self.dev, generator=g)

        u, delta = randn(b, dim, length), randn(b, dim, length, scale=0.5)
        A, D, bias = -torch.exp(randn(dim, n, scale=0.5)), randn(dim), randn(dim)
        B, C, dy = randn(b, k, n, length), randn(b, k, n, length), randn(b, dim, length)
        plain = (u, delta, A, B, C, D, bias)
        ref_in = [t.clone().requires_grad_() for t in plain]
        ref_y = selective_scan_chunked(*ref_in, True)
        ref = [ref_y.detach(), *torch.autograd.grad(ref_y, ref_in, dy)]
        del ref_y, ref_in
        # the SS2D route's own inputs, the same sizes (x (b, L, di), raw steps (b, L, 4 di), B / C (b, L, 4, N))
        x_s, d_s = randn(b, length, di), randn(b, length, dim, scale=0.5)
        bc_s, dy_s = randn(b, length, k, 2 * n), randn(b, length, di)
        routes = {
            "mamba-ssm": lambda ins: mamba_scan(ext)(*ins, True),
            "triton, (batch, dim, L)": lambda ins: selective_scan_triton(*ins[:5], ins[5], ins[6], True),
        }
        rows = self.res.setdefault("scan", [])
        for dtype in (torch.bfloat16, torch.float32):
            name = str(dtype).replace("torch.", "")
            ins = [(t.to(dtype) if i in (0, 1, 3, 4) else t).contiguous().requires_grad_() for i, t in enumerate(plain)]
            for route, fn in routes.items():
                row = {"route": route, "inputs": name}
                try:
                    y = fn(ins)
                    got = [y, *torch.autograd.grad(y, ins, dy.to(y.dtype))]
                    row["max_rel_err"] = max(
                        float((a.detach().float() - r).abs().max() / r.abs().max().clamp_min(1e-30))
                        for a, r in zip(got, ref)
                    )
                    del y, got
                    row["fwd_ms"] = self.time_ms(lambda fn=fn: fn(ins))
                    row["fwd_bwd_ms"] = self.time_ms(lambda fn=fn: torch.autograd.grad(fn(ins), ins, dy.to(dtype)))
                except Exception:  # noqa: BLE001 - report and go on
                    row["error"] = traceback.format_exc()[-1500:]
                rows.append(row)
                print(json.dumps(row), flush=True)
                self.save()
            s_ins = [t.to(dtype).requires_grad_() for t in (x_s, d_s)]
            A_s = A.clone().requires_grad_()
            bc = bc_s.to(dtype).requires_grad_()

            def ss2d(s_ins=s_ins, A_s=A_s, bc=bc):
                return ss2d_scan_triton(s_ins[0], s_ins[1], A_s, bc[..., :n], bc[..., n:], D, bias, side, side)

            row = {"route": "triton, SS2D in place", "inputs": name}
            try:
                row["fwd_ms"] = self.time_ms(ss2d)
                row["fwd_bwd_ms"] = self.time_ms(
                    lambda ss2d=ss2d, s_ins=s_ins, A_s=A_s, bc=bc: torch.autograd.grad(
                        ss2d(), [*s_ins, A_s, bc], dy_s.to(dtype)
                    )
                )
            except Exception:  # noqa: BLE001
                row["error"] = traceback.format_exc()[-1500:]
            rows.append(row)
            print(json.dumps(row), flush=True)
            self.save()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--src", help="a checkout of state-spaces/mamba (or its csrc/selective_scan)")
    p.add_argument("--arch", type=int, default=90, help="compute capability x 10 to build for (H100 / H200: 90)")
    p.add_argument("--build-dir", default="/tmp/mamba_selective_scan_build")
    p.add_argument("--json", default=None, help="write the results to this JSON file (after every part)")
    p.add_argument("--dry", action="store_true", help="rehearse on the CPU at toy sizes (a stand-in extension)")
    p.add_argument(
        "--build-only", action="store_true", help="build the extension (and record its seconds), time nothing"
    )
    args = p.parse_args(argv)
    if args.dry:
        os.environ["TRITON_INTERPRET"] = "1"
    elif not args.src:
        p.error("--src is required (a checkout of state-spaces/mamba)")
    sys.path[:0] = [str(ROOT / "src"), str(ROOT / "benchmarks")]
    import torch

    if not args.dry and not torch.cuda.is_available():
        print("bench_mamba_scan: skipped (no CUDA device)")
        return 0
    torch.backends.cuda.matmul.allow_tf32 = False
    bench = Bench(args)
    ext = bench.build()
    if args.build_only:
        bench.log("built; nothing timed (--build-only)")
        return 0
    bench.compare(ext)
    bench.log("done")
    return 0


if __name__ == "__main__":
    sys.exit(main())
