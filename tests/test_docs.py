"""The documentation site and its API reference build in strict mode (``make docs``), and the strict build can fail.

``mkdocs build --strict`` with the repository's ``mkdocs.yml``: docs/*.md and docs/api.md, whose ``:::`` directives
mkdocstrings renders from the docstrings (griffe, Google style). A broken link, an Args entry naming a parameter the
signature lacks, or an Args section leaving one out (``docs/_ext/params_complete.py``) is a warning, and strict
mode turns it into a failed build. The second group of tests gives the same configuration a tiny module whose
docstring drifts from its signature and checks that the build fails and says why, so the first test cannot pass
because the check is switched off. The last ones check the hook that renders the pages' GitHub-style lists as lists
(``docs/_ext/gfm_lists.py``).
"""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import griffe
import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "mkdocs.yml"
#: the public Python surface the API reference must render (README and docs/ show users calling these)
PUBLIC = (
    "tofdenoise.inference.denoise.denoise",
    "tofdenoise.inference.denoise.load_restorer",
    "tofdenoise.physics.uncertainty.sigma_depth_mm",
    "tofdenoise.physics.calibration.SensorCalibration",
    "tofdenoise.models.registry.build_backbone",
    "tofdenoise.models.tiling.tiled_forward",
    "tofdenoise.models.scan.dispatch.selective_scan",
    "tofdenoise.training.module.DepthRestorer",
    "tofdenoise.data_modules.datamodule.ToFDataModule",
    "tofdenoise.registry.Registry",
)


def _mkdocs_build(config: Path, site_dir: Path) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}  # griffe reads src/ by path, not by import
    return subprocess.run(
        [
            sys.executable,
            "-m",
            "mkdocs",
            "build",
            "--strict",
            "--config-file",
            str(config),
            "--site-dir",
            str(site_dir),
        ],
        cwd=config.parent,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_the_docs_site_builds_strict_with_the_api_reference(tmp_path):
    result = _mkdocs_build(CONFIG, tmp_path / "site")
    assert result.returncode == 0, f"mkdocs build --strict failed:\n{result.stdout}\n{result.stderr}"
    site = tmp_path / "site"
    api = (site / "api" / "index.html").read_text(encoding="utf-8")
    # rendered from the docstrings: each public object's heading, and entries of their parameter tables
    for path in PUBLIC:
        assert f'id="{path}"' in api, f"{path} missing from the API reference"
    for documented in ("model_or_ckpt", "signal_e", "eval_batch_size", "backbone_kwargs", "trainable"):
        assert f"<code>{documented}</code>" in api, f"parameter {documented} missing from the API reference"
    for page in ("physics", "data", "models", "training", "denoise", "results"):
        assert (site / page / "index.html").is_file(), f"docs/{page}.md missing from the site"
    # the records under docs/results/ are the results page's sources, not pages: only its figures are copied
    assert list((site / "results").rglob("*.png")), "the results page's figures are missing"
    assert not [p for p in (site / "results").rglob("*") if p.suffix in (".json", ".csv", ".yaml", ".md")]


def test_every_object_the_api_reference_renders_documents_its_parameters():
    """With an Args section on each (the extension then checks it names every parameter), no public object's
    parameters go undocumented: a prose docstring would slip past both griffe's check and the extension."""
    package = griffe.load("tofdenoise", search_paths=[str(ROOT / "src")], resolve_aliases=False)
    api = (ROOT / "docs" / "api.md").read_text(encoding="utf-8")
    paths: list[str] = []
    for line in api.splitlines():
        if line.startswith("::: "):
            paths.append(line[4:].strip())
        elif line.strip().startswith("members: ["):  # the members a class's directive renders
            owner = paths[-1]
            paths += [f"{owner}.{m.strip()}" for m in line.split("[", 1)[1].rstrip("]").split(",")]
    assert set(PUBLIC) <= set(paths), "the API reference lost a public object"
    undocumented = []
    for path in paths:
        obj = package[path.removeprefix("tofdenoise.")]
        if not (obj.is_function or obj.is_class):
            continue
        params = [p.name for p in obj.parameters if p.name not in ("self", "cls")]
        sections = obj.docstring.parse("google", warnings=False) if obj.docstring else []
        if params and not any(sec.kind is griffe.DocstringSectionKind.parameters for sec in sections):
            undocumented.append(f"{path}({', '.join(params)})")
    assert not undocumented, f"no Args section: {undocumented}"


def _drift_project(tmp_path: Path, docstring: str) -> Path:
    """The repository's mkdocs configuration, pointed at one page and one module ``driftmod`` with ``docstring``."""
    config = yaml.safe_load(CONFIG.read_text(encoding="utf-8"))
    (plugin,) = [p for p in config["plugins"] if isinstance(p, dict) and "mkdocstrings" in p]
    handler = plugin["mkdocstrings"]["handlers"]["python"]
    handler["paths"] = [str(tmp_path / "src")]
    handler["options"]["extensions"] = [str(ROOT / ext) for ext in handler["options"]["extensions"]]
    config["hooks"] = [str(ROOT / hook) for hook in config.get("hooks", [])]
    config.update(docs_dir=str(tmp_path / "docs"), nav=["index.md"])
    config.pop("exclude_docs", None)
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "index.md").write_text(f"# API\n\n{GITHUB_LIST}\n::: driftmod.scale_depth\n", encoding="utf-8")
    (tmp_path / "src").mkdir()
    body = textwrap.indent(textwrap.dedent(docstring).strip("\n"), "    ")
    (tmp_path / "src" / "driftmod.py").write_text(
        f'def scale_depth(depth_mm: float, factor: float = 2.0) -> float:\n    """{body.lstrip()}\n    """\n'
        "    return depth_mm * factor\n",
        encoding="utf-8",
    )
    path = tmp_path / "mkdocs.yml"
    path.write_text(yaml.safe_dump(config, sort_keys=False), encoding="utf-8")
    return path


