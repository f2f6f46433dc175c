"""Runs over several processes: ``jax.distributed`` from flags or the environment, and the processes' agreement.

A run launched in ``N`` processes (one JAX runtime, :func:`jax.distributed.initialize`)
simulates each piece over the devices of all processes; every process holds
the whole result, and only process 0 touches the output file and its lock
(:func:`~nhsde.runs._store.claim`, :func:`~nhsde.runs._store.write`).  Before
any work the processes exchange digests of the configuration, the code
(package versions and sources) and the output file they read, and after every
write a digest of the numbers; any difference, or an error in any process,
raises the same exception in every process instead of leaving the others
waiting in a collective.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import os
from collections.abc import Iterator

import jax
import numpy as np

from ._config import ConfigError

__all__ = ["ENV", "add_flags", "agree", "digest", "initialize", "is_writer", "processes", "several", "to_host"]

ENV = {"coordinator": "NHSDE_COORDINATOR", "num_processes": "NHSDE_NUM_PROCESSES", "process_id": "NHSDE_PROCESS_ID"}
"""The environment variables :func:`initialize` reads for an argument not given."""
_FLAGS = {"coordinator": "--coordinator", "num_processes": "--num-processes", "process_id": "--process-id"}
_BUFFER = 4096  # bytes each process sends when the processes agree
_MESSAGE = 3000  # characters of an error message passed on to the other processes


def _setting(name: str, value, via_flag: bool):
    """``value`` if given, else the environment variable ``ENV[name]`` (``None`` when unset or empty)."""
    given = _FLAGS[name] if via_flag else name
    if value is not None:
        return value, given
    raw = os.environ.get(ENV[name], "").strip()
    return (raw or None), ENV[name] if raw else f"{given} (or {ENV[name]})"


def _bad(name: str, value, allowed: str) -> str:
    return f"{name} is not set: {allowed}" if value is None else f"{name}={value!r}: {allowed}"


def initialize(coordinator=None, num_processes=None, process_id=None, *, via_flag: bool = False) -> bool:
    """Join ``num_processes`` processes into one JAX runtime, process ``process_id``, coordinator ``"host:port"``.

    Each argument not given is read from the environment (``NHSDE_COORDINATOR``,
    ``NHSDE_NUM_PROCESSES``, ``NHSDE_PROCESS_ID``); with none set, nothing is
    done (one process, as without this call).  Returns whether several processes
    run.  Call it before anything else uses JAX.  Incomplete or impossible
    settings raise :class:`ConfigError` naming the flag or variable.
    """
    coordinator, c_name = _setting("coordinator", coordinator, via_flag)
    n, n_name = _setting("num_processes", num_processes, via_flag)
    i, i_name = _setting("process_id", process_id, via_flag)
    if coordinator is None and n is None and i is None:
        return jax.distributed.is_initialized()
    try:
        n = int(n) if n is not None else None
    except ValueError:
        raise ConfigError(_bad(n_name, n, "expected a whole number of processes ≥ 1.")) from None
    try:
        i = int(i) if i is not None else None
    except ValueError:
        raise ConfigError(_bad(i_name, i, "expected this process's index, 0 … number of processes − 1.")) from None
    if n is None or n < 1:
        raise ConfigError(_bad(n_name, n, "give the number of processes (≥ 1) with the coordinator and process id."))
    if n == 1 and i in (None, 0):
        return jax.distributed.is_initialized()  # one process: nothing to join
    if coordinator is None or ":" not in str(coordinator):
        raise ConfigError(_bad(c_name, coordinator, "give the coordinator as HOST:PORT, e.g. 10.0.0.1:1234."))
    if i is None or not 0 <= i < n:
        raise ConfigError(_bad(i_name, i, f"expected this process's index, 0 … {n - 1}."))
    if jax.distributed.is_initialized():
        if (jax.process_count(), jax.process_index()) != (n, i):
            raise ConfigError(
                f"jax.distributed already runs process {jax.process_index()} of {jax.process_count()}, "
                f"not {i} of {n} ({n_name}, {i_name})."
            )
        return True
    jax.distributed.initialize(str(coordinator), num_processes=n, process_id=i)
    return True


def several() -> bool:
    """Whether this JAX runtime spans several processes."""
    return jax.process_count() > 1


def is_writer() -> bool:
    """Whether this process writes the output files: process 0 (the only process of a single-process run)."""
    return jax.process_index() == 0


def to_host(a) -> np.ndarray:
    """``a`` as a NumPy array in this process: over several processes an array spread over the devices of all (such
    as ``Ensemble.paths``) is gathered first, a collective (every process calls it alike)."""
    if isinstance(a, jax.Array) and not a.is_fully_addressable:
        from jax.experimental import multihost_utils

        return np.asarray(multihost_utils.process_allgather(a, tiled=True))
    return np.asarray(a)


def digest(*parts: str) -> str:
    """SHA-256 of ``parts``, each length-prefixed."""
    h = hashlib.sha256()
    for p in parts:
        b = p.encode()
        h.update(f"{len(b)}:".encode() + b)
    return h.hexdigest()


_WHAT = {
    "config": "configuration",
    "code": "code (package versions and sources)",
    "file": "output file (the output must lie on a disk every process sees, e.g. a shared file system)",
    "data": "numbers (the simulation is not reproducible across these processes)",
}


def agree(values: dict[str, str], error: BaseException | None = None):
    """Exchange ``values`` (short strings, e.g. digests) and ``error`` between all processes; a collective.

    Raises in every process alike: ``error`` itself in the process that had it,
    the same type and message naming the process in the others (the lowest
    process with an error wins); else :class:`ConfigError` when a process's
    ``values`` differ from process 0's, naming what differs.  With one process
    it only raises ``error``.
    """
    if not several():
        if error is not None:
            raise error
        return
    from jax.experimental import multihost_utils

    message = None if error is None else (type(error).__name__, str(error)[:_MESSAGE])
    payload = json.dumps({"error": message, "values": values}).encode()
    if len(payload) > _BUFFER:
        raise ValueError(f"agree: values of {len(payload)} bytes; at most {_BUFFER} fit.")
    buffer = np.zeros(_BUFFER, np.uint8)
    buffer[: len(payload)] = np.frombuffer(payload, np.uint8)
    gathered = np.asarray(multihost_utils.process_allgather(buffer))
    seen = [json.loads(bytes(row).rstrip(b"\0")) for row in gathered.reshape(-1, _BUFFER)]
    me = jax.process_index()
    for p, s in enumerate(seen):
        if s["error"] is not None:
            if p == me and error is not None:
                raise error
            kind, text = s["error"]
            cls = {"ConfigError": ConfigError, "OSError": OSError, "FileNotFoundError": OSError}.get(kind, RuntimeError)
            raise cls(f"process {p} of {len(seen)} failed: {text}")
    first = seen[0]["values"]
    differ = sorted({k for s in seen[1:] for k in set(s["values"]) | set(first) if s["values"].get(k) != first.get(k)})
    if differ:
        which = [p for p, s in enumerate(seen) if s["values"] != first]
        raise ConfigError(
            f"the {len(seen)} processes disagree: process{'es' if len(which) > 1 else ''} "
            f"{', '.join(map(str, which))} see{'' if len(which) > 1 else 's'} a different "
            + " and ".join(str(_WHAT.get(k, k)) for k in differ)
            + " than process 0; start every process with the same run file and the same installation."
        )


def add_flags(parser: argparse.ArgumentParser):
    """The options ``--coordinator``, ``--num-processes``, ``--process-id`` of a run over several processes."""
    group = parser.add_argument_group(
        "several processes (jax.distributed; default the environment's NHSDE_COORDINATOR, "
        "NHSDE_NUM_PROCESSES, NHSDE_PROCESS_ID; none: one process)"
    )
    group.add_argument("--coordinator", metavar="HOST:PORT", help="the address of process 0's coordinator")
    group.add_argument("--num-processes", type=int, metavar="N", help="the number of processes")
    group.add_argument("--process-id", type=int, metavar="I", help="this process's index, 0 … N − 1")


@contextlib.contextmanager
def processes(args: argparse.Namespace) -> Iterator[None]:
    """The command's processes: :func:`initialize` from ``args`` (or the environment); in processes other than 0
    standard output is silenced (process 0 reports; errors still reach standard error)."""
    if not initialize(*(getattr(args, k, None) for k in _FLAGS), via_flag=True) or is_writer():
        yield
        return
    with open(os.devnull, "w") as null, contextlib.redirect_stdout(null):
        yield
