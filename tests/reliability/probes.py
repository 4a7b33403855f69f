"""The probe table: every command that reads or writes user files, and the faults each is probed with.

``COMMANDS`` maps a command as a user types it (``tofdenoise <verb>``, ``tofdenoise sensor <subcommand>``) to the
console script and the arguments that select it; the rows name commands by these keys.

``PROBES`` holds one row per (command, family, case). A row gives the arguments (``argv(world)``), what is done to
the inputs first (``damage(world)``), the exit status a user must get, what one line of stderr must name, and which
paths of the world may change (by default nothing may: inputs unchanged, nothing written). ``EXEMPT`` says, with a
reason, which families do not apply to a command. ``test_every_command_has_a_row_in_every_family`` fails when a
verb of ``tofdenoise.cli.main.VERBS`` (or a sub-command of ``tofdenoise sensor``) has neither.

Families: ``bad_frames``, ``bad_captures``, ``bad_yaml``, ``misuse_outputs``, ``concurrent``, ``corrupt_records``,
``full_disk``, ``signals``. How to add a command: docs/reliability.md.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

#: every command a user types: ``tofdenoise <verb>`` for each verb of ``tofdenoise.cli.main.VERBS`` and
#: ``tofdenoise sensor <subcommand>`` for each sub-command of ``sensor`` (test_probes.py checks both ways)
COMMAND_NAMES = (
    "tofdenoise train",
    "tofdenoise classic",
    "tofdenoise fit",
    "tofdenoise validate",
    "tofdenoise test",
    "tofdenoise predict",
    "tofdenoise denoise",
    "tofdenoise export",
    "tofdenoise evaluate",
    "tofdenoise report",
    "tofdenoise grid",
    "tofdenoise reproduce",
    "tofdenoise sensor show-calib",
    "tofdenoise sensor sigma",
    "tofdenoise sensor calibrate",
    "tofdenoise sensor validate",
    "tofdenoise sensor simulate-captures",
    "tofdenoise sensor simulate-calibration",
    "tofdenoise sensor simulate-validation",
    "tofdenoise sensor realset",
    "tofdenoise sensor build-reference",
)
#: command as typed -> (console script, the arguments that select the command)
COMMANDS: dict[str, tuple[str, tuple[str, ...]]] = {
    name: (name.split()[0], tuple(name.split()[1:])) for name in COMMAND_NAMES
}

FAMILIES = (
    "bad_frames",
    "bad_captures",
    "bad_yaml",
    "misuse_outputs",
    "concurrent",
    "corrupt_records",
    "full_disk",
    "signals",
)

W = Any  # the test's World (tests/reliability/conftest.py): ``w / "frames"`` is a path in it


@dataclass(frozen=True)
class Probe:
    command: str
    family: str
    case: str
    argv: Callable[[W], list[Any]]
    damage: Callable[[W], None] | None = None
    status: int = 2
    #: strings one line of stderr must hold together (the file or field the error is about)
    names: Callable[[W], list[str]] = lambda w: []
    #: world paths (relative, prefixes) that may be written or changed; nothing else may
    may_change: tuple[str, ...] = ()
    #: how the row runs: "call" (the entry point in this process), "locked" (another process holds the run lock of
    #: ``lock_dir``), "race" (another run of the command, ``extra["other"](world)``, starts and finishes while this
    #: one works: when it first calls ``extra["during"]``, a function it calls after its checks and before it
    #: publishes), "signal" (a separate process, see test_signals.py)
    runner: str = "call"
    lock_dir: Callable[[W], Path] | None = None
    slow: bool = False
    #: extra checks of the outcome: ``check(world, outcome)``
    check: Callable[[W, Any], None] | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def id(self) -> str:
        return f"{self.command.replace(' ', ':')}-{self.family}-{self.case}"


# ---------------------------------------------------------------------------------------------------- damage


def truncate(rel: str, keep: int = 60) -> Callable[[W], None]:
    def damage(w: W) -> None:
        p = w / rel
        p.write_bytes(p.read_bytes()[:keep])

    return damage


def write_png8(rel: str) -> Callable[[W], None]:
    def damage(w: W) -> None:
        img = cv2.imread(str(w / rel), cv2.IMREAD_UNCHANGED)
        assert cv2.imwrite(str(w / rel), (img // 8).astype(np.uint8))

    return damage


def npy_in_metres(*rels: str) -> Callable[[W], None]:
    def damage(w: W) -> None:
        for rel in rels:
            p = w / rel
            if p.suffix == ".npy":
                np.save(p, np.load(p).astype(np.float32) / 1000.0)
            else:  # a PNG in metres: stored as float .npy beside it, the PNG removed
                img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED).astype(np.float32) / 1000.0
                p.unlink()
                np.save(p.with_suffix(".npy"), img)

    return damage


def depth_times(rel: str, factor: float) -> Callable[[W], None]:
    """A depth frame in other units: x10 (a camera counting 0.1 mm) or / 10 (centimetres), same file type."""

    def damage(w: W) -> None:
        p = w / rel
        if p.suffix == ".npy":
            np.save(p, (np.load(p) * factor).astype(np.float32))
        else:
            img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED).astype(np.float64) * factor
            assert img.max() < 65536 and cv2.imwrite(str(p), np.rint(img).astype(np.uint16))

    return damage


def restored_in_mm(rel: str) -> Callable[[W, Any], None]:
    """The restored frame's valid depths are millimetres of the world's scene (800-1100 mm)."""

    def check(w: W, outcome: Any) -> None:
        restored = cv2.imread(str(w / rel), cv2.IMREAD_UNCHANGED)
        assert 700 < float(np.median(restored[restored > 0])) < 1200, outcome.err

    return check


def npy_dtype(rel: str, dtype: str) -> Callable[[W], None]:
    def damage(w: W) -> None:
        np.save(w / rel, np.load(w / rel).astype(dtype))

    return damage


def absurd_depth(rel: str, block: bool = False) -> Callable[[W], None]:
    """Depth values of 2^40 mm (1.1e12 mm): the whole frame, or a 10 x 20 block of valid pixels (median unchanged)."""

    def damage(w: W) -> None:
        depth = np.load(w / rel)
        if block:
            depth[20:30, 20:40] = 2.0**40
        else:
            depth[:] = 2.0**40
        np.save(w / rel, depth)

    return damage


def _no_warning_line(outcome: Any) -> None:
    """No Python warning (with its source line) reached the user."""
    assert "Warning:" not in outcome.err, outcome.err


#: the block of ``amp/sub/b.npy`` that ``nan_amplitude(..., block=True)`` makes NaN (depth is valid there)
NAN_AMPLITUDE_BLOCK = (slice(20, 30), slice(20, 40))


def nan_amplitude(rel: str, block: bool = False) -> Callable[[W], None]:
    """An amplitude frame that is NaN everywhere (a dropped IR stream saved as float), or in one block."""

    def damage(w: W) -> None:
        amp = np.load(w / rel)
        if block:
            amp[NAN_AMPLITUDE_BLOCK] = np.nan
        else:
            amp[:] = np.nan
        np.save(w / rel, amp)

    return damage


def sigma_nan_where_the_amplitude_is(w: W, outcome: Any) -> None:
    """The sigma_D map of ``frames/sub/b.npy`` is NaN (invalid) in the NaN block of its amplitude, finite at the
    other valid depths."""
    sigma = np.load(w / "out/d/sub/b_sigma_mm.npy")
    depth_valid = np.isfinite(np.load(w / "frames/sub/b.npy"))
    assert np.isnan(sigma[NAN_AMPLITUDE_BLOCK]).all(), "sigma_D is not NaN where the amplitude is NaN"
    elsewhere = depth_valid.copy()
    elsewhere[NAN_AMPLITUDE_BLOCK] = False
    assert np.isfinite(sigma[elsewhere]).all() and np.isnan(sigma[~depth_valid]).all()


def remove(rel: str) -> Callable[[W], None]:
    def damage(w: W) -> None:
        p = w / rel
        if p.is_dir():
            import shutil

            shutil.rmtree(p)
        else:
            p.unlink()

    return damage


def _no_run_record(run_dir: Path) -> None:
    """A refused run wrote nothing of a run into its folder: no ``.hydra/``, log, ``config.log`` or ``csv/``."""
    left = sorted(p.name for p in run_dir.iterdir()) if run_dir.exists() else []
    assert set(left) <= {"run.lock"}, f"{run_dir} holds {left}"


def first_stack(w: W, folder: str) -> str:
    """The first stack file of a capture folder (from its index.json), relative to the world."""
    index = json.loads((w / folder / "index.json").read_text())
    return f"{folder}/{index['stacks'][0]['file']}"


def mixed_sizes(folder: str) -> Callable[[W], None]:
    def damage(w: W) -> None:
        rel = first_stack(w, folder)
        stack = np.load(w / rel)
        np.save(w / rel, np.concatenate([stack, stack], axis=-1))  # (F, N, H, 2W)

    return damage


def truncate_stack(folder: str) -> Callable[[W], None]:
    def damage(w: W) -> None:
        truncate(first_stack(w, folder), 200)(w)

    return damage


#: a calibration YAML broken four ways (the bad_yaml family): name -> (damage of calib.yaml, what the error names)
def _yaml_syntax(w: W) -> None:
    (w / "calib.yaml").write_text((w / "calib.yaml").read_text() + "dark_std_e: [1, 2\n")


def _yaml_latin1(w: W) -> None:
    (w / "calib.yaml").write_bytes("# caméra du labo\n".encode("latin-1") + (w / "calib.yaml").read_bytes())


def _yaml_field(key: str, value: Any) -> Callable[[W], None]:
    def damage(w: W) -> None:
        data = yaml.safe_load((w / "calib.yaml").read_text())
        data[key] = value
        (w / "calib.yaml").write_text(yaml.safe_dump(data))

    return damage


def _yaml_renamed(key: str, typo: str) -> Callable[[W], None]:
    """A field of the calibration file renamed (a typo): the field is missing and an unknown one is there."""

    def damage(w: W) -> None:
        data = yaml.safe_load((w / "calib.yaml").read_text())
        data[typo] = data.pop(key)
        (w / "calib.yaml").write_text(yaml.safe_dump(data))

    return damage


CALIB_DAMAGE: dict[str, tuple[Callable[[W], None], list[str]]] = {
    "syntax-error": (_yaml_syntax, ["calib.yaml"]),
    "latin1": (_yaml_latin1, ["calib.yaml", "UTF-8"]),
    "unknown-field": (_yaml_field("dark_stdev_e", 40.0), ["calib.yaml", "dark_stdev_e"]),
    "misspelt-field": (
        _yaml_renamed("dark_std_e", "dark_stdev_e"),
        ["calib.yaml", "unknown field 'dark_stdev_e' (did you mean 'dark_std_e'?)", "missing"],
    ),
    "out-of-range": (_yaml_field("range_sigma_mm", [-3.0, 0.0, 0.0]), ["calib.yaml", "range_sigma_mm"]),
}

#: a LightningCLI config broken four ways: name -> (text of the file, what the error names)
LIGHTNING_CONFIG_DAMAGE: dict[str, tuple[bytes, list[str]]] = {
    "syntax-error": (b"trainer:\n  max_epochs: [1, 2\n", ["bad.yaml"]),
    "latin1": ("# réglages\ntrainer:\n  max_epochs: 1\n".encode("latin-1"), ["bad.yaml"]),
    "unknown-field": (b"trainer:\n  max_epochz: 1\n", ["bad.yaml", "'trainer.max_epochz'", "'trainer.max_epochs'"]),
    "unknown-field-of-the-data": (
        b"data:\n  init_args:\n    batch_sise: 4\n",
        ["bad.yaml", "'data.init_args.batch_sise'", "'data.init_args.batch_size'"],
    ),
    "out-of-range": (b"data:\n  init_args:\n    batch_size: -4\n", ["batch_size"]),
}


# ------------------------------------------------------------------------------------------------- arguments


def denoise_args(w: W, *extra: Any, out: str = "out/d") -> list[Any]:
    return [w / "frames", "--ckpt", w / "model.ckpt", "--out", w / out, "--device", "cpu", "--quiet", *extra]


def eval_args(w: W, out: str = "out/m.json") -> list[Any]:
    return ["--pred", w / "pred", "--ref", w / "ref", "--out", w / out]


def calibrate_args(w: W, out: str = "out/c.yaml") -> list[Any]:
    c = w / "captures"
    return ["--sweep", c / "sweep", "--dark", c / "dark", "--distances", c / "distances", "--out", w / out]


def page_args(w: W, page: str = "out/results.md") -> list[Any]:
    return ["--page-only", "--results", w / "results", "--page", w / page]


def grid_args(w: W, *extra: Any) -> list[Any]:
    return ["robustness", "--out", w / "grid", *_grid_select(), "--table-only", *extra]


def _grid_select() -> list[str]:
    return ["--backbones", "unet", "--noises", "hetero", "--losses", "l1", "--sensors", "default", "--seeds", "0"]


GRID_RUN = "unet-default-hetero-l1-s0"

SIM_SMALL: dict[str, list[str]] = {
    "tofdenoise sensor simulate-calibration": [
        "--sweep-steps", "4", "--sweep-frames", "2", "--dark-frames", "2", "--distance-frames", "2", "--size", "2",
    ],
    "tofdenoise sensor simulate-captures": ["--scenes", "1", "--frames", "2", "--height", "16", "--width", "16"],
    "tofdenoise sensor simulate-validation": ["--frames", "2", "--roi-px", "2"],
    "tofdenoise sensor realset": ["--scenes", "1", "--frames", "2", "--height", "16", "--width", "16"],
}  # fmt: skip
SENSOR_OPTION = {
    "tofdenoise sensor simulate-calibration": "--sensor",
    "tofdenoise sensor simulate-captures": "--sensor",
    "tofdenoise sensor simulate-validation": "--sensor",
    "tofdenoise sensor realset": "--sensor",
}


def train_args(w: W, *extra: str, run: str = "out/run") -> list[str]:
    return [*_tiny_overrides()(w / run, w / "cache"), "logger=csv", *extra]


def sweep_args(w: W, *extra: str) -> list[str]:
    """``tofdenoise train -m``: the tiny run as a multirun of one job, ``out/sweep/job``."""
    tiny = _tiny_overrides()(
        w / "out/run", w / "cache", **({"backbone": "deeptof"} if "backbone=deeptof" in extra else {})
    )
    return ["-m", *[a for a in tiny if not a.startswith("paths.run_dir=")], f"hydra.sweep.dir={w / 'out/sweep'}",
            "hydra.sweep.subdir=job", "logger=csv", *[e for e in extra if e != "backbone=deeptof"]]  # fmt: skip


def _tiny_overrides():
    """``tiny_overrides`` of tests/conftest.py: the tiny Hydra run settings of the entry-point tests."""
    import importlib.util
    import sys

    name = "_tests_conftest_for_probes"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, Path(__file__).parents[1] / "conftest.py")
        sys.modules[name] = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(sys.modules[name])
    return sys.modules[name].tiny_overrides


def lightning_args(w: W, *extra: Any, root: str = "out/cli") -> list[Any]:
    from tofdenoise.paths import CONFIG_DIR

    return [
        "--config",
        Path(CONFIG_DIR) / "cli" / "smoke.yaml",
        "--trainer.default_root_dir",
        w / root,
        "--trainer.enable_progress_bar",
        "false",
        *extra,
    ]


# ------------------------------------------------------------------------------------------------------ rows

P = Probe
PROBES: list[Probe] = []
#: what Hydra writes into a run folder before the run code starts (its config and its log): a refused run leaves
#: only these (and no checkpoint, record or lock)
_HYDRA_RUN = ("out/run/.hydra", "out/run/config.log", "out/run/train.log", "out/run/classic.log")

# bad frames: a truncated PNG, an 8-bit PNG, a frame of another dtype, depths in metres instead of millimetres.
# tofdenoise denoise goes on with the other frames and lists the bad one as FAILED (exit 1); nothing is written
# for the bad frame.
_DENOISE_OTHER = {"a": ("out/d/sub/b.png",), "b": ("out/d/a.png",)}
PROBES += [
    P("tofdenoise denoise", "bad_frames", "truncated-png", denoise_args, truncate("frames/a.png", 100), 1,
      lambda w: ["FAILED", str(w / "frames/a.png")], _DENOISE_OTHER["a"]),
    P("tofdenoise denoise", "bad_frames", "png-8bit", denoise_args, write_png8("frames/a.png"), 1,
      lambda w: ["FAILED", str(w / "frames/a.png")], _DENOISE_OTHER["a"]),
    P("tofdenoise denoise", "bad_frames", "npy-complex", denoise_args, npy_dtype("frames/sub/b.npy", "complex64"), 1,
      lambda w: ["FAILED", str(w / "frames/sub/b.npy")], _DENOISE_OTHER["b"]),
    P("tofdenoise denoise", "bad_frames", "metres", denoise_args, npy_in_metres("frames/sub/b.npy"), 1,
      lambda w: ["FAILED", str(w / "frames/sub/b.npy"), "--depth-scale-mm"], _DENOISE_OTHER["b"]),
    P("tofdenoise denoise", "bad_frames", "depth-in-0.1mm-units", denoise_args, depth_times("frames/a.png", 10), 1,
      lambda w: ["FAILED", str(w / "frames/a.png"), "median valid depth 9", "beyond 2998 mm",
                 "looks like 0.1 mm units: pass --depth-scale-mm 0.1"], _DENOISE_OTHER["a"]),
    P("tofdenoise denoise", "bad_frames", "depth-in-cm", denoise_args, depth_times("frames/sub/b.npy", 0.1), 1,
      lambda w: ["FAILED", str(w / "frames/sub/b.npy"), "median valid depth 9", "nearer than 300 mm",
                 "looks like centimetres: pass --depth-scale-mm 10"], _DENOISE_OTHER["b"]),
    P("tofdenoise denoise", "bad_frames", "depth-in-0.1mm-units-scale-given",
      lambda w: [w / "frames/a.png", *denoise_args(w, "--depth-scale-mm", "0.1", out="out/s")[1:]],
      depth_times("frames/a.png", 10), 0, may_change=("out/s",), check=restored_in_mm("out/s/a.png")),
    P("tofdenoise denoise", "bad_frames", "absurd-depth-2e40-mm-scale-given",
      lambda w: [w / "frames/sub/b.npy", *denoise_args(w, "--depth-scale-mm", "1")[1:]],
      absurd_depth("frames/sub/b.npy"), 1,
      lambda w: ["FAILED", str(w / "frames/sub/b.npy"), "deeper than 65535 mm", "1.1e+12 mm"],
      check=lambda w, o: _no_warning_line(o)),
    P("tofdenoise denoise", "bad_frames", "absurd-depth-2e40-mm-in-a-block", denoise_args,
      absurd_depth("frames/sub/b.npy", block=True), 1,
      lambda w: ["FAILED", str(w / "frames/sub/b.npy"), "200 valid pixel(s) deeper than 65535 mm"],
      _DENOISE_OTHER["b"], check=lambda w, o: _no_warning_line(o)),
    P("tofdenoise denoise", "bad_frames", "amplitude-all-nan",
      lambda w: denoise_args(w, "--amplitude", w / "amp", "--sensor", w / "calib.yaml"),
      nan_amplitude("amp/sub/b.npy"), 1,
      lambda w: ["FAILED", str(w / "frames/sub/b.npy"), str(w / "amp/sub/b.npy"), "no finite value"],
      ("out/d/a.png", "out/d/a_sigma_mm.npy")),
    P("tofdenoise denoise", "bad_frames", "amplitude-partly-nan",
      lambda w: denoise_args(w, "--amplitude", w / "amp", "--sensor", w / "calib.yaml"),
      nan_amplitude("amp/sub/b.npy", block=True), 0, may_change=("out/d",),
      check=sigma_nan_where_the_amplitude_is),
    P("tofdenoise evaluate", "bad_frames", "truncated-png", eval_args, truncate("pred/s0.png", 100), 2,
      lambda w: ["error", "s0.png"]),
    P("tofdenoise evaluate", "bad_frames", "png-8bit", eval_args, write_png8("pred/s0.png"), 2,
      lambda w: ["error", "s0.png"]),
    P("tofdenoise evaluate", "bad_frames", "metres", eval_args, npy_in_metres("pred/s0.png", "ref/s0.png"), 2,
      lambda w: ["error", "s0.npy", "mm"]),
    P("tofdenoise sensor build-reference", "bad_frames", "truncated-png",
      lambda w: [w / "scenes", "--force", "--quiet"], truncate("scenes/scene_0000/hiexp/depth_mm_000.png", 100), 2,
      lambda w: ["error", "depth_mm_000.png"]),
]  # fmt: skip

# bad calibration captures: a missing index.json, stacks of mixed sizes, a truncated stack
PROBES += [
    P("tofdenoise sensor calibrate", "bad_captures", "missing-index", calibrate_args,
      remove("captures/sweep/index.json"),
      2, lambda w: ["error", "index.json", "sweep"]),
    P("tofdenoise sensor calibrate", "bad_captures", "mixed-sizes", calibrate_args, mixed_sizes("captures/sweep"), 2,
      lambda w: ["error", str(w / "captures/sweep/step_"), "px"]),
    P("tofdenoise sensor calibrate", "bad_captures", "truncated-stack", calibrate_args,
      truncate_stack("captures/sweep"),
      2, lambda w: ["error", first_stack(w, "captures/sweep").split("/")[-1]]),
    P("tofdenoise sensor validate", "bad_captures", "missing-index",
      lambda w: ["--out", w / "out/v", "--captures", w / "frames"], None, 2,
      lambda w: ["error", "index.json"]),
    P("tofdenoise sensor build-reference", "bad_captures", "no-hiexp", lambda w: [w / "scenes/scene_0000", "--quiet"],
      remove("scenes/scene_0000/hiexp"), 2, lambda w: ["error", "scene_0000"]),
    P("tofdenoise train", "bad_captures", "negative-fixed-noise-sigma",
      lambda w: train_args(w, "noise=fixed", "++noise.kwargs.sigma_mm=-5"), None, 2,
      lambda w: ["error", "noise.kwargs", "sigma_mm", "-5"],
      check=lambda w, outcome: _no_run_record(w / "out/run")),
    P("tofdenoise train", "bad_captures", "multirun-negative-fixed-noise-sigma",
      lambda w: sweep_args(w, "noise=fixed", "++noise.kwargs.sigma_mm=-5,-6"), None, 2,
      lambda w: ["error", "noise.kwargs", "sigma_mm", "-5"]),
    P("tofdenoise train", "bad_captures", "empty-real-dir",
      lambda w: train_args(w, f"++data.real_dir={w / 'frames/sub'}"), None, 2, lambda w: ["error", "data"],
      _HYDRA_RUN),
    P("tofdenoise classic", "bad_captures", "empty-real-dir",
      lambda w: train_args(w, f"++data.real_dir={w / 'frames/sub'}"), None, 2, lambda w: ["error", "data"],
      _HYDRA_RUN),
    P("tofdenoise fit", "bad_captures", "empty-real-dir",
      lambda w: lightning_args(w, "--data.init_args.real_dir", w / "frames/sub"), None, 2,
      lambda w: ["error", "real_dir"]),
]  # fmt: skip

# bad YAML: the calibration file (every reader) and the LightningCLI config
_CALIB_READERS: dict[str, Callable[[W], list[Any]]] = {
    "tofdenoise sensor show-calib": lambda w: ["--sensor", w / "calib.yaml"],
    "tofdenoise sensor sigma": lambda w: ["--depth-mm", "1000", "--signal-e", "5000", "--sensor", w / "calib.yaml"],
    "tofdenoise sensor validate": lambda w: ["--out", w / "out/v", "--sensor", w / "calib.yaml", "--quick"],
    "tofdenoise denoise": lambda w: denoise_args(w, "--amplitude", w / "amp", "--sensor", w / "calib.yaml"),
    **{
        cmd: (lambda c: lambda w: ["--out", w / "out/sim", SENSOR_OPTION[c], w / "calib.yaml", *SIM_SMALL[c]])(cmd)
        for cmd in SENSOR_OPTION
    },
    "tofdenoise train": lambda w: train_args(w, f"++data.sensor={w / 'calib.yaml'}"),
    "tofdenoise classic": lambda w: train_args(w, f"++data.sensor={w / 'calib.yaml'}"),
}
for _cmd, _argv in _CALIB_READERS.items():
    for _case, (_damage, _names) in CALIB_DAMAGE.items():
        PROBES.append(
            P(_cmd, "bad_yaml", _case, _argv, _damage, 2, (lambda n: lambda w: ["error", *n])(_names),
              _HYDRA_RUN if _cmd in ("tofdenoise train", "tofdenoise classic") else ())
        )  # fmt: skip
PROBES.append(
    P("tofdenoise denoise", "bad_yaml", "misspelt-preset",
      lambda w: denoise_args(w, "--amplitude", w / "amp", "--sensor", "cam57"), None, 2,
      lambda w: ["error", "cam57", "presets", "cam75", "default"])
)  # fmt: skip


def _one_line(w: W, outcome: Any) -> None:
    """stderr is the one error line (jsonargparse's usage text, 58 lines, was printed before it)."""
    lines = [line for line in outcome.err.splitlines() if line.strip()]
    assert len(lines) == 1, outcome.err


def _lightning_config(text: bytes) -> Callable[[W], None]:
    def damage(w: W) -> None:
        (w / "bad.yaml").write_bytes(text)

    return damage


for _case, (_text, _names) in LIGHTNING_CONFIG_DAMAGE.items():
    PROBES.append(
        P("tofdenoise fit", "bad_yaml", _case, lambda w: lightning_args(w, "--config", w / "bad.yaml"),
          _lightning_config(_text), 2, (lambda n: lambda w: ["error", *n])(_names), check=_one_line)
    )  # fmt: skip


def _last_ckpt(w: W) -> None:
    """A run's resume point, ``out/run/checkpoints/last.ckpt`` (a copy of the world's checkpoint)."""
    (w / "out/run/checkpoints").mkdir(parents=True)
    (w / "out/run/checkpoints/last.ckpt").write_bytes((w / "model.ckpt").read_bytes())


def _foreign_onnx(w: W) -> None:
    """``out/detector.onnx``: a valid ONNX graph of another tool (no tofdenoise_* metadata)."""
    import onnx
    from onnx import TensorProto, helper

    x, y = (helper.make_tensor_value_info(n, TensorProto.FLOAT, [1]) for n in ("x", "y"))
    onnx.save(
        helper.make_model(helper.make_graph([helper.make_node("Identity", ["x"], ["y"])], "detector", [x], [y])),
        str(w / "out/detector.onnx"),
    )


def _finished_unet_run(w: W, folder: str = "out/run") -> None:
    """``out/run``: the folder of a finished tiny U-Net run: its records (``config.yaml`` as the run saved it,
    ``run_info.json`` finished, ``metrics.json``), Hydra's record (``.hydra/``) and log, and its checkpoints."""
    from omegaconf import OmegaConf

    from tofdenoise.config import compose_config
    from tofdenoise.data_modules.datamodule import data_calibration
    from tofdenoise.experiments.train_job import record_calibration
    from tofdenoise.records import learned_verdict, set_entry, write_metrics_json

    overrides = train_args(w)
    cfg = compose_config(overrides)
    record_calibration(cfg, data_calibration(OmegaConf.to_container(cfg.data.sensor, resolve=True)))
    run = w / folder
    (run / ".hydra").mkdir(parents=True)
    (run / "checkpoints").mkdir()
    (run / "config.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))
    (run / ".hydra/config.yaml").write_text(OmegaConf.to_yaml(cfg))
    (run / ".hydra/hydra.yaml").write_text("hydra:\n  run:\n    dir: out/run\n  mode: RUN\n")
    (run / ".hydra/overrides.yaml").write_text(yaml.safe_dump([str(o) for o in overrides]))
    (run / "train.log").write_text("[2026-11-20 10:00:00,000][lightning][INFO] - Seed set to 0\n")
    for name in ("best.ckpt", "last.ckpt"):
        (run / "checkpoints" / name).write_bytes((w / "model.ckpt").read_bytes())
    raw = {"psnr_db": 31.0, "ssim": 0.95, "mse_mm2": 680.0, "mae_mm": 7.2}
    write_metrics_json(
        run / "metrics.json",
        {"synthetic": set_entry({"psnr_db": 40.0, "ssim": 0.99, "mse_mm2": 80.0, "mae_mm": 2.5}, raw)},
        run=learned_verdict(1000, 2.6, 7.2),
    )
    (run / "run_info.json").write_text(json.dumps({"backbone": "unet", "finished": "2026-11-20T10:05:00+0000"}))


def _checkpoint_in_its_folder(w: W) -> None:
    """The checkpoint in a folder of its own (``ckpts/model.ckpt``), as in a run's ``checkpoints/``."""
    (w / "ckpts").mkdir()
    (w / "ckpts/model.ckpt").write_bytes((w / "model.ckpt").read_bytes())


# misuse of outputs: an output that is an input, or that lies where it would replace one
PROBES += [
    P("tofdenoise denoise", "misuse_outputs", "out-is-an-input-frame", lambda w: denoise_args(w, out="frames/a.png"),
      None, 2, lambda w: ["error", "--out", str(w / "frames/a.png"), "input"]),
    P("tofdenoise denoise", "misuse_outputs", "out-is-the-checkpoint", lambda w: denoise_args(w, out="model.ckpt"),
      None, 2, lambda w: ["error", "--out", "would replace the input", str(w / "model.ckpt")]),
    P("tofdenoise denoise", "misuse_outputs", "out-holds-the-checkpoint",
      lambda w: [w / "frames", "--ckpt", w / "ckpts/model.ckpt", "--out", w / "ckpts", "--device", "cpu", "--quiet"],
      _checkpoint_in_its_folder, 2, lambda w: ["error", "--out", "holds the input", str(w / "ckpts/model.ckpt")]),
    P("tofdenoise denoise", "misuse_outputs", "out-is-the-input-folder", lambda w: denoise_args(w, out="frames"),
      None, 2, lambda w: ["error", "--out", "holds the input", str(w / "frames")]),
    P("tofdenoise denoise", "misuse_outputs", "npy-replaces-the-amplitude",
      lambda w: denoise_args(w, "--amplitude", w / "amp", "--npy", out="amp"), None, 2,
      lambda w: ["error", "--out", "amp"]),
    P("tofdenoise evaluate", "misuse_outputs", "out-is-an-input", lambda w: eval_args(w, "pred/s0.png"), None, 2,
      lambda w: ["error", "--out", "s0.png"]),
    P("tofdenoise evaluate", "misuse_outputs", "out-beside-an-input", lambda w: eval_args(w, "pred/s0.json"), None, 2,
      lambda w: ["error", "--out", "s0"]),
    P("tofdenoise report", "misuse_outputs", "out-is-a-record",
      lambda w: [w / "runs", "--out", w / "runs/r1/metrics.html"], None, 2, lambda w: ["error", "--out", "metrics"]),
    P("tofdenoise grid", "misuse_outputs", "markdown-replaces-a-file-of-a-run",
      lambda w: grid_args(w, "--markdown", w / "grid" / GRID_RUN / "notes.md"),
      lambda w: (w / "grid" / GRID_RUN / "notes.md").write_text("my notes\n"), 2,
      lambda w: ["error", "--markdown", "notes.md"]),
    P("tofdenoise reproduce", "misuse_outputs", "page-is-the-discussion",
      lambda w: page_args(w, "results/discussion.md"),
      None, 2, lambda w: ["error", "--page", "discussion.md"]),
    P("tofdenoise sensor calibrate", "misuse_outputs", "out-is-the-capture-index",
      lambda w: calibrate_args(w, "captures/sweep/index.json"), None, 2, lambda w: ["error", "index.json"]),
    P("tofdenoise sensor calibrate", "misuse_outputs", "out-is-a-capture-folder",
      lambda w: calibrate_args(w, "captures/dark"), None, 2, lambda w: ["error", "dark"]),
    P("tofdenoise sensor validate", "misuse_outputs", "out-replaces-the-calibration",
      lambda w: ["--out", w / "out/v", "--sensor", w / "out/v/validation.json", "--quick"],
      lambda w: ((w / "out/v").mkdir(), (w / "out/v/validation.json").write_text(
          json.dumps(yaml.safe_load((w / "calib.yaml").read_text())))),
      2, lambda w: ["error", "validation.json"]),
    P("tofdenoise export", "misuse_outputs", "onnx-is-the-checkpoint",
      lambda w: [w / "model.ckpt", "--onnx", w / "model.ckpt", "--no-check"], None, 2,
      lambda w: ["error", "model.ckpt"]),
    P("tofdenoise export", "misuse_outputs", "onnx-replaces-a-runs-last-checkpoint",
      lambda w: [w / "model.ckpt", "--onnx", w / "out/run/checkpoints/last.ckpt", "--no-check"], _last_ckpt, 2,
      lambda w: ["error", str(w / "out/run/checkpoints/last.ckpt"), "expected a .onnx file"]),
    P("tofdenoise export", "misuse_outputs", "onnx-replaces-an-image",
      lambda w: [w / "model.ckpt", "--onnx", w / "frames/a.png", "--no-check"], None, 2,
      lambda w: ["error", str(w / "frames/a.png"), "expected a .onnx file"]),
    P("tofdenoise export", "misuse_outputs", "onnx-replaces-a-graph-of-another-tool",
      lambda w: [w / "model.ckpt", "--onnx", w / "out/detector.onnx", "--no-check"], _foreign_onnx, 2,
      lambda w: ["error", str(w / "out/detector.onnx"), "not an ONNX export of tofdenoise"]),
    P("tofdenoise train", "misuse_outputs", "run-dir-is-a-file",
      lambda w: train_args(w, run="out/notes.txt"),
      lambda w: ((w / "out").mkdir(exist_ok=True), (w / "out/notes.txt").write_text("my notes\n")), 2,
      lambda w: ["error", str(w / "out/notes.txt"), "is a file"]),
    P("tofdenoise train", "misuse_outputs", "init-weights-inside-the-run",
      lambda w: train_args(w, f"++model.init_weights={w / 'out/run/checkpoints/best.ckpt'}"),
      lambda w: ((w / "out/run/checkpoints").mkdir(parents=True),
                 (w / "out/run/checkpoints/best.ckpt").write_bytes((w / "model.ckpt").read_bytes())),
      2, lambda w: ["error", "holds the input", "best.ckpt"], _HYDRA_RUN),
    P("tofdenoise train", "misuse_outputs", "another-config-in-a-finished-run",
      lambda w: [*_tiny_overrides()(w / "out/run", w / "cache", backbone="deeptof"), "logger=csv"], _finished_unet_run,
      2, lambda w: ["error", str(w / "out/run"), "backbone.name: 'unet' there, 'deeptof' now"]),
    P("tofdenoise train", "misuse_outputs", "multirun-job-folder-holds-a-finished-run-of-another-config",
      lambda w: sweep_args(w, "backbone=deeptof"), lambda w: _finished_unet_run(w, "out/sweep/job"), 2,
      lambda w: ["error", str(w / "out/sweep/job"), "backbone.name: 'unet' there, 'deeptof' now"]),
    P("tofdenoise fit", "misuse_outputs", "init-weights-inside-the-run",
      lambda w: lightning_args(w, "--model.init_args.init_weights", w / "out/cli/checkpoints/best.ckpt"),
      lambda w: ((w / "out/cli/checkpoints").mkdir(parents=True),
                 (w / "out/cli/checkpoints/best.ckpt").write_bytes((w / "model.ckpt").read_bytes())),
      2, lambda w: ["error", "holds the input", "best.ckpt"]),
]  # fmt: skip
for _cmd, _opt in SENSOR_OPTION.items():
    PROBES.append(
        P(_cmd, "misuse_outputs", "out-holds-the-camera-file",
          (lambda c, o: lambda w: ["--out", w.root, o, w / "calib.yaml", *SIM_SMALL[c]])(_cmd, _opt), None, 2,
          lambda w: ["error", "calib.yaml"])
    )  # fmt: skip


def recording_files():
    """The recording writers of tests/inference/recording_files.py (``write_bag``, ``write_kinect_mkv``)."""
    import importlib.util
    import sys

    name = "_recording_files_for_probes"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, Path(__file__).parents[1] / "inference/recording_files.py")
        sys.modules[name] = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(sys.modules[name])
    return sys.modules[name]


def static_recording(w: W, rel: str, frames: int = 6, h: int = 10, w_px: int = 14, offset_mm: float = 0.0) -> Path:
    """A static recording of one scene at ``w / rel`` (a ROS 1 bag of depth and amplitude)."""
    rng = np.random.default_rng(int(offset_mm))
    y, x = np.mgrid[0:h, 0:w_px]
    depth = np.rint(1200 + offset_mm + 6 * x + 4 * y + rng.normal(0, 3, (frames, h, w_px))).astype(np.uint16)
    amplitude = rng.integers(100, 3000, (frames, h, w_px)).astype(np.uint16)
    (w / rel).parent.mkdir(parents=True, exist_ok=True)
    return recording_files().write_bag(w / rel, 1, depth, amplitude=amplitude)


def _two_recordings(w: W) -> None:
    """``rec/desk1.bag`` and ``rec/desk2.bag``: two static recordings of one scene (ROS 1 bags, 6 frames of 10 x 14)."""
    for k in (1, 2):
        static_recording(w, f"rec/desk{k}.bag", offset_mm=40 * k)


def _realset_scene(k: int) -> Callable[[W], list[Any]]:
    return lambda w: ["--from-recording", w / f"rec/desk{k}.bag", "--out", w / "out/rs7", "--scene", "desk"]


def _scene_is_the_other_runs(w: W, outcome: Any) -> None:
    meta = json.loads((w / "out/rs7/desk/recording.json").read_text())
    assert meta["recording"] == str(w / "rec/desk2.bag"), meta
    assert sorted(p.name for p in (w / "out/rs7").iterdir()) == ["desk"], "a partial scene was left"


def _kinect_without_ir(w: W) -> None:
    """``rec/depth-only.mkv``: an Azure Kinect recording of 4 frames with a DEPTH track and no IR track."""
    y, x = np.mgrid[0:10, 0:14]
    depth = np.repeat((1200 + 6 * x + 4 * y)[None], 4, axis=0).astype(np.uint16)
    (w / "rec").mkdir(exist_ok=True)
    recording_files().write_kinect_mkv(w / "rec/depth-only.mkv", depth)


def _one_failed_line(w: W, outcome: Any) -> None:
    """The recording is one FAILED line (it was one per frame, "... in None")."""
    failed = [line for line in outcome.err.splitlines() if "FAILED" in line]
    assert len(failed) == 1 and "in None" not in outcome.err, outcome.err


PROBES.append(
    P("tofdenoise denoise", "bad_frames", "kinect-recording-without-ir-with-sensor",
      lambda w: [w / "rec/depth-only.mkv", "--ckpt", w / "model.ckpt", "--out", w / "out/d", "--sensor",
                 w / "calib.yaml", "--device", "cpu", "--quiet"], _kinect_without_ir, 1,
      lambda w: ["FAILED", str(w / "rec/depth-only.mkv"), "no amplitude / IR stream", "it has: DEPTH",
                 "--amplitude-stream"], check=_one_failed_line)
)  # fmt: skip
PROBES.append(
    P("tofdenoise sensor realset", "misuse_outputs", "out-is-the-recording",
      lambda w: ["--from-recording", w / "rec/desk1.bag", "--out", w / "rec/desk1.bag"], _two_recordings, 2,
      lambda w: ["error", "--out", "would replace the input", str(w / "rec/desk1.bag")])
)  # fmt: skip


# concurrent writers: another process holds the run folder's lock; two runs onto one output
PROBES += [
    P("tofdenoise sensor realset", "concurrent", "two-recordings-one-scene", _realset_scene(1), _two_recordings, 2,
      lambda w: ["error", str(w / "out/rs7/desk"), "exists", "another run wrote it"], ("out/rs7/desk",),
      runner="race", check=_scene_is_the_other_runs,
      extra={"other": _realset_scene(2), "during": "tofdenoise.inference.recording_realset.build_reference"}),
    P("tofdenoise train", "concurrent", "run-folder-locked", train_args, None, 2,
      lambda w: ["error", str(w / "out/run/run.lock")], runner="locked", lock_dir=lambda w: w / "out/run"),
    P("tofdenoise classic", "concurrent", "run-folder-locked", train_args, None, 2,
      lambda w: ["error", str(w / "out/run/run.lock")], runner="locked", lock_dir=lambda w: w / "out/run"),
    P("tofdenoise fit", "concurrent", "run-folder-locked", lightning_args, None, 2,
      lambda w: ["error", str(w / "out/cli/run.lock")], runner="locked", lock_dir=lambda w: w / "out/cli"),
]  # fmt: skip


# corrupt records: run records and checkpoints that cannot be used
def _null_metric(rel: str) -> Callable[[W], None]:
    def damage(w: W) -> None:
        data = json.loads((w / rel).read_text())
        data["synthetic"]["mae_mm"] = None
        (w / rel).write_text(json.dumps(data))

    return damage


def _text_metric(rel: str) -> Callable[[W], None]:
    def damage(w: W) -> None:
        data = json.loads((w / rel).read_text())
        data["synthetic"]["mae_mm"] = "abc"
        (w / rel).write_text(json.dumps(data))

    return damage


def _no_synthetic(rel: str) -> Callable[[W], None]:
    """The ``synthetic`` section removed (a record edited by hand, or merged from a run of the real set only)."""

    def damage(w: W) -> None:
        data = json.loads((w / rel).read_text())
        data["real"] = data.pop("synthetic")
        (w / rel).write_text(json.dumps(data))

    return damage


def _nan_metric(rel: str) -> Callable[[W], None]:
    """A NaN metric: ``json.dumps`` writes the non-strict ``NaN`` token, which Python's ``json`` reads back."""

    def damage(w: W) -> None:
        data = json.loads((w / rel).read_text())
        data["synthetic"]["mae_mm"] = float("nan")
        (w / rel).write_text(json.dumps(data))

    return damage


def _write(rel: str, text: str) -> Callable[[W], None]:
    def damage(w: W) -> None:
        (w / rel).write_text(text)

    return damage


def _bad_per_image(rel: str) -> Callable[[W], None]:
    """A per-image CSV (read for the results page's bootstrap intervals) with a value that is no number."""

    def damage(w: W) -> None:
        (w / rel).parent.mkdir(parents=True, exist_ok=True)
        (w / rel).write_text("index,name,mae_mm\n0,scene_000001,oops\n")

    return damage


_REC = "results/cpu/dvss-range-l1-s1"
_GRID_REC = f"grid/{GRID_RUN}"
PROBES += [
    P("tofdenoise reproduce", "corrupt_records", "truncated-metrics", page_args,
      truncate(f"{_REC}/metrics.json", 40), 2,
      lambda w: ["error", f"{_REC}/metrics.json"]),
    P("tofdenoise reproduce", "corrupt_records", "null-metric", page_args, _null_metric(f"{_REC}/metrics.json"), 2,
      lambda w: ["error", f"{_REC}/metrics.json", "mae_mm"]),
    P("tofdenoise reproduce", "corrupt_records", "text-metric", page_args, _text_metric(f"{_REC}/metrics.json"), 2,
      lambda w: ["error", f"{_REC}/metrics.json", "mae_mm"]),
    P("tofdenoise reproduce", "corrupt_records", "no-synthetic-section", page_args,
      _no_synthetic(f"{_REC}/metrics.json"), 2, lambda w: ["error", f"{_REC}/metrics.json", "'synthetic'"]),
    P("tofdenoise reproduce", "corrupt_records", "nan-metric", page_args, _nan_metric(f"{_REC}/metrics.json"), 2,
      lambda w: ["error", f"{_REC}/metrics.json", "synthetic.mae_mm", "NaN"]),
    P("tofdenoise reproduce", "corrupt_records", "run-info-not-json", page_args, _write(f"{_REC}/run_info.json", "{x"),
      2, lambda w: ["error", f"{_REC}/run_info.json"]),
    P("tofdenoise reproduce", "corrupt_records", "per-image-not-numbers", page_args,
      _bad_per_image(f"{_REC}/per_image/synthetic.csv"), 2,
      lambda w: ["error", f"{_REC}/per_image/synthetic.csv", "per-image record"]),
    P("tofdenoise reproduce", "corrupt_records", "results-folder-missing",
      lambda w: ["--page-only", "--results", w / "no-results", "--page", w / "out/results.md"], None, 2,
      lambda w: ["error", "--results", str(w / "no-results"), "no such folder"]),
    P("tofdenoise reproduce", "corrupt_records", "discussion-missing", page_args, remove("results/discussion.md"), 0,
      lambda w: ["warning", "results/discussion.md", "without its discussion"], ("out",)),
    P("tofdenoise report", "corrupt_records", "truncated-metrics", lambda w: [w / "runs", "--out", w / "out/r.html"],
      truncate("runs/r1/metrics.json", 40), 2, lambda w: ["runs/r1", "metrics.json"]),
    P("tofdenoise report", "corrupt_records", "text-metric", lambda w: [w / "runs", "--out", w / "out/r.html"],
      _text_metric("runs/r1/metrics.json"), 2, lambda w: ["runs/r1", "mae_mm"]),
    P("tofdenoise grid", "corrupt_records", "truncated-metrics", grid_args,
      truncate(f"{_GRID_REC}/metrics.json", 40), 2,
      lambda w: ["error", f"{_GRID_REC}/metrics.json"]),
    P("tofdenoise grid", "corrupt_records", "no-synthetic-section", grid_args,
      _no_synthetic(f"{_GRID_REC}/metrics.json"), 2, lambda w: ["error", f"{_GRID_REC}/metrics.json", "'synthetic'"]),
    P("tofdenoise grid", "corrupt_records", "nan-metric", grid_args, _nan_metric(f"{_GRID_REC}/metrics.json"), 2,
      lambda w: ["error", f"{_GRID_REC}/metrics.json", "synthetic.mae_mm", "NaN"]),
    P("tofdenoise grid", "corrupt_records", "run-info-not-json", grid_args, _write(f"{_GRID_REC}/run_info.json", "{x"),
      2, lambda w: ["error", f"{_GRID_REC}/run_info.json"]),
    P("tofdenoise denoise", "corrupt_records", "truncated-checkpoint", denoise_args, truncate("model.ckpt", 4000), 2,
      lambda w: ["error", "model.ckpt"]),
    P("tofdenoise denoise", "corrupt_records", "ckpt-is-an-onnx-graph",
      lambda w: [w / "frames", "--ckpt", w / "out/detector.onnx", "--out", w / "out/d", "--device", "cpu"],
      _foreign_onnx, 2,
      lambda w: ["error", str(w / "out/detector.onnx"), "ONNX graph", "Lightning checkpoint (.ckpt)"]),
    P("tofdenoise denoise", "corrupt_records", "ckpt-is-a-png",
      lambda w: [w / "frames", "--ckpt", w / "frames/a.png", "--out", w / "out/d", "--device", "cpu"], None, 2,
      lambda w: ["error", str(w / "frames/a.png"), "PNG image", "Lightning checkpoint (.ckpt)"]),
    P("tofdenoise evaluate", "corrupt_records", "ckpt-is-an-onnx-graph",
      lambda w: ["--ckpt", w / "out/detector.onnx", "--captures", w / "scenes", "--sensor", w / "calib.yaml",
                 "--out", w / "out/m.json", "--device", "cpu"],
      _foreign_onnx, 2,
      lambda w: ["error", str(w / "out/detector.onnx"), "ONNX graph", "Lightning checkpoint (.ckpt)"]),
    P("tofdenoise evaluate", "corrupt_records", "ckpt-is-a-png",
      lambda w: ["--ckpt", w / "frames/a.png", "--captures", w / "scenes", "--sensor", w / "calib.yaml",
                 "--out", w / "out/m.json", "--device", "cpu"], None, 2,
      lambda w: ["error", str(w / "frames/a.png"), "PNG image", "Lightning checkpoint (.ckpt)"]),
    P("tofdenoise export", "corrupt_records", "truncated-checkpoint",
      lambda w: [w / "model.ckpt", "--onnx", w / "out/m.onnx"], truncate("model.ckpt", 4000), 2,
      lambda w: ["error", "model.ckpt"]),
    P("tofdenoise train", "corrupt_records", "resume-checkpoint-of-another-backbone",
      lambda w: [*_tiny_overrides()(w / "out/run", w / "cache", backbone="deeptof"), "logger=csv",
                 f"ckpt_path={w / 'model.ckpt'}"], None, 2,
      lambda w: ["error", str(w / "model.ckpt"), "'unet'", "'deeptof'"],
      check=lambda w, o: _no_run_record(w / "out/run")),
    P("tofdenoise train", "corrupt_records", "truncated-checkpoint-to-test",
      lambda w: train_args(w, "train=false", f"ckpt_path={w / 'model.ckpt'}"), truncate("model.ckpt", 4000), 2,
      lambda w: ["error", "model.ckpt"], _HYDRA_RUN),
    P("tofdenoise fit", "corrupt_records", "truncated-checkpoint-to-resume",
      lambda w: lightning_args(w, "--ckpt_path", w / "model.ckpt"), truncate("model.ckpt", 4000), 2,
      lambda w: ["error", "model.ckpt"]),
    P("tofdenoise test", "corrupt_records", "truncated-checkpoint",
      lambda w: lightning_args(w, "--ckpt_path", w / "model.ckpt"), truncate("model.ckpt", 4000), 2,
      lambda w: ["error", "model.ckpt"]),
    P("tofdenoise validate", "corrupt_records", "truncated-checkpoint",
      lambda w: lightning_args(w, "--ckpt_path", w / "model.ckpt"), truncate("model.ckpt", 4000), 2,
      lambda w: ["error", "model.ckpt"]),
    P("tofdenoise predict", "corrupt_records", "truncated-checkpoint",
      lambda w: lightning_args(w, "--ckpt_path", w / "model.ckpt"), truncate("model.ckpt", 4000), 2,
      lambda w: ["error", "model.ckpt"]),
]  # fmt: skip


def _each_frame_whole_or_absent(w: W, outcome: Any) -> None:
    """A frame whose outputs could not all be written has none of them (``f.png`` without ``f.npy`` was left), and
    the cause is said once ("(disk full?) (disk full?)" was)."""
    out = w / "out/d"
    files = sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file()) if out.is_dir() else []
    assert files == [], f"outputs of failed frames left: {files}"
    assert "(disk full?) (disk full?)" not in outcome.err, outcome.err
    failed = [line for line in outcome.err.splitlines() if "FAILED" in line]
    assert len(failed) == 2 and all(line.count("disk full?") == 1 for line in failed), outcome.err


