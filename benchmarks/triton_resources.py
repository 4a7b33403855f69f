"""Compile the Triton selective-scan kernels ahead of time for a GPU architecture -- no GPU needed -- and print
the registers, spills and shared memory that ptxas reports for each launch setting.

Usage: python benchmarks/triton_resources.py [--arch 90] [--warps 4 8] [--block-d 2 4 8 16]

Triton lowers each kernel to PTX, and the ptxas that ships with Triton assembles it for ``sm_<arch>a`` (the
H100 is 90). A setting whose backward spills registers to local memory is a poor default. Register use does not
give speed, so time the kernels on the GPU (``benchmarks/tune_scan_triton.py``); this table narrows the sweep
on a machine without one. Needs Triton (``make venv`` installs it next to a CPU torch).
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "src"))


def _compile(kernel, dtype: str, consts: dict, arch: int, warps: int):
    import triton
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    read_as_given = {"u_ptr", "delta_ptr", "B_ptr", "C_ptr", "dy_ptr", "ddelta_ptr"}  # bf16 under autocast
    names = kernel.arg_names
    signature = {}
    for name in names:
        if name in consts:
            signature[name] = "constexpr"
        elif name.endswith("_ptr"):
            signature[name] = f"*{dtype}" if name in read_as_given else "*fp32"
        else:
            signature[name] = "i32"
    source = ASTSource(fn=kernel, signature=signature, constexprs={(names.index(k),): v for k, v in consts.items()})
    return triton.compile(source, target=GPUTarget("cuda", arch, 32), options={"num_warps": warps})


def _ptxas_report(ptx: str, arch: int) -> tuple[int, int, int]:
    """(registers, spill store bytes, spill load bytes) from ``ptxas -v``."""
    import triton

    ptxas = Path(triton.__file__).parent / "backends" / "nvidia" / "bin" / "ptxas"
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "kernel.ptx"
        src.write_text(ptx)
        result = subprocess.run(
            [str(ptxas), f"-arch=sm_{arch}a", "-v", str(src), "-o", str(Path(tmp) / "kernel.cubin")],
            capture_output=True,
            text=True,
            check=True,
        )
    regs = re.search(r"Used (\d+) registers", result.stderr)
    spills = re.search(r"(\d+) bytes spill stores, (\d+) bytes spill loads", result.stderr)
    if regs is None or spills is None:
        raise RuntimeError(f"triton_resources: unexpected ptxas output:\n{result.stderr}")
    return int(regs.group(1)), int(spills.group(1)), int(spills.group(2))


def route_kernels(st, route: str) -> list[tuple]:
    """(name, kernel, extra constants or None) of the kernels the route runs with the module's settings (FORWARD /
    ADJOINT for SS2D, PLAIN_FORWARD / PLAIN_ADJOINT for the plain route); the sequential kernels take their own
    channels per program and warps."""
    forward, adjoint = (st.FORWARD, st.ADJOINT) if route == "SS2D" else (st.PLAIN_FORWARD, st.PLAIN_ADJOINT)
    seq = dict(BLOCK_D=st.SEQ_BLOCK_D_MAX, STAGES=st.SEQ_STAGES)
    if forward == "sequential":
        out = [
            ("seq_fwd_first", st.seq_fwd_kernel, dict(seq, FIRST_PASS=True)),
            ("seq_fwd", st.seq_fwd_kernel, dict(seq, FIRST_PASS=False)),
        ]
    else:
        out = [("seg_fwd", st.seg_fwd_kernel, None), ("fwd", st.fwd_kernel, None)]
    out.append(
        ("seq_adjoint", st.seq_adjoint_kernel, seq) if adjoint == "sequential" else ("seg_bwd", st.seg_bwd_kernel, None)
    )
    if route == "SS2D" and adjoint == "sequential" and st.BACKWARD == "sequential":
        bwd = dict(
            BLOCK_D=st.SEQ_BLOCK_D_MAX, WARPS=st.SEQ_BWD_NUM_WARPS, OWN_BC=True, SUB_T=st.SEQ_BWD_SUB or st.CHUNK
        )
        return out + [("seq_bwd", st.seq_bwd_kernel, bwd)]
    return out + [("bwd", st.bwd_kernel, None)]


def resources(st, route: str, dtype: str, warps: int, block_d: int, arch: int = 90, d_state: int = 16) -> list[dict]:
    """Compile the kernels the route runs (:func:`route_kernels`: each pass of the forward and of the backward; the
    sequential kernels at their own channels per program and warps) of module ``st``
    (``tofdenoise.models.scan.triton``, imported without the interpreter) for one setting; one row per kernel with
    the ptxas figures."""
    consts = dict(
        CHUNK_T=st.CHUNK,
        BLOCK_D=block_d,
        BLOCK_N=1 << (d_state - 1).bit_length(),
        HAS_D=True,
        HAS_BIAS=True,
        SOFTPLUS=True,
        SS2D=route == "SS2D",
    )
    rows = []
    kernels = route_kernels(st, route)
    for name, kernel, extra in kernels:
        kconsts = {k: v for k, v in {**consts, **(extra or {})}.items() if k in kernel.arg_names}
        kernel_warps = (extra or {}).get("WARPS", st.SEQ_NUM_WARPS) if extra else warps
        compiled = _compile(kernel, dtype, kconsts, arch, kernel_warps)
        regs, spill_st, spill_ld = _ptxas_report(compiled.asm["ptx"], arch)
        rows.append(
            {
                "route": route,
                "kernel": name,
                "dtype": dtype,
                "warps": kernel_warps,
                "block_d": kconsts["BLOCK_D"],
                "registers": regs,
                "spill_store_bytes": spill_st,
                "spill_load_bytes": spill_ld,
                "shared_bytes": compiled.metadata.shared,
            }
        )
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--arch", type=int, default=90, help="compute capability x 10 (H100: 90)")
    p.add_argument("--warps", type=int, nargs="+", default=[4, 8])
    p.add_argument("--block-d", type=int, nargs="+", default=[2, 4, 8, 16], help="channels per program (SS2D)")
    p.add_argument("--d-state", type=int, default=16)
    args = p.parse_args(argv)
    os.environ["TRITON_INTERPRET"] = "0"  # compile, do not interpret
    from tofdenoise.models.scan import triton as st

    if st.triton is None:
        print("triton_resources: skipped (Triton is not installed)")
        return 0
    print(f"Triton {st.triton.__version__}, sm_{args.arch}a, d_state {args.d_state}, chunk {st.CHUNK}")
    print("| route | kernel | inputs | warps | BLOCK_D | registers | spill stores / loads (bytes) | shared (bytes) |")
    print("|---|---|---|---:|---:|---:|---|---:|")
    for route, blocks in (("plain", [st.BLOCK_D_MAX]), ("SS2D", args.block_d)):
        for dtype in ("fp32", "bf16"):
            for warps in args.warps:
                for block_d in blocks:
                    for r in resources(st, route, dtype, warps, block_d, args.arch, args.d_state):
                        print(
                            f"| {route} | {r['kernel']} | {dtype} | {warps} | {block_d} | {r['registers']} | "
                            f"{r['spill_store_bytes']} / {r['spill_load_bytes']} | {r['shared_bytes']} |",
                            flush=True,
                        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
