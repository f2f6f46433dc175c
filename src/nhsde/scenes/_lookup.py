"""Scenes by name: the shipped ones, those installed packages add (entry points), and ``MODULE:CLASS``."""

from __future__ import annotations

import functools
import hashlib
import importlib
import importlib.machinery
import importlib.util
import inspect
import sys
from collections.abc import Mapping
from importlib.metadata import entry_points
from pathlib import Path
from typing import cast

from ._base import AbstractScene, is_abstract

__all__ = ["ENTRY_POINT_GROUP", "find_scene", "import_scene", "installed_scenes", "module_source", "scene_source_hash"]

ENTRY_POINT_GROUP = "nhsde.scenes"
"""The entry-point group through which an installed package adds scenes: ``name = "module:Class"``."""


def installed_scenes(shipped: Mapping[str, type[AbstractScene]]) -> dict[str, str]:
    """``name → "MODULE:CLASS"`` of the entry points in :data:`ENTRY_POINT_GROUP` (names of ``shipped`` win)."""
    return {ep.name: ep.value for ep in entry_points(group=ENTRY_POINT_GROUP) if ep.name not in shipped}


def _scene_classes(module) -> list[str]:
    return [
        name
        for name, obj in vars(module).items()
        if isinstance(obj, type) and issubclass(obj, AbstractScene) and not is_abstract(obj)
    ]


def module_source(module_name: str, folder: Path | None = None) -> Path | None:
    """The source file ``import module_name`` would run, found without running any code (``folder`` searched
    first, then ``sys.path``; the parents of a dotted name are found, not imported); ``None`` if there is none."""
    locations: list[str] | None = ([str(folder)] if folder is not None else []) + sys.path
    spec = None
    for part in module_name.split("."):
        spec = importlib.machinery.PathFinder.find_spec(part, locations)
        if spec is None:
            return None
        locations = list(spec.submodule_search_locations or [])
    origin = spec.origin if spec is not None else None
    return Path(origin) if origin and origin.endswith(".py") else None


def _import_module(module_name: str, folder: Path | None):
    """``module_name``, looked for in ``folder`` first (that module only: its own imports resolve as usual)."""
    top = module_name.split(".")[0]
    if folder is not None and top not in sys.modules:
        spec = importlib.machinery.PathFinder.find_spec(top, [str(folder)])
        if spec is not None and spec.loader is not None:
            module = importlib.util.module_from_spec(spec)
            sys.modules[top] = module
            try:
                spec.loader.exec_module(module)
            except BaseException:
                del sys.modules[top]
                raise
    return importlib.import_module(module_name)


def import_scene(spec: str, *, folder: Path | None = None, sha256: str | None = None) -> type[AbstractScene]:
    """The scene class ``CLASS`` of ``MODULE`` (imported from ``folder``, then ``sys.path``, running its code); a
    ``ValueError`` that says which part is wrong: the form, the module, the attribute, or a class that is not a
    concrete scene.  With ``sha256``, the module's source must have that SHA-256, checked before it runs."""
    module_name, _, attribute = spec.partition(":")
    if not module_name or not attribute or ":" in attribute:
        raise ValueError("expected MODULE:CLASS, e.g. my_scenes:KnifeEdge (a module importable from the Python path).")
    if sha256 is not None:
        path = module_source(module_name, folder)
        found = None if path is None else hashlib.sha256(path.read_bytes()).hexdigest()
        if found != sha256.lower():
            raise ValueError(
                f"module {module_name!r} ({path or 'not found'}) has SHA-256 {found}, not the {sha256} recorded "
                "for it; it was not imported (its code did not run)."
            )
    try:
        module = _import_module(module_name, folder)
    except ModuleNotFoundError as e:
        if e.name is not None and (module_name == e.name or module_name.startswith(e.name + ".")):
            where = "" if folder is None else f" or in {folder}"
            raise ValueError(f"no module named {e.name!r} on the Python path{where}.") from None
        raise ValueError(f"importing module {module_name!r} failed: {e}.") from e
    except Exception as e:  # the module's own code failed: a syntax error, an exception at import
        raise ValueError(f"importing module {module_name!r} failed: {type(e).__name__}: {e}.") from e
    try:
        obj = functools.reduce(getattr, attribute.split("."), module)
    except AttributeError:
        found = _scene_classes(module)
        raise ValueError(
            f"module {module_name!r} has no attribute {attribute!r}; "
            + (f"its scene classes: {', '.join(found)}." if found else "it defines no scene class.")
        ) from None
    if not (isinstance(obj, type) and issubclass(obj, AbstractScene)):
        raise ValueError(
            f"{attribute} is {'a class' if isinstance(obj, type) else 'a ' + type(obj).__name__}, not a scene class "
            "(a subclass of nhsde.scenes.AbstractScene, e.g. of AbstractSpecScene)."
        )
    if is_abstract(obj):
        missing = sorted(
            {*getattr(obj, "__abstractmethods__", ()), *(getattr(obj, "__abstractvars__", None) or ())}
            | {*(getattr(obj, "__abstractclassvars__", None) or ())}
        )
        raise ValueError(f"{attribute} is an abstract scene; it leaves {', '.join(missing)} unimplemented.")
    return cast(type[AbstractScene], obj)


def find_scene(
    name: str, shipped: Mapping[str, type[AbstractScene]], *, folder: Path | None = None, sha256: str | None = None
) -> type[AbstractScene]:
    """The scene class of ``name``: a name of ``shipped``, an installed scene's name, or ``MODULE:CLASS`` (looked
    for in ``folder`` first, checked against ``sha256`` before it runs: :func:`import_scene`); a ``ValueError``
    saying what is wrong (without the name)."""
    if name in shipped:
        return shipped[name]
    installed = installed_scenes(shipped)
    if name in installed:
        try:
            return import_scene(installed[name])
        except ValueError as e:
            raise ValueError(
                f"the installed entry point {name} = {installed[name]!r} ({ENTRY_POINT_GROUP}): {e}"
            ) from e
    if ":" in name:
        return import_scene(name, folder=folder, sha256=sha256)
    known = [*shipped, *installed]
    raise ValueError(f"unknown scene; known scenes: {', '.join(known)}; or MODULE:CLASS for a scene class of your own.")


def scene_source_hash(cls: type[AbstractScene]) -> str | None:
    """SHA-256 of the source file of the module defining ``cls``; ``None`` for nhsde's own scenes (the
    package's source hash covers them).  A module whose source cannot be read raises a ``ValueError``."""
    if cls.__module__ == "nhsde" or cls.__module__.startswith("nhsde."):
        return None
    try:
        path = inspect.getsourcefile(sys.modules[cls.__module__])
        data = Path(path).read_bytes() if path else None
    except (KeyError, TypeError, OSError):
        data = None
    if data is None:
        raise ValueError(
            f"scene {cls.__module__}:{cls.__qualname__}: the source of module {cls.__module__!r} cannot be read, "
            "so a run of it could not be checked when it resumes; define the scene in a .py file."
        )
    return hashlib.sha256(data).hexdigest()
