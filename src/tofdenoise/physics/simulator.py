"""Tap-level iToF capture simulator and the camera's standard N-phase demodulation.

What a frame goes through (per pixel, per tap n, electrons):
1. expected photo-electrons  lambda_n = exposure * a * c(psi(D) - theta_n)            (paper Eq. 3-4)
2. Poisson photo-electrons   k_n ~ Poisson(lambda_n)                                 (shot noise, exact)
3. dark/ambient offset and Gaussian dark/read noise  y_n = k_n + mu_dark + N(0, s^2)
   with s^2 = sigma_dark^2 - g^2/12 when quantising (the calibrated sigma_dark is measured on quantised
   dark frames, so it already holds the ADC share g^2/12), else s = sigma_dark
4. clipping to [0, full_well]; a pixel with any tap at full well is flagged `saturated`
5. optional ADC quantisation to the gain g [e-/DN]: y_n = g round(y_n / g) (taps stay in electrons)
6. demodulation (`demodulate`): first DFT bin B = sum_n y_n exp(i theta_n), phase atan2(Im B, Re B),
   corrected for the tap response's phase offset (and for cyclic error when a harmonic aliases into the
   first bin, via an exact inverse look-up table built from the calibrated c), depth = psi / (4 pi f / c),
   wrapped to [0, unambiguous range); amplitude = 2 |B| / N [e-] (expectation a |C1| without aliasing).

The dark offset cancels in B (sum_n exp(i theta_n) = 0). Exposure scales the returned signal only; the
dark/ambient floor is the calibrated one (calibrate at the setting you simulate).
Fixed-pattern noise (``calib.fixed_pattern``, ``tofdenoise.physics.fixed_pattern``): when the camera has one,
its column phase offsets shift psi in step 1, its PRNU multiplies lambda_n and its per-pixel tap offsets are added
in step 3, in every frame (dark frames included); the pattern is drawn for the frame's (H, W) = the last two axes.
Validity: input pixel valid (depth > 0, signal > 0, finite), no saturated tap, amplitude above
`min_amplitude_e` (default: 5 x the dark-only amplitude noise sqrt(2/N) sigma_dark). Invalid pixels get
depth 0. Frames are generated in chunks to bound memory.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import numpy as np
import torch

from tofdenoise.physics.calibration import SensorCalibration
from tofdenoise.physics.fixed_pattern import camera_pattern, column_phase_depth_mm
from tofdenoise.physics.uncertainty import tap_responses

LUT_SIZE = 8192
DEFAULT_CHUNK_ELEMENTS = 8_000_000


@dataclass
class CaptureFrames:
    """Simulated (or decoded) captures: F frames of H x W pixels.

    depth_mm (F,H,W) float32 (0 where invalid), amplitude (F,H,W) float32 [e-], valid (F,H,W) bool,
    saturated (F,H,W) bool, taps (F,N,H,W) float32 [e-] or None.
    """

    depth_mm: torch.Tensor
    amplitude: torch.Tensor
    valid: torch.Tensor
    saturated: torch.Tensor
    taps: torch.Tensor | None = None

    @property
    def num_frames(self) -> int:
        return int(self.depth_mm.shape[0])


# ----------------------------------------------------------------------------------------------------
# Phase decoding (first DFT bin -> psi)
# ----------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PhaseDecoder:
    """Maps the measured first-bin phase phi = atan2(Im B, Re B) in [-pi, pi] to the target phase psi.

    offset_rad: phi - psi when no harmonic aliases into the first bin (then psi = phi - offset_rad exactly).
    table / slope: inverse look-up psi(u_j) (unwrapped) on u_j = -pi + 2 pi j / M, j = 0..M, and its
    increments, for linear interpolation (None when not needed).
    """

    offset_rad: float
    table: np.ndarray | None
    slope: np.ndarray | None
    _cache: dict = field(default_factory=dict, compare=False, hash=False, repr=False)

    def _tables(self, scale: float, dtype: torch.dtype, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
        key = (scale, dtype, str(device))
        hit = self._cache.get(key)
        if hit is None:
            assert self.table is not None and self.slope is not None
            hit = (
                torch.as_tensor(self.table * scale, dtype=dtype, device=device),
                torch.as_tensor(self.slope * scale, dtype=dtype, device=device),
            )
            self._cache[key] = hit
        return hit

    def decode(self, phi: torch.Tensor, scale: float = 1.0, period: float = 2.0 * math.pi) -> torch.Tensor:
        """psi * scale wrapped to [0, period * scale) (scale = 1 / (rad per mm) gives depth in mm)."""
        if self.table is None:
            out = phi - self.offset_rad
            if scale != 1.0:
                out.mul_(scale)
            return torch.remainder(out, period * scale)
        m = self.table.shape[0]  # M intervals
        table, slope = self._tables(scale, phi.dtype, phi.device)
        j = (phi + math.pi).mul_(m / (2.0 * math.pi))
        i0 = j.to(torch.int64).clamp_(0, m - 1)
        frac = j.sub_(i0)
        flat = i0.reshape(-1)
        out = table.index_select(0, flat).view(phi.shape)
        out.addcmul_(frac, slope.index_select(0, flat).view(phi.shape))
        return torch.remainder(out, period * scale)


def _first_bin(calib: SensorCalibration, psi: np.ndarray) -> np.ndarray:
    """B(psi) / a = sum_n c(psi - theta_n) exp(i theta_n) for noise-free taps (float64)."""
    theta = calib.tap_phases_rad
    taps = calib.tap_response.value(psi[:, None] - theta[None, :])
    return (taps * np.exp(1j * theta)[None, :]).sum(axis=1)


@lru_cache(maxsize=32)
def phase_decoder(calib: SensorCalibration) -> PhaseDecoder:
    """Build (and cache) the phase decoder of a calibration; ValueError if c makes phi(psi) non-invertible."""
    psi = np.linspace(0.0, 2.0 * np.pi, LUT_SIZE, endpoint=False)
    phi = np.unwrap(np.angle(_first_bin(calib, psi)))
    offset = float(phi[0] - psi[0])
    deviation = float(np.max(np.abs(phi - psi - offset)))
    if deviation < 1e-9:
        return PhaseDecoder(offset_rad=offset, table=None, slope=None)
    dphi = np.diff(np.concatenate([phi, [phi[0] + 2.0 * np.pi]]))
    if np.any(dphi <= 0):
        raise ValueError(
            "tap_response: harmonics aliasing into the first DFT bin make the measured phase non-monotonic "
            f"in depth for N={calib.num_taps} taps; the camera phase cannot be decoded"
        )
    phi_ext = np.concatenate([phi - 4 * np.pi, phi - 2 * np.pi, phi, phi + 2 * np.pi, phi + 4 * np.pi])
    psi_ext = np.concatenate([psi - 4 * np.pi, psi - 2 * np.pi, psi, psi + 2 * np.pi, psi + 4 * np.pi])
    u = -np.pi + 2.0 * np.pi * np.arange(LUT_SIZE + 1) / LUT_SIZE
    table = np.interp(u, phi_ext, psi_ext)
    return PhaseDecoder(offset_rad=offset, table=table[:-1].copy(), slope=np.diff(table))


def _dft_weights(num_taps: int) -> tuple[list[float], list[float]]:
    """cos(theta_n), sin(theta_n) with analytic zeros/ones made exact (so they can be skipped)."""
    theta = 2.0 * np.pi * np.arange(num_taps) / num_taps
    cos, sin = np.cos(theta), np.sin(theta)
    cos[np.abs(cos) < 1e-12] = 0.0
    sin[np.abs(sin) < 1e-12] = 0.0
    return [float(v) for v in cos], [float(v) for v in sin]


def _first_bin_parts(t: torch.Tensor, calib: SensorCalibration, tap_axis: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(Re B, Im B) of B = sum_n y_n exp(i theta_n), summing tap planes (no copy of the tap axis)."""
    cos, sin = _dft_weights(calib.num_taps)
    planes = t.unbind(dim=tap_axis)

    def combo(weights: list[float]) -> torch.Tensor:
        out = None
        for plane, wgt in zip(planes, weights):
            if wgt == 0.0:
                continue
            if out is None:
                out = plane * wgt if wgt != 1.0 else plane.clone()
            elif wgt == 1.0:
                out += plane
            elif wgt == -1.0:
                out -= plane
            else:
                out.add_(plane, alpha=wgt)
        return out if out is not None else torch.zeros_like(planes[0])

    return combo(cos), combo(sin)


