"""Realistic invalid regions ("holes") for training inputs, so that networks learn to ignore them.

A real iToF frame marks 5-25 % of its pixels invalid (depth 0). Three mechanisms are modelled, each a pure
function of its inputs and an explicit ``torch.Generator`` (same generator state -> same holes):

1. **Low signal** (``low_signal_holes``): the camera drops a pixel whose demodulated amplitude falls below a
   validity threshold. The threshold is the simulator's (``tofdenoise.physics.simulator.default_min_amplitude_e``:
   5 x the dark-only amplitude noise sqrt(2/N) sigma_dark). The training signal a(p) is mapped into the
   calibration's signal interval (paper Sec. III-A), where no pixel is that dark, so the frame is "captured
   darker" for the validity decision: a per-sample scale s puts a target fraction f ~ U(0, max_fraction) of the
   valid pixels' expected amplitude s a |C1| below the threshold (s = thr / (|C1| q_f(a)), q_f the f-quantile
   of a). The measured amplitude is |s a |C1| + n| with n complex Gaussian noise of per-quadrature std
   sqrt(2/N (s a c0 + sigma_dark^2)) (the N-phase DFT of taps with variance s a r_n + sigma_dark^2, paper Eq. 6),
   and the pixel is invalid where it is below the threshold. The holes therefore follow the scene's darkest,
   farthest surfaces with ragged, noisy borders, as in real frames. Only the validity decision uses the scaled
   signal; the depth noise of the pixels that stay valid is the training noise model's.
2. **Depth edges** (``edge_holes``): mixed ("flying") pixels at depth discontinuities, which cameras filter:
   a pixel whose depth differs from a 4-neighbour by more than ``edge_jump`` x its depth is invalid with
   probability ``edge_prob``.
3. **Dropout blobs** (``blob_holes``): random irregular blobs (specular saturation, multipath rejection, dust):
   a Poisson number (mean ``blob_density`` per 10^4 px) of star-shaped regions with radius U(r_min, r_max)
   px, an elongation and orientation, and a boundary modulated by the 2nd and 3rd angular harmonics.

With the physical signal route (``HoleModel.physical_signal``, set by the datamodule for
``data.signal_route=physical``) the signal a(p) is already what the camera collects: mechanism 1 uses it as it
is (scale s = 1, no target fraction) and a fourth mechanism joins:
4. **Saturation** (``saturation_holes``): a pixel whose brightest expected tap max_n a r_n(D) + mu_dark reaches
   the full well is flagged by the camera (near white surfaces, specular highlights).

``HoleModel`` combines them; ``apply_holes`` zeroes every map of a sample at the holes and removes them from
the valid mask (so the loss and the metrics ignore them). The fill rule for invalid input pixels before the
network is ``DepthRestorer``'s (see docs/training.md).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import torch

from tofdenoise.physics.photometry import saturated
from tofdenoise.physics.simulator import default_min_amplitude_e

__all__ = [
    "HoleModel",
    "apply_holes",
    "blob_holes",
    "edge_holes",
    "low_signal_holes",
    "measured_amplitude_below_threshold",
    "saturation_holes",
]


def _uniform(
    generator: torch.Generator, low: float = 0.0, high: float = 1.0, size: tuple[int, ...] = ()
) -> torch.Tensor:
    return low + (high - low) * torch.rand(size, generator=generator, dtype=torch.float64)


def measured_amplitude_below_threshold(
    signal_e: torch.Tensor, valid: torch.Tensor, calib: Any, scale: float, generator: torch.Generator
) -> torch.Tensor:
    """Pixels whose measured amplitude |s a |C1| + n| falls below the simulator's validity threshold, n complex
    Gaussian noise of per-quadrature std sqrt(2/N (s a c0 + sigma_dark^2)) (the N-phase DFT of the taps)."""
    c1 = calib.tap_response.first_harmonic_amplitude
    thr = default_min_amplitude_e(calib)
    a = signal_e.double().clamp_min(0.0) * scale
    std = torch.sqrt(2.0 / calib.num_taps * (a * calib.tap_response.c0 + calib.dark_std_e**2))
    noise = torch.randn((2, *signal_e.shape), generator=generator, dtype=torch.float64)
    measured = torch.hypot(a * c1 + std * noise[0], std * noise[1])
    return valid.bool() & (measured < thr)


def saturation_holes(depth_mm: torch.Tensor, signal_e: torch.Tensor, valid: torch.Tensor, calib: Any) -> torch.Tensor:
    """Pixels whose brightest expected tap a max_n r_n(D) + mu_dark reaches the full well (paper Eq. 4)."""
    sat = saturated(depth_mm.double().numpy(), signal_e.double().numpy(), calib)
    return valid.bool() & torch.from_numpy(sat)


def low_signal_holes(
    signal_e: torch.Tensor, valid: torch.Tensor, calib: Any, fraction: float, generator: torch.Generator
) -> torch.Tensor:
    """Pixels invalid because the darkened frame's measured amplitude falls below the simulator's threshold.

    ``signal_e``: returned signal a(p) [e-] (H, W); ``valid``: bool (H, W); ``fraction``: target share f of
    the valid pixels whose *expected* amplitude is below the threshold (the noisy decision makes the actual
    share scatter around f). Returns a bool (H, W) hole mask (False outside ``valid``); f <= 0 gives none.
    """
    if not 0.0 <= fraction < 1.0:
        raise ValueError(f"low_signal_holes: fraction must be in [0, 1), got {fraction}")
    valid = valid.bool()
    holes = torch.zeros_like(valid)
    values = signal_e[valid].double()
    if fraction <= 0.0 or values.numel() == 0:
        return holes
    c1 = calib.tap_response.first_harmonic_amplitude
    thr = default_min_amplitude_e(calib)
    q = (
        float(torch.quantile(values, fraction))
        if values.numel() <= 8_000_000
        else float(torch.quantile(values[:: math.ceil(values.numel() / 8_000_000)], fraction))
    )
    if not q > 0:
        return holes
    return measured_amplitude_below_threshold(signal_e, valid, calib, thr / (c1 * q), generator)


def edge_holes(
    depth_mm: torch.Tensor, valid: torch.Tensor, jump: float, prob: float, generator: torch.Generator
) -> torch.Tensor:
    """Pixels next to a depth discontinuity (|D - D_neighbour| > jump D, 4-neighbourhood, both valid), each
    invalid with probability ``prob``. Returns a bool (H, W) mask."""
    valid = valid.bool()
    d = depth_mm.double()
    edge = torch.zeros_like(valid)
    for dim in (0, 1):
        diff = (d.narrow(dim, 1, d.shape[dim] - 1) - d.narrow(dim, 0, d.shape[dim] - 1)).abs()
        both = valid.narrow(dim, 1, d.shape[dim] - 1) & valid.narrow(dim, 0, d.shape[dim] - 1)
        near = torch.minimum(d.narrow(dim, 1, d.shape[dim] - 1), d.narrow(dim, 0, d.shape[dim] - 1))
        jumps = both & (diff > jump * near)
        edge.narrow(dim, 1, d.shape[dim] - 1).logical_or_(jumps)
        edge.narrow(dim, 0, d.shape[dim] - 1).logical_or_(jumps)
    draw = torch.rand(valid.shape, generator=generator, dtype=torch.float64)
    return edge & (draw < prob)


def blob_holes(
    shape: tuple[int, int], density: float, radius_px: tuple[float, float], generator: torch.Generator
) -> torch.Tensor:
    """Random irregular blobs: Poisson(density x H x W / 10^4) of them, each star-shaped around a uniform
    centre with boundary radius r(theta) = r0 (1 + 0.2 cos(2 theta + p2) + 0.1 cos(3 theta + p3)) on an
    ellipse of axis ratio U(0.5, 1) and random orientation, r0 ~ U(radius_px). Returns bool (H, W)."""
    h, w = int(shape[0]), int(shape[1])
    holes = torch.zeros((h, w), dtype=torch.bool)
    lam = torch.tensor([density * h * w / 1e4], dtype=torch.float64)
    count = int(torch.poisson(lam, generator=generator)) if density > 0 else 0
    if count == 0:
        return holes
    r_lo, r_hi = float(radius_px[0]), float(radius_px[1])
    ys = torch.arange(h, dtype=torch.float64)[:, None]
    xs = torch.arange(w, dtype=torch.float64)[None, :]
    params = _uniform(generator, size=(count, 7))
    for cy, cx, r0, ratio, angle, p2, p3 in params.tolist():
        cy, cx = cy * h, cx * w
        r0 = r_lo + (r_hi - r_lo) * r0
        ratio = 0.5 + 0.5 * ratio
        angle, p2, p3 = math.pi * angle, 2 * math.pi * p2, 2 * math.pi * p3
        extent = int(math.ceil(r0 * 1.3)) + 1
        y0, y1 = max(0, int(cy) - extent), min(h, int(cy) + extent + 1)
        x0, x1 = max(0, int(cx) - extent), min(w, int(cx) + extent + 1)
        if y0 >= y1 or x0 >= x1:
            continue
        dy, dx = ys[y0:y1] - cy, xs[:, x0:x1] - cx
        u = dx * math.cos(angle) + dy * math.sin(angle)
        v = (-dx * math.sin(angle) + dy * math.cos(angle)) / ratio
        theta = torch.atan2(v, u)
        boundary = r0 * (1 + 0.2 * torch.cos(2 * theta + p2) + 0.1 * torch.cos(3 * theta + p3))
        holes[y0:y1, x0:x1] |= torch.hypot(u, v) <= boundary
    return holes


@dataclass(frozen=True)
class HoleModel:
    """The hole mechanisms of this module with their settings (``data.holes_kwargs``).

    max_low_signal_fraction: low-signal holes cover f ~ U(0, this) of the valid pixels (0 = off); not used with
        ``physical_signal``.
    physical_signal: the signal is a camera's (physical route): low-signal holes at its own level (s = 1) and
        saturation holes; set by the datamodule from ``data.signal_route``.
    edge_jump, edge_prob: depth-edge holes (relative jump threshold, probability; prob 0 = off).
    blob_density: mean number of dropout blobs per 10^4 px (0 = off); blob_radius_px: (min, max) radius.
    """

    max_low_signal_fraction: float = 0.15
    edge_jump: float = 0.05
    edge_prob: float = 0.5
    blob_density: float = 1.0
    blob_radius_px: tuple[float, float] = (2.0, 12.0)
    physical_signal: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "blob_radius_px", tuple(float(r) for r in self.blob_radius_px))
        if not 0.0 <= self.max_low_signal_fraction < 1.0:
            raise ValueError(
                f"data.holes_kwargs.max_low_signal_fraction must be in [0, 1), got {self.max_low_signal_fraction}"
            )
        if not 0.0 <= self.edge_prob <= 1.0 or not self.edge_jump > 0:
            raise ValueError(
                f"data.holes_kwargs: need edge_jump > 0 and 0 <= edge_prob <= 1, got "
                f"edge_jump={self.edge_jump}, edge_prob={self.edge_prob}"
            )
        lo_hi = self.blob_radius_px
        if self.blob_density < 0 or len(lo_hi) != 2 or not 0 < lo_hi[0] <= lo_hi[1]:
            raise ValueError(
                f"data.holes_kwargs: need blob_density >= 0 and blob_radius_px = [min, max] with "
                f"0 < min <= max, got {self.blob_density}, {list(lo_hi)}"
            )

    def to_dict(self) -> dict[str, Any]:
        return {**asdict(self), "blob_radius_px": list(self.blob_radius_px)}

    def sample(
        self,
        depth_mm: torch.Tensor,
        signal_e: torch.Tensor,
        valid: torch.Tensor,
        calib: Any,
        generator: torch.Generator,
    ) -> torch.Tensor:
        """Hole mask (bool, shape of ``depth_mm``; 2-D, or (1, H, W)) of one sample, drawn from ``generator``."""
        squeeze = depth_mm.dim() == 3
        d = depth_mm[0] if squeeze else depth_mm
        a = signal_e[0] if squeeze else signal_e
        v = (valid[0] if squeeze else valid).bool()
        if self.physical_signal:
            holes = measured_amplitude_below_threshold(a, v, calib, 1.0, generator)
            holes |= saturation_holes(d, a, v, calib)
        else:
            fraction = float(_uniform(generator, 0.0, self.max_low_signal_fraction))
            holes = low_signal_holes(a, v, calib, fraction, generator)
        if self.edge_prob > 0:
            holes |= edge_holes(d, v, self.edge_jump, self.edge_prob, generator)
        if self.blob_density > 0:
            holes |= blob_holes(tuple(d.shape), self.blob_density, self.blob_radius_px, generator)
        holes &= v
        return holes[None] if squeeze else holes


def apply_holes(maps: dict[str, torch.Tensor], holes: torch.Tensor) -> dict[str, torch.Tensor]:
    """Zero every map at ``holes`` and clear them in ``maps["mask"]`` (a new dict; the inputs are not changed)."""
    keep = ~holes.bool()
    return {k: torch.where(keep, v, torch.zeros((), dtype=v.dtype)) for k, v in maps.items()}
