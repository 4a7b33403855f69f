"""The paper's tables as grids of runs, their numbers, and the orderings the paper claims.

Each table is a list of :class:`Row` (a method as the paper names it, the run that reproduces it, the paper's
numbers). A run is identified by ``(backbone, noise, loss)`` and a seed, so a run that appears in several tables
(DVSS + hetero + L1 is a row of Tables 1, 2 and 3) is trained once: its folder is ``<backbone>-<noise>-<loss>-s<seed>``.

The paper's orderings are :class:`Claim` s: a chain of rows whose metric must increase (MAE, lower is better).
A claim is checked in every seed separately; ``docs/results.md`` says in how many seeds it holds.

Tables (``../shared/seeds`` paper, Sec. V):

* ``1``: Table I (synthetic test set) and the real-set comparison (Table IV): DeepToF, ToF-KPN, RCF, the
  classical amplitude-guided bilateral filter (not in the paper), DVSS with L1 and with L_full. Baselines train
  with L1 on the hetero synthesis, like DVSS w/ L1.
* ``2``: Table II: DVSS structure ablation with L1 (``dvss_no_local`` = w/o DWConv & SCR, ``dvss_no_dwconv``,
  ``dvss_se``, ``dvss``) and the loss ablation L1 / L_nar / L_full on the full DVSS.
* ``3``: Table III: DVSS trained with fixed / range / hetero noise, and U-Net / Restormer / DVSS with range vs
  hetero, all with L1; synthetic test split and the real set. Beyond the paper, each backbone also with the
  noise-level-blind Gaussian (``noise=blind``: one sigma per image from the hetero sigma_D range, the way blind
  denoisers are trained), the baseline a reviewer would ask for that the paper did not try.

Every table shows the synthetic test split twice: as the paper scores it (inputs noised by the hetero model, the
"paper protocol"), and captured by the tap-level simulator (``sim_`` columns, the ``simulated`` set: a noise that
no training model generated, ``data_modules.simulated_test``).
* ``dynrange``: beyond the paper: where the noise model pays. U-Net and DVSS trained with fixed / range / hetero
  noise (L1; validation and test always hetero) across the camera's signal dynamic range: the linear route with
  a_max / a_min = 16, 64, 256 (``data.signal_dynamic_range``, rows tagged ``dr16`` ...) and the physical route
  (the default world: these rows are Table III's runs), plus U-Net at 4x the steps on the physical route
  (``x4``) to separate the world from a short schedule. ``tofdenoise.experiments.dynrange`` computes the gains.
  A study, not a table, for the user: ``tofdenoise reproduce --study dynrange`` (``targets``); its runs are kept
  here because they are rows like the tables' rows (shared runs, records, claims).
* ``schedule``: beyond the paper: does the gain last? DVSS trained with fixed / range / hetero noise (L1) for
  ``SCHEDULE_EPOCHS`` epochs, 10x the ``gpu-short`` profile's 10 (about 4,500 optimiser steps there), with its
  validation curve kept (``csv/metrics.csv``), so that the gap between the training noises can be followed along
  training. Meant for ``--profile gpu-short`` (``SCHEDULE_PROFILES``: the page shows it there only);
  ``tofdenoise reproduce --study schedule --profile gpu-short --seeds 0``.
* ``dataseed``: beyond the paper: Table III's rows again with ``data.seed=1`` (rows tagged ``d1``): another
  procedural world, split, hole draw and set of test inputs, so that a step's spread covers the data as well as the
  training seed. Its orderings are Table III's; the page pools both data seeds (``pooled_steps``). Meant for
  ``--profile cpu`` (``DATA_SEED_PROFILES``); ``tofdenoise reproduce --study dataseed --profile cpu --seeds 0 1 2``.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

from tofdenoise.reporting.numbers import METRICS_BY_KEY, MetricColumn, read_number

from .runner import RunSpec

__all__ = [
    "Row",
    "Claim",
    "TABLES",
    "TABLE_TITLES",
    "CLAIMS",
    "run_name",
    "row_spec",
    "table_rows",
    "table_specs",
    "TABLE_COLUMNS",
    "TABLE_PROFILES",
    "column_source",
    "region_set",
    "REGION_PREFIXES",
    "REGION_SETS",
    "column_metric",
    "metric_value",
    "chain_units",
    "claim_diffs",
    "pooled_steps",
]

#: a table column is a metric of ``reporting.numbers.METRIC_COLUMNS`` on the synthetic test set (``mae_mm``),
#: prefixed ``real_``, on the real set (``real_mae_mm``), or, prefixed ``truth_``, on the real set scored against
#: its rendered truth (a simulated set only: ``real_vs_truth.json``, written by ``tofdenoise reproduce`` for each
#: finished learned run, or by ``tofdenoise evaluate --ckpt``;
#: the records' set ``TRUTH_SET``); prefixed ``sim_``, on the simulator-noised test split (``SIM_SET``; a record
#: written before that split existed has none: its cells show as not run)
#: A synthetic or simulator-noised column may name a region of the image after its set's prefix: ``offedge_``
#: (``offedge_mae_mm``, ``sim_offedge_mae_mm``), the pixels away from the target's depth steps, or ``edge_``, the
#: pixels at them (flying pixels; ``regions.json``, written by ``tofdenoise reproduce`` for each finished learned
#: run or by ``tofdenoise evaluate --run --edge-jump-mm``; the records' set ``<set>/<region>``, see
#: :func:`region_set`)
REAL_PREFIX = "real_"
TRUTH_PREFIX = "truth_"
SIM_PREFIX = "sim_"
TRUTH_SET = "real_truth"
SIM_SET = "simulated"
REGION_PREFIXES = {"offedge_": "off_edge", "edge_": "edge"}
#: the sets whose images are scored by region
REGION_SETS = ("synthetic", SIM_SET)


def region_set(set_name: str, region: str) -> str:
    """The records' name of a region of a test set: ``simulated/off_edge``."""
    return f"{set_name}/{region}"


