"""Readers for depth / amplitude / mask files with errors that name the file and the expectation.

Supported formats (chosen by suffix):
- ``.png`` / ``.tif`` / ``.tiff``: read with OpenCV, unchanged bit depth (8- or 16-bit, one channel;
  a 3-channel image is accepted for amplitude and converted to grey).
- ``.npy``: a 2-D numeric array.
- ``.npz``: the array named by ``key`` (or the only array).
- ``.mat``: MATLAB v5 files through ``scipy.io.loadmat`` (``key`` required).
- ``.exr``: scanline OpenEXR (NONE/RLE/ZIPS/ZIP) by the built-in reader (``exr.py``), which picks the depth or the
  amplitude channel by its name (or takes the one named); other variants through
  OpenCV, which only reads EXR when ``OPENCV_IO_ENABLE_OPENEXR=1`` is set before ``cv2`` is imported *and* the
  build includes OpenEXR (this module sets the variable before it imports ``cv2``).

Writers are atomic (`tofdenoise.atomic`: temporary file in the same folder + ``os.replace``).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")  # must precede the first cv2 import

import warnings
from pathlib import Path

import cv2
import numpy as np

from tofdenoise.atomic import atomic_write_png

IMAGE_SUFFIXES = (".png", ".tif", ".tiff")
ARRAY_SUFFIXES = (".npy", ".npz")
SUPPORTED_SUFFIXES = IMAGE_SUFFIXES + ARRAY_SUFFIXES + (".mat", ".exr")


class DataFileError(ValueError):
    """A data file exists but its content is not what the reader expects."""


def _require_file(path: Path, what: str) -> None:
    if not path.is_file():
        raise FileNotFoundError(f"{what} file not found: {path}")


def read_image(
    path: str | Path,
    *,
    what: str = "image",
    allowed_dtypes: tuple[type, ...] = (np.uint8, np.uint16),
    channels: str = "one",
) -> np.ndarray:
    """Read an image file unchanged. ``channels``: "one" (error on colour) or "grey" (convert colour)."""
    path = Path(path)
    _require_file(path, what)
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise DataFileError(f"{what} file {path} could not be decoded as an image (corrupt or unsupported format)")
    if image.ndim == 3:
        if image.shape[2] == 1:
            image = image[:, :, 0]
        elif channels == "grey" and image.shape[2] in (3, 4):
            image = cv2.cvtColor(image[:, :, :3], cv2.COLOR_BGR2GRAY)
        else:
            raise DataFileError(f"{what} file {path} has {image.shape[2]} channels; expected a single-channel image")
    if allowed_dtypes and image.dtype.type not in allowed_dtypes:
        names = ", ".join(np.dtype(d).name for d in allowed_dtypes)
        raise DataFileError(f"{what} file {path} has dtype {image.dtype}; expected one of: {names}")
    return image


def read_png_uint16(path: str | Path, *, what: str = "16-bit PNG") -> np.ndarray:
    """Read a single-channel 16-bit PNG; any other bit depth is an error."""
    return read_image(path, what=what, allowed_dtypes=(np.uint16,))


def read_npy(path: str | Path, *, what: str = "array", key: str | None = None) -> np.ndarray:
    path = Path(path)
    _require_file(path, what)
    try:
        loaded = np.load(path, allow_pickle=False)
    except Exception as exc:  # truncated file, bad header, pickled object ...
        raise DataFileError(f"{what} file {path} could not be read as a NumPy array: {exc}") from exc
    if isinstance(loaded, np.lib.npyio.NpzFile):
        with loaded:
            names = list(loaded.files)
            if key is None and len(names) == 1:
                key = names[0]
            if key not in names:
                raise DataFileError(f"{what} file {path} has arrays {names}; expected key {key!r}")
            loaded = loaded[key]
    array = np.asarray(loaded)
    if not (
        np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer) or array.dtype == np.bool_
    ):
        raise DataFileError(f"{what} file {path} has dtype {array.dtype}; expected a numeric array")
    return array


def read_mat(path: str | Path, key: str, *, what: str = "MATLAB") -> np.ndarray:
    """Read variable ``key`` from a MATLAB v5 ``.mat`` file (v7.3/HDF5 files are reported as such)."""
    import scipy.io

    path = Path(path)
    _require_file(path, what)
    try:
        content = scipy.io.loadmat(str(path), variable_names=[key])
    except NotImplementedError as exc:  # scipy raises this for v7.3 (HDF5) files
        raise DataFileError(f"{what} file {path} is a MATLAB v7.3 (HDF5) file; expected MATLAB v5 format") from exc
    except Exception as exc:
        raise DataFileError(f"{what} file {path} could not be read as a MATLAB v5 file: {exc}") from exc
    if key not in content:
        raise DataFileError(f"{what} file {path} has no variable {key!r}")
    array = np.asarray(content[key])
    if not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)):
        raise DataFileError(f"{what} file {path} variable {key!r} has dtype {array.dtype}; expected numeric")
    return array


def read_exr(
    path: str | Path,
    *,
    what: str = "EXR",
    kind: str = "depth",
    channel: str | None = None,
    channel_setting: str | None = None,
) -> np.ndarray:
    """Read the depth (``kind="depth"``) or the amplitude (``kind="amplitude"``) of an OpenEXR image as float32 (H, W).

    Single-part scanline files with NONE/RLE/ZIPS/ZIP compression are decoded by ``tofdenoise.data_modules.exr``
    (numpy + zlib, no codec needed), which picks the channel by its name (``exr.depth_channel``,
    ``exr.amplitude_channels``) or takes ``channel`` (a full channel name); a choice that is not clear is a
    ``DataFileError`` naming the channels and ``channel_setting`` (the option that names one). Other EXR variants
    (PIZ, tiled, ...) go to OpenCV, which needs ``OPENCV_IO_ENABLE_OPENEXR=1`` before cv2 is imported and a build
    with OpenEXR; it returns the colour channels only (no names, no ``Z``), so a colour result is taken only when
    its channels are equal (an amplitude: converted to grey).
    """
    from tofdenoise.data_modules.exr import ExrChannelError, ExrError, read_exr_amplitude, read_exr_depth

    if kind not in ("depth", "amplitude"):
        raise ValueError(f"read_exr: kind must be 'depth' or 'amplitude', got {kind!r}")
    path = Path(path)
    _require_file(path, what)
    reader = read_exr_depth if kind == "depth" else read_exr_amplitude
    try:
        return reader(path, channel, channel_setting)
    except ExrChannelError as exc:
        raise DataFileError(f"{what}: {exc}") from None
    except ExrError as exc:
        own_error = exc
    try:
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED | cv2.IMREAD_ANYDEPTH)
    except cv2.error:
        image = None
    if image is None:
        raise DataFileError(
            f"{what} file {path} could not be read: {own_error}; OpenCV could not decode it either (it needs "
            "OPENCV_IO_ENABLE_OPENEXR=1 set before cv2 is imported and a build with OpenEXR). "
            "Convert the file to .npy (float, mm)."
        )
    if channel is not None:
        raise DataFileError(
            f"{what} file {path}: {own_error}; OpenCV decodes it without channel names, so channel {channel!r} "
            "cannot be chosen (re-save it as a ZIP-compressed scanline EXR, or convert it to .npy)"
        )
    if image.ndim == 3:
        colour = image[:, :, :3]
        if np.all(colour == colour[:, :, :1]):
            image = colour[:, :, 0]
        elif kind == "amplitude":
            image = cv2.cvtColor(colour.astype(np.float32), cv2.COLOR_BGR2GRAY)
        else:
            raise DataFileError(
                f"{what} file {path}: {own_error}; OpenCV decodes its colour channels only, which differ, so none "
                "of them is known to be the depth (re-save it as a ZIP-compressed scanline EXR, or convert it to .npy)"
            )
    return image.astype(np.float32, copy=False)


def read_array(
    path: str | Path,
    *,
    what: str,
    key: str | None = None,
    image_dtypes: tuple[type, ...] = (np.uint8, np.uint16),
    channels: str = "one",
    exr_kind: str = "depth",
    exr_channel: str | None = None,
    channel_setting: str | None = None,
) -> np.ndarray:
    """Read a 2-D map from any supported format (by suffix); returns the stored dtype. An ``.exr`` gives its
    ``exr_kind`` channel (``read_exr``: "depth" or "amplitude"), or ``exr_channel`` when named."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in IMAGE_SUFFIXES:
        array = read_image(path, what=what, allowed_dtypes=image_dtypes, channels=channels)
    elif suffix in ARRAY_SUFFIXES:
        array = read_npy(path, what=what, key=key)
    elif suffix == ".mat":
        if key is None:
            raise ValueError(f"reading {what} file {path}: a .mat file needs a variable name (key)")
        array = read_mat(path, key, what=what)
    elif suffix == ".exr":
        array = read_exr(path, what=what, kind=exr_kind, channel=exr_channel, channel_setting=channel_setting)
    else:
        raise DataFileError(
            f"{what} file {path} has unsupported suffix {suffix!r}; expected one of {', '.join(SUPPORTED_SUFFIXES)}"
        )
    array = np.squeeze(array) if array.ndim > 2 else array
    if array.ndim != 2:
        raise DataFileError(f"{what} file {path} has shape {array.shape}; expected a 2-D map (H, W)")
    return array