# full disk: every write fails (ENOSPC on a real small file system, EFBIG under RLIMIT_FSIZE here); one line naming
# the output, exit status 2 (1 for a frame of tofdenoise denoise, listed as FAILED), no partial file
PROBES += [
    P("tofdenoise denoise", "full_disk", "every-frame", lambda w: denoise_args(w, "--npy"), None, 1,
      lambda w: ["FAILED", str(w / "out/d"), "could not write"], ("out/d",), check=_each_frame_whole_or_absent),
    P("tofdenoise denoise", "full_disk", "the-png-fits-the-npy-does-not",
      lambda w: denoise_args(w, "--npy", "--amplitude", w / "amp", "--sensor", w / "calib.yaml"), None, 1,
      lambda w: ["FAILED", str(w / "out/d"), "could not write", ".npy", "none of the frame's outputs"], ("out/d",),
      check=_each_frame_whole_or_absent, extra={"file_limit": 4096}),
    P("tofdenoise evaluate", "full_disk", "json", eval_args, None, 2, lambda w: ["error", "m.json"], ("out",)),
    P("tofdenoise report", "full_disk", "html", lambda w: [w / "runs", "--out", w / "out/r.html"], None, 2,
      lambda w: ["error", "r.html"], ("out",)),
    P("tofdenoise grid", "full_disk", "markdown", lambda w: grid_args(w, "--markdown", w / "out/t.md"), None, 2,
      lambda w: ["error", "t.md"], ("out",)),
    P("tofdenoise reproduce", "full_disk", "page", page_args, None, 2, lambda w: ["error", "results.md"], ("out",)),
    P("tofdenoise sensor calibrate", "full_disk", "calibration", calibrate_args, None, 2,
      lambda w: ["error", "c.yaml"], ("out",)),
    P("tofdenoise sensor validate", "full_disk", "validation",
      lambda w: ["--out", w / "out/v", "--quick", "--frames", "4", "--roi-px", "4"], None, 2,
      lambda w: ["error", "out/v"], ("out",)),
    P("tofdenoise sensor build-reference", "full_disk", "reference", lambda w: [w / "scenes", "--force", "--quiet"],
      None, 2, lambda w: ["error", "scene_0000"]),
    P("tofdenoise export", "full_disk", "onnx", lambda w: [w / "model.ckpt", "--onnx", w / "out/m.onnx", "--no-check"],
      None, 2, lambda w: ["error", "m.onnx"], ("out",)),
]  # fmt: skip
for _cmd in ("tofdenoise sensor simulate-calibration", "tofdenoise sensor simulate-captures",
             "tofdenoise sensor simulate-validation"):  # fmt: skip
    PROBES.append(
        P(_cmd, "full_disk", "captures", (lambda c: lambda w: ["--out", w / "out/sim", *SIM_SMALL[c]])(_cmd), None, 2,
          lambda w: ["error", "out/sim"], ("out",))
    )  # fmt: skip