def column_source(column: str) -> tuple[str, str]:
    """(metrics.json set, metric key) of a table column; a KeyError for a column that names no metric."""
    if column.startswith(REAL_PREFIX):
        set_name, key = "real", column[len(REAL_PREFIX) :]
    elif column.startswith(TRUTH_PREFIX):
        set_name, key = TRUTH_SET, column[len(TRUTH_PREFIX) :]
    elif column.startswith(SIM_PREFIX):
        set_name, key = SIM_SET, column[len(SIM_PREFIX) :]
    else:
        set_name, key = "synthetic", column
    for prefix, region in REGION_PREFIXES.items():
        if set_name in REGION_SETS and key.startswith(prefix):
            set_name, key = region_set(set_name, region), key[len(prefix) :]
            break
    if key not in METRICS_BY_KEY:
        raise KeyError(column)
    return set_name, key


def column_metric(column: str) -> MetricColumn:
    """The metric (header, decimals, direction) a table column shows."""
    return METRICS_BY_KEY[column_source(column)[1]]


@dataclass(frozen=True)
class Row:
    """One row of a table: the method's label, the run that reproduces it, and the paper's numbers."""

    key: str
    label: str
    backbone: str
    noise: str = "hetero"
    loss: str = "l1"
    paper: Mapping[str, float] = field(default_factory=dict, compare=False, hash=False)
    #: "train": a ``tofdenoise train`` run; "classical": the tuned, parameter-free filter (``tofdenoise.cli.classic``)
    kind: str = "train"
    #: a variant of the (backbone, noise, loss) run: its folder gets ``-<tag>`` and its ``overrides`` are applied
    tag: str = ""
    overrides: tuple[str, ...] = ()

    def run_stem(self) -> str:
        if self.kind == "classical":
            return self.backbone
        stem = f"{self.backbone}-{self.noise}-{self.loss}"
        return f"{stem}-{self.tag}" if self.tag else stem

    @property
    def seed_independent(self) -> bool:
        """True where the training seed cannot change the row's numbers: the raw input (validation and test inputs
        are synthesised from ``data.seed``, not from the run's ``seed``) and a classical filter (nothing is
        trained; its grid is tuned on those same inputs). Such a row has one value, not a mean over seeds."""
        return self.key == "raw" or self.kind == "classical"


@dataclass(frozen=True)
class Claim:
    """An ordering the paper reports: ``metric`` increases along ``chain`` (row keys, best first)."""

    table: str
    text: str
    metric: str
    chain: tuple[str, ...]


def run_name(row: Row, seed: int) -> str:
    """The folder name of ``row``'s run for ``seed`` (shared by every table the row appears in). A classical row
    has one run for every seed (``Row.seed_independent``): running it per seed would repeat one result and count
    it as several."""
    if row.kind == "classical":
        return row.run_stem()
    return f"{row.run_stem()}-s{seed}"


