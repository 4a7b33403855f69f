"""The classical, non-learned row: amplitude-guided joint bilateral filtering of depth (Kinect v2 style).

For every pixel p, with N_r(p) the pixels q of the disc |q - p| <= r (r = ``radius_px``) inside the frame::

    D_hat(p) = D(p) + sum_q w(p, q) (D(q) - D(p)) / sum_q w(p, q)

    w(p, q) = v(q) * (a(q) / a_max)^gamma * exp(-|q - p|^2 / (2 sigma_s^2)) * exp(-(D(q) - D(p))^2 / (2 sigma_d^2))

(the weighted mean of the neighbours' depth, written as a correction of D(p) so that a constant surface stays
exactly constant in floating point). D is the noisy depth in mm, v(q) = 1 where the input pixel is valid and 0
in holes (a hole never contributes), a the ToF amplitude and a_max its per-image maximum over valid pixels:

- the spatial Gaussian (sigma_s = ``sigma_spatial_px``) and the range Gaussian on depth differences
  (sigma_d = ``sigma_depth_mm``; ``inf`` = no range term: a plain, validity-normalised Gaussian blur) are the
  bilateral filter of the Kinect v2 depth pipeline and of ToF camera firmware;
- the amplitude (confidence) factor guides it by the signal: the depth noise of an iToF pixel falls with its
  amplitude (paper Eq. 7, sigma_D ~ 1/a when read noise dominates, ~ 1/sqrt(a) when shot noise does), so
  ``amplitude_power`` gamma = 2 or 1 makes the weights inverse-variance weights in those two limits, and 0
  ignores the amplitude. A global amplitude scale cancels in the ratio; dividing by a_max only keeps the numbers
  in range.

Where no neighbour (the pixel itself included) has a weight (a hole surrounded by holes, or every neighbour
beyond the range term's reach), the output is the input depth. The frame border is not padded with data:
pixels outside the frame have no weight (the window shrinks), so no value is invented there.

No separable shortcut exists (the range term depends on the centre pixel); the filter loops over the 2r + 1
rows of the window, each row's 2r + 1 offsets one vectorised operation on the whole batch (strided views of the
padded frame), in O((2r + 1) B H W) memory
(measured time per 480 x 640 frame: docs/models.md#classical-row-joint-bilateral-filter).

``JointBilateral`` (registered as the backbone ``bilateral``, ``trainable=False``) applies it to the network
input of ``DepthRestorer`` (``tofdenoise.models.conditioning``), so it sees exactly what a network with the
signal channel sees: channel 0 = depth / depth_scale_mm with holes filled (``input_centering`` ``none`` or
``image``: a constant offset leaves depth differences exact), channel 1 = amplitude x mask / per-image max, 0 at
invalid pixels, which therefore get no weight.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from .common import check_input
from .registry import register_backbone

__all__ = ["joint_bilateral_filter", "default_radius_px", "JointBilateral"]


def default_radius_px(sigma_spatial_px: float) -> int:
    """Window radius used when none is given: ceil(2 sigma_s) (the spatial weight at the rim is exp(-2) = 0.14)."""
    return max(1, math.ceil(2.0 * float(sigma_spatial_px)))


def _check_params(sigma_spatial_px: float, sigma_depth_mm: float, amplitude_power: float, radius_px: int) -> None:
    if not (math.isfinite(sigma_spatial_px) and sigma_spatial_px > 0):
        raise ValueError(f"bilateral filter: sigma_spatial_px must be a finite number > 0, got {sigma_spatial_px}")
    if not sigma_depth_mm > 0:  # inf is allowed (no range term); NaN fails here
        raise ValueError(f"bilateral filter: sigma_depth_mm must be > 0 (inf = no range term), got {sigma_depth_mm}")
    if not (math.isfinite(amplitude_power) and amplitude_power >= 0):
        raise ValueError(f"bilateral filter: amplitude_power must be a finite number >= 0, got {amplitude_power}")
    if int(radius_px) != radius_px or radius_px < 0:
        raise ValueError(f"bilateral filter: radius_px must be an integer >= 0, got {radius_px}")


def joint_bilateral_filter(
    depth_mm: Tensor,
    amplitude: Tensor,
    valid: Tensor | None = None,
    *,
    sigma_spatial_px: float,
    sigma_depth_mm: float,
    amplitude_power: float = 1.0,
    radius_px: int | None = None,
) -> Tensor:
    """Amplitude-guided joint bilateral filter of depth (module docstring formula), (B, 1, H, W) -> (B, 1, H, W).

    Args:
        depth_mm: noisy depth in mm; its value at invalid pixels only matters as the output there when no
            neighbour has a weight (and as the centre value of the range term at that pixel).
        amplitude: ToF amplitude (any positive scale), same shape; its per-image maximum over valid pixels
            normalises it.
        valid: input pixels that may contribute (bool, same shape); default: depth finite and > 0 and amplitude
            finite and > 0.
        sigma_spatial_px: sigma_s of the formula, the spatial Gaussian's std in pixels.
        sigma_depth_mm: sigma_d of the formula, the range Gaussian's std in mm (``inf``: no range term).
        amplitude_power: gamma of the formula, the exponent of the normalised amplitude weight.
        radius_px: r of the formula, the window's half-size in pixels (default: ``default_radius_px(sigma_s)``).

    Computed in float32 (float64 inputs stay float64); the result has the dtype of that computation.
    """
    if depth_mm.dim() != 4 or depth_mm.shape[1] != 1:
        raise ValueError(f"joint_bilateral_filter: depth_mm must be (B, 1, H, W), got {tuple(depth_mm.shape)}")
    if amplitude.shape != depth_mm.shape:
        raise ValueError(
            f"joint_bilateral_filter: amplitude shape {tuple(amplitude.shape)} != depth shape {tuple(depth_mm.shape)}"
        )
    r = default_radius_px(sigma_spatial_px) if radius_px is None else radius_px
    _check_params(float(sigma_spatial_px), float(sigma_depth_mm), float(amplitude_power), r)
    r = int(r)
    dtype = torch.float64 if depth_mm.dtype == torch.float64 else torch.float32
    depth = depth_mm.to(dtype)
    amp = amplitude.to(dtype)
    if valid is None:
        valid = torch.isfinite(depth) & (depth > 0) & torch.isfinite(amp) & (amp > 0)
    elif valid.shape != depth_mm.shape:
        raise ValueError(
            f"joint_bilateral_filter: valid shape {tuple(valid.shape)} != depth shape {tuple(depth_mm.shape)}"
        )
    valid = valid.bool() & torch.isfinite(depth) & torch.isfinite(amp) & (amp >= 0)
    zero = torch.zeros((), dtype=dtype, device=depth.device)
    amp = torch.where(valid, amp, zero)
    peak = amp.amax(dim=(1, 2, 3), keepdim=True)
    peak = torch.where(peak > 0, peak, torch.ones_like(peak))
    confidence = torch.where(valid, (amp / peak) ** float(amplitude_power), zero)  # 0 ** 0 = 1 at a valid pixel
    centre = torch.where(torch.isfinite(depth), depth, zero)
    h, w = depth.shape[-2:]
    pad = (r, r, r, r)
    d_pad = torch.nn.functional.pad(torch.where(valid, depth, zero), pad)
    c_pad = torch.nn.functional.pad(confidence, pad)  # outside the frame: no weight
    inv_2ss = 1.0 / (2.0 * float(sigma_spatial_px) ** 2)
    inv_2sd = 0.0 if math.isinf(sigma_depth_mm) else 1.0 / (2.0 * float(sigma_depth_mm) ** 2)
    dx = torch.arange(-r, r + 1, dtype=dtype, device=depth.device)
    num = torch.zeros_like(centre)
    den = torch.zeros_like(centre)
    centre_row = centre.unsqueeze(-2)  # (B, 1, H, 1, W)
    for dy in range(-r, r + 1):
        # the 2r + 1 horizontal offsets of one window row at once: strided views (B, 1, H, 2r + 1, W), no copy
        rows = slice(r + dy, r + dy + h)
        d_win = d_pad[..., rows, :].unfold(-1, w, 1)
        c_win = c_pad[..., rows, :].unfold(-1, w, 1)
        # spatial weight, 0 outside the disc |(dy, dx)| <= r
        spatial = torch.exp(-(dy * dy + dx.square()) * inv_2ss) * (dy * dy + dx.square() <= r * r)
        diff = d_win - centre_row
        weight = c_win * spatial[:, None]
        if inv_2sd > 0:
            weight = weight * torch.exp(-inv_2sd * diff.square())
        # an invalid or out-of-disc neighbour has weight 0 and a finite diff: it adds exactly 0
        num = num + (weight * diff).sum(dim=-2)
        den = den + weight.sum(dim=-2)
    has_weight = den > 0
    correction = torch.where(has_weight, num / torch.where(has_weight, den, torch.ones_like(den)), zero)
    return torch.where(has_weight, centre + correction, depth)


@register_backbone("bilateral", trainable=False)
class JointBilateral(nn.Module):
    """:func:`joint_bilateral_filter` as a backbone without parameters, on ``DepthRestorer``'s network input.

    Input (B, 2, H, W): channel 0 = (depth - constant offset) / ``depth_scale_mm`` (``input_centering`` ``none``
    or ``image``), channel 1 = normalised amplitude, 0 at invalid pixels (``use_signal_channel=True``).
    Output (B, 1, H, W) in the same units as channel 0. ``DepthRestorer`` passes its own ``depth_scale_mm`` and
    refuses the other settings (``input_centering_modes``, ``needs_signal_channel``): a local offset would
    change the depth differences the range term compares.
    """

    #: the ``model.conditioning.centering`` modes under which channel 0 differences are depth differences
    input_centering_modes = ("none", "image")
    #: the filter needs the amplitude channel (and reads invalid pixels from its zeros)
    needs_signal_channel = True

    def __init__(
        self,
        in_channels: int = 2,
        sigma_spatial_px: float = 2.0,
        sigma_depth_mm: float = 20.0,
        amplitude_power: float = 1.0,
        radius_px: int | None = None,
        depth_scale_mm: float = 100.0,
    ) -> None:
        super().__init__()
        if in_channels != 2:
            raise ValueError(
                f"bilateral backbone: needs in_channels=2 (depth and amplitude: "
                f"DepthRestorer(use_signal_channel=True)), got {in_channels}"
            )
        if not depth_scale_mm > 0:
            raise ValueError(f"bilateral backbone: depth_scale_mm must be > 0, got {depth_scale_mm}")
        radius = default_radius_px(sigma_spatial_px) if radius_px is None else radius_px
        _check_params(float(sigma_spatial_px), float(sigma_depth_mm), float(amplitude_power), radius)
        self.in_channels = in_channels
        self.sigma_spatial_px = float(sigma_spatial_px)
        self.sigma_depth_mm = float(sigma_depth_mm)
        self.amplitude_power = float(amplitude_power)
        self.radius_px = int(radius)
        self.depth_scale_mm = float(depth_scale_mm)

    def extra_repr(self) -> str:
        return (
            f"sigma_spatial_px={self.sigma_spatial_px}, sigma_depth_mm={self.sigma_depth_mm}, "
            f"amplitude_power={self.amplitude_power}, radius_px={self.radius_px}"
        )

    def forward(self, x: Tensor) -> Tensor:
        check_input(x, self.in_channels, "JointBilateral")
        depth_mm = x[:, :1].float() * self.depth_scale_mm
        amplitude = x[:, 1:2].float()
        valid = torch.isfinite(depth_mm) & torch.isfinite(amplitude) & (amplitude > 0)
        out = joint_bilateral_filter(
            depth_mm,
            amplitude,
            valid,
            sigma_spatial_px=self.sigma_spatial_px,
            sigma_depth_mm=self.sigma_depth_mm,
            amplitude_power=self.amplitude_power,
            radius_px=self.radius_px,
        )
        return out / self.depth_scale_mm