# signals: a separate process (tests/reliability/test_signals.py runs these rows)
PROBES += [
    P("tofdenoise denoise", "signals", "sigint-over-many-frames", lambda w: [], runner="signal", status=130),
    P("tofdenoise denoise", "signals", "sigkill-over-many-frames", lambda w: [], runner="signal", status=-9, slow=True),
    P("tofdenoise denoise", "concurrent", "two-writers-one-out", lambda w: [], runner="signal", status=0, slow=True),
    P("tofdenoise train", "signals", "sigint-mid-training", lambda w: [], runner="signal", status=130, slow=True),
    P("tofdenoise sensor realset", "signals", "sigint-while-writing-a-scene", lambda w: [], runner="signal",
      status=130),
    P("tofdenoise sensor realset", "signals", "sigkill-while-writing-a-scene-then-rerun", lambda w: [],
      runner="signal", status=-9, slow=True),
]  # fmt: skip

# ------------------------------------------------------------------------------------------------ exemptions

_NO_FRAMES = "reads no depth frames"
_NO_CAPTURES = "reads no calibration captures or capture sets"
_NO_YAML = "reads no calibration or config YAML file"
_NO_OUTPUT = "writes no file (prints to stdout)"
_NO_RUN = "writes no run folder, and its outputs are written by atomic rename (two writers: the last complete file)"
_NO_RECORDS = "reads no run record or checkpoint"
_SHORT = "finishes in seconds and writes every file by atomic rename: a signal leaves the old file or the new one"
_HYDRA_SAME = "the same Hydra entry code as tofdenoise train (config.hydra_console_script): see its rows"
_LCLI_SAME = "the same LightningCLI front end as `tofdenoise fit` (lightning_cli.ToFLightningCLI): see its rows"
_CHILDREN = "runs each training as a tofdenoise train process: the train rows cover it"
_REALSET = "runs simulate-calibration, calibrate, simulate-captures and simulate-validation in this process: their rows"