#: a list as GitHub renders it: straight after a paragraph line, nested by 2 spaces (docs/_ext/gfm_lists.py)
GITHUB_LIST = """Two kinds:
- **first**, with a nested list:
  - nested one
  - nested two
- **second**
"""

GOOD = """
    Scale a depth.

    Args:
        depth_mm: the depth [mm].
        factor: the scale.
    """


@pytest.mark.parametrize(
    ("docstring", "message"),
    [
        (
            """
            Scale a depth.

            Args:
                depth_mm: the depth [mm].
                factor: the scale.
                gain_db: a parameter the signature does not have.
            """,
            "Parameter 'gain_db' does not appear in the function signature",
        ),
        (
            """
            Scale a depth.

            Args:
                depth_mm: the depth [mm].
            """,
            "parameter(s) factor of driftmod.scale_depth missing from its docstring's Args section",
        ),
    ],
    ids=["documents-a-parameter-the-signature-lacks", "leaves-a-parameter-out"],
)
def test_a_docstring_that_drifts_from_its_signature_fails_the_strict_build(tmp_path, docstring, message):
    result = _mkdocs_build(_drift_project(tmp_path, docstring), tmp_path / "site")
    output = result.stdout + result.stderr
    assert result.returncode != 0, f"the strict build passed a drifted docstring:\n{output}"
    assert message in output, output


def test_the_same_module_with_a_matching_docstring_builds(tmp_path):
    """The control of the drift tests: their failure comes from the docstring, not from the set-up."""
    result = _mkdocs_build(_drift_project(tmp_path, GOOD), tmp_path / "site")
    assert result.returncode == 0, result.stdout + result.stderr
    page = (tmp_path / "site" / "index.html").read_text(encoding="utf-8")
    assert "the scale." in page
    # the page's GitHub-style list renders as a list with a nested one, not as text run into the paragraph
    assert "<p>Two kinds:</p>" in page
    assert page.count("<li>") == 4 and page.count("<ul>") == 2, page


def _gfm_lists():
    spec = importlib.util.spec_from_file_location("gfm_lists", ROOT / "docs" / "_ext" / "gfm_lists.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.gfm_lists


@pytest.mark.parametrize(
    ("github", "python_markdown"),
    [
        ("Text:\n- a\n  more a\n  - a.1\n- b", "Text:\n\n- a\n    more a\n    - a.1\n- b"),
        ("Text:\n1. one\n2. two", "Text:\n\n1. one\n2. two"),
        # CommonMark: an ordered item interrupts a paragraph only when it starts at 1
        ("In\n2026. a year", "In\n2026. a year"),
        # fenced code is left alone, and an unindented fence ends the list
        ("- a\n```\n- b\n  c\n```\n\n  after", "- a\n```\n- b\n  c\n```\n\n  after"),
        ("# Title\n- a\n\nParagraph\n  indented", "# Title\n- a\n\nParagraph\n  indented"),
    ],
)
def test_github_style_lists_are_rewritten_for_python_markdown(github, python_markdown):
    assert _gfm_lists()(github) == python_markdown
