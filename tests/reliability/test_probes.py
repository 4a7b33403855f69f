"""Every family of fault against every command that reads or writes user files (the table: probes.py).

Each row runs the command's real entry point and asserts what a user gets: the exit status, one line of stderr
naming the file or field (never a traceback), and the world's files: inputs unchanged (sha256 before and after),
nothing written but what the row allows, and no temporary file left behind.
"""

from __future__ import annotations

import hashlib
import importlib.util
import sys
from pathlib import Path

import pytest

_spec = importlib.util.spec_from_file_location("_reliability_probes", Path(__file__).with_name("probes.py"))
probes = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = probes
_spec.loader.exec_module(probes)


#: sha256 of an empty file
EMPTY_SHA256 = hashlib.sha256(b"").hexdigest()


def _params(runner: str):
    return [
        pytest.param(p, id=p.id, marks=[pytest.mark.slow] if p.slow else [])
        for p in probes.PROBES
        if p.runner == runner
    ]


def assert_outcome(probe, world, before: dict[str, str], outcome) -> None:
    """The generic checks of a row (module docstring)."""
    shown = f"\nstatus {outcome.status}\nstdout:\n{outcome.out[-2000:]}\nstderr:\n{outcome.err[-3000:]}"
    assert outcome.escaped is None, f"a traceback reached the user:\n{outcome.escaped}{shown}"
    assert "Traceback (most recent call last)" not in outcome.err, shown
    assert outcome.status == probe.status, shown
    names = [str(n) for n in probe.names(world)]
    if names:
        lines = [line for line in outcome.err.splitlines() if all(n in line for n in names)]
        assert lines, f"no line of stderr names {names}{shown}"
    after = world.snapshot()
    allowed = tuple(probe.may_change)

    def free(rel: str) -> bool:
        # an empty flock file beside a rebuilt output (``atomic.exclusive_lock``: ``.<name>.lock``) holds no data
        # and must stay, removing it would race its next holder
        name = rel.rsplit("/", 1)[-1]
        if name.startswith(".") and name.endswith(".lock") and rel not in before and after.get(rel) == EMPTY_SHA256:
            return True
        return any(rel == a or rel.startswith(a.rstrip("/") + "/") for a in allowed)

    changed = sorted(r for r in set(before) | set(after) if before.get(r) != after.get(r) and not free(r))
    assert not changed, f"files written, changed or removed: {changed}{shown}"
    temporary = [r for r in after if Path(r).name.startswith(".") and ".tmp" in Path(r).name]
    assert not temporary, f"temporary files left behind: {temporary}"
    if probe.check is not None:
        probe.check(world, outcome)


@pytest.mark.parametrize("probe", _params("call"))
def test_probe(probe, world, call):
    if probe.damage is not None:
        probe.damage(world)
    before = world.snapshot()
    script, prefix = probes.COMMANDS[probe.command]
    full_disk = probe.extra.get("file_limit", True) if probe.family == "full_disk" else False
    outcome = call(script, [*prefix, *probe.argv(world)], full_disk=full_disk)
    assert_outcome(probe, world, before, outcome)


@pytest.mark.parametrize("probe", _params("locked"))
def test_probe_with_the_run_folder_locked_by_another_process(probe, world, call, lock_holder):
    if probe.damage is not None:
        probe.damage(world)
    run_dir = probe.lock_dir(world)
    with lock_holder(run_dir, "the other writer") as pid:
        before = world.snapshot()
        script, prefix = probes.COMMANDS[probe.command]
        outcome = call(script, [*prefix, *probe.argv(world)])
        assert_outcome(probe, world, before, outcome)
        assert f"pid {pid}" in outcome.err


@pytest.mark.parametrize("probe", _params("race"))
def test_probe_with_another_run_finishing_meanwhile(probe, world, call, monkeypatch):
    """Two runs started together onto one output, in a fixed order: the other run (``extra["other"]``) starts and
    finishes while this one works (at its first call of ``extra["during"]``, after its checks, before it publishes).
    The other run succeeds; this one gets what the row says (the generic checks allow the other run's output)."""
    import importlib

    if probe.damage is not None:
        probe.damage(world)
    before = world.snapshot()
    script, prefix = probes.COMMANDS[probe.command]
    module_name, attr = probe.extra["during"].rsplit(".", 1)
    module = importlib.import_module(module_name)
    original, others = getattr(module, attr), []

    def during(*args, **kwargs):
        if not others:  # once: the other run's own call passes straight through
            others.append(None)
            others[0] = call(script, [*prefix, *probe.extra["other"](world)])
        return original(*args, **kwargs)

    monkeypatch.setattr(module, attr, during)
    outcome = call(script, [*prefix, *probe.argv(world)])
    assert others and others[0] is not None, f"{probe.extra['during']} was not called"
    assert others[0].status == 0 and others[0].escaped is None, f"the other run failed:\n{others[0].err}"
    assert_outcome(probe, world, before, outcome)


# ----------------------------------------------------------------------------------- the table covers every command


def _sensor_subcommands() -> set[str]:
    from tofdenoise.cli.sensor import build_parser

    (sub,) = [a for a in build_parser()._actions if a.dest == "command"]
    return set(sub.choices)