def read_depth_mm(
    path: str | Path,
    *,
    what: str = "depth",
    scale_mm: float = 1.0,
    key: str | None = None,
    exr_channel: str | None = None,
    channel_setting: str | None = None,
) -> np.ndarray:
    """Read a depth map in millimetres as float32; NaN/inf/<=0 are left for the caller's validity mask.

    16-bit PNGs hold mm (0 = invalid); float arrays / EXR hold mm (multiplied by ``scale_mm``).
    8-bit data is rejected whatever the format (an 8-bit PNG, a uint8/int8 ``.npy``/``.npz``/``.mat``): 256 levels
    cannot hold depth in mm (``refuse_8bit_depth``).
    """
    array = read_array(
        path, what=what, key=key, image_dtypes=(), exr_channel=exr_channel, channel_setting=channel_setting
    )  # an image's dtype is checked here
    if array.dtype == np.bool_:
        raise DataFileError(f"{what} file {path} is boolean; expected depth values in mm")
    refuse_8bit_depth(array, path, what)
    if Path(path).suffix.lower() in IMAGE_SUFFIXES and array.dtype != np.uint16:
        raise DataFileError(f"{what} file {path} has dtype {array.dtype}; expected one of: uint16")
    return array.astype(np.float32) * np.float32(scale_mm)


