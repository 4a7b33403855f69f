"""ToFDataModule: one LightningDataModule for every data source, configured by plain values (Hydra / CLI)."""

from __future__ import annotations

import json
import logging
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset

from tofdenoise.atomic import atomic_write_text
from tofdenoise.data_modules.cache import MapCache, canonical_digest
from tofdenoise.data_modules.datasets import MapProvider, RealCaptures, SyntheticPairs, stable_seed
from tofdenoise.data_modules.file_stamps import content_digest, stamps_state
from tofdenoise.data_modules.holes import HoleModel
from tofdenoise.data_modules.maps import check_signal_route
from tofdenoise.data_modules.real_captures import build_reference, list_scenes, load_real_scene
from tofdenoise.data_modules.simulated_test import (
    SIMULATED_SET,
    SimulatedCaptures,
    SimulatedTestSettings,
    simulated_cache,
)
from tofdenoise.data_modules.sources import SourceContext, source_from_config
from tofdenoise.data_modules.splits import SPLIT_NAMES, ids_digest, load_or_make_split
from tofdenoise.data_modules.transforms import crop_coverage
from tofdenoise.physics.calibration import SensorCalibration, resolve_calibration
from tofdenoise.physics.noise_models import available_noise_models, build_noise_model, variance_matching_scale
from tofdenoise.records import VARIANCE_MATCH_WEIGHTS

log = logging.getLogger(__name__)

GAUSSIAN_BASELINES = ("range", "fixed")
#: the noise model whose sigma range comes from the training split (``noise_kwargs.percentiles``)
BLIND_NOISE = "blind"
DEFAULT_BLIND_PERCENTILES = (5.0, 95.0)
#: the pixels a Gaussian baseline's variance is matched on, and a blind model's sigma range is read from: the one
#: rule (``training_pixels``), recorded with every variance scale and in ``summary()``
TRAINING_PIXELS_RULE = "after_holes"
TRAINING_PIXELS_RULE_TEXT = (
    "the training pixels: valid in the maps and not a hole of the hole model (one seeded hole draw per training "
    "sample; all valid pixels when holes are off)"
)
#: pixels per training sample that enter the blind model's percentiles at most (an even stride over the sample)
BLIND_PIXELS_PER_SAMPLE = 50_000


def _crop_pair(crop_size: int | Sequence[int] | None) -> tuple[int, int] | None:
    if crop_size is None or crop_size == 0:
        return None
    if isinstance(crop_size, int):
        pair = (crop_size, crop_size)
    else:
        values = [int(v) for v in crop_size]
        if len(values) != 2:
            raise ValueError(f"data.crop_size must be an int, [height, width] or null, got {crop_size!r}")
        pair = (values[0], values[1])
    if min(pair) < 1:
        raise ValueError(f"data.crop_size must be positive, got {crop_size!r}")
    return pair


@dataclass(frozen=True)
class PreparedData:
    """What ``setup`` loads from ``cache_dir`` (written there by ``prepare_data``, on this rank or another)."""

    source: Any
    split_path: Path
    splits: dict[str, list[str]]  # usable sample ids per split (samples without a valid pixel removed)
    skipped: dict[str, list[str]]  # split -> ids left out; "real": capture scenes left out
    cache: MapCache
    provider: MapProvider
    noise_model: Any  # the training noise model (a Gaussian baseline variance-matched)
    variance_scale: dict | None  # the stored variance-matching record of the training noise, if any
    eval_noise_model: Any  # synthesises the validation / test / predict inputs (``eval_noise``)
    real_scenes: list[Path]
    simulated_cache: MapCache | None = None  # the simulator-noised test split's captures (``simulated_test``)


def data_calibration(
    sensor: dict[str, Any] | str | None, signal_route: str = "linear", signal_dynamic_range: float | None = None
):
    """The calibration a :class:`ToFDataModule` of these settings uses (and a run records as its ``sensor``):
    ``sensor`` resolved (a preset, a file or a mapping), with ``signal_min_e`` from ``signal_dynamic_range``."""
    calib = resolve_calibration(sensor)
    if signal_dynamic_range is not None:
        if str(signal_route).lower() != "linear" or not float(signal_dynamic_range) > 1:
            raise ValueError(
                f"data.signal_dynamic_range={signal_dynamic_range!r}: a ratio a_max / a_min > 1 of the linear "
                f"signal route (data.signal_route={signal_route!r})"
            )
        calib = calib.replace(signal_min_e=calib.signal_max_e / float(signal_dynamic_range))
    return calib


