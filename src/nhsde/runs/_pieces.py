"""The piece loop: :func:`run` integrates a run file's paths in pieces, writing the netCDF file after each.

Piece ``k`` is paths ``k·chunk …`` of the ensemble the seed defines
(``simulate(first_path=k·chunk)``); ``simulate`` reduces it to moment sums
about the first piece's shift (``Save(about=shift)``), which are kept in
float64 and added in piece order.  The scene is built once per run.

Over several processes (``jax.distributed``, see :mod:`~nhsde.runs._distributed`)
every process runs this same loop: each piece is simulated over the devices of
all processes, every process resumes from the same file (on a disk all see),
and only process 0 writes it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import diffrax as dfx

from .._ensemble import Save
from .._simulate import simulate
from ._config import RunConfig, x64_enabled
from ._store import Pieces, claim, dataset, provenance, resume, write

if TYPE_CHECKING:
    import xarray as xr  # imported where used: `import nhsde.runs` leaves it (and pandas) until a run file

__all__ = ["need_x64", "run"]


def need_x64():
    if not x64_enabled():
        raise RuntimeError(
            "runs keep float64 moment sums: call jax.config.update('jax_enable_x64', True) first "
            "(precision = 'float32' still simulates in float32)."
        )


def run(
    config: RunConfig,
    out,
    *,
    on_start: Callable[[int], None] | None = None,
    on_piece: Callable[[int], None] | None = None,
    progress_meter: dfx.AbstractProgressMeter | None = None,
) -> xr.Dataset:
    """Run (or resume) ``config``, writing the netCDF file ``out`` after every piece; returns the dataset written last.

    An existing ``out`` of the same configuration, intact (its checksum), started
    by the same code (package versions and sources), is resumed from its last
    piece, bitwise as if never interrupted; anything else there is refused
    (:class:`ConfigError` naming the file), before any work, as is an output
    another process is writing.  ``on_start(k)`` is called once the output is
    checked, with the pieces already done; ``on_piece(k)`` after piece ``k`` is
    safely written (an exception there interrupts the run as a kill would);
    ``progress_meter`` is passed to :func:`~nhsde.simulate` for every piece.

    Launched in several processes after :func:`jax.distributed.initialize`
    (or :func:`~nhsde.runs.main`'s ``--coordinator``, ``--num-processes``,
    ``--process-id``), every process calls ``run`` with the same configuration
    and ``out``: each piece is computed over all processes' devices, only process
    0 touches ``out`` and its lock, the others read it to resume alike, and
    every process returns the same statistics.  A process seeing another
    configuration, other code or another file, and an error in any process, is
    refused in all (:class:`ConfigError`); ``on_start`` and ``on_piece`` run in
    every process and must act alike in all (one that raises in some
    processes only leaves the others waiting).
    """
    if config.kind != "simulate":
        raise ValueError(f"run: this is a {config.kind!r} configuration; use run_fit.")
    need_x64()
    out = Path(out)
    d = config.data
    n_total, chunk = d["paths"]["n"], d["paths"]["chunk"]
    keep = d["statistics"]["keep_paths"]
    with claim(out, config) as found:
        pieces, prov = (Pieces(), provenance(config)) if found is None else resume(found, out, config)
        if on_start is not None:
            on_start(len(pieces.sums))
        built = config.build()
        ds = None
        for k in range(len(pieces.sums), math.ceil(n_total / chunk)):
            ens = simulate(
                built.system,
                built.y0,
                built.key,
                n_paths=min(chunk, n_total - k * chunk),
                first_path=k * chunk,
                t0=d["solver"]["t0"],
                t1=d["solver"]["t1"],
                dt=d["solver"]["dt"],
                solver=d["solver"]["name"],
                save=Save(names=built.names, n=d["statistics"]["save_points"], paths=keep, about=pieces.shift),
                on_failure="exclude",
                progress_meter=progress_meter,
            )
            pieces.add(ens, keep)
            ds = dataset(config, built, pieces, prov)
            write(ds, out)
            if on_piece is not None:
                on_piece(k)
    return dataset(config, built, pieces, prov) if ds is None else ds