def demodulate(taps: Any, calib: SensorCalibration, tap_axis: int = -3) -> tuple[torch.Tensor, torch.Tensor]:
    """Standard N-phase demodulation of tap values [e-] -> (depth_mm, amplitude [e-]).

    taps: tensor/array with the N taps on `tap_axis` (default -3: (F,N,H,W) or (N,H,W)). depth is in
    [0, unambiguous range); amplitude = 2 |B| / N. No validity decision is made here.
    """
    t = torch.as_tensor(taps)
    if not torch.is_floating_point(t):
        t = t.float()
    n = calib.num_taps
    if t.shape[tap_axis] != n:
        raise ValueError(f"taps: expected {n} taps on axis {tap_axis}, got shape {tuple(t.shape)}")
    re, im = _first_bin_parts(t, calib, tap_axis)
    phi = torch.atan2(im, re)
    depth = phase_decoder(calib).decode(phi, scale=1.0 / calib.phase_per_mm)
    amplitude = (2.0 / n) * torch.hypot(re, im)
    return depth, amplitude


def default_min_amplitude_e(calib: SensorCalibration) -> float:
    """5 x the dark-only amplitude noise per quadrature, sqrt(2 / N) sigma_dark."""
    return 5.0 * math.sqrt(2.0 / calib.num_taps) * calib.dark_std_e