class ToFDataModule(L.LightningDataModule):
    """Clean depth + signal + sigma_D maps from a source, noisy depth synthesised by a physics noise model.

    Every argument is a plain value; the Hydra configs in ``configs/data`` and ``configs/noise`` set them
    (``data.<name>``). Call ``prepare_data()`` then ``setup(stage)``, or hand it to a Lightning ``Trainer``.

    Args:
        source: the data source by name (``DATA_SOURCES``): "procedural" (built-in scenes, default),
            "flyingthings3d" or "folder".
        source_kwargs: that source's own settings (its ``config_keys()``: e.g. procedural num_samples, height,
            width, min_depth_mm, max_depth_mm, max_depth_fraction, hfov_deg; folder root, list_file,
            depth_unit_mm; flyingthings3d root, list_files), passed to its ``from_config`` with what this
            datamodule supplies (``SourceContext``: ``seed`` and the calibration). An unknown key is an error
            naming ``data.source_kwargs.<key>`` and the valid ones.
        noise: the training noise model ("hetero", "range", "fixed", "none").
        noise_kwargs: its settings (``build_noise_model``).
        eval_noise: the noise model that synthesises the validation, test and predict inputs (default "hetero",
            the physics-faithful synthesis; its default kwargs, a Gaussian baseline variance-matched like the
            training noise), whatever ``noise`` is: runs trained with different noise models are validated and
            tested on identical inputs (the same fixed per-sample seed).
        sensor: the calibration: None (the default), a path, a preset name, a mapping in the ``to_dict()``
            layout or a ``SensorCalibration``.
        real_dir: a capture set (see ``real_captures``); adds the "real" test loader.
        simulated_test: add the simulator-noised test split (test set ``"simulated"``,
            ``tofdenoise.data_modules.simulated_test``): the test samples captured by the tap-level simulator
            (Poisson, dark and read noise, ADC, fixed-pattern noise, mixed pixels, atan2 demodulation, the camera's
            own validity) instead of noised by ``eval_noise``; scored beside the paper-protocol split
            (``"synthetic"``), cached next to the maps.
        simulated_test_kwargs: ``mixed_pixels`` (default 3), ``fixed_pattern`` (used when the calibration has none;
            default the stand-in camera's).
        cache_dir: where splits, per-sample maps and records live.
        use_cache: store the per-sample maps there and read them back.
        crop_size: the training crop: an int, [h, w], or None for full images.
        flips: random horizontal/vertical flips in training.
        batch_size: the training batch size.
        eval_batch_size: the validation, test and predict batch size.
        num_workers: DataLoader worker processes (also used to compute missing maps in ``prepare_data``).
        pin_memory: the DataLoader's ``pin_memory``.
        persistent_workers: keep the workers between epochs (only with ``num_workers`` > 0).
        seed: the split permutation, the evaluation noise, and the source's seed (``SourceContext``:
            procedural scenes).
        split_ratios: train:val:test.
        match_variance: rescale the Gaussian baselines (range/fixed) to the hetero mean variance over the
            training split's training pixels (paper Sec. V-A; ``TRAINING_PIXELS_RULE``: after the hole model's
            holes), computed once and stored next to the cache. The ``blind`` model's sigma range is the
            ``noise_kwargs.percentiles`` (default 5th, 95th) of sigma_D over the same pixels.
        signal_lower_percentile: the amplitude normalisation's lower percentile (None: the physics default).
        signal_upper_percentile: its upper percentile (None: the physics default).
        signal_route: how the source's amplitude becomes the returned signal a(p) [e-]: "linear" (the paper's
            mapping into the calibration's [a_min, a_max], per-image percentiles) or "physical" (a = K t A V from
            a radiometric amplitude, ``tofdenoise.physics.photometry``; the procedural scenes' default, needs the
            calibration's ``signal_at_1m_e``). With "physical" the low-signal and saturation holes come from the
            camera's own threshold and full well (``HoleModel.physical_signal``).
        signal_dynamic_range: with the linear route, map into [a_max / r, a_max] instead of the calibration's
            interval (a_max = its ``signal_max_e``): the dynamic-range study (``make reproduce STUDY=dynrange``).
            None: the calibration's own interval.
        real_min_count: valid high-exposure frames a reference pixel of the capture set needs (None: half of
            the frames).
        holes: give synthetic inputs realistic invalid regions (low signal, depth edges, dropout blobs;
            ``tofdenoise.data_modules.holes``), zero there and out of ``mask``: random in training, fixed per
            sample (seeded) in validation/test/predict.
        holes_kwargs: ``HoleModel`` settings.
    """

    def __init__(
        self,
        source: str = "procedural",
        source_kwargs: dict[str, Any] | None = None,
        noise: str = "hetero",
        noise_kwargs: dict[str, Any] | None = None,
        eval_noise: str = "hetero",
        sensor: dict[str, Any] | str | None = None,
        real_dir: str | None = None,
        cache_dir: str = ".cache/tofdenoise/data",
        use_cache: bool = True,
        crop_size: int | list[int] | None = 320,
        flips: bool = True,
        batch_size: int = 4,
        eval_batch_size: int = 1,
        num_workers: int = 0,
        pin_memory: bool = False,
        persistent_workers: bool = False,
        seed: int = 0,
        split_ratios: list[float] | tuple[float, float, float] = (6.0, 2.0, 2.0),
        match_variance: bool = True,
        signal_lower_percentile: float | None = None,
        signal_upper_percentile: float | None = None,
        signal_route: str = "linear",
        signal_dynamic_range: float | None = None,
        real_min_count: int | None = None,
        holes: bool = True,
        holes_kwargs: dict[str, Any] | None = None,
        simulated_test: bool = True,
        simulated_test_kwargs: dict[str, Any] | None = None,
    ):
        super().__init__()

        if isinstance(sensor, SensorCalibration):
            sensor = sensor.to_dict()
        noise_kwargs = dict(noise_kwargs or {})
        if source_kwargs is None or isinstance(source_kwargs, Mapping):  # anything else: an error in make_source
            source_kwargs = dict(source_kwargs or {})
        split_ratios = [float(r) for r in split_ratios]
        self.save_hyperparameters()
        self.source_name = source
        self.calib = data_calibration(sensor, signal_route, signal_dynamic_range)
        self.noise_name = str(noise).lower()
        self.noise_kwargs = noise_kwargs

        self.eval_noise_name = str(eval_noise).lower()
        if self.eval_noise_name not in available_noise_models():
            raise ValueError(f"unknown data.eval_noise {eval_noise!r}; valid: {', '.join(available_noise_models())}")
        if self.noise_name == BLIND_NOISE:
            blind_percentiles(self.noise_kwargs)  # fail fast on a bad range
        self.crop = _crop_pair(crop_size)
        self.simulated_settings = SimulatedTestSettings.from_kwargs(simulated_test_kwargs) if simulated_test else None

        try:
            self.hole_model = HoleModel(**dict(holes_kwargs or {})) if holes else None
        except TypeError as exc:
            raise ValueError(
                f"data.holes_kwargs: {exc}; valid keys: max_low_signal_fraction, edge_jump, edge_prob, "
                "blob_density, blob_radius_px"
            ) from None
        if batch_size < 1 or eval_batch_size < 1:
            raise ValueError("data.batch_size and data.eval_batch_size must be >= 1")
        self.cache_root = Path(cache_dir).expanduser()
        self.real_dir = real_dir
        if real_dir:  # fail before any training: a missing or empty capture set is a config error
            list_scenes(real_dir)
        # the paper's protocol (the hetero-noised split) first, then the simulator-noised split, then the capture set
        self.test_set_names: list[str] = (
            ["synthetic"] + ([SIMULATED_SET] if simulated_test else []) + (["real"] if real_dir else [])
        )
        self._prepared: PreparedData | None = None
        self.datasets: dict[str, Any] = {}

        # fail fast: unknown source or source setting, a missing dataset folder, bad sizes / depth range, a signal
        # route that cannot apply
        self.signal_route = check_signal_route(signal_route, self.make_source(), self.calib)
        if self.hole_model is not None and self.signal_route == "physical":
            self.hole_model = replace(self.hole_model, physical_signal=True)

    # ------------------------------------------------------------------ pieces
    def make_source(self):
        """The data source ``data.source`` names, built by its class from ``data.source_kwargs`` and what this
        datamodule supplies to every source (``SourceContext``: the seed and the calibration)."""
        hp = self.hparams
        context = SourceContext(seed=int(hp.seed), calibration=self.calib)
        return source_from_config(self.source_name, hp.source_kwargs, context)

    @property
    def split_path(self) -> Path:
        return self.prepared.split_path

    @property
    def cache(self) -> MapCache:
        return self.prepared.cache

    @property
    def noise_model(self):
        return self.prepared.noise_model

    @property
    def splits(self) -> dict[str, list[str]]:
        return self.prepared.splits

    @property
    def skipped_samples(self) -> dict[str, list[str]]:
        """Split name -> sample ids left out (no valid pixel; ``"real"``: capture scenes without a common valid
        region or without an input frame)."""
        return self.prepared.skipped

    @property
    def prepared(self) -> PreparedData:
        """The prepared data, loaded from ``cache_dir`` on first use (``setup``)."""
        if self._prepared is None:
            self._prepared = self._load_prepared()
        return self._prepared

    # ------------------------------------------------------------------ preparation
    def prepare_data(self) -> None:
        """Write what ``setup`` reads: source description, seeded split, per-sample maps and their index, the
        variance scale of a Gaussian baseline and the capture set's references. Lightning runs it on one
        process (rank 0); every write is atomic and skipped when up to date, so calling it again is cheap.
        Nothing is kept on the instance: ``setup`` loads the same files on every rank."""
        self._load_prepared()

    def _load_prepared(self) -> PreparedData:
        """The preparation steps in order; each reuses what is stored under ``cache_dir`` and writes what is
        missing, so the same call prepares (rank 0) and loads (every rank)."""
        source, described, base = self._open_source()
        split_path, splits = self._load_split(base, source.sample_ids(), described)
        cache, provider = self._map_cache(base, described, source)
        index, changed = self._sample_index(provider, cache, [i for name in SPLIT_NAMES for i in splits[name]])
        splits, skipped = self._drop_empty(splits, index)
        if not splits["train"]:
            raise ValueError(f"the {source.name} source has no usable training sample")
        self._check_crop(splits["train"], index)
        train = _TrainingSet(splits["train"], _files_digest(index, splits["train"]))
        noise_model, scale_record = self._noise(self.noise_name, self.noise_kwargs, provider, cache, train)
        eval_model, _ = self._noise(self.eval_noise_name, {}, provider, cache, train)
        real_scenes = self._real_scenes(skipped) if self.real_dir else []
        sim_cache = (
            self._simulated_captures(base, provider, cache, splits["test"], changed)
            if self.simulated_settings
            else None
        )
        return PreparedData(
            source=source,
            split_path=split_path,
            splits=splits,
            skipped=skipped,
            cache=cache,
            provider=provider,
            noise_model=noise_model,
            variance_scale=scale_record,
            eval_noise_model=eval_model,
            real_scenes=real_scenes,
            simulated_cache=sim_cache,
        )

    def _open_source(self) -> tuple[Any, dict, Path]:
        """The source (checked: a listed but missing sample fails here, before training), its description and
        its folder under ``cache_dir`` (``source.json`` written there)."""
        source = self.make_source()
        source.check()
        described = source.describe()
        base = self.cache_root / f"{source.name}-{canonical_digest(described)[:12]}"
        base.mkdir(parents=True, exist_ok=True)
        atomic_write_text(base / "source.json", json.dumps(described, indent=1, default=str) + "\n")
        return source, described, base

    def _load_split(self, base: Path, ids: list[str], described: dict) -> tuple[Path, dict[str, list[str]]]:
        """The seeded split file ``split_seed<S>_<ratios>.json`` (reused when it matches, else written)."""
        hp = self.hparams
        ratio_tag = "-".join(f"{r:g}" for r in hp.split_ratios)
        split_path = base / f"split_seed{hp.seed}_{ratio_tag}.json"
        return split_path, load_or_make_split(split_path, ids, hp.seed, hp.split_ratios, described)

    def _map_cache(self, base: Path, described: dict, source: Any) -> tuple[MapCache, MapProvider]:
        """The map cache of this source x calibration x signal mapping, and the provider reading through it."""
        hp = self.hparams
        key = {
            "source": described,
            "calibration": self.calib.fingerprint(),
            "signal_percentiles": [hp.signal_lower_percentile, hp.signal_upper_percentile],
            "signal_route": self.signal_route,
            # the physical route's maps hold only what the camera can measure (maps.measurable): version 2
            **({"maps_version": 2} if self.signal_route == "physical" else {}),
        }
        cache = MapCache(base, key, enabled=hp.use_cache)
        provider = MapProvider(
            source, self.calib, cache, hp.signal_lower_percentile, hp.signal_upper_percentile, self.signal_route
        )
        return cache, provider

    @staticmethod
    def _drop_empty(
        splits: dict[str, list[str]], index: dict[str, dict]
    ) -> tuple[dict[str, list[str]], dict[str, list[str]]]:
        """Splits without the samples that have no valid pixel (warned), and those left out per split."""
        kept, skipped = {}, {}
        for name in SPLIT_NAMES:
            empty = [i for i in splits[name] if index[i]["num_valid"] == 0]
            if empty:
                warnings.warn(
                    f"{name} split: {len(empty)} sample(s) with no valid pixel skipped: "
                    f"{', '.join(empty[:5])}{' ...' if len(empty) > 5 else ''}",
                    stacklevel=3,
                )
                skipped[name] = empty
            kept[name] = [i for i in splits[name] if index[i]["num_valid"] > 0]
        return kept, skipped

    def _check_crop(self, train_ids: list[str], index: dict[str, dict]) -> None:
        """A training crop larger than a training sample is a configuration error naming data.crop_size."""
        if self.crop is None:
            return
        too_small = [i for i in train_ids if index[i]["shape"][0] < self.crop[0] or index[i]["shape"][1] < self.crop[1]]
        if too_small:
            shape = index[too_small[0]]["shape"]
            raise ValueError(
                f"data.crop_size={list(self.crop)} does not fit sample {too_small[0]} of size "
                f"{shape[0]}x{shape[1]}; lower data.crop_size (or set it to null)"
            )

    def _noise(self, name: str, kwargs: dict[str, Any], provider: MapProvider, cache: MapCache, train: _TrainingSet):
        """A noise model and its record: a Gaussian baseline is variance-matched over the training pixels
        (``match_variance``), the blind model gets its sigma range from them (both records stored next to the
        maps); any other model has none."""
        if name == BLIND_NOISE:
            return self._blind_range(kwargs, provider, cache, train)
        noise_model = build_noise_model(name, self.calib, **kwargs)
        if name in GAUSSIAN_BASELINES and self.hparams.match_variance:
            return self._match_variance(name, kwargs, noise_model, provider, cache, train)
        return noise_model, None

    def training_pixels(self, sample_id: str, maps: Any) -> np.ndarray:
        """The pixels of training sample ``sample_id`` a network is trained on (``TRAINING_PIXELS_RULE``): valid in
        its maps and not a hole of the hole model, drawn once from a generator seeded by (seed, id). Training draws
        fresh holes on every read; one draw per sample is an unbiased sample of them."""
        valid = np.asarray(maps.mask, dtype=bool)
        if self.hole_model is None or not valid.any():
            return valid
        generator = torch.Generator().manual_seed(stable_seed(self.hparams.seed, "train_pixels", sample_id, "holes"))
        holes = self.hole_model.sample(
            torch.from_numpy(np.asarray(maps.depth_mm, dtype=np.float32)),
            torch.from_numpy(np.asarray(maps.signal_e, dtype=np.float32)),
            torch.from_numpy(valid),
            self.calib,
            generator,
        )
        return valid & ~holes.numpy()

    def _training_samples(self, provider: MapProvider, train_ids: list[str]) -> Iterator[tuple[Any, Any, Any]]:
        """(depth_mm, sigma_mm, training pixels) of each training sample, in ``train_ids``' order, read in DataLoader
        workers when data.num_workers > 0: the maps and the hole draw cost about 0.4 s a 480 x 640 sample on one
        core, minutes for a 180-scene world in one process. Each sample is computed as in this process."""
        workers = int(self.hparams.num_workers) if len(train_ids) > 1 else 0
        dataset = _TrainingPixels(provider, train_ids, self.training_pixels)
        # its own generator: an iterator draws its base seed from the loader's generator, and this loader runs only
        # where the statistics are not stored yet, so drawing from torch's global one would start the first run of
        # a cache from another training stream than the runs after it
        private = torch.Generator().manual_seed(0)
        yield from DataLoader(dataset, batch_size=None, num_workers=workers, collate_fn=_unchanged, generator=private)

    def _pixels_key(self, cache: MapCache, train: _TrainingSet) -> dict[str, Any]:
        """What the training pixels depend on: the maps, the training ids, the rule, the hole model and the seed;
        for a file-backed source also the content of the training samples' files (``files``: a changed file gives
        another key; a source without files keeps the key it always had)."""
        key = {
            "maps": cache.digest,
            "train_ids": ids_digest(train.ids),
            "pixels": TRAINING_PIXELS_RULE,
            "holes": None if self.hole_model is None else self.hole_model.to_dict(),
            "seed": int(self.hparams.seed),
        }
        if train.files_digest is not None:
            key["files"] = train.files_digest
        return key

    def _blind_range(self, kwargs: dict[str, Any], provider: MapProvider, cache: MapCache, train: _TrainingSet):
        """The blind model with its sigma range: given (``sigma_lo_mm`` / ``sigma_hi_mm``), or the percentiles of
        sigma_D over the training pixels (computed once, stored next to the maps)."""
        lo_p, hi_p = blind_percentiles(kwargs)
        given = {k: kwargs[k] for k in ("sigma_lo_mm", "sigma_hi_mm") if k in kwargs}
        rest = {k: v for k, v in kwargs.items() if k not in ("percentiles", "sigma_lo_mm", "sigma_hi_mm")}
        if len(given) == 2:
            return build_noise_model(BLIND_NOISE, self.calib, **given, **rest), None
        key = {**self._pixels_key(cache, train), "percentiles": [lo_p, hi_p]}
        name = f"blind_range_{canonical_digest(key)[:12]}.json"
        record = cache.load_record(name, expected_key=key)
        if record is None:
            values = []
            for _, sigma_mm, pixels in self._training_samples(provider, train.ids):
                sigma = sigma_mm[pixels].astype(np.float64)
                values.append(sigma[:: max(1, -(-sigma.size // BLIND_PIXELS_PER_SAMPLE))])
            pooled = np.concatenate(values) if values else np.zeros(0)
            if pooled.size == 0:
                raise ValueError("noise=blind: no training pixel to read the sigma_D range from")
            lo, hi = (float(v) for v in np.percentile(pooled, [lo_p, hi_p]))
            record = {
                "sigma_lo_mm": lo,
                "sigma_hi_mm": hi,
                "percentiles": [lo_p, hi_p],
                "pixels": TRAINING_PIXELS_RULE,
                "num_train_samples": len(train.ids),
                "note": "per-image sigma of the blind model: log-uniform between these percentiles of sigma_D",
            }
            cache.save_record(name, record, key=key)
        lo, hi = given.get("sigma_lo_mm", record["sigma_lo_mm"]), given.get("sigma_hi_mm", record["sigma_hi_mm"])
        log.info("blind noise: sigma log-uniform in [%.4g, %.4g] mm", lo, hi)
        model = build_noise_model(BLIND_NOISE, self.calib, sigma_lo_mm=lo, sigma_hi_mm=hi, **rest)
        return model, record

    def _sample_index(
        self, provider: MapProvider, cache: MapCache, ids: list[str]
    ) -> tuple[dict[str, dict], list[str]]:
        """Valid-pixel count and shape per sample (computing, and caching, any maps not seen yet), and the samples
        computed again because their files changed. For a file-backed source each entry records the stamps of the
        sample's files (``file_stamps``); an entry whose files changed, or that records none, is computed again
        (with its cached maps), with one warning that names how many; with ``use_cache=False`` too."""
        record = cache.load_record("index.json") or {}
        index: dict[str, dict] = dict(record.get("samples", {}))
        changed, restamped = [], False
        for sample_id in ids:
            files = provider.files(sample_id)
            if files is None or sample_id not in index:
                continue
            state, stamps = stamps_state(index[sample_id].get("files"), files)
            if state == "changed":
                changed.append(sample_id)
                del index[sample_id]
            elif state == "restamped":
                index[sample_id] = {**index[sample_id], "files": stamps}
                restamped = True
        todo = [i for i in ids if i not in index]
        workers = int(self.hparams.num_workers) if len(todo) > 1 else 0
        # computed in DataLoader workers when data.num_workers > 0 (each writes its own cache entries atomically)
        for sample_id, entry in DataLoader(_IndexEntries(provider, todo), batch_size=None, num_workers=workers):
            index[sample_id] = entry
        if todo or restamped:
            cache.save_record("index.json", {"samples": index})
        if changed:
            warnings.warn(
                f"the {provider.source.name} source: {len(changed)} sample(s) computed again because their files "
                f"changed since their maps were cached (or the cache recorded no file stamps): "
                f"{', '.join(changed[:5])}{' ...' if len(changed) > 5 else ''}",
                stacklevel=3,
            )
        return index, changed

    def _match_variance(
        self,
        noise_name: str,
        noise_kwargs: dict[str, Any],
        noise_model,
        provider: MapProvider,
        cache: MapCache,
        train: _TrainingSet,
    ):
        crop = None if self.crop is None else list(self.crop)
        key = {
            "noise": noise_name,
            "noise_kwargs": noise_kwargs,
            **self._pixels_key(cache, train),
            "weights": VARIANCE_MATCH_WEIGHTS,
            "crop": crop,
        }
        name = f"variance_scale_{noise_name}_{canonical_digest(key)[:12]}.json"
        record = cache.load_record(name, expected_key=key)
        if record is None:
            samples = (
                (depth_mm, sigma_mm, pixels, crop_coverage(*np.shape(depth_mm), self.crop))
                for depth_mm, sigma_mm, pixels in self._training_samples(provider, train.ids)
            )
            scale = float(variance_matching_scale(noise_model, samples))
            record = {
                "scale": scale,
                "noise": noise_name,
                "pixels": TRAINING_PIXELS_RULE,
                "weights": VARIANCE_MATCH_WEIGHTS,
                "crop": crop,
                "num_train_samples": len(train.ids),
                "note": "std multiplier giving the hetero mean perturbation variance over the training pixels ("
                + TRAINING_PIXELS_RULE_TEXT
                + "), each weighted by the share of random training crops that cover it",
            }
            if noise_name == "fixed":  # the matched sigma itself
                record["sigma_mm"] = scale * float(noise_model.sigma_mm)
            cache.save_record(name, record, key=key)
            record = cache.load_record(name, expected_key=key) or record
        log.info("variance-matched %s noise: scale %.6g", noise_name, record["scale"])
        return noise_model.with_scale(float(record["scale"])), record

    def _simulated_captures(
        self, base: Path, provider: MapProvider, cache: MapCache, test_ids: list[str], changed: list[str]
    ) -> MapCache:
        """The simulator-noised test split's captures, computed for every test sample not stored yet or whose files
        changed (``changed``; a capture whose files changed later is recomputed when it is read: its stamps)."""
        hp = self.hparams
        sim = simulated_cache(base, self.simulated_settings, cache.digest, hp.seed, self.calib, hp.use_cache)
        dataset = self._simulated_dataset(provider, sim, test_ids)
        recompute = set(changed)
        todo = [i for i in test_ids if i in recompute or not sim.path(i).is_file()] if hp.use_cache else []
        workers = int(hp.num_workers) if len(todo) > 1 else 0
        for _ in DataLoader(_Captures(dataset, todo), batch_size=None, num_workers=workers):
            pass
        return sim

    def _simulated_dataset(self, provider: MapProvider, sim: MapCache, test_ids: list[str]) -> SimulatedCaptures:
        hp = self.hparams
        percentiles = (hp.signal_lower_percentile, hp.signal_upper_percentile)
        return SimulatedCaptures(provider, test_ids, sim, self.simulated_settings, hp.seed, percentiles)

    def _real_scenes(self, skipped: dict[str, list[str]]) -> list[Path]:
        """Usable scenes of the capture set (references built or reused); scenes left out go to ``skipped``."""
        hp = self.hparams
        incomplete: list[str] = []  # scene folders without an input frame (list_scenes warns)
        scenes = list_scenes(self.real_dir, incomplete=incomplete)
        usable = []
        empty = []
        for scene in scenes:
            build_reference(scene, min_count=hp.real_min_count)
            if load_real_scene(scene, self.calib, hp.real_min_count)["mask"].any():
                usable.append(scene)
            else:
                empty.append(scene.name)
        if empty:
            warnings.warn(
                f"real capture set {self.real_dir}: {len(empty)} scene(s) with no common valid pixel "
                f"skipped: {', '.join(empty[:5])}",
                stacklevel=2,
            )
        if empty or incomplete:
            skipped["real"] = sorted(empty + incomplete)
        if not usable:
            raise ValueError(f"real capture set {self.real_dir} has no scene with a valid common region")
        return usable

    # ------------------------------------------------------------------ datasets
    def setup(self, stage: str | None = None) -> None:
        """Load what ``prepare_data`` wrote (in this process or another) and build the datasets.

        Args:
            stage: Lightning's stage (``"fit"``, ``"validate"``, ``"test"``, ``"predict"``) or None; every split's
                dataset is built whatever the stage.
        """
        state = self.prepared
        hp = self.hparams
        provider, splits, model, eval_model = state.provider, state.splits, state.noise_model, state.eval_noise_model
        holes = self.hole_model
        self.datasets = {
            "train": SyntheticPairs(
                provider,
                splits["train"],
                "train",
                model,
                hp.seed,
                train=True,
                crop=self.crop,
                flips=hp.flips,
                holes=holes,
            ),
            "val": SyntheticPairs(provider, splits["val"], "val", eval_model, hp.seed, train=False, holes=holes),
            "test": SyntheticPairs(provider, splits["test"], "test", eval_model, hp.seed, train=False, holes=holes),
        }
        if state.simulated_cache is not None:
            self.datasets[SIMULATED_SET] = self._simulated_dataset(provider, state.simulated_cache, splits["test"])
        if state.real_scenes:
            calib, min_count = self.calib, hp.real_min_count
            self.datasets["real"] = RealCaptures(state.real_scenes, _RealLoader(calib, min_count))

    def _loader(self, dataset, train: bool) -> DataLoader:
        hp = self.hparams
        workers = int(hp.num_workers)
        return DataLoader(
            dataset,
            batch_size=hp.batch_size if train else hp.eval_batch_size,
            shuffle=train,
            drop_last=train and len(dataset) >= hp.batch_size,
            num_workers=workers,
            pin_memory=hp.pin_memory,
            persistent_workers=bool(hp.persistent_workers) and workers > 0,
        )

    def _dataset(self, name: str):
        if not self.datasets:
            self.setup()
        return self.datasets[name]

    def train_dataloader(self) -> DataLoader:
        return self._loader(self._dataset("train"), train=True)

    def val_dataloader(self) -> DataLoader:
        return self._loader(self._dataset("val"), train=False)

    def test_dataloader(self) -> list[DataLoader]:
        """One loader per ``test_set_names`` entry, in that order."""
        dataset_of = {"synthetic": "test", SIMULATED_SET: SIMULATED_SET, "real": "real"}
        return [self._loader(self._dataset(dataset_of[name]), train=False) for name in self.test_set_names]

    def predict_dataloader(self) -> DataLoader:
        return self._loader(self._dataset("test"), train=False)

    def summary(self) -> dict[str, Any]:
        """Plain description of what was prepared (sizes, paths, skipped samples, variance scale)."""
        state = self.prepared
        return {
            "source": self.source_name,
            "noise": self.noise_name,
            "eval_noise": self.eval_noise_name,
            "split_file": str(state.split_path),
            "cache_folder": str(state.cache.folder),
            "cache_enabled": state.cache.enabled,
            "sizes": {k: len(v) for k, v in state.splits.items()},
            "skipped": {k: len(v) for k, v in state.skipped.items()},
            "variance_scale": None if state.variance_scale is None else state.variance_scale.get("scale"),
            # which pixels the variance match (or the blind range) was read from: ``TRAINING_PIXELS_RULE``
            "noise_record": state.variance_scale,
            "test_sets": list(self.test_set_names),
            "simulated_test": None
            if self.simulated_settings is None
            else {
                "mixed_pixels": self.simulated_settings.mixed_pixels,
                "fixed_pattern": self.simulated_settings.camera(self.calib).fixed_pattern.to_dict()
                if self.simulated_settings.camera(self.calib).fixed_pattern is not None
                else None,
            },
            "real_scenes": len(state.real_scenes),
            # what the source is (its description, part of the cache key): e.g. the procedural max_depth_mm
            "source_settings": state.source.describe(),
            "holes": None if self.hole_model is None else self.hole_model.to_dict(),
            "calibration": self.calib.fingerprint()[:16],
        }


class _IndexEntries(Dataset):
    """Computes (and caches) one sample's maps; yields (id, {"num_valid", "shape"})."""

    def __init__(self, provider: MapProvider, sample_ids: list[str]):
        self.provider, self.sample_ids = provider, sample_ids

    def __len__(self) -> int:
        return len(self.sample_ids)

    def __getitem__(self, i: int) -> tuple[str, dict]:
        maps, _, stamps = self.provider.get_stamped(self.sample_ids[i])
        entry: dict[str, Any] = {"num_valid": maps.num_valid, "shape": list(maps.depth_mm.shape)}
        if stamps is not None:  # a file-backed source: the files these counts were computed from
            entry["files"] = stamps
        return self.sample_ids[i], entry


@dataclass(frozen=True)
class _TrainingSet:
    """The training split's ids and, for a file-backed source, a digest of their files' content (None without
    files): what a variance scale or a blind range is keyed on beside the maps' key."""

    ids: list[str]
    files_digest: str | None


def _files_digest(index: dict[str, dict], ids: list[str]) -> str | None:
    """Digest of the size and SHA-256 of every file of ``ids`` as ``index`` records them (None when no entry records
    files: a source without files keeps its keys)."""
    if not any("files" in index[i] for i in ids):
        return None
    return canonical_digest([[i, content_digest(index[i].get("files", {}))] for i in ids])


class _TrainingPixels(Dataset):
    """One training sample's (depth_mm, sigma_mm, training pixels) (``ToFDataModule.training_pixels``)."""

    def __init__(self, provider: MapProvider, sample_ids: list[str], pixels: Callable[[str, Any], np.ndarray]):
        self.provider, self.sample_ids, self.pixels = provider, sample_ids, pixels

    def __len__(self) -> int:
        return len(self.sample_ids)

    def __getitem__(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        maps = self.provider.maps(self.sample_ids[i])
        return maps.depth_mm, maps.sigma_mm, self.pixels(self.sample_ids[i], maps)


def _unchanged(item: Any) -> Any:
    """A DataLoader's per-sample conversion that keeps numpy arrays as they are."""
    return item


class _Captures(Dataset):
    """Computes (and caches) the simulated captures of some test samples (DataLoader workers)."""

    def __init__(self, dataset: SimulatedCaptures, sample_ids: list[str]):
        self.dataset, self.sample_ids = dataset, sample_ids

    def __len__(self) -> int:
        return len(self.sample_ids)

    def __getitem__(self, i: int) -> int:
        self.dataset.capture(self.sample_ids[i])
        return i


def blind_percentiles(kwargs: Mapping[str, Any]) -> tuple[float, float]:
    """``noise_kwargs.percentiles`` of the blind model (default ``DEFAULT_BLIND_PERCENTILES``), checked."""
    value = kwargs.get("percentiles", DEFAULT_BLIND_PERCENTILES)
    try:
        lo, hi = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"noise.kwargs.percentiles must be [low, high] percentiles, got {value!r}") from None
    if not 0.0 <= lo < hi <= 100.0:
        raise ValueError(f"noise.kwargs.percentiles must satisfy 0 <= low < high <= 100, got {[lo, hi]}")
    return lo, hi


class _RealLoader:
    """Picklable loader of one real scene (DataLoader workers)."""

    def __init__(self, calib: Any, min_count: int | None):
        self.calib = calib
        self.min_count = min_count

    def __call__(self, scene: Path) -> dict[str, np.ndarray]:
        return load_real_scene(scene, self.calib, self.min_count)
