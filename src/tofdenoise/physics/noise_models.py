"""Depth noise models for synthesis, chosen by name: `hetero`, `range`, `fixed`, `blind`, `none`.

All models add zero-mean Gaussian depth noise D_noisy = D + s(p) eps(p), eps ~ N(0, 1), with a
per-pixel standard deviation s(p) [mm]:

- `hetero` (the paper's model, Eq. 18): s = scale * sigma_D(p), the WLS depth uncertainty map.
- `range` (range-aware Gaussian baseline, Sec. IV): s = scale * (alpha0 + alpha1 D + alpha2 D^2), D in mm,
  clamped at 0; coefficients from `calib.range_sigma_mm` or the `alpha_mm` keyword.
- `fixed` (scene-independent Gaussian): s = scale * sigma_mm everywhere (default sigma_mm = 5.0 mm, the
  default calibration's sigma_D at 1 m for a = 17.9 ke-, a mid-interval signal).
- `blind` (noise-level-blind Gaussian, beyond the paper): one s per image, drawn log-uniformly from
  [sigma_lo_mm, sigma_hi_mm] (the datamodule sets them to the 5th and 95th percentiles of the hetero sigma_D over
  the training pixels), the same s at every pixel of that image: how blind denoisers are trained (a random
  noise level per image, no noise map). Log-uniform, not uniform: sigma_D spans a ratio (p95/p5 of 5-18 on the
  default worlds), and a uniform draw over such a range would give the quietest octave a few per cent of the
  images although a quarter of the pixels live there; log-uniform gives every octave the same share.
- `none`: s = 0 (clean input; useful for sanity checks).

`scale` multiplies the STANDARD DEVIATION (the variance scales by scale^2). `variance_matching_scale`
returns the scale that makes a model's mean perturbation variance equal to the hetero model's mean
variance sigma_D^2 over the same valid pixels (the paper's controlled comparison), each pixel weighted by how often
training draws it where weights are given (a random crop covers a map's border less often than its centre).

Sampling takes an explicit `torch.Generator`, so validation/test noise is reproducible. Invalid pixels
(mask False, non-finite depth or std, depth <= 0) are returned unchanged.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, replace
from typing import Any

import torch

from tofdenoise.physics.calibration import SensorCalibration
from tofdenoise.registry import Registry

DEFAULT_FIXED_SIGMA_MM: float = 5.0


def _tensor(x: Any, like: torch.Tensor | None = None) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        t = x
    else:
        t = torch.as_tensor(x)
    if like is not None:
        t = t.to(device=like.device)
    if not torch.is_floating_point(t):
        t = t.float()
    return t


def _randn_like(x: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
    """Standard normal noise shaped like x; the generator's device is honoured (moved to x's device)."""
    if generator is None:
        return torch.randn(x.shape, dtype=x.dtype, device=x.device)
    gen_device = generator.device
    if gen_device.type == x.device.type:
        return torch.randn(x.shape, dtype=x.dtype, device=x.device, generator=generator)
    return torch.randn(x.shape, dtype=x.dtype, device=gen_device, generator=generator).to(x.device)


@dataclass(frozen=True)
class NoiseModel:
    """Base class: zero-mean Gaussian depth noise with a per-pixel std `std_mm(depth_mm, sigma_d_mm)`."""

    name: str = "base"
    scale: float = 1.0

    def base_std_mm(self, depth_mm: torch.Tensor, sigma_d_mm: torch.Tensor | None) -> torch.Tensor:
        raise NotImplementedError

    def std_mm(self, depth_mm: Any, sigma_d_mm: Any = None) -> torch.Tensor:
        """Per-pixel standard deviation [mm] (scale included), same shape as depth_mm."""
        d = _tensor(depth_mm)
        s = None if sigma_d_mm is None else _tensor(sigma_d_mm, like=d)
        return self.scale * self.base_std_mm(d, s)

    def valid_mask(self, depth_mm: torch.Tensor, std: torch.Tensor, valid: Any = None) -> torch.Tensor:
        ok = torch.isfinite(depth_mm) & (depth_mm > 0) & torch.isfinite(std)
        if valid is not None:
            v = _tensor(valid, like=depth_mm) if not isinstance(valid, torch.Tensor) else valid.to(depth_mm.device)
            ok = ok & (v.bool() if v.dtype != torch.bool else v)
        return ok

    def sample(
        self,
        depth_mm: Any,
        sigma_d_mm: Any = None,
        valid: Any = None,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """Noisy depth D + s eps on valid pixels; invalid pixels are returned as they are."""
        d = _tensor(depth_mm)
        return self._add_noise(d, self.std_mm(d, sigma_d_mm), valid, generator)

    def _add_noise(
        self, d: torch.Tensor, std: torch.Tensor, valid: Any, generator: torch.Generator | None
    ) -> torch.Tensor:
        """``d + std eps`` on the valid pixels (``valid_mask``), ``d`` elsewhere; ``std`` broadcast to ``d``."""
        std = torch.broadcast_to(std, d.shape)
        ok = self.valid_mask(d, std, valid)
        eps = _randn_like(d, generator)
        noisy = d + torch.where(ok, std, torch.zeros_like(std)) * eps
        return torch.where(ok, noisy, d)

    def with_scale(self, scale: float) -> NoiseModel:
        """A copy with the std multiplier set to `scale` (replaces, does not compound)."""
        scale = float(scale)
        if not math.isfinite(scale) or scale < 0:
            raise ValueError(f"noise scale must be a finite number >= 0, got {scale}")
        return replace(self, scale=scale)


@dataclass(frozen=True)
class HeteroNoise(NoiseModel):
    """D + sigma_D(p) eps(p) (paper Eq. 18): the WLS depth uncertainty map, passed in as sigma_d_mm."""

    name: str = "hetero"

    def base_std_mm(self, depth_mm: torch.Tensor, sigma_d_mm: torch.Tensor | None) -> torch.Tensor:
        if sigma_d_mm is None:
            raise ValueError("hetero noise needs the sigma_D map (sigma_d_mm), got None")
        return sigma_d_mm


@dataclass(frozen=True)
class RangeNoise(NoiseModel):
    """Range-aware Gaussian: sigma(D) = alpha0 + alpha1 D + alpha2 D^2 (D in mm), clamped at 0."""

    name: str = "range"
    alpha_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def base_std_mm(self, depth_mm: torch.Tensor, sigma_d_mm: torch.Tensor | None) -> torch.Tensor:
        a0, a1, a2 = self.alpha_mm
        return (a0 + depth_mm * (a1 + a2 * depth_mm)).clamp_min(0.0)


@dataclass(frozen=True)
class FixedNoise(NoiseModel):
    """Scene-independent Gaussian: one sigma_mm for every pixel."""

    name: str = "fixed"
    sigma_mm: float = DEFAULT_FIXED_SIGMA_MM

    def base_std_mm(self, depth_mm: torch.Tensor, sigma_d_mm: torch.Tensor | None) -> torch.Tensor:
        return torch.full_like(depth_mm, float(self.sigma_mm))


@dataclass(frozen=True)
class BlindNoise(NoiseModel):
    """Noise-level-blind Gaussian: per image one sigma ~ log-uniform [sigma_lo_mm, sigma_hi_mm], i.i.d. over its
    pixels. An image is a (H, W) or (1, H, W) tensor; a 4-D (B, C, H, W) batch draws one sigma per batch item."""

    name: str = "blind"
    sigma_lo_mm: float = 1.0
    sigma_hi_mm: float = 10.0

    def draw_sigma_mm(self, count: int, generator: torch.Generator | None) -> torch.Tensor:
        """``count`` per-image sigmas [mm] (scale included), log-uniform on [sigma_lo_mm, sigma_hi_mm]."""
        u = torch.rand((count,), generator=generator, dtype=torch.float64)
        lo, hi = math.log(self.sigma_lo_mm), math.log(self.sigma_hi_mm)
        return self.scale * torch.exp(lo + (hi - lo) * u)

    def base_std_mm(self, depth_mm: torch.Tensor, sigma_d_mm: torch.Tensor | None) -> torch.Tensor:
        # the geometric mean of the range: what std_mm reports without a draw (sample() draws per image)
        return torch.full_like(depth_mm, math.sqrt(self.sigma_lo_mm * self.sigma_hi_mm))

    def sample(
        self,
        depth_mm: Any,
        sigma_d_mm: Any = None,
        valid: Any = None,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        d = _tensor(depth_mm)
        count = int(d.shape[0]) if d.dim() == 4 else 1
        sigma = self.draw_sigma_mm(count, generator).to(device=d.device, dtype=d.dtype)
        std = sigma.view(-1, *([1] * (d.dim() - 1))) if d.dim() == 4 else sigma.view(*([1] * d.dim()))
        return self._add_noise(d, std, valid, generator)


@dataclass(frozen=True)
class NoNoise(NoiseModel):
    """No perturbation (std 0)."""

    name: str = "none"

    def base_std_mm(self, depth_mm: torch.Tensor, sigma_d_mm: torch.Tensor | None) -> torch.Tensor:
        return torch.zeros_like(depth_mm)


def _check_scale(scale: Any) -> float:
    try:
        s = float(scale)
    except (TypeError, ValueError):
        raise ValueError(f"noise kwarg 'scale' must be a number, got {scale!r}") from None
    if not math.isfinite(s) or s < 0:
        raise ValueError(f"noise kwarg 'scale' must be a finite number >= 0, got {scale!r}")
    return s


NOISE_MODELS: Registry[NoiseModel] = Registry("noise model")


@NOISE_MODELS.register("hetero")
def _hetero(calib: SensorCalibration | None = None, scale: float = 1.0) -> NoiseModel:
    return HeteroNoise(scale=_check_scale(scale))


@NOISE_MODELS.register("range")
def _range(calib: SensorCalibration | None = None, scale: float = 1.0, alpha_mm: Any = None) -> NoiseModel:
    if alpha_mm is None:
        if calib is None or calib.range_sigma_mm is None:
            raise ValueError(
                "noise model 'range' needs coefficients: pass alpha_mm=[alpha0, alpha1, alpha2] or a "
                "calibration with range_sigma_mm set"
            )
        alpha_mm = calib.range_sigma_mm
    alpha_t = tuple(float(v) for v in alpha_mm)
    if len(alpha_t) != 3 or not all(math.isfinite(v) for v in alpha_t):
        raise ValueError(f"noise kwarg 'alpha_mm' must be 3 finite numbers, got {alpha_mm!r}")
    return RangeNoise(alpha_mm=alpha_t, scale=_check_scale(scale))  # type: ignore[arg-type]


@NOISE_MODELS.register("fixed")
def _fixed(
    calib: SensorCalibration | None = None, scale: float = 1.0, sigma_mm: float = DEFAULT_FIXED_SIGMA_MM
) -> NoiseModel:
    sigma = float(sigma_mm)
    if not math.isfinite(sigma) or sigma < 0:
        raise ValueError(f"noise kwarg 'sigma_mm' must be a finite number >= 0, got {sigma}")
    return FixedNoise(sigma_mm=sigma, scale=_check_scale(scale))


def _positive_mm(value: Any, what: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"noise kwarg '{what}' must be a number of mm, got {value!r}") from None
    if not math.isfinite(v) or v <= 0:
        raise ValueError(f"noise kwarg '{what}' must be a finite number > 0 (mm), got {value!r}")
    return v


@NOISE_MODELS.register("blind")
def _blind(
    calib: SensorCalibration | None = None,
    scale: float = 1.0,
    sigma_lo_mm: float | None = None,
    sigma_hi_mm: float | None = None,
) -> NoiseModel:
    if sigma_lo_mm is None or sigma_hi_mm is None:
        raise ValueError(
            "noise model 'blind' needs its sigma range: sigma_lo_mm and sigma_hi_mm (the datamodule sets them from "
            "the training split's sigma_D percentiles, data.blind_percentiles)"
        )
    lo, hi = _positive_mm(sigma_lo_mm, "sigma_lo_mm"), _positive_mm(sigma_hi_mm, "sigma_hi_mm")
    if lo > hi:
        raise ValueError(f"noise kwargs: sigma_lo_mm ({lo}) must not exceed sigma_hi_mm ({hi})")
    return BlindNoise(sigma_lo_mm=lo, sigma_hi_mm=hi, scale=_check_scale(scale))


@NOISE_MODELS.register("none")
def _none(calib: SensorCalibration | None = None, scale: float = 1.0) -> NoiseModel:
    return NoNoise(scale=_check_scale(scale))


def available_noise_models() -> list[str]:
    """Registered noise model names, the paper's ``hetero`` first."""
    return NOISE_MODELS.names()