_DVSS_L1 = {
    "psnr_db": 40.37,
    "ssim": 0.9985,
    "mse_mm2": 91.75,
    "mae_mm": 2.78,
    "real_psnr_db": 35.12,
    "real_mae_mm": 5.04,
}

TABLE_TITLES = {
    "1": "Table I: comparison with iToF denoising methods (synthetic test set) and on the real set (Table IV)",
    "2": "Table II: DVSS structure ablation (L1) and training-objective ablation",
    "3": "Table III: training-noise models and their cross-backbone generalisation (L1)",
}

TABLES: dict[str, tuple[Row, ...]] = {
    "1": (
        Row("raw", "Raw iToF (the noisy input)", "dvss", "hetero", "l1", {"real_psnr_db": 31.68, "real_mae_mm": 7.21}),
        Row(
            "deeptof",
            "DeepToF",
            "deeptof",
            paper={
                "psnr_db": 37.99,
                "ssim": 0.9951,
                "mse_mm2": 158.94,
                "mae_mm": 6.12,
                "real_psnr_db": 33.29,
                "real_mae_mm": 6.18,
            },
        ),
        Row(
            "tofkpn",
            "ToF-KPN",
            "tofkpn",
            paper={
                "psnr_db": 39.19,
                "ssim": 0.9969,
                "mse_mm2": 120.52,
                "mae_mm": 4.88,
                "real_psnr_db": 34.76,
                "real_mae_mm": 5.31,
            },
        ),
        Row(
            "rcf",
            "RCF (our reading)",
            "rcf",
            paper={
                "psnr_db": 39.53,
                "ssim": 0.9972,
                "mse_mm2": 111.41,
                "mae_mm": 4.63,
                "real_psnr_db": 34.48,
                "real_mae_mm": 5.52,
            },
        ),
        Row("bilateral", "Joint bilateral (classical, not in the paper)", "bilateral", kind="classical"),
        Row("dvss_l1", "DVSS w/ L1", "dvss", "hetero", "l1", _DVSS_L1),
        Row(
            "dvss_full",
            "DVSS w/ L_full",
            "dvss",
            "hetero",
            "full",
            {
                "psnr_db": 40.85,
                "ssim": 0.9987,
                "mse_mm2": 82.30,
                "mae_mm": 2.54,
                "real_psnr_db": 35.42,
                "real_mae_mm": 4.87,
            },
        ),
    ),
    "2": (
        Row(
            "no_local",
            "w/o DWConv & SCR (L1)",
            "dvss_no_local",
            paper={"psnr_db": 39.76, "ssim": 0.9954, "mse_mm2": 105.66, "mae_mm": 3.55},
        ),
        Row(
            "no_dwconv",
            "w/o DWConv (L1)",
            "dvss_no_dwconv",
            paper={"psnr_db": 40.00, "ssim": 0.9976, "mse_mm2": 99.89, "mae_mm": 3.19},
        ),
        Row("se", "w/ SE (L1)", "dvss_se", paper={"psnr_db": 40.16, "ssim": 0.9983, "mse_mm2": 96.35, "mae_mm": 3.06}),
        Row(
            "dvss_l1",
            "Full DVSS (L1)",
            "dvss",
            "hetero",
            "l1",
            {k: v for k, v in _DVSS_L1.items() if not k.startswith("real")},
        ),
        Row(
            "dvss_nar",
            "Full DVSS (L_nar)",
            "dvss",
            "hetero",
            "nar",
            {"psnr_db": 40.66, "ssim": 0.9986, "mse_mm2": 85.90, "mae_mm": 2.62},
        ),
        Row(
            "dvss_full",
            "Full DVSS (L_full)",
            "dvss",
            "hetero",
            "full",
            {"psnr_db": 40.85, "ssim": 0.9987, "mse_mm2": 82.30, "mae_mm": 2.54},
        ),
    ),
    "3": (
        Row(
            "dvss_fixed",
            "DVSS, fixed Gaussian",
            "dvss",
            "fixed",
            "l1",
            {"psnr_db": 39.40, "mae_mm": 3.42, "real_psnr_db": 34.41, "real_mae_mm": 5.82},
        ),
        Row(
            "dvss_range",
            "DVSS, range-aware Gaussian",
            "dvss",
            "range",
            "l1",
            {"psnr_db": 39.89, "mae_mm": 3.08, "real_psnr_db": 34.88, "real_mae_mm": 5.36},
        ),
        Row(
            "dvss_hetero",
            "DVSS, hetero (proposed)",
            "dvss",
            "hetero",
            "l1",
            {"psnr_db": 40.37, "mae_mm": 2.78, "real_psnr_db": 35.12, "real_mae_mm": 5.04},
        ),
        Row(
            "unet_range",
            "U-Net, range-aware Gaussian",
            "unet",
            "range",
            "l1",
            {"psnr_db": 38.56, "mae_mm": 4.18, "real_psnr_db": 33.67, "real_mae_mm": 6.34},
        ),
        Row(
            "unet_hetero",
            "U-Net, hetero (proposed)",
            "unet",
            "hetero",
            "l1",
            {"psnr_db": 39.01, "mae_mm": 3.76, "real_psnr_db": 34.12, "real_mae_mm": 5.84},
        ),
        Row(
            "restormer_range",
            "Restormer, range-aware Gaussian",
            "restormer",
            "range",
            "l1",
            {"psnr_db": 39.22, "mae_mm": 3.58, "real_psnr_db": 34.19, "real_mae_mm": 5.91},
        ),
        Row(
            "restormer_hetero",
            "Restormer, hetero (proposed)",
            "restormer",
            "hetero",
            "l1",
            {"psnr_db": 39.68, "mae_mm": 3.22, "real_psnr_db": 34.55, "real_mae_mm": 5.46},
        ),
        # beyond the paper: the noise-level-blind Gaussian (one sigma per image, log-uniform over the training
        # split's sigma_D 5th-95th percentiles), per backbone
        Row("dvss_blind", "DVSS, blind Gaussian (not in the paper)", "dvss", "blind", "l1"),
        Row("unet_blind", "U-Net, blind Gaussian (not in the paper)", "unet", "blind", "l1"),
        Row("restormer_blind", "Restormer, blind Gaussian (not in the paper)", "restormer", "blind", "l1"),
    ),
}

