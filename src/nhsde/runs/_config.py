"""Run and fit files: the strict TOML schema, :class:`RunConfig`, :class:`ConfigError`, :func:`load_config`.

Every key is checked against the schema: unknown keys, wrong types,
out-of-range values, unknown scenes, options, parameters, state components or
saved names are rejected with the key named.  Values are only ever compared
with known names and numbers; the one exception is ``scene = "MODULE:CLASS"``,
a scene class of the user's, whose module is imported (running its code, as
``import`` does) from the Python path.
"""

from __future__ import annotations

import dataclasses
import hashlib
import inspect
import json
import re
import reprlib
import stat
import sys
import tomllib
from pathlib import Path
from typing import Any, NamedTuple, cast

import jax
import jax.numpy as jnp

from .._brownian import BLOCK
from .._options import FixedSteps
from .._simulate import MAX_PATH_INDEX, MIN_PATHS
from .._solvers import SOLVERS, solver_needs
from .._system import StochasticSystem
from ..scenes import SCENES, AbstractScene, find_scene
from ..scenes._lookup import module_source

__all__ = [
    "ACCURACY_SOLVERS",
    "Built",
    "ConfigError",
    "RunConfig",
    "default_statistic",
    "load_config",
    "parse_statistic",
    "x64_enabled",
]


def x64_enabled() -> bool:
    """Whether float64 is on (``jax.config.update('jax_enable_x64', True)``)."""
    return jax.dtypes.canonicalize_dtype(jnp.float64) == jnp.float64


class ConfigError(ValueError):
    """A run file, output path or stored run that cannot be used; the message names the key (``key``) or file."""

    def __init__(self, message: str, key: str | None = None):
        super().__init__(message)
        self.key = key


_REQUIRED = object()
_INT64 = 2**63
MAX_STEPS = FixedSteps.max_steps
"""Steps per path a run may take: :class:`~nhsde.FixedSteps`' default budget."""
MAX_FILE_SIZE = 2**20
"""Bytes a run file may have (a run file is a few hundred)."""


@dataclasses.dataclass(frozen=True)
class _Field:
    kind: str  # "int", "float", "str", "bool", "names"
    default: object = _REQUIRED
    allowed: tuple | None = None  # for "str"
    minimum: float | None = None  # for numbers
    strict: bool = False  # minimum excluded
    maximum: int | None = None  # for "int"
    multiple_of: int | None = None  # for "int"


ACCURACY_SOLVERS = ("any", "euler", "weak2")
"""``accuracy.solver``: the solvers :func:`~nhsde.statistics.to_accuracy` compares (``weak2``: Gaussian increments)."""


def _schema(kind: str, accuracy: bool = False) -> dict:
    """The allowed keys; ``"scene-…"`` tables depend on the scene.  With an ``[accuracy]`` table, ``paths.n`` is
    not used (the estimator chooses the paths) and may be left out."""
    schema: dict[str, Any] = {
        "scene": _Field("str"),
        "seed": _Field("int", 0, minimum=0, maximum=_INT64 - 1),
        "precision": _Field("str", "float64", allowed=("float32", "float64")),
        "options": "scene-options",
        "parameters": "scene-parameters",
        "initial_state": "scene-state",
        "solver": {
            "name": _Field("str", "euler", allowed=tuple(SOLVERS)),
            "dt": _Field("float", minimum=0, strict=True),
        },
        "paths": {"n": _Field("int", minimum=MIN_PATHS, maximum=MAX_PATH_INDEX)},
        "statistics": {"save": _Field("names", None)},
    }
    if kind == "simulate":
        schema["solver"] |= {"t0": _Field("float", 0.0), "t1": _Field("float")}
        schema["paths"] |= {"chunk": _Field("int", 8192, minimum=BLOCK, maximum=MAX_PATH_INDEX + 1, multiple_of=BLOCK)}
        schema["statistics"] |= {"save_points": _Field("int", 11, minimum=2), "keep_paths": _Field("bool", False)}
        schema["accuracy"] = {
            "rmse": _Field("float", None, minimum=0, strict=True),
            "relative_rmse": _Field("float", None, minimum=0, strict=True),
            "statistic": _Field("str", None),
            "solver": _Field("str", "any", allowed=ACCURACY_SOLVERS),
            "max_path_steps": _Field("float", 1e11, minimum=0, strict=True),
        }
        if accuracy:
            schema["paths"]["n"] = _Field("int", 4096, minimum=MIN_PATHS, maximum=MAX_PATH_INDEX)
    else:
        schema["fit"] = {
            "data": _Field("str"),
            "vary": _Field("names", ["eps", "nu"]),
            "max_steps": _Field("int", 100, minimum=1),
        }
    return schema


