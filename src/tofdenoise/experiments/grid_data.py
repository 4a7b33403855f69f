"""A grid's data prepared once before its runs train several at a time.

Each training run prepares its data (``ToFDataModule.prepare_data``: the split, every sample's clean / signal / σ_D
maps, the simulator-noised test captures, the Gaussian baselines' variance match and the blind model's σ range)
and stores it under ``data.cache_dir``, where the next run with the same data finds it. Runs started together on a
fresh cache (``tofdenoise reproduce --executor local --workers N``) each compute the same maps at once: on a GPU
machine three DVSS runs of the ``gpu-short`` profile spent their first minute building the same 300 scenes, with 4
loader workers each. :func:`prepare_grid_data` does it once first, in this process, with every CPU core.

The runs are unchanged by it: what a run trains on is read from the cache whoever wrote it (the stored maps and
records are the same to the bit whatever the number of loader workers), and a run's draws from torch's global
generator do not depend on whether its cache was cold or warm (``tests/data_modules/test_datamodule.py``).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Sequence

from hydra.errors import HydraException
from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from tofdenoise.config import ConfigError, compose_config, instantiate_node
from tofdenoise.experiments.runner import RunSpec

__all__ = ["prepare_grid_data"]


def prepare_grid_data(
    specs: Sequence[RunSpec], workers: int | None = None, log: Callable[[str], None] = print
) -> list[str]:
    """Prepare the data of each distinct ``data`` node among ``specs``' training runs (their overrides composed as
    ``tofdenoise train`` composes them), one after another with ``workers`` loader workers (default: every CPU);
    returns the names of the runs whose data were prepared, one per distinct node. A run whose config cannot be
    composed or built is left to fail in its own process, with its own message (logged here too)."""
    workers = (os.cpu_count() or 1) if workers is None else workers
    seen: set[str] = set()
    prepared = []
    for spec in specs:
        if spec.entry != "train":
            continue
        try:
            cfg = compose_config(list(spec.overrides))
            key = OmegaConf.to_yaml(cfg.data, resolve=True)
            if key in seen:
                continue
            seen.add(key)
            t0 = time.perf_counter()
            datamodule = instantiate_node(cfg.data, "data", num_workers=workers)
            datamodule.prepare_data()
        except (ConfigError, HydraException, OmegaConfBaseException, ValueError, FileNotFoundError) as exc:
            reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            log(f"[reproduce] {spec.name}: data not prepared ahead ({reason}); the run prepares its own")
            continue
        prepared.append(spec.name)
        log(f"[reproduce] data of {spec.name} prepared ahead in {time.perf_counter() - t0:.0f} s ({workers} workers)")
    return prepared