#: the dynamic-range study: tag -> (label, overrides); "" is the physical route, the default world (Table III's runs)
DYNAMIC_RANGES: dict[str, tuple[str, tuple[str, ...]]] = {
    "dr16": ("a_max/a_min = 16", ("++data.signal_route=linear", "++data.signal_dynamic_range=16")),
    "dr64": ("a_max/a_min = 64", ("++data.signal_route=linear", "++data.signal_dynamic_range=64")),
    "dr256": ("a_max/a_min = 256", ("++data.signal_route=linear", "++data.signal_dynamic_range=256")),
    "": ("physical route", ()),
}
DYNRANGE_BACKBONES: dict[str, str] = {"unet": "U-Net", "dvss": "DVSS"}
DYNRANGE_NOISES: dict[str, str] = {"fixed": "fixed", "range": "range", "hetero": "hetero"}
#: the long-schedule control: 4x the optimiser steps (the CPU profile's 12 epochs -> 48), physical route, U-Net
LONG_SCHEDULE = ("x4", "physical route, 4x steps", ("trainer.max_epochs=48",))


def dynrange_key(backbone: str, noise: str, tag: str) -> str:
    return f"{backbone}_{noise}_{tag or 'phys'}"


def _dynrange_rows() -> tuple[Row, ...]:
    rows = []
    for backbone, b_label in DYNRANGE_BACKBONES.items():  # U-Net first: its runs are the quick ones
        for tag, (dr_label, overrides) in DYNAMIC_RANGES.items():
            for noise in DYNRANGE_NOISES:
                label = f"{b_label}, {noise}, {dr_label}"
                rows.append(
                    Row(dynrange_key(backbone, noise, tag), label, backbone, noise, "l1", tag=tag, overrides=overrides)
                )
        if backbone == "unet":
            tag, dr_label, overrides = LONG_SCHEDULE
            for noise in DYNRANGE_NOISES:
                label = f"{b_label}, {noise}, {dr_label}"
                rows.append(
                    Row(dynrange_key(backbone, noise, tag), label, backbone, noise, "l1", tag=tag, overrides=overrides)
                )
    return tuple(rows)


TABLES["dynrange"] = _dynrange_rows()
TABLE_TITLES["dynrange"] = (
    "Beyond the paper: where the noise model pays (training noise across the signal dynamic range, L1)"
)

