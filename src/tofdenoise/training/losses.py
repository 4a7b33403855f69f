"""Training losses of the paper (Sec. V-A): ``l1``, ``nar`` (noise-aware reconstruction), ``full``.

Public API:

- ``build_loss(name, **kwargs) -> DepthLoss`` (unknown name -> ValueError listing the valid names; unknown
  keyword -> ValueError listing the accepted keywords), ``available_losses() -> ["full", "l1", "nar"]``.
- A loss is an ``nn.Module`` called ``loss(pred, target, sigma_mm, mask) -> scalar Tensor`` with
  ``pred``/``target`` the depth in millimetres (``DepthRestorer`` passes both relative to the same offset) and
  ``sigma_mm``/``mask`` of the same shape, (B, 1, H, W) or (B, H, W). ``loss.terms(...)`` returns a dict with
  the total under ``"loss"`` and the parts (``"l1"``; ``"nar"``; ``"nar"``, ``"grad"``) for logging.

Definitions (Omega = valid pixels, i.e. mask nonzero and target finite; sums run over all images of the
batch, so a batch average pools the valid pixels of its images):

- Charbonnier penalty rho(x) = sqrt(x^2 + eps^2), eps = 1e-3 mm (the paper converts all depth to millimetres:
  rho is a smooth approximation of L1, not a Huber loss with a 1 mm knee).
- Normalised uncertainty sigma~(t) = (sigma_D(t) - min_Omega sigma_D) / (max_Omega sigma_D - min_Omega sigma_D
  + eta), min/max per image over its valid pixels, eta = 1e-6; w(t) = 1 + beta sigma~(t), beta = 0.5.
  A non-finite sigma_D at a valid pixel is treated as the image's largest uncertainty (weight 1 + beta).
- ``l1``   = 1/|Omega| sum_Omega |pred - target|.
- ``nar``  = 1/|Omega| sum_Omega w rho(pred - target).
- ``full`` = nar + lambda_g L_grad, lambda_g = 0.1, with
  L_grad = 1/|Omega| [sum rho(dx pred - dx target) + sum rho(dy pred - dy target)], forward differences
  dx D(y, x) = D(y, x+1) - D(y, x) (dy likewise) that count only where both of their pixels are valid.

Values in invalid pixels (NaN, garbage) never reach the result or the gradient: they are replaced with
``torch.where`` before any arithmetic. A batch without a valid pixel gives exactly 0 with a gradient path
(zero gradient, no NaN).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

from tofdenoise.registry import Registry

__all__ = [
    "charbonnier",
    "normalized_sigma",
    "uncertainty_weight",
    "DepthLoss",
    "L1DepthLoss",
    "NoiseAwareLoss",
    "FullLoss",
    "build_loss",
    "available_losses",
]


def charbonnier(x: Tensor, eps: float = 1e-3) -> Tensor:
    """Charbonnier penalty rho(x) = sqrt(x^2 + eps^2) (paper Eq. for rho)."""
    return torch.sqrt(x * x + eps * eps)


def _prepare(pred: Tensor, target: Tensor, sigma_mm: Tensor | None, mask: Tensor) -> tuple[Tensor, ...]:
    """Check shapes, bring to (B, 1, H, W) and build the valid map; invalid values replaced by 0."""

    def b1hw(x: Tensor, name: str) -> Tensor:
        if x.ndim == 3:
            return x[:, None]
        if x.ndim == 4 and x.shape[1] == 1:
            return x
        raise ValueError(f"loss input '{name}': expected shape (B, 1, H, W) or (B, H, W), got {tuple(x.shape)}")

    pred = b1hw(pred, "pred")
    target = b1hw(target, "target")
    mask = b1hw(mask, "mask")
    if target.shape != pred.shape or mask.shape != pred.shape:
        raise ValueError(
            f"loss inputs differ in shape: pred {tuple(pred.shape)}, target {tuple(target.shape)}, "
            f"mask {tuple(mask.shape)}"
        )
    valid = (mask != 0) & torch.isfinite(target)
    if mask.is_floating_point():
        valid = valid & ~torch.isnan(mask)
    zero = pred.new_zeros(())
    pred_v = torch.where(valid, pred, zero)
    target_v = torch.where(valid, target.to(pred.dtype), zero)
    if sigma_mm is not None:
        sigma_mm = b1hw(sigma_mm, "sigma_mm")
        if sigma_mm.shape != pred.shape:
            raise ValueError(f"loss input 'sigma_mm' shape {tuple(sigma_mm.shape)} != pred {tuple(pred.shape)}")
    return pred_v, target_v, sigma_mm, valid


def normalized_sigma(sigma_mm: Tensor, valid: Tensor, eta: float = 1e-6) -> Tensor:
    """Per-image min-max normalised depth uncertainty sigma~ over valid pixels (0 where invalid).

    sigma~ = (sigma - min_Omega sigma) / (max_Omega sigma - min_Omega sigma + eta). Non-finite sigma values at
    valid pixels are mapped to 1 (the largest uncertainty). Input/output (B, 1, H, W); no gradient.
    """
    sigma = sigma_mm.detach()
    if not sigma.is_floating_point():
        sigma = sigma.float()
    finite = valid & torch.isfinite(sigma)
    inf = torch.tensor(float("inf"), dtype=sigma.dtype, device=sigma.device)
    s_min = torch.where(finite, sigma, inf).amin(dim=(1, 2, 3), keepdim=True)
    s_max = torch.where(finite, sigma, -inf).amax(dim=(1, 2, 3), keepdim=True)
    has = torch.isfinite(s_min) & torch.isfinite(s_max)
    s_min = torch.where(has, s_min, 0.0)
    s_max = torch.where(has, s_max, 0.0)
    s = torch.where(finite, sigma, s_min)
    norm = (s - s_min) / (s_max - s_min + eta)
    norm = torch.where(valid & ~torch.isfinite(sigma), 1.0, norm)
    return torch.where(valid, norm, 0.0)


def uncertainty_weight(sigma_mm: Tensor, valid: Tensor, beta: float = 0.5, eta: float = 1e-6) -> Tensor:
    """w(t) = 1 + beta * sigma~(t) (paper Eq. for w); 0 at invalid pixels."""
    return torch.where(valid, 1.0 + beta * normalized_sigma(sigma_mm, valid, eta), 0.0)


def _valid_count(valid: Tensor, like: Tensor) -> Tensor:
    return valid.sum().to(like.dtype).clamp(min=1.0)


class DepthLoss(nn.Module):
    """Base class: ``forward(pred, target, sigma_mm, mask) -> scalar``; ``terms(...)`` gives the parts."""

    name: str = ""

    def __init__(self) -> None:  # no keywords: ``build_loss`` lists what each loss accepts from its signature
        super().__init__()

    def terms(self, pred: Tensor, target: Tensor, sigma_mm: Tensor | None, mask: Tensor) -> dict[str, Tensor]:
        raise NotImplementedError

    def forward(self, pred: Tensor, target: Tensor, sigma_mm: Tensor | None, mask: Tensor) -> Tensor:
        return self.terms(pred, target, sigma_mm, mask)["loss"]


class L1DepthLoss(DepthLoss):
    """``l1``: mean absolute error over valid pixels (sigma_mm is ignored)."""

    name = "l1"

    def terms(self, pred: Tensor, target: Tensor, sigma_mm: Tensor | None, mask: Tensor) -> dict[str, Tensor]:
        p, t, _, valid = _prepare(pred, target, None, mask)
        l1 = (p - t).abs().sum() / _valid_count(valid, p)
        return {"loss": l1, "l1": l1.detach()}


class NoiseAwareLoss(DepthLoss):
    """``nar``: L_nar = 1/|Omega| sum_Omega w(t) rho(pred - target), w = 1 + beta sigma~_D."""

    name = "nar"

    def __init__(self, beta: float = 0.5, eps: float = 1e-3, eta: float = 1e-6) -> None:
        super().__init__()
        if beta < 0:
            raise ValueError(f"loss kwarg 'beta' must be >= 0, got {beta}")
        if eps <= 0:
            raise ValueError(f"loss kwarg 'eps' (Charbonnier) must be > 0, got {eps}")
        if eta <= 0:
            raise ValueError(f"loss kwarg 'eta' must be > 0, got {eta}")
        self.beta, self.eps, self.eta = float(beta), float(eps), float(eta)

    def extra_repr(self) -> str:
        return f"beta={self.beta}, eps={self.eps}, eta={self.eta}"

    def _nar(self, p: Tensor, t: Tensor, sigma_mm: Tensor | None, valid: Tensor) -> Tensor:
        if sigma_mm is None:
            raise ValueError(f"loss '{self.name}' needs the sigma_D map (batch key 'sigma'); got sigma_mm=None")
        w = uncertainty_weight(sigma_mm, valid, self.beta, self.eta).to(p.dtype)
        rho = torch.where(valid, charbonnier(p - t, self.eps), 0.0)
        return (w * rho).sum() / _valid_count(valid, p)

    def terms(self, pred: Tensor, target: Tensor, sigma_mm: Tensor | None, mask: Tensor) -> dict[str, Tensor]:
        p, t, s, valid = _prepare(pred, target, sigma_mm, mask)
        nar = self._nar(p, t, s, valid)
        return {"loss": nar, "nar": nar.detach()}


def gradient_consistency(p: Tensor, t: Tensor, valid: Tensor, eps: float = 1e-3) -> Tensor:
    """L_grad = 1/|Omega| [sum rho(dx p - dx t) + sum rho(dy p - dy t)] over differences with both pixels valid."""
    e = p - t
    vx = valid[..., :, 1:] & valid[..., :, :-1]
    vy = valid[..., 1:, :] & valid[..., :-1, :]
    gx = torch.where(vx, charbonnier(e[..., :, 1:] - e[..., :, :-1], eps), 0.0)
    gy = torch.where(vy, charbonnier(e[..., 1:, :] - e[..., :-1, :], eps), 0.0)
    return (gx.sum() + gy.sum()) / _valid_count(valid, p)


class FullLoss(NoiseAwareLoss):
    """``full``: L_full = L_nar + lambda_g L_grad (paper Eq. for L_full)."""

    name = "full"

    def __init__(self, beta: float = 0.5, eps: float = 1e-3, eta: float = 1e-6, lambda_g: float = 0.1) -> None:
        super().__init__(beta=beta, eps=eps, eta=eta)
        if lambda_g < 0:
            raise ValueError(f"loss kwarg 'lambda_g' must be >= 0, got {lambda_g}")
        self.lambda_g = float(lambda_g)

    def extra_repr(self) -> str:
        return super().extra_repr() + f", lambda_g={self.lambda_g}"

    def terms(self, pred: Tensor, target: Tensor, sigma_mm: Tensor | None, mask: Tensor) -> dict[str, Tensor]:
        p, t, s, valid = _prepare(pred, target, sigma_mm, mask)
        nar = self._nar(p, t, s, valid)
        grad = gradient_consistency(p, t, valid, self.eps)
        return {"loss": nar + self.lambda_g * grad, "nar": nar.detach(), "grad": grad.detach()}


LOSSES: Registry[DepthLoss] = Registry("loss")
LOSSES.register("l1")(L1DepthLoss)
LOSSES.register("nar")(NoiseAwareLoss)
LOSSES.register("full")(FullLoss)


def available_losses() -> list[str]:
    """Registered loss names, sorted."""
    return sorted(LOSSES.names())


def build_loss(name: str, **kwargs: Any) -> DepthLoss:
    """Instantiate a loss by name with plain keyword values (e.g. from ``configs/loss/<name>.yaml``).

    Args:
        name: ``l1``, ``nar`` (uncertainty-weighted Charbonnier) or ``full`` (``nar`` plus gradient consistency);
            ``available_losses()`` lists them. Matched without regard to case.
        **kwargs: the loss's settings: ``beta``, ``eps``, ``eta`` of ``nar`` and ``full``, ``lambda_g`` of ``full``.

    Raises:
        ValueError: an unknown name or keyword argument; the message lists what is accepted.
    """
    return LOSSES.build(name, **kwargs)
