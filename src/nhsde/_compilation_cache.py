"""JAX's persistent compilation cache, in the user's cache folder: a second process skips the compiler."""

from __future__ import annotations

import os
from pathlib import Path

import jax
from jax.experimental.compilation_cache import compilation_cache

__all__ = ["COMPILATION_CACHE_VARIABLE", "default_compilation_cache", "enable_compilation_cache"]

COMPILATION_CACHE_VARIABLE = "NHSDE_COMPILATION_CACHE"
"""The environment variable that moves the cache (a folder) or turns it off (``off``)."""


def default_compilation_cache() -> Path | None:
    """The cache folder: ``$NHSDE_COMPILATION_CACHE`` if set (``None`` if it is ``off``), else
    ``$XDG_CACHE_HOME/nhsde/jax`` or ``~/.cache/nhsde/jax``."""
    given = os.environ.get(COMPILATION_CACHE_VARIABLE, "").strip()
    if given.lower() == "off":
        return None
    if given:
        return Path(given).expanduser()
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "nhsde" / "jax"


def enable_compilation_cache(path: str | os.PathLike | None = None) -> Path | None:
    """Turn on JAX's persistent compilation cache: compiled programs are kept in ``path`` and a later process that
    compiles the same program (same code, shapes, JAX version and device) loads it instead of compiling again.

    Every program is cached, however short its compilation (``jax_persistent_cache_min_compile_time_secs = 0``
    and no minimum size): most of a first ``simulate``'s time goes to many small programs.  The ``nhsde``
    command calls this at start; a library user calls ``nhsde.enable_compilation_cache()`` once.  The cache is
    trusted code: keep it in a folder only you can write to.

    Arguments:
        path: the folder (created if missing); default :func:`default_compilation_cache`: the environment
            variable ``NHSDE_COMPILATION_CACHE`` (a folder, or ``off`` to leave the cache off), else
            ``$XDG_CACHE_HOME/nhsde/jax`` or ``~/.cache/nhsde/jax``.

    Returns:
        the cache folder, or ``None`` when ``NHSDE_COMPILATION_CACHE=off`` left it off.

    Raises:
        ValueError: the folder cannot be created, naming it.
    """
    folder = default_compilation_cache() if path is None else Path(path).expanduser()
    if folder is None:
        return None
    try:
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    except OSError as e:
        raise ValueError(
            f"compilation cache {str(folder)!r}: cannot create the folder ({e.strerror}); set "
            f"{COMPILATION_CACHE_VARIABLE} to another folder or to off."
        ) from None
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    compilation_cache.set_cache_dir(str(folder))
    compilation_cache.reset_cache()  # a folder set before takes effect only after a reset
    return folder
