"""JAX's persistent compilation cache, in the user's cache folder: a second process skips the compiler."""

from __future__ import annotations

import os
from pathlib import Path

import jax
from jax.experimental.compilation_cache import compilation_cache

__all__ = ["COMPILATION_CACHE_VARIABLE", "check_private", "default_compilation_cache", "enable_compilation_cache"]

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


def check_private(folder: Path) -> None:
    """Refuse a cache folder that another user could write to, as ssh refuses such key files: the cache holds
    executable code.  The folder must be the user's own and writable by no group or other; a folder above it must
    not let others replace it (writable by others only with the sticky bit, as ``/tmp``)."""
    uid = os.getuid() if hasattr(os, "getuid") else None
    info = folder.stat()
    problem = None
    if uid is not None and info.st_uid != uid:
        problem = f"it belongs to user id {info.st_uid}, not to you ({uid})"
    elif info.st_mode & 0o022:
        problem = f"its mode {info.st_mode & 0o777:o} lets others write to it (chmod go-w, or 700)"
    else:
        for parent in folder.resolve().parents:
            mode = parent.stat().st_mode
            if mode & 0o002 and not mode & 0o1000:
                problem = f"{parent} above it is writable by everyone, without the sticky bit"
                break
    if problem:
        raise ValueError(
            f"compilation cache {str(folder)!r}: not used: {problem}; the cache holds code that runs, so keep it "
            f"where only you can write (or set {COMPILATION_CACHE_VARIABLE}=off)."
        )


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
        ValueError: the folder cannot be created, or others could write to it (:func:`check_private`), naming it.
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
    check_private(folder)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    compilation_cache.set_cache_dir(str(folder))
    compilation_cache.reset_cache()  # a folder set before takes effect only after a reset
    return folder