def _commands_of_the_package(verbs=None, sensor_subcommands=None) -> set[str]:
    """Every command a user types: ``tofdenoise <verb>`` for each verb of ``tofdenoise.cli.main.VERBS``, and for
    ``sensor`` one command per sub-command."""
    from tofdenoise.cli.main import VERBS

    commands = set()
    for verb in VERBS if verbs is None else verbs:
        if verb == "sensor":
            subs = _sensor_subcommands() if sensor_subcommands is None else sensor_subcommands
            commands |= {f"tofdenoise sensor {name}" for name in subs}
        else:
            commands.add(f"tofdenoise {verb}")
    return commands


def _uncovered(commands: set[str]) -> list[str]:
    """(command / family) pairs with neither a probe row nor an exemption."""
    rows = {(p.command, p.family) for p in probes.PROBES}
    return [
        f"{command} / {family}"
        for command in sorted(commands)
        for family in probes.FAMILIES
        if (command, family) not in rows and not probes.EXEMPT.get(command, {}).get(family)
    ]


def test_a_verb_without_rows_fails_the_coverage_check():
    """The check can fail: a new verb (or sensor sub-command) with no probe row and no exemption is reported."""
    from tofdenoise.cli.main import VERBS

    new = _commands_of_the_package([*VERBS, "calibrate-all"], [*_sensor_subcommands(), "flash"])
    assert new - set(probes.COMMANDS) == {"tofdenoise calibrate-all", "tofdenoise sensor flash"}
    missing = _uncovered(new)
    assert f"tofdenoise calibrate-all / {probes.FAMILIES[0]}" in missing
    assert f"tofdenoise sensor flash / {probes.FAMILIES[-1]}" in missing
    assert not _uncovered(set(probes.COMMANDS))


def test_every_command_has_a_row_in_every_family():
    """A new verb or sensor sub-command fails here until it has a row (or a reasoned exemption) per family."""
    from lightning.pytorch.cli import LightningCLI

    from tofdenoise.cli.main import VERBS

    lightning = {name for name, verb in VERBS.items() if verb.grammar == "lightning"}
    assert lightning == set(LightningCLI.subcommands())  # every Lightning subcommand is a verb
    package = _commands_of_the_package()
    assert package == set(probes.COMMANDS), (
        f"commands without an entry in probes.COMMANDS: {sorted(package - set(probes.COMMANDS))}; "
        f"entries that are no command: {sorted(set(probes.COMMANDS) - package)}"
    )
    rows = {(p.command, p.family) for p in probes.PROBES}
    assert {p.family for p in probes.PROBES} <= set(probes.FAMILIES)
    missing = []
    for command in probes.COMMANDS:
        for family in probes.FAMILIES:
            exempt = probes.EXEMPT.get(command, {}).get(family)
            has_row = (command, family) in rows
            if not has_row and not exempt:
                missing.append(f"{command} / {family}")
            assert not (has_row and exempt), f"{command} / {family} has rows and an exemption: keep one"
            assert exempt is None or len(exempt) > 15, f"{command} / {family}: say why it is exempt"
    assert not missing, "no probe row and no exemption: " + ", ".join(missing)
    assert len({p.id for p in probes.PROBES}) == len(probes.PROBES), "two rows with one id"


def test_the_table_is_not_empty_where_it_matters():
    """Every writing command is probed for misuse of its outputs and a full disk, and the probes call real entry
    points: every row runs the one console script, ``tofdenoise``, with its verb."""
    from importlib.metadata import entry_points

    from tofdenoise.cli.main import VERBS

    scripts = {e.name for e in entry_points(group="console_scripts") if e.value.startswith("tofdenoise.")}
    assert scripts == {"tofdenoise"}
    assert {probes.COMMANDS[p.command][0] for p in probes.PROBES} == {"tofdenoise"}
    assert {probes.COMMANDS[p.command][1][0] for p in probes.PROBES} <= set(VERBS)
    families = {(p.command, p.family) for p in probes.PROBES}
    for command in ("tofdenoise denoise", "tofdenoise evaluate", "tofdenoise report", "tofdenoise sensor calibrate"):
        assert (command, "misuse_outputs") in families and (command, "full_disk") in families


# ----------------------------------------------------------------------------- a real full disk (slow, needs root)


def _full_disk_rows():
    return [
        pytest.param(p, id=p.id, marks=[pytest.mark.slow])
        for p in probes.PROBES
        if p.family == "full_disk"
        and p.runner == "call"
        and all(a.startswith("out") for a in p.may_change)
        and p.may_change
    ]


@pytest.mark.parametrize("probe", _full_disk_rows())
def test_probe_on_a_real_full_file_system(probe, world, call):
    """The full_disk rows once more, on a real 64 KiB tmpfs mounted at the world's ``out/`` and filled up before the
    command runs: the writes fail with ENOSPC (the fast rows simulate it with RLIMIT_FSIZE, EFBIG)."""
    import errno
    import subprocess

    mount = world / "out"
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(mount)], capture_output=True)
    if done.returncode != 0:
        pytest.skip(f"mount -t tmpfs needs root (CAP_SYS_ADMIN): {done.stderr.decode().strip()[:200]}")
    try:
        try:
            with open(mount / "filler", "wb") as fh:
                while True:
                    fh.write(b"\0" * 4096)
                    fh.flush()
        except OSError as exc:
            assert exc.errno == errno.ENOSPC
        if probe.damage is not None:
            probe.damage(world)
        before = world.snapshot()
        script, prefix = probes.COMMANDS[probe.command]
        outcome = call(script, [*prefix, *probe.argv(world)])
        assert_outcome(probe, world, before, outcome)
        assert "No space left on device" in outcome.err
    finally:
        subprocess.run(["umount", str(mount)], check=True)
