"""MkDocs hooks for the nhsde site (``mkdocs.yml``: ``hooks: [docs/hooks.py]``).

- The research notebooks (``notebooks/*.ipynb``) and the measured work-precision
  figures (``benchmarks/results/*.png``) stay where they live in the repository
  and are added to the site under the same paths, so pages link to them as
  ``../notebooks/….ipynb`` and ``../benchmarks/results/….png`` and ``--strict``
  checks those links like any other.
- Every ``notebooks/*.py`` (the jupytext source the tests execute) must have a
  paired ``.ipynb`` with the same cells; a missing or stale pair is a warning,
  hence an error under ``--strict`` (fix: ``jupytext --sync notebooks/*.py``).
- Docstrings are written with Sphinx roles (``:class:`~nhsde.Ensemble```); on the
  API pages the role prefix is dropped and the ``~`` shortening applied, so they
  read as code.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

from mkdocs.plugins import event_priority
from mkdocs.structure.files import File

log = logging.getLogger("mkdocs.hooks.nhsde")

ROOT = Path(__file__).resolve().parents[1]
SHARED = ("notebooks/*.ipynb", "benchmarks/results/*.png")


@event_priority(100)  # before mkdocs-jupyter turns .ipynb files into pages
def on_files(files, config):
    for pattern in SHARED:
        for path in sorted(ROOT.glob(pattern)):
            uri = path.relative_to(ROOT).as_posix()
            if files.get_file_from_path(uri) is None:
                site, urls = config["site_dir"], config["use_directory_urls"]
                files.append(File(uri, src_dir=str(ROOT), dest_dir=site, use_directory_urls=urls))
    _check_notebook_pairs()
    return files


def _cells(path: Path):
    import jupytext

    nb = jupytext.read(path)
    return [(c.cell_type, c.source.strip()) for c in nb.cells]


def _check_notebook_pairs():
    for source in sorted((ROOT / "notebooks").glob("*.py")):
        if source.name.startswith("_"):
            continue
        paired = source.with_suffix(".ipynb")
        if not paired.exists():
            pair = f"jupytext --set-formats ipynb,py:percent notebooks/{source.name}"
            log.warning(f"notebooks/{paired.name} is missing; run: {pair}")
        elif _cells(source) != _cells(paired):
            log.warning(
                f"notebooks/{paired.name} differs from notebooks/{source.name} (the executed source); "
                f"run: jupytext --sync notebooks/{source.name}"
            )


_ROLE = re.compile(r":(?:py:)?(?:class|func|meth|mod|data|attr|obj|exc|const):(<code>)")
_TILDE = re.compile(r"<code>~\.*(?:\w+\.)*(\w+)</code>")


def on_page_content(html, page, config, files):
    if not page.file.src_uri.startswith("api/"):
        return html
    html = _ROLE.sub(r"\1", html)
    return _TILDE.sub(r"<code>\1</code>", html)