EXEMPT: dict[str, dict[str, str]] = {
    "tofdenoise fit": {
        "bad_frames": "reads the training data through data sources (tests/data_modules)",
        "full_disk": "checkpoints are written by the same CheckpointWriter as tofdenoise train (its tmpfs row)",
        "signals": "Lightning's own KeyboardInterrupt handling, as in tofdenoise train (its row)",
    },
    **{
        f"tofdenoise {verb}": {
            "bad_frames": _LCLI_SAME,
            "bad_captures": _LCLI_SAME,
            "bad_yaml": _LCLI_SAME,
            "misuse_outputs": _LCLI_SAME,
            "concurrent": _LCLI_SAME,
            "full_disk": _LCLI_SAME,
            "signals": _LCLI_SAME,
        }
        for verb in ("validate", "test", "predict")
    },
    "tofdenoise train": {
        "bad_frames": "reads the training data through data sources (tests/data_modules)",
        "full_disk": "a checkpoint write that fails: tests/training/test_checkpointing.py (not probed end to end "
        "on a full file system yet)",
    },
    "tofdenoise classic": {
        "bad_frames": "reads the training data through data sources (tests/data_modules)",
        "misuse_outputs": "reads no file that its run folder's records could replace (only a calibration: its "
        "bad_yaml rows)",
        "corrupt_records": _NO_RECORDS,
        "full_disk": _HYDRA_SAME,
        "signals": _HYDRA_SAME,
    },
    "tofdenoise sensor show-calib": {
        "bad_frames": _NO_FRAMES,
        "bad_captures": _NO_CAPTURES,
        "misuse_outputs": _NO_OUTPUT,
        "concurrent": _NO_OUTPUT,
        "corrupt_records": _NO_RECORDS,
        "full_disk": _NO_OUTPUT,
        "signals": _NO_OUTPUT,
    },
    "tofdenoise sensor calibrate": {
        "bad_frames": "reads capture stacks, not depth frames: its bad_captures rows",
        "bad_yaml": "reads no YAML (index.json is JSON: its missing-index row)",
        "concurrent": _NO_RUN,
        "corrupt_records": _NO_RECORDS,
        "signals": _SHORT,
    },
    "tofdenoise sensor validate": {
        "bad_frames": "reads capture stacks, not depth frames: its bad_captures rows",
        "concurrent": _NO_RUN,
        "corrupt_records": _NO_RECORDS,
        "signals": _SHORT,
    },
    "tofdenoise sensor build-reference": {
        "bad_yaml": _NO_YAML,
        "misuse_outputs": "writes each scene's reference into that scene's folder by design (docs/reliability.md, "
        "Not covered)",
        "concurrent": _NO_RUN,
        "corrupt_records": _NO_RECORDS,
        "signals": _SHORT,
    },
    "tofdenoise sensor realset": {
        "bad_frames": _NO_FRAMES,
        "bad_captures": _REALSET,
        "concurrent": _REALSET,
        "corrupt_records": "realset.json is rewritten when it does not parse (the steps are redone)",
        "full_disk": _REALSET,
        "signals": "resumable: finished steps and complete scenes are skipped on the next run",
    },
    "tofdenoise evaluate": {
        "bad_captures": _NO_CAPTURES,
        "bad_yaml": _NO_YAML,
        "concurrent": _NO_RUN,
        "signals": _SHORT,
    },
    "tofdenoise report": {
        "bad_frames": _NO_FRAMES,
        "bad_captures": _NO_CAPTURES,
        "bad_yaml": "a run's Hydra config.yaml is read only for labels (tests/cli/test_report.py)",
        "concurrent": _NO_RUN,
        "signals": _SHORT,
    },
    "tofdenoise grid": {
        "bad_frames": _NO_FRAMES,
        "bad_captures": _CHILDREN,
        "bad_yaml": _CHILDREN,
        "concurrent": _CHILDREN,
        "signals": _CHILDREN,
    },
    "tofdenoise denoise": {"bad_captures": _NO_CAPTURES},
    "tofdenoise reproduce": {
        "bad_frames": _NO_FRAMES,
        "bad_captures": _CHILDREN,
        "bad_yaml": _CHILDREN,
        "concurrent": _CHILDREN,
        "signals": _CHILDREN,
    },
    "tofdenoise export": {
        "bad_frames": _NO_FRAMES,
        "bad_captures": _NO_CAPTURES,
        "bad_yaml": _NO_YAML,
        "concurrent": _NO_RUN,
        "signals": _SHORT,
    },
}
for _cmd in ("tofdenoise sensor sigma",):
    EXEMPT[_cmd] = EXEMPT["tofdenoise sensor show-calib"]
for _cmd in SENSOR_OPTION:
    EXEMPT.setdefault(_cmd, {})
    EXEMPT[_cmd].update(
        {
            "bad_frames": _NO_FRAMES,
            "concurrent": _NO_RUN,
            "corrupt_records": _NO_RECORDS,
            "signals": EXEMPT["tofdenoise sensor realset"]["signals"],
        }
    )
    if _cmd != "tofdenoise sensor realset":
        EXEMPT[_cmd]["bad_captures"] = "reads no captures: it writes them"
del EXEMPT["tofdenoise sensor realset"]["concurrent"]  # --from-recording: its two-recordings-one-scene row
del EXEMPT["tofdenoise sensor realset"]["signals"]  # --from-recording: its sigint and sigkill rows