#: the long-schedule study: 10x gpu-short's 10 epochs
SCHEDULE_EPOCHS = 100
#: its validation every 5 epochs (20 points on the curve; every 2, gpu-short's, would be 50 passes over the 60
#: validation scenes at 480 x 640) and torch.compile for its steps (about 4,500: a compile of about a minute pays
#: back at 86 against 116 ms a bf16 step on an H200), so that a run fits one 10-minute GPU allocation
SCHEDULE_OVERRIDES = ("trainer.check_val_every_n_epoch=5", "model.compile=true")
#: the profiles whose page shows the schedule study (its schedule is defined relative to gpu-short's)
SCHEDULE_PROFILES = ("gpu-short",)
TABLES["schedule"] = tuple(
    Row(
        f"dvss_{noise}_long",
        f"DVSS, {noise}, {SCHEDULE_EPOCHS} epochs",
        "dvss",
        noise,
        "l1",
        tag=f"e{SCHEDULE_EPOCHS}",
        overrides=(*SCHEDULE_OVERRIDES, f"trainer.max_epochs={SCHEDULE_EPOCHS}"),
    )
    for noise in ("fixed", "range", "hetero")
)
TABLE_TITLES["schedule"] = f"Beyond the paper: does the gain last? DVSS, training noise, {SCHEDULE_EPOCHS} epochs (L1)"
#: the second data seed: Table III's rows again on another draw of the world, its split and its test inputs
DATA_SEED = 1
DATA_SEED_TAG = f"d{DATA_SEED}"
TABLES["dataseed"] = tuple(
    replace(row, key=f"{row.key}_{DATA_SEED_TAG}", tag=DATA_SEED_TAG, overrides=(f"++data.seed={DATA_SEED}",))
    for row in TABLES["3"]
)
TABLE_TITLES["dataseed"] = (
    f"Beyond the paper: Table III on a second data seed (data.seed={DATA_SEED}: another world, split and test inputs)"
)
#: the profile whose page shows the data-seed study (the one it is meant for: a CPU profile's world is small)
DATA_SEED_PROFILES = ("cpu",)
#: the tables each profile's page shows (every table where not listed)
TABLE_PROFILES: dict[str, tuple[str, ...]] = {"schedule": SCHEDULE_PROFILES, "dataseed": DATA_SEED_PROFILES}

#: Table III's columns (and its data-seed repeat's): the paper's, the simulator-noised split, the off-edge pixels
_NOISE_COLUMNS = (
    "psnr_db",
    "mae_mm",
    "offedge_mae_mm",
    "sim_mae_mm",
    "sim_offedge_mae_mm",
    "real_psnr_db",
    "real_mae_mm",
    "truth_mae_mm",
)
#: which metric columns each table shows (the paper's)
TABLE_COLUMNS: dict[str, tuple[str, ...]] = {
    "1": ("psnr_db", "ssim", "mse_mm2", "mae_mm", "sim_mae_mm", "real_psnr_db", "real_mae_mm", "truth_mae_mm"),
    "2": ("psnr_db", "ssim", "mse_mm2", "mae_mm", "sim_mae_mm"),
    "3": _NOISE_COLUMNS,
    "dynrange": ("psnr_db", "mae_mm", "real_mae_mm"),
    "schedule": ("psnr_db", "mae_mm", "real_mae_mm", "truth_mae_mm"),
    "dataseed": _NOISE_COLUMNS,
}