#: integer dtypes too narrow for depth in millimetres (at most 255 distinct steps)
EIGHT_BIT_DTYPES = (np.dtype(np.uint8), np.dtype(np.int8))


def refuse_8bit_depth(array: np.ndarray, path: str | Path, what: str = "depth") -> None:
    """A ``DataFileError`` naming the file, its dtype and what is expected when ``array`` holds 8-bit integers: the
    one message for an 8-bit PNG and an 8-bit array alike (a uint8 ``.npy`` of depth / 20 was read as 0-255 mm)."""
    if np.asarray(array).dtype in EIGHT_BIT_DTYPES:
        raise DataFileError(
            f"{what} file {path} has dtype {array.dtype}; 8-bit values cannot hold depth in millimetres: expected a "
            "16-bit PNG/TIFF (uint16 mm, 0 = invalid) or a float or 16/32-bit integer array in mm (.npy, .npz, "
            ".mat, .exr)"
        )


def read_amplitude(
    path: str | Path,
    *,
    what: str = "amplitude",
    key: str | None = None,
    exr_channel: str | None = None,
    channel_setting: str | None = None,
) -> np.ndarray:
    """Read an amplitude map (8/16-bit image, float array or EXR) as float32 in its own units. A colour image is
    converted to grey; an EXR gives its amplitude channel (``exr.amplitude_channels``: never its depth channel)."""
    array = read_array(
        path,
        what=what,
        key=key,
        image_dtypes=(np.uint8, np.uint16),
        channels="grey",
        exr_kind="amplitude",
        exr_channel=exr_channel,
        channel_setting=channel_setting,
    )
    if array.dtype == np.bool_:
        raise DataFileError(f"{what} file {path} is boolean; expected amplitude values")
    return array.astype(np.float32)


