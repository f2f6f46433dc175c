"""The ``>>>`` examples in the docstrings and in the documentation pages run and print what they show.

Every module of the package is searched, the private ones included: the public names are re-exported
from private modules (``nhsde._simulate.simulate`` is ``nhsde.simulate``), and their docstrings live
there.  ``doctest`` only collects objects defined in the module it searches, so each example runs once.
"""

import doctest
import importlib
import io
import pkgutil
from pathlib import Path

import jax

# the examples print float64 values, as the tests compute them (conftest.py does the same for the suite)
jax.config.update("jax_enable_x64", True)

import pytest

import nhsde

SKIP = {"nhsde.runs.__main__"}  # running it is the command line
MIN_DOCSTRINGS = 30
"""Fewer docstrings with examples than this means the collection broke, not that the docs lost them."""
FLAGS = doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE


def _module_names() -> list[str]:
    names = ["nhsde"]
    for info in pkgutil.walk_packages(nhsde.__path__, prefix="nhsde."):
        if info.name not in SKIP:
            names.append(info.name)
    return sorted(names)


def _tests(name: str) -> list[doctest.DocTest]:
    module = importlib.import_module(name)
    tests = doctest.DocTestFinder(exclude_empty=True).find(module, name, globs=dict(vars(module)))
    return sorted((t for t in tests if t.examples), key=lambda t: t.name)


MODULES = _module_names()
DOCUMENTED = {name: [t.name for t in _tests(name)] for name in MODULES}
"""Every module's docstrings with examples, found at collection: the examples test runs only modules that have some."""


def test_examples_are_collected():
    documented = [n for names in DOCUMENTED.values() for n in names]
    assert len(documented) >= MIN_DOCSTRINGS, f"only {len(documented)} docstrings with examples found: {documented}"
    for must in ("nhsde._simulate.simulate", "nhsde.scenes._ball.BallOnVibratingPlane"):
        assert must in documented, f"{must} lost its example"


DOCS = Path(__file__).resolve().parents[1] / "docs"
PAGES = sorted(str(p.relative_to(DOCS)) for p in DOCS.rglob("*.md") if ">>> " in p.read_text())
"""The documentation pages with ``>>>`` examples (a blank line ends each example's output before its fence)."""


def test_pages_are_collected():
    assert "guide/your-own-scene.md" in PAGES


@pytest.mark.parametrize("page", PAGES)
def test_page_examples(page):
    text = (DOCS / page).read_text()
    test = doctest.DocTestParser().get_doctest(text, {"__name__": "__doc_page__"}, page, str(DOCS / page), 0)
    runner = doctest.DocTestRunner(optionflags=FLAGS)
    report = io.StringIO()
    runner.run(test, out=report.write)
    result = runner.summarize(verbose=False)
    assert result.attempted >= 1 and result.failed == 0, (
        f"{result.failed} of {result.attempted} examples in {page} failed:\n{report.getvalue()}"
    )


@pytest.mark.parametrize("name", sorted(name for name, found in DOCUMENTED.items() if found))
def test_module_examples(name):
    tests = _tests(name)
    runner = doctest.DocTestRunner(optionflags=FLAGS)
    report = io.StringIO()
    for test in tests:
        runner.run(test, out=report.write)
    result = runner.summarize(verbose=False)
    assert result.attempted >= len(tests) >= 1, f"{name}: {result.attempted} examples run from {len(tests)} docstrings"
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples in {name} failed:\n{report.getvalue()}"