CLAIMS: tuple[Claim, ...] = (
    Claim("1", "DVSS L_full < DVSS L1 (synthetic MAE)", "mae_mm", ("dvss_full", "dvss_l1")),
    Claim("1", "DVSS L1 < RCF < ToF-KPN < DeepToF (synthetic MAE)", "mae_mm", ("dvss_l1", "rcf", "tofkpn", "deeptof")),
    Claim(
        "1",
        "real MAE: DVSS L_full < ToF-KPN < RCF < DeepToF < raw",
        "real_mae_mm",
        ("dvss_full", "tofkpn", "rcf", "deeptof", "raw"),
    ),
    # the same ordering against the stand-in's rendered truth instead of its reference (beyond the paper: its real
    # set has no truth)
    Claim(
        "1",
        "real vs truth MAE: DVSS L_full < ToF-KPN < RCF < DeepToF < raw",
        "truth_mae_mm",
        ("dvss_full", "tofkpn", "rcf", "deeptof", "raw"),
    ),
    Claim(
        "2",
        "structure (L1): full < w/ SE < w/o DWConv < w/o DWConv & SCR (MAE)",
        "mae_mm",
        ("dvss_l1", "se", "no_dwconv", "no_local"),
    ),
    Claim("2", "objective: L_full < L_nar < L1 (MAE)", "mae_mm", ("dvss_full", "dvss_nar", "dvss_l1")),
    Claim("3", "DVSS: hetero < range < fixed (synthetic MAE)", "mae_mm", ("dvss_hetero", "dvss_range", "dvss_fixed")),
    Claim("3", "DVSS: hetero < range < fixed (real MAE)", "real_mae_mm", ("dvss_hetero", "dvss_range", "dvss_fixed")),
    Claim("3", "hetero < range for U-Net (synthetic MAE)", "mae_mm", ("unet_hetero", "unet_range")),
    Claim("3", "hetero < range for Restormer (synthetic MAE)", "mae_mm", ("restormer_hetero", "restormer_range")),
    Claim("3", "hetero < range for U-Net (real MAE)", "real_mae_mm", ("unet_hetero", "unet_range")),
    Claim("3", "hetero < range for Restormer (real MAE)", "real_mae_mm", ("restormer_hetero", "restormer_range")),
    Claim(
        "3",
        "DVSS: hetero < range < fixed (real vs truth MAE)",
        "truth_mae_mm",
        ("dvss_hetero", "dvss_range", "dvss_fixed"),
    ),
    Claim("3", "hetero < range for U-Net (real vs truth MAE)", "truth_mae_mm", ("unet_hetero", "unet_range")),
    Claim(
        "3",
        "hetero < range for Restormer (real vs truth MAE)",
        "truth_mae_mm",
        ("restormer_hetero", "restormer_range"),
    ),
    *(
        Claim("3", f"hetero < blind for {label} ({what})", metric, (f"{b}_hetero", f"{b}_blind"))
        for b, label in (("dvss", "DVSS"), ("unet", "U-Net"), ("restormer", "Restormer"))
        for metric, what in (
            ("mae_mm", "synthetic MAE"),
            ("sim_mae_mm", "simulator-noised MAE"),
            ("truth_mae_mm", "real vs truth MAE"),
        )
    ),
    Claim(
        "3",
        "DVSS: hetero < range < fixed (simulator-noised MAE)",
        "sim_mae_mm",
        ("dvss_hetero", "dvss_range", "dvss_fixed"),
    ),
    Claim("3", "hetero < range for U-Net (simulator-noised MAE)", "sim_mae_mm", ("unet_hetero", "unet_range")),
    Claim(
        "3",
        "hetero < range for Restormer (simulator-noised MAE)",
        "sim_mae_mm",
        ("restormer_hetero", "restormer_range"),
    ),
    # the same steps off the depth edges, where a pixel sees one surface: is the lead the noise model's, or the
    # flying pixels' at the edges (regions.json)?
    *(
        Claim("3", f"{label}: {chain_text} ({what} off depth edges)", metric, chain)
        for metric, what in (("offedge_mae_mm", "synthetic MAE"), ("sim_offedge_mae_mm", "simulator-noised MAE"))
        for label, chain_text, chain in (
            ("DVSS", "hetero < range < fixed", ("dvss_hetero", "dvss_range", "dvss_fixed")),
            ("U-Net", "hetero < range", ("unet_hetero", "unet_range")),
            ("Restormer", "hetero < range", ("restormer_hetero", "restormer_range")),
            ("DVSS", "hetero < blind", ("dvss_hetero", "dvss_blind")),
            ("U-Net", "hetero < blind", ("unet_hetero", "unet_blind")),
            ("Restormer", "hetero < blind", ("restormer_hetero", "restormer_blind")),
        )
    ),
    Claim(
        "3",
        "hetero training: DVSS < Restormer < U-Net (synthetic MAE)",
        "mae_mm",
        ("dvss_hetero", "restormer_hetero", "unet_hetero"),
    ),
    *(
        Claim(
            "dynrange",
            f"{b_label}, {label}: hetero < range < fixed (synthetic MAE)",
            "mae_mm",
            tuple(dynrange_key(backbone, noise, tag) for noise in ("hetero", "range", "fixed")),
        )
        for backbone, b_label in DYNRANGE_BACKBONES.items()
        for tag, label in [(t, lab) for t, (lab, _) in DYNAMIC_RANGES.items()]
        + ([(LONG_SCHEDULE[0], LONG_SCHEDULE[1])] if backbone == "unet" else [])
    ),
    Claim(
        "schedule",
        f"DVSS, {SCHEDULE_EPOCHS} epochs: hetero < range < fixed (synthetic MAE)",
        "mae_mm",
        ("dvss_hetero_long", "dvss_range_long", "dvss_fixed_long"),
    ),
    Claim(
        "schedule",
        f"DVSS, {SCHEDULE_EPOCHS} epochs: hetero < range < fixed (real vs truth MAE)",
        "truth_mae_mm",
        ("dvss_hetero_long", "dvss_range_long", "dvss_fixed_long"),
    ),
)

