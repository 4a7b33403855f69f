"""A run's records: what a training or evaluation run leaves in its folder, in one package.

- :mod:`~tofdenoise.records.metrics_json`: ``metrics.json`` (test results per set, restored and raw, plus the
  run-level fields ``RUN_KEYS``): ``set_entry``, ``write_metrics_json``, ``read_metrics_json``, ``metric_sets``,
  ``run_fields``, ``json_number`` (strict JSON numbers);
- :mod:`~tofdenoise.records.verdict`: the learned guard, ``learned_verdict`` / ``classical_verdict`` /
  ``learned_status`` (the one place its rule lives);
- :mod:`~tofdenoise.records.per_image`: ``per_image/<set>.csv``;
- :mod:`~tofdenoise.records.run_folder`: the file names of a run folder, ``read_record`` / ``load_metrics`` /
  ``load_scored_metrics`` (strict: a ``RecordError`` names the file; the last one is what a table of runs can use),
  ``read_run`` (lenient), ``run_finished`` (the one rule of a finished run), ``unreadable_records``,
  ``write_run_info`` and ``write_scene_record`` (the per-scene records, compact);
- :mod:`~tofdenoise.records.provenance`: the git commit of the code that made a record (``code_commit``, written
  into every ``run_info.json``; ``record_commit`` reads it back, ``None`` for older records; ``is_ancestor`` orders
  two commits; ``host_machine`` / ``record_machine`` / ``cpu_label``: the machine a run trained on, and how many
  runs shared it, ``RUNS_AT_ONCE_ENV``; ``written_provenance``: the same for a record no training run writes, such
  as Fig. 6's ``validation.json``).

Writers: ``tofdenoise.callbacks.run_outputs.RunOutputs`` (every trained run), the classical row; readers: the
training job and the grids' runner (skip or return finished runs), ``tofdenoise.reporting`` (report, results page,
grid table). Every file is written through :mod:`tofdenoise.atomic`. This package imports only ``atomic`` (and runs
``git`` for the commit).
"""

from tofdenoise.records.metrics_json import (
    CSV_COLUMNS,
    EDGE_JUMP_MM,
    EXTRA_KEYS,
    METHOD_KINDS,
    METRIC_KEYS,
    RUN_KEYS,
    TEST_SET_LABELS,
    json_number,
    metric_sets,
    read_metrics_json,
    run_fields,
    set_entry,
    validate_metrics_results,
    write_metrics_json,
)
from tofdenoise.records.per_image import read_per_image_csv, write_per_image_csv
from tofdenoise.records.provenance import (
    RUNS_AT_ONCE_ENV,
    code_commit,
    code_digest,
    cpu_label,
    host_machine,
    is_ancestor,
    record_commit,
    record_machine,
    written_provenance,
)
from tofdenoise.records.run_folder import (
    BEST_CHECKPOINT,
    FITTED,
    INTERRUPTED,
    LAST_CHECKPOINT,
    METRICS_NAME,
    PER_IMAGE_DIR,
    REGIONS_NAME,
    REQUIRED_SET,
    RESULT_RECORDS,
    RUN_INFO_NAME,
    TRUTH_NAME,
    UNREADABLE,
    VARIANCE_MATCH_WEIGHTS,
    RecordError,
    fit_best_checkpoints,
    load_metrics,
    load_scored_metrics,
    matched_on_whole_maps,
    read_record,
    read_run,
    remove_results,
    run_finished,
    training_state,
    unreadable_records,
    write_run_info,
    write_scene_record,
)
from tofdenoise.records.verdict import DEFAULT_LEARNED_MARGIN, classical_verdict, learned_status, learned_verdict

__all__ = [
    "VARIANCE_MATCH_WEIGHTS",
    "matched_on_whole_maps",
    "BEST_CHECKPOINT",
    "RUNS_AT_ONCE_ENV",
    "CSV_COLUMNS",
    "EDGE_JUMP_MM",
    "DEFAULT_LEARNED_MARGIN",
    "EXTRA_KEYS",
    "LAST_CHECKPOINT",
    "METHOD_KINDS",
    "METRICS_NAME",
    "METRIC_KEYS",
    "PER_IMAGE_DIR",
    "RUN_INFO_NAME",
    "REQUIRED_SET",
    "RESULT_RECORDS",
    "RUN_KEYS",
    "RecordError",
    "TEST_SET_LABELS",
    "TRUTH_NAME",
    "REGIONS_NAME",
    "classical_verdict",
    "code_commit",
    "code_digest",
    "cpu_label",
    "training_state",
    "fit_best_checkpoints",
    "FITTED",
    "INTERRUPTED",
    "UNREADABLE",
    "host_machine",
    "is_ancestor",
    "json_number",
    "learned_status",
    "learned_verdict",
    "load_metrics",
    "load_scored_metrics",
    "metric_sets",
    "read_metrics_json",
    "read_per_image_csv",
    "read_record",
    "read_run",
    "record_commit",
    "remove_results",
    "record_machine",
    "run_fields",
    "run_finished",
    "set_entry",
    "unreadable_records",
    "validate_metrics_results",
    "write_metrics_json",
    "write_per_image_csv",
    "write_run_info",
    "write_scene_record",
    "written_provenance",
]