def _type_name(value) -> str:
    names = {bool: "a boolean", int: "an integer", float: "a number", str: "a string", list: "an array"}
    return names.get(type(value), "a table" if isinstance(value, dict) else type(value).__name__)


_EXPECTED = {"int": "an integer", "float": "a number", "str": "a string", "bool": "true or false"}


def _is_kind(kind: str, value: object) -> bool:
    return {
        "int": isinstance(value, int) and not isinstance(value, bool),
        "float": isinstance(value, (int, float)) and not isinstance(value, bool),
        "str": isinstance(value, str),
        "bool": isinstance(value, bool),
        "names": isinstance(value, list) and all(isinstance(v, str) for v in value),
    }[kind]


def _check(key: str, field: _Field, value: Any):
    if not _is_kind(field.kind, value):
        expected = _EXPECTED.get(field.kind, "an array of strings")
        raise ConfigError(f"{key}: expected {expected}, got {_type_name(value)} {reprlib.repr(value)}.", key)
    if field.kind == "float":
        if not abs(value) <= sys.float_info.max:  # inf, nan, an integer beyond every float
            raise ConfigError(f"{key} = {reprlib.repr(value)}: must be finite.", key)
        value = float(value)
    if (
        field.kind in ("int", "float")
        and field.minimum is not None
        and (value < field.minimum or (field.strict and value == field.minimum))
    ):
        raise ConfigError(
            f"{key} = {reprlib.repr(value)}: must be {'>' if field.strict else '≥'} {field.minimum:g}.", key
        )
    if field.maximum is not None and value > field.maximum:
        raise ConfigError(f"{key} = {reprlib.repr(value)}: must be ≤ {field.maximum}.", key)
    if field.kind == "int" and not -_INT64 <= value < _INT64:
        raise ConfigError(f"{key} = {reprlib.repr(value)}: beyond the 64-bit integers.", key)
    if field.multiple_of and value % field.multiple_of:
        raise ConfigError(f"{key} = {value}: must be a multiple of {field.multiple_of}.", key)
    if field.allowed is not None and value not in field.allowed:
        allowed = ", ".join(map(repr, field.allowed))
        raise ConfigError(f"{key} = {reprlib.repr(value)}: allowed values are {allowed}.", key)
    if field.kind == "names" and len(set(value)) != len(value):
        raise ConfigError(f"{key} = {reprlib.repr(value)}: names must not repeat.", key)
    return value


def _table(prefix: str, spec: dict, raw, out: dict):
    if not isinstance(raw, dict):
        raise ConfigError(f"{prefix or 'the file'}: expected a table, got {_type_name(raw)}.", prefix or None)
    for key in raw:
        if key not in spec:
            where = f"[{prefix}]" if prefix else "the top level"
            name = f"{prefix}.{key}" if prefix else key
            raise ConfigError(f"{name}: unknown key in {where}; allowed: {', '.join(spec)}.", name)
    for key, field in spec.items():
        name = f"{prefix}.{key}" if prefix else key
        if isinstance(field, dict):
            out[key] = {}
            _table(name, field, raw.get(key, {}), out[key])
        elif isinstance(field, str):  # scene-dependent: checked once the scene is known
            value = raw.get(key, {})
            if not isinstance(value, dict):
                raise ConfigError(f"{name}: expected a table, got {_type_name(value)}.", name)
            out[key] = value
        elif key in raw and not (raw[key] is None and field.default is None):  # null: a stored default
            out[key] = _check(name, field, raw[key])
        elif field.default is _REQUIRED:
            raise ConfigError(f"{name}: required key is missing.", name)
        else:
            out[key] = field.default


def _scene_options(scene_cls) -> dict[str, object]:
    """The scene's keyword options a file can set (``drift=True``, ``route="reduced"``, …) and their defaults."""
    signature = inspect.signature(scene_cls.__init__)
    return {
        name: p.default
        for name, p in signature.parameters.items()
        if p.kind is inspect.Parameter.KEYWORD_ONLY and isinstance(p.default, (bool, str, int, float))
    }


def _construct(cls, data: dict) -> AbstractScene:
    """The scene of ``data`` (constructed once; on failure, a second try tells options from parameters)."""
    try:
        return cls(**data["options"], **data["parameters"])
    except (ValueError, TypeError) as e:
        error = e
    try:
        cls(**data["options"])
        table = "parameters"
    except (ValueError, TypeError) as e:
        table, error = "options", e
    raise ConfigError(f"{table}: {error}", table) from None


