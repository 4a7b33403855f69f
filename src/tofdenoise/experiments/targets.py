"""What ``tofdenoise reproduce`` makes, each by its kind and its own name, and the command that makes it.

- tables: the paper's ``1``, ``2``, ``3`` (``--table 3``, ``make reproduce TABLE=3``; rows in ``tables.TABLES``);
- figures: the paper's ``6`` (the noise-model validation), ``7`` and ``8`` (qualitative: ``figures.FIGURES``)
  (``--figure 6``, ``make reproduce FIGURE=6``);
- studies beyond the paper: ``dynrange``, where the noise model pays across the dynamic range
  (``--study dynrange``, ``make reproduce STUDY=dynrange``; its runs are rows of ``tables.TABLES["dynrange"]``,
  its gains ``dynrange``), and ``schedule``, whether the gain lasts with 10x the ``gpu-short`` steps
  (``--study schedule --profile gpu-short``; rows ``tables.TABLES["schedule"]``), and ``dataseed``, Table III on a
  second data seed (``--study dataseed --profile cpu``; rows ``tables.TABLES["dataseed"]``).

A target's ``key`` names its records: the runs' table (``tables.TABLES`` key) and the folder of its files under
``docs/results/<profile>/`` (``fig6/``, ``fig7/``, ``dynrange/``). The results page, the command line and the Makefile
all name targets through this module.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = [
    "CHECK_TABLES",
    "GPU_PROFILES",
    "KINDS",
    "MAKE_VARIABLES",
    "PROFILES",
    "REALSET_SIZES",
    "Target",
    "target_of_key",
]

#: kind -> the names a user gives (``--<kind> NAME``)
KINDS: dict[str, tuple[str, ...]] = {
    "table": ("1", "2", "3"),
    "figure": ("6", "7", "8"),
    "study": ("dynrange", "schedule", "dataseed"),
}
#: kind -> the Makefile variable of ``make reproduce``
MAKE_VARIABLES: dict[str, str] = {"table": "TABLE", "figure": "FIGURE", "study": "STUDY"}
#: profile -> Hydra overrides shared by every training run of a target
PROFILES: dict[str, tuple[str, ...]] = {
    "cpu": ("experiment=reproduce_cpu",),
    # the paper's settings (Sec. V-A): ToF-FlyingThings3D (data.source_kwargs.root=...), 320 crops, batch 4, 300
    # epochs, one GPU
    "gpu": ("experiment=paper", "logger=csv"),
    # the paper's recipe per step on the procedural world at 480 x 640 with a short schedule: a table's rows as far
    # as a short GPU allocation allows (configs/experiment/paper_short.yaml); finished runs are skipped, so the same
    # command run again goes on from where the last one stopped
    "gpu-short": ("experiment=paper_short", "logger=csv"),
}
#: the tables ``tofdenoise reproduce --check`` covers, one run each (the CPU profile's; the GPU studies have no CPU
#: records to rerun)
CHECK_TABLES = ("1", "2", "3", "dynrange")
#: the profiles whose experiment trains on a CUDA GPU (``trainer=gpu``; a test checks it against the composed configs)
GPU_PROFILES = frozenset({"gpu", "gpu-short"})
#: the stand-in real set of each profile: capture-set size (scenes, height, width). The CPU profile's is the paper's
#: scene count (200) at its training scenes' resolution, and the default of ``tofdenoise sensor realset`` /
#: ``make realset`` (``data_modules.realset.build_realset``'s defaults are the same; a test checks it); ``gpu-short``
#: keeps 24 at 480 x 640, a set a short GPU run can score
REALSET_SIZES: dict[str, tuple[int, int, int]] = {
    "cpu": (200, 128, 160),
    "gpu": (200, 480, 640),
    "gpu-short": (24, 480, 640),
}


@dataclass(frozen=True)
class Target:
    kind: str  # "table", "figure" or "study"
    name: str  # as the user gives it: "3", "6", "dynrange"

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"unknown kind {self.kind!r}; valid: {', '.join(KINDS)}")
        if self.name not in KINDS[self.kind]:
            raise ValueError(f"no {self.kind} {self.name!r}; valid: {', '.join(KINDS[self.kind])}")

    @property
    def key(self) -> str:
        """The records' name: the table's key in ``tables.TABLES`` (``3``, ``dynrange``) or the figure's folder."""
        return f"fig{self.name}" if self.kind == "figure" else self.name

    @property
    def option(self) -> str:
        """``--figure 6``: how ``tofdenoise reproduce`` selects it."""
        return f"--{self.kind} {self.name}"

    def make_command(self, profile: str | None = None, seeds: str | None = None) -> str:
        """``make reproduce FIGURE=6 [PROFILE=cpu] [SEEDS=0,1,2]``."""
        words = ["make reproduce", f"{MAKE_VARIABLES[self.kind]}={self.name}"]
        words += [f"PROFILE={profile}"] if profile else []
        words += [f"SEEDS={seeds}"] if seeds else []
        return " ".join(words)


def target_of_key(key: str) -> Target:
    """The target whose records are named ``key`` (``fig6``: figure 6, ``dynrange``: the study, ``3``: table 3)."""
    for kind, names in KINDS.items():
        for name in names:
            if Target(kind, name).key == key:
                return Target(kind, name)
    raise ValueError(f"no target has the records {key!r}")