def build_noise_model(name: str, calib: SensorCalibration | None = None, **kwargs: Any) -> NoiseModel:
    """Build a noise model by name.

    Args:
        name: one of ``available_noise_models()``: ``hetero`` (the paper's sensor-intrinsic sigma_D),
            ``range``, ``fixed``, ``blind`` or ``none``.
        calib: the sensor calibration (None: the default one).
        **kwargs: the model's settings. All models take ``scale`` (std multiplier, default 1); ``range`` takes
            ``alpha_mm`` ([alpha0, alpha1, alpha2]; default: ``calib.range_sigma_mm``); ``fixed`` takes
            ``sigma_mm`` (default 5.0); ``blind`` takes ``sigma_lo_mm`` and ``sigma_hi_mm`` (required; the
            datamodule supplies them).

    Raises:
        ValueError: an unknown name or keyword argument; the message lists what is accepted.
    """
    return NOISE_MODELS.build(name, calib=calib, **kwargs)


def variance_matching_scale(model: NoiseModel, samples: Iterable[tuple[Any, ...]]) -> float:
    """Scale k such that model.with_scale(k) has the hetero model's mean perturbation variance.

    samples: iterable of (depth_mm, sigma_d_mm, valid) or (depth_mm, sigma_d_mm, valid, weight); valid and weight
    may be None. Over the pixels that are valid for both models,
    k^2 sum(w s_model^2) = sum(w sigma_D^2), with s_model at scale 1 (the model's own scale is ignored) and w the
    per-pixel weight (1 without one): how often training draws the pixel, e.g. its crop coverage
    (``transforms.crop_coverage``), so that the two models put the same expected variance into what a network is
    trained on. Raises ValueError when the model's variance is zero (e.g. `none`), no pixel is valid, or a weight is
    negative or not finite.
    """
    base = model.with_scale(1.0)
    hetero = HeteroNoise()
    sum_model = 0.0
    sum_hetero = 0.0
    count = 0
    for i, item in enumerate(samples):
        try:
            depth_mm, sigma_d_mm, valid, *rest = item
            if len(rest) > 1:
                raise ValueError
        except (TypeError, ValueError):
            raise ValueError(f"samples[{i}] must be a (depth_mm, sigma_d_mm, valid[, weight]) tuple") from None
        d = _tensor(depth_mm)
        s_het = torch.broadcast_to(hetero.std_mm(d, sigma_d_mm), d.shape)
        s_mod = torch.broadcast_to(base.std_mm(d, sigma_d_mm), d.shape)
        ok = hetero.valid_mask(d, s_het, valid) & torch.isfinite(s_mod)
        w = None if not rest or rest[0] is None else torch.broadcast_to(_tensor(rest[0]).double(), d.shape)
        if w is not None and not bool((torch.isfinite(w) & (w >= 0)).all()):
            raise ValueError(f"samples[{i}]: weights must be finite and >= 0")
        if w is not None:
            ok = ok & (w > 0)
        w_ok = 1.0 if w is None else w[ok]
        sum_model += float((w_ok * s_mod[ok].double().pow(2)).sum())
        sum_hetero += float((w_ok * s_het[ok].double().pow(2)).sum())
        count += int(ok.sum())
    if count == 0:
        raise ValueError("variance matching: no valid pixel in the samples")
    if sum_model <= 0:
        raise ValueError(f"variance matching: noise model '{model.name}' has zero variance; nothing to scale")
    return math.sqrt(sum_hetero / sum_model)


__all__ = [
    "BlindNoise",
    "DEFAULT_FIXED_SIGMA_MM",
    "FixedNoise",
    "HeteroNoise",
    "NOISE_MODELS",
    "NoNoise",
    "NoiseModel",
    "RangeNoise",
    "available_noise_models",
    "build_noise_model",
    "variance_matching_scale",
]