SOLVER_HELP = f"one of {', '.join(SOLVERS)} (default euler)"
"""The ``--solver`` flags' help: every alias of :data:`~nhsde.SOLVERS`, so a new solver is listed where it is named."""


class SceneSource(NamedTuple):
    """Where a ``MODULE:CLASS`` scene may come from: ``folder`` searched first for ``MODULE``, and whether its code
    may run unchecked (``trusted``) or only once its source has the SHA-256 ``sha256``."""

    folder: Path | None = None
    trusted: bool = True
    sha256: str | None = None


def _check_module_scene(name: str, source: SceneSource) -> None:
    """A run file's own ``MODULE:CLASS`` runs its code only with its source's SHA-256 recorded (or trusted)."""
    if source.trusted or source.sha256 is not None or ":" not in name or name in SCENES:
        return  # (a shipped or installed scene's name has no colon)
    module = name.partition(":")[0]
    path = module_source(module, source.folder)
    found = "" if path is None else f" (now {hashlib.sha256(path.read_bytes()).hexdigest()}, of {path})"
    raise ConfigError(
        f"scene = {name!r} names a module of your own, whose code runs when it is imported, and this file records "
        f"no scene_sha256 for it: read the module, then add scene_sha256 = its SHA-256{found}, or pass "
        "--trust-scene to run it unchecked; it was not imported.",
        "scene_sha256",
    )


def _check_scene(data: dict, source: SceneSource) -> tuple[AbstractScene, StochasticSystem]:
    """Check the scene-dependent tables; returns the scene and its system (built once, here)."""
    _check_module_scene(data["scene"], source)
    try:
        cls = find_scene(data["scene"], SCENES, folder=source.folder, sha256=source.sha256)
    except ValueError as e:
        raise ConfigError(f"scene = {data['scene']!r}: {e}", "scene") from None
    options = _scene_options(cls)
    kinds = {bool: "bool", str: "str", int: "int", float: "float"}
    for key, value in data["options"].items():
        if key not in options:
            raise ConfigError(
                f"options.{key}: unknown option of {data['scene']}; options: {', '.join(options)}.", f"options.{key}"
            )
        _check(f"options.{key}", _Field(kinds[type(options[key])]), value)
    names = [name for name, *_ in cls.Parameters.describe()]
    for key, value in data["parameters"].items():
        if key not in names:
            raise ConfigError(
                f"parameters.{key}: unknown parameter of {data['scene']}; parameters: {', '.join(names)}.",
                f"parameters.{key}",
            )
        _check(f"parameters.{key}", _Field("float"), value)
    data["parameters"] = {k: float(v) for k, v in data["parameters"].items()}
    scene = _construct(cls, data)  # the scene checks its options and the parameters' declared ranges
    system = scene.build()
    for key, value in data["initial_state"].items():
        if key not in system.layout.names:
            raise ConfigError(
                f"initial_state.{key}: not a state component; the state is {', '.join(system.layout.names)}.",
                f"initial_state.{key}",
            )
        _check(f"initial_state.{key}", _Field("float"), value)
    data["initial_state"] = {k: float(v) for k, v in data["initial_state"].items()}
    save = data["statistics"]["save"]
    if save is not None:
        offered = system.observable_names()
        for name in save:
            if name not in offered:
                raise ConfigError(
                    f"statistics.save: {name!r} is not offered; this scene offers {', '.join(offered)}.",
                    "statistics.save",
                )
    solver = data["solver"]["name"]
    try:
        solver_needs(solver, system)
    except ValueError as e:
        raise ConfigError(f"solver.name = {solver!r}: {e}", "solver.name") from None
    if "fit" in data:
        for name in data["fit"]["vary"]:
            if name not in names:
                raise ConfigError(
                    f"fit.vary: {name!r} is not a parameter of {data['scene']}; parameters: {', '.join(names)}.",
                    "fit.vary",
                )
        if not data["fit"]["vary"]:
            raise ConfigError("fit.vary: name at least one parameter.", "fit.vary")
    return scene, system