def gaussian_noise_std_e(calib: SensorCalibration, quantize: bool) -> float:
    """Std of the Gaussian dark/read term: sigma_dark minus the ADC share g^2/12 when quantising."""
    var = calib.dark_std_e**2
    if quantize and calib.adc_gain_e_per_dn is not None:
        var = max(var - calib.adc_gain_e_per_dn**2 / 12.0, 0.0)
    return math.sqrt(var)


def _to_tensor(x: Any, name: str) -> torch.Tensor:
    t = torch.as_tensor(x)
    if not torch.is_floating_point(t):
        t = t.float()
    if t.ndim < 1:
        raise ValueError(f"{name} must have at least one dimension (H, W), got a scalar")
    return t


def _pattern(calib: SensorCalibration, shape: tuple[int, ...]) -> Any:
    """The camera's fixed pattern for frames whose last two axes are (H, W), or None."""
    if len(shape) < 2:
        return None
    return camera_pattern(calib, int(shape[-2]), int(shape[-1]))


def simulate_taps_chunk(
    mean_signal_e: torch.Tensor,
    calib: SensorCalibration,
    num_frames: int,
    generator: torch.Generator | None,
    quantize: bool,
    tap_offset_e: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Noisy taps (F,N,...) [e-] and per-pixel saturation (F,...) from expected signal electrons (N,...);
    ``tap_offset_e`` (N,...) is a fixed per-pixel tap offset added to the dark offset."""
    lam = mean_signal_e.unsqueeze(0).expand(num_frames, *mean_signal_e.shape).contiguous()
    taps = torch.poisson(lam, generator=generator) if generator is not None else torch.poisson(lam)
    del lam
    s = gaussian_noise_std_e(calib, quantize)
    noise = torch.randn(taps.shape, dtype=taps.dtype, device=taps.device, generator=generator)
    taps.add_(noise.mul_(s)).add_(calib.dark_mean_e)
    del noise
    if tap_offset_e is not None:
        taps.add_(tap_offset_e.to(taps.device, taps.dtype).unsqueeze(0))
    saturated = (taps >= calib.full_well_e).any(dim=1)
    taps.clamp_(0.0, calib.full_well_e)
    if quantize and calib.adc_gain_e_per_dn is not None:
        g = calib.adc_gain_e_per_dn
        taps.div_(g).round_().mul_(g)
    return taps, saturated


def _check_frames_and_exposure(num_frames: Any, exposure: Any) -> None:
    """The frame count is a positive integer and the exposure a finite number > 0 (else a ValueError naming it)."""
    if int(num_frames) != num_frames or num_frames < 1:
        raise ValueError(f"num_frames must be a positive integer, got {num_frames}")
    if not math.isfinite(float(exposure)) or exposure <= 0:
        raise ValueError(f"exposure must be a finite number > 0, got {exposure}")


def simulate_frames(
    depth_mm: Any,
    signal_e: Any,
    calib: SensorCalibration,
    num_frames: int,
    exposure: float = 1.0,
    generator: torch.Generator | None = None,
    quantize: bool = True,
    return_taps: bool = False,
    min_amplitude_e: float | None = None,
    chunk_frames: int | None = None,
) -> CaptureFrames:
    """Simulate `num_frames` captures of a static scene (clean depth [mm], returned signal a [e-]).

    depth_mm and signal_e: same shape (H, W) (any shape works; outputs are (F, *shape)); numpy or torch.
    exposure multiplies the returned signal. `generator` (CPU torch.Generator) makes the draw reproducible.
    Computation is float32 on the inputs' device; frames are produced in chunks of `chunk_frames`
    (default: about 8 M tap values per chunk).
    """
    _check_frames_and_exposure(num_frames, exposure)
    d = _to_tensor(depth_mm, "depth_mm").float()
    a = _to_tensor(signal_e, "signal_e").float().to(d.device)
    if d.shape != a.shape:
        raise ValueError(f"depth_mm {tuple(d.shape)} and signal_e {tuple(a.shape)} must have the same shape")
    in_valid = torch.isfinite(d) & torch.isfinite(a) & (d > 0) & (a > 0)
    d_safe = torch.where(in_valid, d, torch.ones_like(d))
    a_eff = torch.where(in_valid, a * float(exposure), torch.zeros_like(a))
    pattern = _pattern(calib, tuple(d.shape))
    if pattern is not None:  # the column phase offsets shift psi (the clean depth stays the truth)
        d_safe = d_safe + torch.from_numpy(column_phase_depth_mm(pattern, calib)).to(d_safe.device)
    r, _ = tap_responses(d_safe, calib)  # (..., N)
    mean_signal = (a_eff.unsqueeze(-1) * r).clamp_min(0.0).movedim(-1, 0).contiguous()  # (N, ...)
    return _frames_from_means(
        mean_signal, in_valid, calib, num_frames, generator, quantize, return_taps, min_amplitude_e, chunk_frames
    )


def simulate_tap_mean_frames(
    tap_means_e: Any,
    calib: SensorCalibration,
    num_frames: int,
    exposure: float = 1.0,
    generator: torch.Generator | None = None,
    quantize: bool = True,
    return_taps: bool = False,
    min_amplitude_e: float | None = None,
    chunk_frames: int | None = None,
) -> CaptureFrames:
    """Like ``simulate_frames``, from the expected signal photo-electrons of each tap (N, ...) at exposure 1
    (dark offset excluded): e.g. mixed pixels (``tofdenoise.physics.mixed_pixels``), whose taps sum the returns
    of several surfaces. A pixel with no expected signal in any tap is invalid (no return)."""
    _check_frames_and_exposure(num_frames, exposure)
    means = _to_tensor(tap_means_e, "tap_means_e").float()
    if means.ndim < 2 or means.shape[0] != calib.num_taps:
        raise ValueError(
            f"tap_means_e: expected ({calib.num_taps}, ...) with the taps on axis 0, got {tuple(means.shape)}"
        )
    finite = torch.isfinite(means).all(dim=0)
    means = torch.where(finite.unsqueeze(0), means, torch.zeros_like(means))
    in_valid = finite & (means.sum(dim=0) > 0)
    mean_signal = (means * float(exposure)).clamp_min(0.0).contiguous()
    return _frames_from_means(
        mean_signal, in_valid, calib, num_frames, generator, quantize, return_taps, min_amplitude_e, chunk_frames
    )


def _frames_from_means(
    mean_signal: torch.Tensor,
    in_valid: torch.Tensor,
    calib: SensorCalibration,
    num_frames: int,
    generator: torch.Generator | None,
    quantize: bool,
    return_taps: bool,
    min_amplitude_e: float | None,
    chunk_frames: int | None,
) -> CaptureFrames:
    """Noisy frames from the expected signal electrons per tap (N, ...) and the input validity (...)."""
    shape, device = tuple(in_valid.shape), in_valid.device
    n_pix = int(np.prod(shape))
    if chunk_frames is None:
        chunk_frames = max(1, DEFAULT_CHUNK_ELEMENTS // max(1, n_pix * calib.num_taps))
    thr = default_min_amplitude_e(calib) if min_amplitude_e is None else float(min_amplitude_e)
    pattern = _pattern(calib, shape)
    offsets = None
    if pattern is not None:  # PRNU scales the returned signal; the tap offsets join the dark offset
        mean_signal = mean_signal * torch.from_numpy(pattern.gain).to(device)
        offsets = torch.from_numpy(pattern.tap_offset_e).to(device)

    f = int(num_frames)
    depth_out = torch.empty((f, *shape), dtype=torch.float32, device=device)
    amp_out = torch.empty_like(depth_out)
    valid_out = torch.empty((f, *shape), dtype=torch.bool, device=device)
    sat_out = torch.empty_like(valid_out)
    taps_out = torch.empty((f, calib.num_taps, *shape), dtype=torch.float32, device=device) if return_taps else None
    for start in range(0, f, chunk_frames):
        stop = min(f, start + chunk_frames)
        taps, saturated = simulate_taps_chunk(mean_signal, calib, stop - start, generator, quantize, offsets)
        depth, amplitude = demodulate(taps, calib, tap_axis=1)
        valid = in_valid.unsqueeze(0) & ~saturated & (amplitude >= thr)
        depth_out[start:stop] = torch.where(valid, depth, torch.zeros_like(depth))
        amp_out[start:stop] = amplitude
        valid_out[start:stop] = valid
        sat_out[start:stop] = saturated
        if taps_out is not None:
            taps_out[start:stop] = taps
        del taps
    return CaptureFrames(depth_mm=depth_out, amplitude=amp_out, valid=valid_out, saturated=sat_out, taps=taps_out)


def simulate_dark_taps(
    shape: tuple[int, ...],
    calib: SensorCalibration,
    num_frames: int,
    generator: torch.Generator | None = None,
    quantize: bool = True,
) -> torch.Tensor:
    """Emitter-off tap stack (F, N, *shape) [e-]: dark offset + Gaussian dark/read noise (+ ADC)."""
    zeros = torch.zeros((calib.num_taps, *shape), dtype=torch.float32)
    pattern = _pattern(calib, tuple(shape))
    offsets = None if pattern is None else torch.from_numpy(pattern.tap_offset_e)
    taps, _ = simulate_taps_chunk(zeros, calib, num_frames, generator, quantize, offsets)
    return taps


def signal_from_taps_e(taps: torch.Tensor, calib: SensorCalibration, tap_axis: int = -3) -> torch.Tensor:
    """Returned-signal estimate a^ = (mean_n y_n - mu_dark) / c0 (the DC bin; exact in expectation when
    no harmonic k is a multiple of N)."""
    return (taps.mean(dim=tap_axis) - calib.dark_mean_e) / calib.tap_response.c0


__all__ = [
    "CaptureFrames",
    "PhaseDecoder",
    "default_min_amplitude_e",
    "demodulate",
    "gaussian_noise_std_e",
    "phase_decoder",
    "signal_from_taps_e",
    "simulate_dark_taps",
    "simulate_frames",
    "simulate_tap_mean_frames",
    "simulate_taps_chunk",
]
