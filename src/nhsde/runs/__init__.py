"""Runs from TOML files and the ``nhsde`` command, stored as self-describing netCDF.

A run file names a scene, its parameters, the solver, the paths and the
statistics to keep; :func:`load_config` validates it strictly (:class:`ConfigError`
names the key).  :func:`run` integrates the paths in pieces of ``paths.chunk``,
keeps each piece's float64 moment sums about one shift and writes the netCDF
file (``format = "nhsde-run"``, with a checksum) after every piece, atomically
and under a lock; run again after an interruption, it resumes, bitwise as if
never interrupted, and refuses a file that is damaged, edited, of another
configuration or of other sources, naming it.  :func:`run_fit`
fits parameters to a run file (``format = "nhsde-fit"``).  :func:`main` is the
``nhsde`` command: ``nhsde scenes``, ``nhsde simulate SCENE``, ``nhsde simulate
--config run.toml``, ``nhsde fit --config fit.toml``.

Nothing in nhsde imports from this package: it sits on top of everything else.
"""

from ._cli import build_parser as build_parser, main as main
from ._config import Built as Built, ConfigError as ConfigError, RunConfig as RunConfig, load_config as load_config
from ._fit import (
    fit_data as fit_data,
    observations_from_run as observations_from_run,
    read_data as read_data,
    run_fit as run_fit,
)
from ._pieces import run as run
from ._store import (
    FIT_FORMAT as FIT_FORMAT,
    FORMAT as FORMAT,
    FORMAT_VERSION as FORMAT_VERSION,
    checksum as checksum,
    git_revision as git_revision,
    load_run as load_run,
    source_hash as source_hash,
    versions as versions,
)