def _check_times_and_paths(data: dict):
    """What ``simulate`` would refuse mid-run, refused up front: the step budget, a last piece of too few paths."""
    s = data["solver"]
    if s["t1"] <= s["t0"]:
        raise ConfigError(f"solver.t1 = {s['t1']}: must be > solver.t0 = {s['t0']}.", "solver.t1")
    total = (s["t1"] - s["t0"]) / s["dt"]
    if not total <= MAX_STEPS:  # also inf
        raise ConfigError(
            f"solver.t1 = {s['t1']}: (solver.t1 − solver.t0) / solver.dt = {total:.3g} steps per path, "
            f"beyond the budget of {MAX_STEPS}.",
            "solver.t1",
        )
    n, chunk = data["paths"]["n"], data["paths"]["chunk"]
    if (n - 1) % chunk + 1 < MIN_PATHS:
        raise ConfigError(
            f"paths.n = {n}: the last piece of paths.chunk = {chunk} would hold {(n - 1) % chunk + 1} paths; "
            f"a piece needs ≥ {MIN_PATHS}.",
            "paths.n",
        )
    points = data["statistics"]["save_points"]
    interval = (s["t1"] - s["t0"]) / (points - 1)
    steps = round(interval / s["dt"])
    if steps < 1 or abs(steps * s["dt"] - interval) > 1e-9 * interval:
        raise ConfigError(
            f"solver.dt = {s['dt']}: must divide the interval {interval:g} between the "
            f"{points} save points (statistics.save_points) into whole steps.",
            "solver.dt",
        )


def parse_statistic(text: str) -> tuple[str, ...]:
    """``"cov x x"`` → ``('cov', 'x', 'x')``, ``"mean x"`` → ``('mean', 'x')``; a ``ValueError`` otherwise."""
    parts = tuple(text.split())
    if not ((len(parts) == 2 and parts[0] == "mean") or (len(parts) == 3 and parts[0] == "cov")):
        raise ValueError(f"{text!r}: expected 'mean NAME' or 'cov NAME NAME'")
    return parts


def default_statistic(system: StochasticSystem, names: tuple[str, ...]) -> tuple[str, ...]:
    """The variance of the first saved dependent coordinate (the drift), else of the first saved name."""
    layout = system.layout
    drift = [n for n in names if n in layout.names and layout.roles[layout.index(n)] == "dependent_coordinate"]
    first = (drift or list(names))[0]
    return ("cov", first, first)


def _check_accuracy(data: dict, system: StochasticSystem):
    """``[accuracy]``: exactly one target, a statistic of saved names."""
    a = data["accuracy"]
    if (a["rmse"] is None) == (a["relative_rmse"] is None):
        raise ConfigError("accuracy: give exactly one of accuracy.rmse and accuracy.relative_rmse.", "accuracy.rmse")
    save = data["statistics"]["save"]
    names = tuple(system.layout.names if save is None else save)
    if a["statistic"] is not None:
        try:
            statistic = parse_statistic(a["statistic"])
        except ValueError as e:
            raise ConfigError(f"accuracy.statistic = {e}.", "accuracy.statistic") from None
        observables = [n for n, _ in system.observables]
        if save is None and all(n in names or n in observables for n in statistic[1:]):
            # the statistic names an observable of the scene (its energy, say): saved with the state
            names += tuple(n for n in dict.fromkeys(statistic[1:]) if n not in names)
            data["statistics"]["save"] = list(names)
        missing = [n for n in statistic[1:] if n not in names]
        if missing:
            raise ConfigError(
                f"accuracy.statistic = {a['statistic']!r}: {', '.join(missing)} not saved; saved: {', '.join(names)}.",
                "accuracy.statistic",
            )
    s = data["solver"]
    if s["t1"] - s["t0"] < s["dt"] * (1 - 1e-12):
        raise ConfigError(f"solver.dt = {s['dt']}: the coarsest step must not exceed t1 − t0.", "solver.dt")


