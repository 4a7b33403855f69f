"""Depth restoration metrics over valid pixels (paper Sec. V-A): PSNR, MAE, MSE, SSIM.

Public API (used by the LightningModule, the callbacks and ``tofdenoise evaluate``):

- ``METRIC_KEYS = ("psnr_db", "mae_mm", "mse_mm2", "ssim")``
- ``valid_pixel_mask(ref_mm, mask=None, pred_mm=None) -> BoolTensor``
- ``depth_metrics_per_image(pred_mm, ref_mm, mask, d_max_mm=1000.0) -> dict[str, Tensor(B,)]``
  (the four keys plus ``valid_px``; an image without a valid pixel gets NaN in the four keys)
- ``masked_ssim_map(pred_mm, ref_mm, valid, data_range) -> Tensor(B,1,H,W)``
- ``depth_edge_mask(ref_mm, jump_mm=EDGE_JUMP_MM) -> BoolTensor``: the pixels next to a depth step of the
  reference (where an iToF pixel's footprint mixes two depths: flying pixels), for metrics split by region
- ``DepthMetrics(d_max_mm=1000.0)``: a ``torchmetrics.Metric`` with
  ``update(pred_mm, ref_mm, mask, index=None)``, ``compute() -> {"psnr_db", "mae_mm", "mse_mm2", "ssim",
  "mae_mm_pooled"}`` (per-image means, plus the pixel-pooled MAE), ``counts() -> {"images",
  "skipped_images", "valid_px"}`` and ``per_image_rows() -> list[dict]`` (one row per image:
  ``index``, ``valid_px`` and the four keys, sorted by index) for the per-image CSV. Its state is the
  per-image rows; every result is computed over UNIQUE image indices, so under DDP the samples that the
  ``DistributedSampler`` repeats to pad the last batch count once (results equal the single-process ones).

Protocol (the paper's): every metric is computed over the valid pixels of each image and then averaged over
images. A pixel is valid where ``mask`` is nonzero, the reference is finite and > 0, and the prediction is
finite. Values in invalid pixels never influence any result (they are replaced before any arithmetic).
An image with no valid pixel is skipped by :class:`DepthMetrics` and counted in ``skipped_images``.

- ``mse_mm2`` = mean over valid pixels of (pred - ref)^2 [mm^2]; ``mae_mm`` = mean of |pred - ref| [mm].
- ``psnr_db`` = 10 log10(D_max^2 / MSE) with the fixed peak D_max = 1000 mm; nothing is clamped, so a large
  error lowers PSNR as it should (MSE = 0 gives +inf).
- ``ssim``: Gaussian window (sigma 1.5, 11 x 11), K1 = 0.01, K2 = 0.03, data range D_max. The local
  statistics (means, variances, covariance) are Gaussian-weighted averages over the VALID pixels of the
  window only (normalised convolution), with reflect padding at the image border; the SSIM map is then
  averaged over the valid pixels. On a fully valid image this equals torchmetrics'
  ``structural_similarity_index_measure(..., data_range=D_max)`` exactly (tested).

All accumulation is float64.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor
from torchmetrics import Metric
from torchmetrics.utilities.data import dim_zero_cat

from tofdenoise.records.metrics_json import EDGE_JUMP_MM, METRIC_KEYS

__all__ = [
    "FixedBatchCache",
    "METRIC_KEYS",
    "D_MAX_MM",
    "SSIM_SIGMA",
    "SSIM_K1",
    "SSIM_K2",
    "valid_pixel_mask",
    "gaussian_window_1d",
    "masked_ssim_map",
    "EDGE_JUMP_MM",
    "depth_edge_mask",
    "psnr_from_mse_db",
    "depth_metrics_per_image",
    "DepthMetrics",
    "ROW_COLUMNS",
]


D_MAX_MM: float = 1000.0
SSIM_SIGMA: float = 1.5
SSIM_K1: float = 0.01
SSIM_K2: float = 0.03


def _as_b1hw(x: Tensor | Any, name: str) -> Tensor:
    """Return ``x`` as a (B, 1, H, W) tensor; accepts (H, W), (B, H, W) or (B, 1, H, W)."""
    if not isinstance(x, Tensor):
        x = torch.as_tensor(x)
    if x.ndim == 2:
        return x[None, None]
    if x.ndim == 3:
        return x[:, None]
    if x.ndim == 4 and x.shape[1] == 1:
        return x
    raise ValueError(f"{name}: expected shape (H, W), (B, H, W) or (B, 1, H, W), got {tuple(x.shape)}")


def valid_pixel_mask(ref_mm: Tensor, mask: Tensor | None = None, pred_mm: Tensor | None = None) -> Tensor:
    """Boolean map of the pixels that count: ref finite and > 0, mask nonzero, prediction finite.

    All inputs must have the same shape; the result has that shape.
    """
    valid = torch.isfinite(ref_mm) & (ref_mm > 0)
    if mask is not None:
        if mask.shape != ref_mm.shape:
            raise ValueError(f"mask shape {tuple(mask.shape)} != reference shape {tuple(ref_mm.shape)}")
        valid = valid & (mask != 0)
        if mask.is_floating_point():
            valid = valid & ~torch.isnan(mask)
    if pred_mm is not None:
        if pred_mm.shape != ref_mm.shape:
            raise ValueError(f"prediction shape {tuple(pred_mm.shape)} != reference shape {tuple(ref_mm.shape)}")
        valid = valid & torch.isfinite(pred_mm)
    return valid


def gaussian_window_1d(
    sigma: float = SSIM_SIGMA, dtype: torch.dtype = torch.float64, device: torch.device | None = None
) -> Tensor:
    """Normalised 1-D Gaussian of odd size ``2 * int(3.5 sigma + 0.5) + 1`` (11 taps for sigma = 1.5)."""
    half = int(3.5 * sigma + 0.5)
    x = torch.arange(-half, half + 1, dtype=dtype, device=device)
    g = torch.exp(-0.5 * (x / sigma) ** 2)
    return g / g.sum()


def _gaussian_filter(x: Tensor, window: Tensor) -> Tensor:
    """Separable Gaussian filter of a (N, 1, H, W) tensor, reflect padding, output (N, 1, H, W).

    Written as weighted sums of shifted views (in-place adds): exact like a convolution, and for float64 faster
    than ``conv2d`` on CPU (docs/benchmarks.md, "Metrics").
    """
    taps = window.numel()
    pad = (taps - 1) // 2
    h, w = x.shape[-2:]
    mode = "reflect" if (h > pad and w > pad) else "replicate"
    xp = F.pad(x, (pad, pad, pad, pad), mode=mode)
    weights = [float(v) for v in window]
    rows = xp[..., :, 0:w] * weights[0]
    for k in range(1, taps):
        rows.add_(xp[..., :, k : k + w], alpha=weights[k])
    out = rows[..., 0:h, :] * weights[0]
    for k in range(1, taps):
        out.add_(rows[..., k : k + h, :], alpha=weights[k])
    return out


def masked_ssim_map(
    pred_mm: Tensor,
    ref_mm: Tensor,
    valid: Tensor,
    data_range: float = D_MAX_MM,
    sigma: float = SSIM_SIGMA,
    k1: float = SSIM_K1,
    k2: float = SSIM_K2,
) -> Tensor:
    """SSIM map (Wang et al. 2004) with Gaussian-weighted local statistics restricted to valid pixels.

    mu_x = G*(m x) / G*m, sigma_x^2 = G*(m x^2) / G*m - mu_x^2, sigma_xy likewise (normalised convolution);
    SSIM = (2 mu_x mu_y + C1)(2 sigma_xy + C2) / ((mu_x^2 + mu_y^2 + C1)(sigma_x^2 + sigma_y^2 + C2)),
    C1 = (K1 L)^2, C2 = (K2 L)^2, L = ``data_range``. Inputs (B, 1, H, W); float64 result, NaN where invalid.
    """
    p = torch.where(valid, pred_mm.to(torch.float64), 0.0)
    r = torch.where(valid, ref_mm.to(torch.float64), 0.0)
    m = valid.to(torch.float64)
    window = gaussian_window_1d(sigma, dtype=torch.float64, device=p.device)
    b = p.shape[0]
    stats = _gaussian_filter(torch.cat([m, p * m, r * m, p * p * m, r * r * m, p * r * m]), window)
    w_sum, s_p, s_r, s_pp, s_rr, s_pr = stats.split(b)
    denom = torch.where(w_sum > 0, w_sum, 1.0)
    mu_p, mu_r = s_p / denom, s_r / denom
    var_p = torch.clamp(s_pp / denom - mu_p * mu_p, min=0.0)
    var_r = torch.clamp(s_rr / denom - mu_r * mu_r, min=0.0)
    cov = s_pr / denom - mu_p * mu_r
    c1 = (k1 * data_range) ** 2
    c2 = (k2 * data_range) ** 2
    ssim = ((2 * mu_p * mu_r + c1) * (2 * cov + c2)) / ((mu_p**2 + mu_r**2 + c1) * (var_p + var_r + c2))
    return torch.where(valid, ssim, torch.nan)


@torch.no_grad()
def depth_edge_mask(ref_mm: Tensor, jump_mm: float = EDGE_JUMP_MM) -> Tensor:
    """The pixels at a depth step of the reference: a valid reference pixel (finite, > 0) one of whose 8
    neighbours, also valid, differs from it by more than ``jump_mm``. These are the pixels whose footprint an
    iToF camera mixes from two surfaces (flying pixels at occlusion edges, and grazing surfaces where neighbours
    are that far apart); their error is of another kind than the noise on a surface, so ``tofdenoise evaluate
    --edge-jump-mm`` scores them apart. Invalid neighbours (holes, the image border) make no step.

    Args:
        ref_mm: the reference depth [mm], (H, W), (B, H, W) or (B, 1, H, W).
        jump_mm: the step [mm], > 0.

    Returns:
        Bool, (B, 1, H, W).
    """
    if not jump_mm > 0:
        raise ValueError(f"jump_mm must be > 0, got {jump_mm}")
    ref = _as_b1hw(ref_mm, "ref_mm").to(torch.float64)
    valid = torch.isfinite(ref) & (ref > 0)
    r = torch.where(valid, ref, 0.0)
    padded, pad_valid = F.pad(r, (1, 1, 1, 1)), F.pad(valid.to(torch.float64), (1, 1, 1, 1)) > 0
    height, width = ref.shape[-2:]
    edge = torch.zeros_like(valid)
    for dy in range(3):
        for dx in range(3):
            if dy == dx == 1:
                continue
            near = padded[..., dy : dy + height, dx : dx + width]
            near_valid = pad_valid[..., dy : dy + height, dx : dx + width]
            edge |= near_valid & ((near - r).abs() > jump_mm)
    return edge & valid


def psnr_from_mse_db(mse_mm2: Tensor, d_max_mm: float = D_MAX_MM) -> Tensor:
    """PSNR = 10 log10(D_max^2 / MSE) [dB] (paper Sec. V-A), no clamping; MSE = 0 gives +inf."""
    mse = torch.as_tensor(mse_mm2, dtype=torch.float64)
    return 10.0 * torch.log10(torch.as_tensor(d_max_mm, dtype=torch.float64) ** 2 / mse)


@torch.no_grad()
def depth_metrics_per_image(
    pred_mm: Tensor, ref_mm: Tensor, mask: Tensor | None, d_max_mm: float = D_MAX_MM
) -> dict[str, Tensor]:
    """Per-image ``psnr_db``, ``mae_mm``, ``mse_mm2``, ``ssim`` (float64, shape (B,)) plus ``valid_px``.

    A pixel counts where the mask is nonzero, the reference finite and > 0 and the prediction finite.

    Args:
        pred_mm: the restored depth [mm], (B, 1, H, W), (B, H, W) or (H, W).
        ref_mm: the reference depth [mm], same shape.
        mask: the pixels to score, same shape, or None (then only the validity rules above apply).
        d_max_mm: the fixed PSNR/SSIM peak (paper: 1000 mm).

    Returns:
        ``{"psnr_db", "mae_mm", "mse_mm2", "ssim", "valid_px"}``, float64 (B,) each; images without a valid
        pixel get NaN.

    Raises:
        ValueError: the prediction, the reference and the mask differ in shape.
    """
    pred = _as_b1hw(pred_mm, "pred_mm")
    ref = _as_b1hw(ref_mm, "ref_mm")
    m = None if mask is None else _as_b1hw(mask, "mask")
    if pred.shape != ref.shape:
        raise ValueError(f"pred_mm shape {tuple(pred.shape)} != ref_mm shape {tuple(ref.shape)}")
    valid = valid_pixel_mask(ref, m, pred)
    p = torch.where(valid, pred.to(torch.float64), 0.0)
    r = torch.where(valid, ref.to(torch.float64), 0.0)
    n = valid.sum(dim=(1, 2, 3)).to(torch.float64)
    err = p - r
    n_safe = torch.clamp(n, min=1.0)
    mae = err.abs().sum(dim=(1, 2, 3)) / n_safe
    mse = (err * err).sum(dim=(1, 2, 3)) / n_safe
    ssim_map = masked_ssim_map(p, r, valid, data_range=d_max_mm)
    ssim = torch.where(valid, ssim_map, 0.0).sum(dim=(1, 2, 3)) / n_safe
    psnr = psnr_from_mse_db(mse, d_max_mm)
    empty = n == 0
    nan = torch.tensor(math.nan, dtype=torch.float64, device=p.device)
    return {
        "psnr_db": torch.where(empty, nan, psnr),
        "mae_mm": torch.where(empty, nan, mae),
        "mse_mm2": torch.where(empty, nan, mse),
        "ssim": torch.where(empty, nan, ssim),
        "valid_px": n,
    }


#: columns of one stored per-image row of :class:`DepthMetrics` (the metric's only state)
ROW_COLUMNS: tuple[str, ...] = ("index", "valid_px") + METRIC_KEYS


class DepthMetrics(Metric):
    """Accumulates the depth metrics over batches (and DDP processes), exactly over UNIQUE images.

    The state is one row per image seen (``index``, ``valid_px`` and the four per-image values, float64). Every
    result is computed from the rows gathered from all processes after dropping repeated indices, so the
    samples that Lightning's ``DistributedSampler`` repeats to pad the last batch of a process count once:
    ``compute()``, ``counts()`` and ``per_image_rows()`` under DDP equal the single-process results over the
    same images (the sums run in index order, so they agree to the last bit when the per-image values do).

    - ``compute()``: per-image means of ``psnr_db``, ``mae_mm``, ``mse_mm2``, ``ssim`` (images with no valid
      pixel skipped) and ``mae_mm_pooled`` (all valid pixels pooled: sum of mae x valid_px / sum of valid_px).
    - ``counts()``: ``images`` averaged, ``skipped_images`` (no valid pixel), ``valid_px``.
    - ``per_image_rows()``: the rows for the per-image CSV.

    ``update(..., index=None)``: rows without an index are never merged (each counts); that is exact in one
    process but cannot be made exact under DDP (a padded repeat is indistinguishable from a new image), so an
    update without ``index`` while ``torch.distributed`` runs more than one process (and this metric syncs on
    compute) raises ``ValueError``. Rows with the same index are kept once (the first one seen).

    Args:
        d_max_mm: the fixed PSNR/SSIM peak (paper: 1000 mm).
        **kwargs: torchmetrics' ``Metric`` options (``sync_on_compute``, ``process_group`` ...).
    """

    is_differentiable = False
    higher_is_better = None
    full_state_update = False

    def __init__(self, d_max_mm: float = D_MAX_MM, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        if not d_max_mm > 0:
            raise ValueError(f"d_max_mm must be > 0, got {d_max_mm}")
        self.d_max_mm = float(d_max_mm)
        # per-image rows, stored flat (1-D, len(ROW_COLUMNS) values per image) so that DDP gathering works even
        # for a process that saw no image (torchmetrics then gathers an empty tensor of the metric's dtype)
        self.add_state("rows", default=[], dist_reduce_fx="cat")
        self.set_dtype(torch.float64)

    def _world_size(self) -> int:
        """Processes this metric gathers from on ``compute`` (1 without torch.distributed or without sync)."""
        if not self.sync_on_compute or self.distributed_available_fn is None or not self.distributed_available_fn():
            return 1
        return int(torch.distributed.get_world_size(self.process_group))

    def update(
        self,
        pred_mm: Tensor,
        ref_mm: Tensor,
        mask: Tensor | None,  # type: ignore[override]
        index: Tensor | None = None,
        per_image: dict[str, Tensor] | None = None,
    ) -> None:
        """Accumulate one batch.

        Args:
            pred_mm: the restored depth [mm], shapes as ``depth_metrics_per_image`` takes them.
            ref_mm: the reference depth [mm].
            mask: the pixels to score, or None.
            index: each image's position in its dataset (``batch["index"]``); required under DDP.
            per_image: the batch's values already computed by ``depth_metrics_per_image`` with this metric's
                ``d_max_mm`` (e.g. cached ones that do not change between epochs); the maps are then not
                measured again.

        Raises:
            ValueError: no ``index`` while more than one process runs, or an index that is not a whole number
                >= 0 per image.
        """
        per = per_image if per_image is not None else depth_metrics_per_image(pred_mm, ref_mm, mask, self.d_max_mm)
        n_px = per["valid_px"].to(torch.float64)
        b = n_px.shape[0]
        if index is None:
            world = self._world_size()
            if world > 1:
                raise ValueError(
                    f"DepthMetrics.update: index is required with {world} distributed processes: the "
                    "DistributedSampler repeats samples to pad the last batch, and only the image index tells a "
                    "repeat from a new image (pass index=batch['index'])"
                )
            idx = torch.full((b,), math.nan, dtype=torch.float64, device=n_px.device)
        else:
            idx = torch.as_tensor(index, device=n_px.device).reshape(-1).to(torch.float64)
            if idx.numel() != b:
                raise ValueError(f"index has {idx.numel()} entries for a batch of {b} images")
            if not bool(torch.all((idx >= 0) & (idx == torch.floor(idx)))):
                raise ValueError(f"index must hold non-negative whole numbers, got {idx.tolist()}")
        cols = [idx, n_px] + [per[k].to(torch.float64) for k in METRIC_KEYS]
        self.rows.append(torch.stack(cols, dim=1).reshape(-1))

    def _unique_table(self) -> Tensor:
        """(N, len(ROW_COLUMNS)) float64 rows of the current (local or synced) state: one per distinct index
        (the first seen), sorted by index, then the rows without index in the order seen."""
        rows = self.rows
        if isinstance(rows, list) and not rows:
            return torch.zeros((0, len(ROW_COLUMNS)), dtype=torch.float64, device=self.device)
        table = dim_zero_cat(rows).to(torch.float64).reshape(-1, len(ROW_COLUMNS))
        first: dict[int, int] = {}
        unindexed: list[int] = []
        for pos, idx in enumerate(table[:, 0].tolist()):
            if math.isnan(idx):
                unindexed.append(pos)
            else:
                first.setdefault(int(idx), pos)
        order = [first[i] for i in sorted(first)] + unindexed
        return table[torch.tensor(order, dtype=torch.long, device=table.device)]

    def compute(self) -> dict[str, Tensor]:
        """Per-image means of ``psnr_db``, ``mae_mm``, ``mse_mm2``, ``ssim`` over the unique images with a valid
        pixel, and ``mae_mm_pooled`` (all valid pixels pooled); float64 scalars, NaN when no image counts."""
        table = self._unique_table()
        n_px = table[:, 1]
        ok = n_px > 0
        n = int(ok.sum())
        nan = torch.tensor(math.nan, dtype=torch.float64, device=table.device)
        out = {}
        for col, key in enumerate(METRIC_KEYS, start=2):
            out[key] = table[ok, col].sum() / n if n > 0 else nan
        px = n_px.sum()
        out["mae_mm_pooled"] = (table[ok, 3] * n_px[ok]).sum() / px if px > 0 else nan
        return out

    def _synced(self, fn: Any, sync: bool) -> Any:
        """``fn()`` on the rows of every process (``sync`` and torch.distributed initialised; call it on every
        rank then), else on the local rows."""
        if (
            sync
            and not self._is_synced
            and self.distributed_available_fn is not None
            and self.distributed_available_fn()
        ):
            with self.sync_context():
                return fn()
        return fn()

    def counts(self, sync: bool = True) -> dict[str, int]:
        """Number of (unique) images averaged, images skipped (no valid pixel) and valid pixels.

        Args:
            sync: gather from every process like ``compute()`` (with torch.distributed initialised: call it on
                every rank).

        Returns:
            ``{"images", "skipped_images", "valid_px"}``.
        """

        def local() -> dict[str, int]:
            table = self._unique_table()
            ok = table[:, 1] > 0
            return {
                "images": int(ok.sum()),
                "skipped_images": int((~ok).sum()),
                "valid_px": int(table[:, 1].sum().item()),
            }

        return self._synced(local, sync)

    def per_image_rows(self, sync: bool = True) -> list[dict[str, float | int | None]]:
        """One dict per image (``index`` None where no index was given), sorted by index; rows with equal index
        (DistributedSampler padding) are kept once.

        Args:
            sync: gather the rows of every process (with torch.distributed initialised: call it on every rank).

        Returns:
            ``[{"index", "valid_px", "psnr_db", "mae_mm", "mse_mm2", "ssim"}, ...]``, the per-image CSV's rows.
        """

        def local() -> list[dict[str, float | int | None]]:
            out: list[dict[str, float | int | None]] = []
            for r in self._unique_table().detach().cpu().tolist():
                row: dict[str, float | int | None] = {
                    "index": None if math.isnan(r[0]) else int(r[0]),
                    "valid_px": int(r[1]),
                }
                row.update({k: float(v) for k, v in zip(METRIC_KEYS, r[2:])})
                out.append(row)
            return out

        return self._synced(local, sync)


class FixedBatchCache:
    """Values computed from a batch that repeats every epoch (the validation set under fixed-seed noise), kept
    per loader position and recomputed when the batch at that position ever differs.

    A batch is recognised by its fingerprint: the shape, sum and sum of squares (float64, NaN as 0) of its noisy
    input, reference and mask; any change of the data or its noise changes it."""

    def __init__(self) -> None:
        self._entries: dict[Any, tuple[Tensor, Any]] = {}

    @staticmethod
    def fingerprint(batch: dict[str, Any]) -> Tensor:
        parts = []
        for name in ("noisy", "clean", "mask"):
            x = batch[name].detach().to(torch.float64).nan_to_num(0.0, 0.0, 0.0)
            parts += [torch.tensor(float(x.numel()), dtype=torch.float64, device=x.device), x.sum(), x.square().sum()]
        return torch.stack(parts).cpu()

    def get(self, key: Any, batch: dict[str, Any], compute: Callable[[], Any]) -> Any:
        """The value stored for ``key`` when ``batch`` is the one it was computed from, else ``compute()``."""
        fingerprint = self.fingerprint(batch)
        hit = self._entries.get(key)
        if hit is not None and torch.equal(hit[0], fingerprint):
            return hit[1]
        value = compute()
        self._entries[key] = (fingerprint, value)
        return value