#: Table III's orderings on the second data seed (the same chains, rows tagged ``d1``)
CLAIMS += tuple(
    Claim("dataseed", claim.text, claim.metric, tuple(f"{key}_{DATA_SEED_TAG}" for key in claim.chain))
    for claim in CLAIMS
    if claim.table == "3"
)


def table_rows(table: str) -> tuple[Row, ...]:
    if table not in TABLES:
        raise ValueError(f"unknown table {table!r}; valid: {', '.join(TABLES)}")
    return TABLES[table]


def row_spec(
    row: Row,
    seed: int,
    common: Sequence[str] = (),
    per_backbone: Mapping[str, Sequence[str]] | None = None,
    table: str = "",
) -> RunSpec:
    """The run of ``row`` for ``seed`` (its folder is :func:`run_name`). A classical row becomes a ``RunSpec`` with
    ``entry="classical"`` (run by ``python -m tofdenoise.cli.classic``, which reads the same overrides)."""
    if row.kind == "classical":
        overrides: tuple[str, ...] = (*common, f"seed={seed}")
    else:
        overrides = (
            f"backbone={row.backbone}",
            f"noise={row.noise}",
            f"loss={row.loss}",
            f"seed={seed}",
            *common,
            *(per_backbone or {}).get(row.backbone, ()),
            *row.overrides,
        )
    meta = {"table": table, "row": row.key, "seed": seed, "kind": row.kind}
    return RunSpec(run_name(row, seed), overrides, meta, entry=row.kind)


def table_specs(
    table: str,
    seeds: Sequence[int],
    common: Sequence[str] = (),
    per_backbone: Mapping[str, Sequence[str]] | None = None,
) -> list[RunSpec]:
    """The runs of ``table`` for ``seeds`` (one per distinct run; the raw row needs no run of its own).

    ``common``: overrides for every training run (the profile's experiment, the sensor, the real set);
    ``per_backbone``: extra overrides for one backbone (:func:`row_spec`).
    """
    specs: dict[str, RunSpec] = {}
    rows = table_rows(table)
    # the dynamic-range study runs backbone by backbone (every seed of the quick U-Net runs first), the tables
    # seed by seed
    groups = [[r for r in rows if r.backbone == b] for b in dict.fromkeys(r.backbone for r in rows)]
    for group in groups if table == "dynrange" else [list(rows)]:
        for seed in seeds:
            for row in group:
                if row.key == "raw" or run_name(row, seed) in specs:
                    continue
                specs[run_name(row, seed)] = row_spec(row, seed, common, per_backbone, table)
    return list(specs.values())


def metric_value(metrics: Mapping[str, Any] | None, column: str, raw: bool = False) -> float:
    """One table column's value (:func:`column_source`) of a run's ``metrics.json`` (``raw``: the noisy input's);
    NaN when absent."""
    if not metrics:
        return math.nan
    set_name, key = column_source(column)
    entry = metrics.get(set_name) or {}
    if raw:
        entry = entry.get("raw") or {}
    v = read_number(entry.get(key))
    return math.nan if v is None else v


def row_values(row: Row, seeds: Sequence[int], metrics_of: Any, column: str) -> list[float]:
    """Per-seed values of ``column`` for ``row``; ``metrics_of(run_name) -> metrics.json dict or None``.

    The raw row reads the noisy input's metrics from the DVSS L1 run of the same seed (every run of a seed is
    evaluated on identical inputs: ``data.eval_noise``).
    """
    if row.key == "raw":
        return [metric_value(metrics_of(run_name(row, s)), column, raw=True) for s in seeds]
    return [metric_value(metrics_of(run_name(row, s)), column) for s in seeds]


def chain_values(claim: Claim, seeds: Sequence[int], metrics_of: Any) -> list[list[float]]:
    """Per row of ``claim``'s chain (best first), its per-seed values of ``claim.metric`` (NaN where missing)."""
    rows = {r.key: r for r in TABLES[claim.table]}
    return [row_values(rows[k], seeds, metrics_of, claim.metric) for k in claim.chain]