class Built(NamedTuple):
    """What a run simulates: the scene, its system, the initial state, the key, the saved names and their roles."""

    scene: AbstractScene
    system: StochasticSystem
    y0: jax.Array
    key: jax.Array
    names: tuple[str, ...]
    roles: tuple[str, ...]


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """A validated run (``kind='simulate'``) or fit (``kind='fit'``) description.

    ``data`` is the canonical nested dict with every default filled in; two
    configurations describe the same run exactly when their ``data`` agree.
    ``base`` is the directory relative paths in it (``fit.data``) refer to.
    """

    kind: str
    data: dict
    base: Path
    _scene: AbstractScene = dataclasses.field(compare=False, repr=False)
    _system: StochasticSystem = dataclasses.field(compare=False, repr=False)
    _x64: bool = dataclasses.field(compare=False, repr=False)

    def to_json(self) -> str:
        return json.dumps(self.data, sort_keys=True)

    @classmethod
    def from_dict(
        cls, raw: dict, kind: str = "simulate", base: Path | str = ".", scene_source: SceneSource = SceneSource()
    ) -> RunConfig:
        """Validate the parsed TOML ``raw``; :class:`ConfigError` names the offending key.  A ``MODULE:CLASS``
        scene is imported as ``scene_source`` allows (by default from ``sys.path``, as ``import`` would)."""
        if kind not in ("simulate", "fit"):
            raise ValueError(f"kind={kind!r}; allowed: 'simulate', 'fit'.")
        if isinstance(raw, dict) and "scene_sha256" in raw:  # the module's hash: checked, not part of the run
            raw = dict(raw)
            sha256 = raw.pop("scene_sha256")
            if not (isinstance(sha256, str) and re.fullmatch(r"[0-9a-fA-F]{64}", sha256)):
                raise ConfigError(f"scene_sha256 = {sha256!r}: expected 64 hexadecimal digits.", "scene_sha256")
            scene_source = scene_source._replace(sha256=sha256)
        data: dict = {}
        accuracy = isinstance(raw, dict) and "accuracy" in raw
        _table("", _schema(kind, accuracy), raw, data)
        if kind == "simulate" and not accuracy:
            del data["accuracy"]  # absent: the plain run, its canonical data unchanged
        scene, system = _check_scene(data, scene_source)
        if kind == "simulate":
            _check_times_and_paths(data)
            if accuracy:
                _check_accuracy(data, system)
        return cls(kind, data, Path(base), scene, system, x64_enabled())

    @property
    def scene_class(self) -> type[AbstractScene]:
        """The class of the file's ``scene``: shipped, installed, or the user's ``MODULE:CLASS``."""
        return type(self._scene)

    def parameters(self) -> dict[str, float]:
        """Every parameter of the scene: the file's values and the defaults of the rest."""
        described = self.scene_class.Parameters.describe()
        return {name: float(cast(float, default)) for name, default, *_ in described} | self.data["parameters"]

    def build(self) -> Built:
        """The scene, system, initial state, key, saved names and roles of this run.

        The scene validated with the file is reused (built once), unless it was
        built without float64 and float64 is on now.
        """
        d = self.data
        scene, system = self._scene, self._system
        if x64_enabled() and not self._x64:
            scene = type(scene)(**d["options"], **d["parameters"])
            system = scene.build()
        y0 = scene.initial_state().astype(jnp.dtype(d["precision"]))
        for name, value in d["initial_state"].items():
            y0 = y0.at[system.layout.index(name)].set(value)
        save = d["statistics"]["save"]
        names = system.layout.names if save is None else tuple(save)
        layout = system.layout
        roles = tuple(layout.roles[layout.index(n)] if n in layout.names else "observable" for n in names)
        return Built(scene, system, y0, jax.random.key(d["seed"]), names, roles)


def load_config(path, kind: str = "simulate", trust_scene: bool = False) -> RunConfig:
    """Read and validate the TOML file ``path``; :class:`ConfigError` names the offending key (or the file).

    A ``MODULE:CLASS`` scene is looked for beside the file first, and imported only when the file records its
    source's SHA-256 (``scene_sha256``, checked before the import) or ``trust_scene`` is given: a run file received
    from someone else runs no code of theirs unasked."""
    path = Path(path)
    try:
        info = path.stat()
        regular = stat.S_ISREG(info.st_mode)  # reading a FIFO would wait for a writer
        text = path.read_bytes() if regular and info.st_size <= MAX_FILE_SIZE else b""
    except OSError as e:
        raise ConfigError(f"{path}: cannot read the file ({e.strerror}).") from None
    if not regular or info.st_size > MAX_FILE_SIZE:
        raise ConfigError(f"{path}: not a regular file of at most {MAX_FILE_SIZE} bytes.")
    try:
        raw = tomllib.loads(text.decode("utf-8"))
    except UnicodeDecodeError as e:
        raise ConfigError(f"{path}: not a text file (byte {e.start} is not UTF-8).") from None
    except RecursionError:
        raise ConfigError(f"{path}: not valid TOML: nested too deeply.") from None
    except ValueError as e:  # TOMLDecodeError, or an integer of more than 4300 digits
        raise ConfigError(f"{path}: not valid TOML: {e}.") from None
    try:
        base = path.resolve().parent
        return RunConfig.from_dict(raw, kind, base=base, scene_source=SceneSource(base, trust_scene))
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}", e.key) from None
