"""What the network sees: invalid pixels filled, depth centred on a local offset and scaled (pure functions).

Every backbone receives the same conditioned input, in training, validation, test, predict and
``tofdenoise denoise`` (one implementation, called by ``DepthRestorer.condition``):

1. **Holes filled** (:func:`fill_invalid_mm`). Input pixels that are not valid (0, negative, NaN or inf:
   the camera's "no measurement") get a smooth surface continuing their surroundings instead of a 0 that a
   network reads as a 1 m cliff. Valid pixels keep their exact value, so no noise is smoothed away before the
   network. ``fill="harmonic"`` (default): the *pull-push* pyramid (the masked mean of the pixel's 2^k x 2^k
   block at the finest level k whose block holds a valid pixel, bilinearly interpolated) relaxed towards the
   harmonic fill at every level, with the completely valid blocks held fixed (:data:`RELAX_ITERS` red-black
   over-relaxation sweeps of Laplace's equation per level): continuous with the valid pixels at the hole's
   border and exact on planes.
   ``fill="pullpush"`` (checkpoints written before 2026-11-27): the pull-push value alone. A partial block's
   mean sits at the centroid of its valid pixels, not at the block centre, so on a sloped surface the fill is
   off by about one pixel's worth of slope at the border (5 mm at 5 mm/px) and by several inside: a step the
   network reads as a depth edge, and changes the valid pixels next to the hole for it. The restored depth at
   input-invalid pixels is masked again afterwards (``DepthRestorer.predict_step``, ``tofdenoise denoise``
   without ``--fill-holes``).
2. **Centred on a local offset**, a smooth surface that follows the scene. The network's depth channel is
   ``(filled - offset) / depth_scale_mm``: zero-mean noise and detail below ``block_px``, the same for a scene
   at 0.5 m or at 4 m; with ``depth_scale_mm`` = 100 the noise (3-12 mm) is 0.03-0.12 and surface detail of
   order 1. ``centering="gaussian"`` (default, :func:`gaussian_offset_mm`): the filled depth smoothed by a
   Gaussian of sigma ``block_px / 2`` (the bandwidth of the block offset below), the same operation at every
   pixel. ``centering="local"`` (checkpoints written before 2026-11-27, :func:`local_offset_mm`): block means of
   ``block_px`` x ``block_px`` pixels, bilinearly interpolated. That offset is piecewise linear with kinks on
   the block centres (rows and columns at 7.5 mod 16), so on any curved surface the centred input has cusps on
   a 16-pixel grid, and the network's smoothing of them left a faint 16-pixel grid in the restored depth.
3. **The offset is added back exactly** in float32 outside the network: restored = offset +
   depth_scale_mm x network output. Residual backbones add their input channel 0 to their head, so at
   initialisation the restored depth is the filled input itself.

Why (issue "trustworthy runs", items 1 and 7): raw depth / 1000 is positive everywhere (0.3-4), so every
first-layer feature of a ReLU network is roughly (sum of its weights) x depth with one sign over the whole image:
half the channels are dead for every input from the start. Centred but still divided by 1000, the input is
~0.005 (the noise): Adam moves every weight and bias by ~lr (1e-3) per step whatever the gradient's size, so
biases swamp the activations and the last ReLUs die behind the zero-initialised residual head, leaving the network
at the identity (measured: 75 % of the last U-Net block's channels dead after 50 steps; at 100 mm, 12 %). Under bf16
autocast a value in [1, 2) has a step of 2^-7 = 7.8 mm, coarser than
the noise to be removed; bf16 keeps 8 significant bits, so a centred value below 125 mm is resolved to 0.5 mm or
better, whatever the depth of the scene (:func:`bf16_step_mm`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = [
    "valid_input_mask",
    "fill_invalid_mm",
    "gaussian_offset_mm",
    "local_offset_mm",
    "image_offset_mm",
    "bf16_step_mm",
    "condition_input",
    "InputConditioning",
    "DEFAULT_BLOCK_PX",
    "CENTERING_MODES",
    "FILL_MODES",
    "RELAX_ITERS",
]

#: side of the averaging blocks of the local offset, in pixels
DEFAULT_BLOCK_PX = 16
#: ``gaussian`` (default: a Gaussian-smoothed local offset), ``local`` (interpolated block means: the offset of
#: checkpoints written before 2026-11-27), ``image`` (one valid-pixel median per image), ``none`` (no offset)
CENTERING_MODES = ("gaussian", "local", "image", "none")
#: ``harmonic`` (default: pull-push relaxed towards the harmonic fill), ``pullpush`` (checkpoints before 2026-11-27)
FILL_MODES = ("harmonic", "pullpush")
#: red-black sweeps of the harmonic fill per pyramid level (all levels together cost about 1.3 x this many
#: full-size sweeps): on a 5 mm/px plane the fill next to a hole of radius 40 px is within 0.01 mm of the plane,
#: 0.1 mm at its centre (pull-push alone: 9 and 32 mm)
RELAX_ITERS = 8


def valid_input_mask(depth_mm: Tensor) -> Tensor:
    """Boolean map of the measured input pixels: finite and > 0 (0, negatives, NaN and inf are holes)."""
    return torch.isfinite(depth_mm) & (depth_mm > 0)


def _check_b1hw(x: Tensor, name: str) -> None:
    if x.dim() != 4 or x.shape[1] != 1:
        raise ValueError(f"{name}: expected a (B, 1, H, W) tensor, got shape {tuple(x.shape)}")


def _masked_half(values: Tensor, weight: Tensor) -> tuple[Tensor, Tensor]:
    """One pull step: 2 x 2 block sums of ``values * weight`` and of ``weight`` (odd sides: partial blocks).

    One zero row and column are always padded: the floor-mode pooling drops them on an even side and uses them
    for the last partial block on an odd one (the same windows as padding ``side % 2``, with no shape-dependent
    padding, so the exported graph takes any frame size)."""
    v = F.pad(values * weight, (0, 1, 0, 1))
    m = F.pad(weight, (0, 1, 0, 1))
    return F.avg_pool2d(v, 2) * 4.0, F.avg_pool2d(m, 2) * 4.0


#: the 4-neighbour mean (one relaxation step of Laplace's equation)
_NEIGHBOUR_MEAN = ((0.0, 0.25, 0.0), (0.25, 0.0, 0.25), (0.0, 0.25, 0.0))
#: over-relaxation factor of the red-black sweeps (1 = Gauss-Seidel; the optimum for an n-pixel-wide hole is
#: 2 / (1 + sin(pi / n)): 1.7 suits holes of 10-40 px)
SOR_OMEGA = 1.7


def _relax(filled: Tensor, fixed: Tensor, sweeps: int) -> Tensor:
    """``sweeps`` red-black successive over-relaxation sweeps of Laplace's equation over the pixels not ``fixed``
    (image borders: zero normal derivative, by edge replication)."""
    kernel = torch.tensor(_NEIGHBOUR_MEAN, dtype=filled.dtype, device=filled.device).view(1, 1, 3, 3)
    h, w = filled.shape[-2:]
    rows = torch.arange(h, device=filled.device).view(-1, 1)
    cols = torch.arange(w, device=filled.device).view(1, -1)
    black = (rows + cols) % 2 == 1
    for _ in range(sweeps):
        for colour in (~black, black):
            mean = F.conv2d(F.pad(filled, (1, 1, 1, 1), mode="replicate"), kernel)
            filled = torch.where(fixed | ~colour, filled, filled + SOR_OMEGA * (mean - filled))
    return filled


def fill_invalid_mm(
    depth_mm: Tensor, valid: Tensor | None = None, levels: int | None = None, relax_iters: int = 0
) -> Tensor:
    """Depth (B, 1, H, W) with every invalid pixel filled (valid pixels unchanged, float32).

    Pull: level k+1 holds, per 2 x 2 block of level k, the weighted mean of its valid values and the count of
    valid pixels behind it. Push: from the coarsest level down, a level's empty pixels take the bilinear
    interpolation of the filled level above. An image with no valid pixel is returned as zeros.

    ``relax_iters`` > 0 (the ``harmonic`` fill): at every level, after the push, ``relax_iters`` red-black
    over-relaxation sweeps of Laplace's equation move every pixel whose block is not completely valid towards the
    harmonic interpolation of the complete blocks around it (their means are the surface at the block centre,
    where a partial block's mean is biased towards its valid pixels). At the finest level the complete blocks are
    the valid pixels: the fill meets them without a step, and a plane is continued as a plane. 0: pull-push
    alone.

    ``levels``: ``None`` stops pulling at the first complete level (or 1 x 1); a number runs exactly that many
    pull steps with no data-dependent branch (the ONNX export, ``tofdenoise.inference.export``). Both give the
    same values when ``2**levels`` >= the frame's longer side: past the first complete level every pixel keeps
    its own value, and a 1 x 1 level stays 1 x 1.
    """
    _check_b1hw(depth_mm, "fill_invalid_mm(depth_mm)")
    valid = valid_input_mask(depth_mm) if valid is None else valid.bool()
    if valid.shape != depth_mm.shape:
        raise ValueError(f"fill_invalid_mm: valid shape {tuple(valid.shape)} != depth shape {tuple(depth_mm.shape)}")
    depth = torch.where(valid, depth_mm.float(), torch.zeros((), dtype=torch.float32, device=depth_mm.device))
    if levels is None and bool(valid.all()):
        return depth
    if relax_iters < 0:
        raise ValueError(f"fill_invalid_mm: relax_iters must be >= 0, got {relax_iters}")
    weight = valid.float()
    area = torch.ones_like(weight)  # in-frame pixels behind each block (odd sides: partial edge blocks)
    pyramid: list[tuple[Tensor, Tensor, Tensor]] = []
    values = depth
    while True:
        pyramid.append((values, weight, area))
        if levels is not None:
            if len(pyramid) > levels:
                break
        elif max(values.shape[-2:]) <= 1 or bool((weight > 0).all()):
            break
        sums, counts = _masked_half(values, weight)
        values = sums / counts.clamp_min(1e-12)
        weight = counts
        area = _masked_half(area, area)[1]
    values, weight, area = pyramid[-1]  # coarsest level: complete unless a whole image is empty (then zeros stay)
    filled = _relax(values, weight >= area, relax_iters) if relax_iters else values
    for values, weight, area in reversed(pyramid[:-1]):
        up = F.interpolate(filled, size=values.shape[-2:], mode="bilinear", align_corners=False)
        filled = torch.where(weight > 0, values, up)
        if relax_iters:
            filled = _relax(filled, weight >= area, relax_iters)
    return filled


def local_offset_mm(filled_mm: Tensor, block_px: int = DEFAULT_BLOCK_PX) -> Tensor:
    """Smooth local depth level (B, 1, H, W): means of ``block_px`` x ``block_px`` blocks (edge blocks partial),
    bilinearly interpolated back to full size. ``filled_mm`` must have no holes (:func:`fill_invalid_mm`).

    Interpolating block means reproduces a plane exactly away from the border blocks, so on smooth surfaces the
    centred depth is the noise plus curvature; at depth edges it is the edge.
    """
    _check_b1hw(filled_mm, "local_offset_mm(filled_mm)")
    if block_px < 1:
        raise ValueError(f"local_offset_mm: block_px must be >= 1, got {block_px}")
    h, w = filled_mm.shape[-2:]
    x = filled_mm.float()
    ph, pw = (-h) % block_px, (-w) % block_px
    ones = torch.ones_like(x)
    sums = F.avg_pool2d(F.pad(x, (0, pw, 0, ph)), block_px)
    counts = F.avg_pool2d(F.pad(ones, (0, pw, 0, ph)), block_px)
    means = sums / counts
    # block centres sit at (i + 0.5) block_px in the padded frame: interpolate on that grid, then crop
    up = F.interpolate(means, size=(h + ph, w + pw), mode="bilinear", align_corners=False)
    return up[..., :h, :w]


def gaussian_offset_mm(filled_mm: Tensor, block_px: int = DEFAULT_BLOCK_PX) -> Tensor:
    """Smooth local depth level (B, 1, H, W): ``filled_mm`` smoothed by a Gaussian of sigma ``block_px / 2``
    (separable, truncated at 3 sigma; near the frame border the mean of the in-frame pixels under the kernel).
    ``filled_mm`` must have no holes (:func:`fill_invalid_mm`).

    The same weights at every pixel: the offset, and the centred depth ``filled - offset``, have no structure tied
    to a block grid (the block offset of :func:`local_offset_mm` has kinks on its block centres). A symmetric
    kernel reproduces a plane exactly away from the border (3 sigma); on a smooth surface the centred depth is the
    noise plus a smooth curvature term. sigma = block_px / 2 is the bandwidth of the block offset (box of
    ``block_px`` then bilinear interpolation: variance 3 block_px^2 / 12 = (block_px / 2)^2).
    """
    _check_b1hw(filled_mm, "gaussian_offset_mm(filled_mm)")
    if block_px < 1:
        raise ValueError(f"gaussian_offset_mm: block_px must be >= 1, got {block_px}")
    sigma = block_px / 2.0
    radius = max(1, math.ceil(3.0 * sigma))
    taps = torch.arange(-radius, radius + 1, dtype=torch.float32, device=filled_mm.device)
    kernel = torch.exp(-0.5 * (taps / sigma) ** 2)
    kernel = kernel / kernel.sum()
    row, col = kernel.view(1, 1, 1, -1), kernel.view(1, 1, -1, 1)

    def smooth(x: Tensor) -> Tensor:
        return F.conv2d(F.conv2d(x, row, padding=(0, radius)), col, padding=(radius, 0))

    x = filled_mm.float()
    return smooth(x) / smooth(torch.ones_like(x[:1]))


def image_offset_mm(filled_mm: Tensor, valid: Tensor) -> Tensor:
    """Per-image median of the valid pixels (B, 1, 1, 1); 0 for an image without valid pixel."""
    b = filled_mm.shape[0]
    vals = torch.where(valid, filled_mm.float(), torch.full_like(filled_mm, math.nan, dtype=torch.float32))
    med = vals.reshape(b, -1).nanmedian(dim=1).values
    return torch.nan_to_num(med, nan=0.0).reshape(b, 1, 1, 1)


def bf16_step_mm(value_mm: Tensor | float, depth_scale_mm: float) -> Tensor:
    """Spacing of bfloat16 numbers (8 significant bits) around ``value_mm / depth_scale_mm``, in millimetres:
    the finest depth difference a bf16 network input can show at that value."""
    v = torch.as_tensor(value_mm, dtype=torch.float64).abs() / depth_scale_mm
    exponent = torch.floor(torch.log2(v.clamp_min(torch.finfo(torch.float32).tiny)))
    return torch.pow(2.0, exponent - 7) * depth_scale_mm


def condition_input(
    noisy_mm: Tensor,
    amplitude: Tensor | None = None,
    *,
    centering: str = "gaussian",
    block_px: int = DEFAULT_BLOCK_PX,
    depth_scale_mm: float = 100.0,
    use_signal_channel: bool = False,
    fill_levels: int | None = None,
    fill: str = "harmonic",
) -> tuple[Tensor, Tensor]:
    """The network input (B, C, H, W) and the offset (mm) to add back to ``depth_scale_mm`` x its output.

    Channel 0: ``(filled - offset) / depth_scale_mm``: the noisy depth with its invalid pixels filled
    (:func:`fill_invalid_mm`, ``fill_levels`` levels, all needed when None; ``fill`` "harmonic" or "pullpush") and
    centred on the smooth local offset (``centering`` "gaussian": :func:`gaussian_offset_mm`; "local":
    :func:`local_offset_mm`), the image median ("image") or 0 ("none"). Channel 1 (``use_signal_channel``): the
    amplitude divided by its per-image maximum over the valid *input* pixels (on a capture set the scoring mask
    also depends on the reference; the input must not). Computed in float32 (callers disable autocast).
    """
    if centering not in CENTERING_MODES:
        raise ValueError(f"input centering: unknown mode {centering!r}; valid: {', '.join(CENTERING_MODES)}")
    if fill not in FILL_MODES:
        raise ValueError(f"input fill: unknown mode {fill!r}; valid: {', '.join(FILL_MODES)}")
    valid = valid_input_mask(noisy_mm)
    relax = RELAX_ITERS if fill == "harmonic" else 0
    filled = fill_invalid_mm(noisy_mm.float(), valid, levels=fill_levels, relax_iters=relax)
    if centering == "gaussian":
        offset = gaussian_offset_mm(filled, int(block_px))
    elif centering == "local":
        offset = local_offset_mm(filled, int(block_px))
    elif centering == "image":
        offset = image_offset_mm(filled, valid)
    else:
        offset = torch.zeros_like(filled[:, :, :1, :1])
    x = (filled - offset) / depth_scale_mm
    if use_signal_channel:
        if amplitude is None:
            raise KeyError("input conditioning with the signal channel needs the amplitude (batch['amplitude'])")
        amp = amplitude.float() * valid  # the input's own validity, not the scoring mask
        peak = amp.amax(dim=(1, 2, 3), keepdim=True).clamp_min(1e-12)
        x = torch.cat([x, amp / peak], dim=1)
    return x, offset


@dataclass(frozen=True)
class InputConditioning:
    """What the network sees, as one group of settings (``model.conditioning`` in the configs; the checkpoint
    keeps it as a plain mapping, ``to_dict``).

    Args:
        depth_scale_mm: fixed divisor turning (centred) millimetres into network units. 100 mm puts the noise
            (3-12 mm) at 0.03-0.12 and surface detail near 1: inputs of unit order, which Adam's first steps
            cannot swamp.
        centering: ``gaussian`` (default: minus the Gaussian-smoothed local offset), ``local`` (minus the
            interpolated block means; checkpoints written before 2026-11-27), ``image`` (minus the per-image valid
            median) or ``none`` (raw depth / depth_scale_mm).
        block_px: scale of the local offset in pixels (``local``: the block side; ``gaussian``: 2 x sigma).
        use_signal_channel: the normalised amplitude as a second input channel.
        fill: how invalid input pixels are filled: ``harmonic`` (default) or ``pullpush`` (checkpoints written
            before 2026-11-27; a checkpoint without this setting is read as ``pullpush``,
            ``training/legacy_hparams.py``).
    """

    depth_scale_mm: float = 100.0
    centering: str = "gaussian"
    block_px: int = DEFAULT_BLOCK_PX
    use_signal_channel: bool = False
    fill: str = "harmonic"

    def __post_init__(self) -> None:
        if not float(self.depth_scale_mm) > 0:
            raise ValueError(f"conditioning.depth_scale_mm must be > 0, got {self.depth_scale_mm}")
        if self.centering not in CENTERING_MODES:
            raise ValueError(
                f"conditioning.centering: unknown mode {self.centering!r}; valid: {', '.join(CENTERING_MODES)}"
            )
        if int(self.block_px) < 1:
            raise ValueError(f"conditioning.block_px must be >= 1, got {self.block_px}")
        if self.fill not in FILL_MODES:
            raise ValueError(f"conditioning.fill: unknown mode {self.fill!r}; valid: {', '.join(FILL_MODES)}")
        object.__setattr__(self, "depth_scale_mm", float(self.depth_scale_mm))
        object.__setattr__(self, "block_px", int(self.block_px))
        object.__setattr__(self, "use_signal_channel", bool(self.use_signal_channel))

    @property
    def in_channels(self) -> int:
        """Input channels of the network: the depth, and the amplitude with ``use_signal_channel``."""
        return 2 if self.use_signal_channel else 1

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def __call__(
        self, noisy_mm: Tensor, amplitude: Tensor | None = None, fill_levels: int | None = None
    ) -> tuple[Tensor, Tensor]:
        """:func:`condition_input` with these settings: the network input and the offset (mm) to add back."""
        return condition_input(
            noisy_mm,
            amplitude,
            centering=self.centering,
            block_px=self.block_px,
            depth_scale_mm=self.depth_scale_mm,
            use_signal_channel=self.use_signal_channel,
            fill_levels=fill_levels,
            fill=self.fill,
        )
