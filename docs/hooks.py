"""MkDocs hooks for the nhsde site (``mkdocs.yml``: ``hooks: [docs/hooks.py]``).

- The research notebooks (``notebooks/*.ipynb``) and the measured work-precision
  figures (``benchmarks/results/*.png``) stay where they live in the repository
  and are added to the site under the same paths, so pages link to them as
  ``../notebooks/….ipynb`` and ``../benchmarks/results/….png`` and ``--strict``
  checks those links like any other.
- Every ``notebooks/*.py`` (the jupytext source the tests execute) must have a
  paired ``.ipynb`` with the same cell sources (outputs are not compared), and
  that ``.ipynb`` must be stored executed, top to bottom, with its outputs: the
  pages render those outputs (figures included) without running anything.  A
  missing, stale or unexecuted pair is a warning, hence an error under
  ``--strict``; the message gives the command that fixes it.
  ``tests/test_notebooks.py`` runs the same checks (:func:`notebook_pair_problems`,
  :func:`notebook_output_problems`; this file loads without mkdocs installed,
  so the test can import it by path).
- Docstrings are written with Sphinx roles (``:class:`~nhsde.Ensemble```); on the
  API pages the role prefix is dropped and the ``~`` shortening applied, so they
  read as code.
"""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path

try:
    from mkdocs.plugins import event_priority
except ImportError:  # loaded by tests/test_notebooks.py without the docs extra

    def event_priority(priority):
        return lambda method: method


log = logging.getLogger("mkdocs.hooks.nhsde")

ROOT = Path(__file__).resolve().parents[1]
SHARED = ("notebooks/*.ipynb", "benchmarks/results/*.png")


EXECUTE = "jupyter nbconvert --to notebook --execute --inplace --ExecutePreprocessor.record_timing=False"


@event_priority(100)  # before mkdocs-jupyter turns .ipynb files into pages
def on_files(files, config):
    from mkdocs.structure.files import File

    for pattern in SHARED:
        for path in sorted(ROOT.glob(pattern)):
            uri = path.relative_to(ROOT).as_posix()
            if files.get_file_from_path(uri) is None:
                site, urls = config["site_dir"], config["use_directory_urls"]
                files.append(
                    File(uri, src_dir=str(ROOT), dest_dir=site, use_directory_urls=urls)
                )
    for problem in notebook_pair_problems() + notebook_output_problems():
        log.warning(problem)
    return files


def _sources(root: Path):
    return sorted(
        p for p in (root / "notebooks").glob("*.py") if not p.name.startswith("_")
    )


def _cells(path: Path):
    import jupytext

    nb = jupytext.read(path)
    return [(c.cell_type, c.source.strip()) for c in nb.cells]


def notebook_pair_problems(root: Path = ROOT) -> list[str]:
    """One message per ``notebooks/*.py`` whose ``.ipynb`` is missing or has other cell sources (needs jupytext)."""
    problems = []
    for source in _sources(root):
        paired = source.with_suffix(".ipynb")
        if not paired.exists():
            pair = f"jupytext --set-formats ipynb,py:percent notebooks/{source.name}"
            problems.append(
                f"notebooks/{paired.name} is missing; run: {pair}, then: {EXECUTE} notebooks/{paired.name}"
            )
        elif _cells(source) != _cells(paired):
            problems.append(
                f"notebooks/{paired.name} differs from notebooks/{source.name} (the executed source); "
                f"run: jupytext --sync notebooks/{source.name}, then: {EXECUTE} notebooks/{paired.name}"
            )
    return problems


def notebook_output_problems(root: Path = ROOT) -> list[str]:
    """One message per stored ``notebooks/*.ipynb`` not executed top to bottom in one run.

    Every non-empty code cell must carry an execution count, and the counts must be
    1, 2, 3, … in cell order (what ``jupyter nbconvert --execute`` stores), so the
    stored outputs are those of the stored sources run in order.
    """
    problems = []
    for source in _sources(root):
        paired = source.with_suffix(".ipynb")
        if not paired.exists():
            continue
        cells = json.loads(paired.read_text(encoding="utf-8"))["cells"]
        counts = [
            c.get("execution_count")
            for c in cells
            if c["cell_type"] == "code" and "".join(c["source"]).strip()
        ]
        if counts != list(range(1, len(counts) + 1)):
            problems.append(
                f"notebooks/{paired.name} is not stored executed in order (execution counts {counts}); "
                f"run: {EXECUTE} notebooks/{paired.name}"
            )
    return problems


_ROLE = re.compile(r":(?:py:)?(?:class|func|meth|mod|data|attr|obj|exc|const):(<code>)")
_TILDE = re.compile(r"<code>~\.*(?:\w+\.)*(\w+)</code>")


def on_page_content(html, page, config, files):
    if not page.file.src_uri.startswith("api/"):
        return html
    html = _ROLE.sub(r"\1", html)
    return _TILDE.sub(r"<code>\1</code>", html)
