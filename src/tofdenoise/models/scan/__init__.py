"""The selective scan (Mamba's S6 recurrence): one module per job, one dispatcher.

- :mod:`.common`: the input contract, the effective step, the skip term, SS2D's four-direction layout; imports
  nothing from this package.
- :mod:`.reference`: the pure-PyTorch scans (the reference loop, the sequential baseline, the default chunked scan)
  and :func:`ss2d_scan_reference`, the plain computation of the kernels' SS2D contract.
- :mod:`.cpu`: the native C++ kernel (``csrc/selective_scan_cpu.cpp``, built on first use).
- :mod:`.triton`: the Triton kernels (CUDA; Triton's interpreter in the tests). :mod:`.mamba`: mamba-ssm's kernel.
- :mod:`.ops`: the kernels as ``torch.library`` custom operators (``tofdenoise::selective_scan``,
  ``tofdenoise::ss2d_scan`` and their backwards) with fake implementations and autograd, so ``torch.compile``
  traces them; the CPU and Triton entry points call them. Imported here, which registers them.
- :mod:`.dispatch`: :func:`resolve_scan_backend`, the one place that chooses a route (``selective_scan`` and SS2D
  ask it), :func:`available_scan_backends`, :func:`selective_scan`.

The kernel modules import :mod:`.common` and :mod:`.reference` (their self-check oracle), never :mod:`.dispatch`
nor this package's names (``tests/test_layering.py``). Importing this package builds nothing and does not import
Triton.
"""

from . import ops  # noqa: F401 - registers the tofdenoise:: scan operators the kernel modules call
from .common import cross_merge, cross_scan
from .dispatch import SCAN_BACKENDS, available_scan_backends, resolve_scan_backend, selective_scan
from .reference import selective_scan_chunked, selective_scan_ref, selective_scan_sequential, ss2d_scan_reference

__all__ = [
    "SCAN_BACKENDS",
    "available_scan_backends",
    "resolve_scan_backend",
    "selective_scan",
    "selective_scan_chunked",
    "selective_scan_ref",
    "selective_scan_sequential",
    "ss2d_scan_reference",
    "cross_scan",
    "cross_merge",
]