def check_same_shape(
    reference: np.ndarray, other: np.ndarray, *, reference_path: str | Path, other_path: str | Path, what: str
) -> None:
    if reference.shape != other.shape:
        raise DataFileError(
            f"{what} file {other_path} has shape {other.shape}; expected {reference.shape} to match {reference_path}"
        )


def write_png(path: str | Path, image: np.ndarray, dtype: type = np.uint16) -> Path:
    """Write a single-channel PNG of ``dtype`` (uint16 or uint8) atomically; values must already be in range."""
    image = np.asarray(image)
    if image.dtype != dtype or image.ndim != 2:
        raise ValueError(
            f"write_png({path}): expected a 2-D {np.dtype(dtype).name} array, got {image.dtype} {image.shape}"
        )
    return atomic_write_png(path, image)


def write_png_uint16(path: str | Path, image: np.ndarray) -> Path:
    return write_png(path, image, np.uint16)


#: the largest depth a 16-bit millimetre PNG holds
PNG16_MAX_MM = 65535
#: a depth map whose median valid depth lies below this is not in millimetres (a map in metres, most likely): refused
#: by ``tofdenoise evaluate`` and by the folder training source (``tofdenoise denoise`` checks the narrower
#: ``inference.frames.plausible_depth_range_mm``)
MIN_MEDIAN_DEPTH_MM = 20.0


def depth_mm_to_png16(depth_mm: np.ndarray) -> np.ndarray:
    """Depth [mm] -> uint16 millimetres for a 16-bit depth PNG, where 0 means invalid (the convention every
    reader here uses). Rounds half to even. Validity is kept wherever it can be: a positive depth below 0.5 mm
    becomes 1, not 0. NaN, inf, depth <= 0 and depths that do not fit (>= 65535.5 mm) become 0: a value that
    cannot be stored is marked invalid rather than clipped to a wrong depth."""
    d = np.asarray(depth_mm, dtype=np.float64)
    ok = np.isfinite(d) & (d > 0) & (d < PNG16_MAX_MM + 0.5)
    out = np.zeros(d.shape, dtype=np.uint16)
    out[ok] = np.maximum(np.rint(d[ok]), 1).astype(np.uint16)
    return out


def write_depth_png16(path: str | Path, depth_mm: np.ndarray) -> Path:
    """Write a (H, W) depth map [mm] as a 16-bit millimetre PNG atomically (``depth_mm_to_png16``); warns,
    naming the file, when finite depths beyond 65535 mm had to be stored as invalid."""
    d = np.asarray(depth_mm, dtype=np.float64)
    beyond = int(np.count_nonzero(np.isfinite(d) & (d >= PNG16_MAX_MM + 0.5)))
    if beyond:
        warnings.warn(
            f"{path}: {beyond} pixel(s) deeper than {PNG16_MAX_MM} mm do not fit a 16-bit millimetre PNG "
            "and were written as invalid (0)",
            RuntimeWarning,
            stacklevel=2,
        )
    return write_png_uint16(path, depth_mm_to_png16(d))


def write_png_uint8(path: str | Path, image: np.ndarray) -> Path:
    return write_png(path, image, np.uint8)