def chain_units(
    claim: Claim, seeds: Sequence[int], metrics_of: Any, units_of: Any
) -> list[list[Mapping[str, float]]] | None:
    """Per row of ``claim``'s chain (best first), its per-unit values of ``claim.metric`` (test image or scene name
    -> value) in each seed in which every row of the chain has a value (the seeds :func:`claim_steps` pairs);
    ``units_of(run_name, set_name, key) -> {unit: value} or None`` reads a run's per-image record (the raw row:
    key ``raw_<key>`` of the DVSS L1 run of the seed, as :func:`row_values`). None when no seed is complete or a
    run of a complete seed has no per-image record."""
    rows = {r.key: r for r in TABLES[claim.table]}
    per_row = chain_values(claim, seeds, metrics_of)
    complete = [seeds[i] for i in range(len(seeds)) if all(math.isfinite(v[i]) for v in per_row)]
    if not complete:
        return None
    set_name, key = column_source(claim.metric)
    out: list[list[Mapping[str, float]]] = []
    for row_key in claim.chain:
        row = rows[row_key]
        wanted = f"raw_{key}" if row.key == "raw" else key
        values = [units_of(run_name(row, s), set_name, wanted) for s in complete]
        if any(not v for v in values):
            return None
        out.append(values)
    return out


def claim_holds(claim: Claim, seed: int, metrics_of: Any) -> bool | None:
    """Whether ``claim`` holds for ``seed``: True / False, or None when a value is missing."""
    values = [v[0] for v in chain_values(claim, [seed], metrics_of)]
    if any(not math.isfinite(v) for v in values):
        return None
    return all(a < b for a, b in zip(values, values[1:]))


def claim_steps(claim: Claim, seeds: Sequence[int], metrics_of: Any) -> list[tuple[float, float | None]]:
    """How far apart the rows of ``claim``'s chain lie, paired by seed: per step (row k -> row k+1) the mean over
    the seeds of ``value(k+1) - value(k)`` in ``claim.metric`` (positive where that step of the ordering holds) and
    the standard deviation of that per-seed difference (None with fewer than 2 seeds), both over the seeds in which
    every row of the chain has a value. The rows of one seed share its data order and, within a backbone, its
    initial weights, so the spread of the per-seed difference is the noise a step must clear (it is not the larger
    spread of either row). ``[]`` when no seed is complete."""
    return [_mean_sd(diffs) for diffs in claim_diffs(claim, seeds, metrics_of)]


def _mean_sd(diffs: Sequence[float]) -> tuple[float, float | None]:
    return statistics.fmean(diffs), statistics.stdev(diffs) if len(diffs) >= 2 else None


def claim_diffs(claim: Claim, seeds: Sequence[int], metrics_of: Any) -> list[list[float]]:
    """Per step of ``claim``'s chain (row k -> row k+1), the per-seed differences ``value(k+1) - value(k)`` over the
    seeds in which every row of the chain has a value (what :func:`claim_steps` summarises); ``[]`` when no seed is
    complete."""
    per_row = chain_values(claim, seeds, metrics_of)
    complete = [i for i in range(len(seeds)) if all(math.isfinite(v[i]) for v in per_row)]
    if not complete:
        return []
    return [[b[i] - a[i] for i in complete] for a, b in zip(per_row, per_row[1:])]


def pooled_steps(
    claims: Sequence[Claim], seeds: Sequence[int], metrics_of: Any
) -> tuple[list[tuple[float, float | None]], int, int]:
    """One ordering measured on several data seeds (``claims``: the same chain on each, e.g. Table III's and the
    ``dataseed`` study's), pooled over every complete (data seed, training seed) pair: per step the mean and the
    standard deviation of the paired difference over the pairs, the number of pairs, and in how many of them every
    step holds (the ordering holds)."""
    diffs_per_claim = [claim_diffs(claim, seeds, metrics_of) for claim in claims]
    diffs_per_claim = [d for d in diffs_per_claim if d]
    if not diffs_per_claim:
        return [], 0, 0
    steps = len(diffs_per_claim[0])
    pooled = [[x for d in diffs_per_claim for x in d[k]] for k in range(steps)]
    pairs = len(pooled[0])
    holds = sum(all(pooled[k][i] > 0 for k in range(steps)) for i in range(pairs))
    return [_mean_sd(p) for p in pooled], pairs, holds
