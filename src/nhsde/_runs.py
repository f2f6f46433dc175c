"""Runs described by TOML files, stored as self-describing netCDF (xarray).

A run file names a scene, its parameters, the solver, the paths and the
statistics to keep; :func:`load_config` validates it strictly (unknown keys,
wrong types, out-of-range values and unknown scenes are rejected with the key
named; values are only ever compared with known names and numbers, so no
configuration can execute code).  :func:`run` integrates the paths in pieces of
``paths.chunk``: piece ``k`` is paths ``k·chunk …`` of the ensemble the seed
defines (``simulate(first_path=…)``), reduced to float64 moment sums about a
common shift and written, with all pieces before it, to the output file
(atomically: a new file replaces the old one).  A run interrupted at any point
resumes from its last written piece; the pieces are computed bitwise alike and
summed in piece order, so the resumed result is bitwise that of an
uninterrupted run.

The file holds the statistics (``mean``, ``cov``, ``mean_se``, ``cov_se`` over
``time × name``), the per-piece sums, optionally every path, and as attributes
the validated configuration, the key, the package versions and the git
revision of the source.
"""

from __future__ import annotations

import dataclasses
import datetime
import inspect
import json
import math
import os
import subprocess
import tomllib
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ._brownian import BLOCK  # pieces start at multiples of simulate's path block

__all__ = ["ConfigError", "RunConfig", "load_config", "load_run", "observations_from_run", "run", "run_fit"]

FORMAT = "nhsde-run"
FIT_FORMAT = "nhsde-fit"
FORMAT_VERSION = 1


class ConfigError(ValueError):
    """A run file that does not describe a valid run; the message names the key."""


# ----------------------------------------------------------------------------- schema

_REQUIRED = object()


@dataclasses.dataclass(frozen=True)
class _Field:
    kind: str  # "int", "float", "str", "bool", "names"
    default: object = _REQUIRED
    allowed: tuple | None = None  # for "str"
    minimum: float | None = None  # for numbers
    strict: bool = False  # minimum excluded
    multiple_of: int | None = None  # for "int"


def _solver_names():
    from ._solvers import SOLVERS

    return tuple(SOLVERS)


def _schema(kind: str) -> dict:
    """The allowed keys; ``"scene-…"`` tables depend on the scene."""
    schema = {
        "scene": _Field("str"),
        "seed": _Field("int", 0, minimum=0),
        "precision": _Field("str", "float64", allowed=("float32", "float64")),
        "options": "scene-options",
        "parameters": "scene-parameters",
        "initial_state": "scene-state",
        "solver": {
            "name": _Field("str", "euler", allowed=_solver_names()),
            "dt": _Field("float", minimum=0, strict=True),
        },
        "paths": {"n": _Field("int", minimum=1)},
        "statistics": {"save": _Field("names", None)},
    }
    if kind == "simulate":
        schema["solver"] |= {"t0": _Field("float", 0.0), "t1": _Field("float")}
        schema["paths"] |= {"chunk": _Field("int", 8192, minimum=BLOCK, multiple_of=BLOCK)}
        schema["statistics"] |= {"save_points": _Field("int", 11, minimum=2), "keep_paths": _Field("bool", False)}
    else:
        schema["fit"] = {
            "data": _Field("str"),
            "vary": _Field("names", ["eps", "nu"]),
            "max_steps": _Field("int", 100, minimum=1),
        }
    return schema


def _type_name(value) -> str:
    return {
        bool: "a boolean",
        int: "an integer",
        float: "a number",
        str: "a string",
        list: "an array",
        dict: "a table",
    }.get(type(value), type(value).__name__)


def _check(key: str, field: _Field, value):
    expected = {
        "int": "an integer",
        "float": "a number",
        "str": "a string",
        "bool": "true or false",
        "names": "an array of strings",
    }[field.kind]
    ok = {
        "int": isinstance(value, int) and not isinstance(value, bool),
        "float": isinstance(value, (int, float)) and not isinstance(value, bool),
        "str": isinstance(value, str),
        "bool": isinstance(value, bool),
        "names": isinstance(value, list) and all(isinstance(v, str) for v in value),
    }[field.kind]
    if not ok:
        raise ConfigError(f"{key}: expected {expected}, got {_type_name(value)} {value!r}.")
    if field.kind == "float":
        value = float(value)
        if not math.isfinite(value):
            raise ConfigError(f"{key} = {value}: must be finite.")
    if (
        field.kind in ("int", "float")
        and field.minimum is not None
        and (value < field.minimum or (field.strict and value == field.minimum))
    ):
        raise ConfigError(f"{key} = {value}: must be {'>' if field.strict else '≥'} {field.minimum:g}.")
    if field.multiple_of and value % field.multiple_of:
        raise ConfigError(f"{key} = {value}: must be a multiple of {field.multiple_of}.")
    if field.allowed is not None and value not in field.allowed:
        raise ConfigError(f"{key} = {value!r}: allowed values are {', '.join(map(repr, field.allowed))}.")
    if field.kind == "names" and len(set(value)) != len(value):
        raise ConfigError(f"{key} = {value}: names must not repeat.")
    return value


def _table(prefix: str, spec: dict, raw, out: dict):
    if not isinstance(raw, dict):
        raise ConfigError(f"{prefix or 'the file'}: expected a table, got {_type_name(raw)}.")
    for key in raw:
        if key not in spec:
            where = f"[{prefix}]" if prefix else "the top level"
            raise ConfigError(
                f"{prefix + '.' if prefix else ''}{key}: unknown key in {where}; allowed: {', '.join(spec)}."
            )
    for key, field in spec.items():
        name = f"{prefix}.{key}" if prefix else key
        if isinstance(field, dict):
            out[key] = {}
            _table(name, field, raw.get(key, {}), out[key])
        elif isinstance(field, str):  # scene-dependent: checked once the scene is known
            value = raw.get(key, {})
            if not isinstance(value, dict):
                raise ConfigError(f"{name}: expected a table, got {_type_name(value)}.")
            out[key] = value
        elif key in raw:
            out[key] = _check(name, field, raw[key])
        elif field.default is _REQUIRED:
            raise ConfigError(f"{name}: required key is missing.")
        else:
            out[key] = field.default


def _scene_options(scene_cls) -> dict[str, object]:
    """The scene's keyword options (``drift=True``, ``route="reduced"``, …) and their defaults."""
    signature = inspect.signature(scene_cls.__init__)
    return {
        name: p.default
        for name, p in signature.parameters.items()
        if p.kind is inspect.Parameter.KEYWORD_ONLY and p.default is not inspect.Parameter.empty
    }


def _check_scene(data: dict):
    from ._solvers import solver_needs
    from .scenes import SCENES

    if data["scene"] not in SCENES:
        raise ConfigError(f"scene = {data['scene']!r}: unknown scene; known scenes: {', '.join(SCENES)}.")
    cls = SCENES[data["scene"]]
    options = _scene_options(cls)
    kinds = {bool: "bool", str: "str", int: "int", float: "float"}
    for key, value in data["options"].items():
        if key not in options:
            raise ConfigError(f"options.{key}: unknown option of {data['scene']}; options: {', '.join(options)}.")
        _check(f"options.{key}", _Field(kinds[type(options[key])]), value)
    names = [name for name, *_ in cls.Parameters.describe()]
    for key, value in data["parameters"].items():
        if key not in names:
            raise ConfigError(
                f"parameters.{key}: unknown parameter of {data['scene']}; parameters: {', '.join(names)}."
            )
        _check(f"parameters.{key}", _Field("float"), value)
    data["parameters"] = {k: float(v) for k, v in data["parameters"].items()}
    for table, kwargs in (("options", data["options"]), ("parameters", data["options"] | data["parameters"])):
        try:  # the scene checks its options' values and the parameters' declared ranges, naming them
            scene = cls(**kwargs)
        except (ValueError, TypeError) as e:
            raise ConfigError(f"{table}: {e}") from None
    system = scene.build()
    for key, value in data["initial_state"].items():
        if key not in system.layout.names:
            raise ConfigError(
                f"initial_state.{key}: not a state component; the state is {', '.join(system.layout.names)}."
            )
        _check(f"initial_state.{key}", _Field("float"), value)
    data["initial_state"] = {k: float(v) for k, v in data["initial_state"].items()}
    save = data["statistics"]["save"]
    if save is not None:
        offered = system.observable_names()
        for name in save:
            if name not in offered:
                raise ConfigError(f"statistics.save: {name!r} is not offered; this scene offers {', '.join(offered)}.")
    solver = data["solver"]["name"]
    try:
        solver_needs(solver, system)
    except ValueError as e:
        raise ConfigError(f"solver.name = {solver!r}: {e}") from None
    if "fit" in data:
        for name in data["fit"]["vary"]:
            if name not in names:
                raise ConfigError(
                    f"fit.vary: {name!r} is not a parameter of {data['scene']}; parameters: {', '.join(names)}."
                )
        if not data["fit"]["vary"]:
            raise ConfigError("fit.vary: name at least one parameter.")


def _check_times(data: dict):
    s = data["solver"]
    if s["t1"] <= s["t0"]:
        raise ConfigError(f"solver.t1 = {s['t1']}: must be > solver.t0 = {s['t0']}.")
    interval = (s["t1"] - s["t0"]) / (data["statistics"]["save_points"] - 1)
    steps = round(interval / s["dt"])
    if steps < 1 or abs(steps * s["dt"] - interval) > 1e-9 * interval:
        raise ConfigError(
            f"solver.dt = {s['dt']}: must divide the interval {interval:g} between the "
            f"{data['statistics']['save_points']} save points (statistics.save_points) into whole steps."
        )


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

    def to_json(self) -> str:
        return json.dumps(self.data, sort_keys=True)

    @classmethod
    def from_dict(cls, raw: dict, kind: str = "simulate", base: Path | str = ".") -> RunConfig:
        if kind not in ("simulate", "fit"):
            raise ValueError(f"kind={kind!r}; allowed: 'simulate', 'fit'.")
        data: dict = {}
        _table("", _schema(kind), raw, data)
        _check_scene(data)
        if kind == "simulate":
            _check_times(data)
        return cls(kind, data, Path(base))


def load_config(path, kind: str = "simulate") -> RunConfig:
    """Read and validate the TOML file ``path``; :class:`ConfigError` names the offending key."""
    path = Path(path)
    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as e:
        raise ConfigError(f"{path}: cannot read the file ({e.strerror}).") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: not valid TOML: {e}.") from None
    try:
        return RunConfig.from_dict(raw, kind, base=path.resolve().parent)
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}") from None


# ----------------------------------------------------------------------------- provenance


def versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for pkg in ("nhsde", "jax", "jaxlib", "diffrax", "equinox", "optax", "numpy", "xarray", "h5netcdf"):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            out[pkg] = "not installed"
    return out


def git_revision() -> str:
    """``git rev-parse HEAD`` of the source tree nhsde runs from (``+dirty`` with local changes), else ``"unknown"``."""
    root = Path(__file__).resolve().parents[2]  # src/nhsde/_runs.py → the repository

    def git(*args):
        out = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, timeout=10, check=False)
        return out.stdout.strip() if out.returncode == 0 else None

    try:
        top = git("rev-parse", "--show-toplevel")
        if top is None or Path(top).resolve() != root:
            return "unknown"  # installed, or inside some other repository
        head, status = git("rev-parse", "HEAD"), git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    if head is None:
        return "unknown"
    return head + ("+dirty" if status else "")


def _provenance() -> dict:
    return {
        "versions": json.dumps(versions(), sort_keys=True),
        "git_revision": git_revision(),
        "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    }


# ----------------------------------------------------------------------------- simulate


def _need_x64():
    import jax

    if not jax.config.jax_enable_x64:
        raise RuntimeError(
            "runs keep float64 moment sums: call jax.config.update('jax_enable_x64', True) first "
            "(precision = 'float32' still simulates in float32)."
        )


def build(config: RunConfig):
    """``(system, y0, key, names)`` of a configuration."""
    import jax
    import jax.numpy as jnp

    from .scenes import get_scene

    d = config.data
    scene = get_scene(d["scene"])(**d["options"], **d["parameters"])
    system = scene.build()
    y0 = scene.initial_state().astype(jnp.dtype(d["precision"]))
    for name, value in d["initial_state"].items():
        y0 = y0.at[system.layout.index(name)].set(value)
    names = system.layout.names if d["statistics"]["save"] is None else tuple(d["statistics"]["save"])
    return system, y0, jax.random.key(d["seed"]), names


def _piece_sums(paths, failed, shift):
    """float64 sums ``Σz, Σzzᵀ, Σz_i z_j², Σz_i² z_j²`` of ``z = paths − shift`` over good paths."""
    z = np.where(failed[:, None, None], 0.0, np.asarray(paths, np.float64) - shift)
    zz = np.einsum("pti,ptj->tij", z, z)
    return z.sum(0), zz, np.einsum("pti,ptj->tij", z, z * z), np.einsum("pti,ptj->tij", z * z, z * z)


def _statistics(shift, s1, s2, s3, s4, n):
    """Mean, covariance and their standard errors from moment sums, as ``simulate`` forms them."""
    import jax.numpy as jnp

    from ._ensemble import _central_product_moment, _safe_sqrt

    nf = float(n)
    mean = shift + s1 / nf
    cov = (s2 - np.einsum("ti,tj->tij", s1, s1) / nf) / max(nf - 1, 1.0)
    mean_se = np.sqrt(np.maximum(np.diagonal(cov, axis1=1, axis2=2), 0.0) / nf)
    moment = _central_product_moment(*(jnp.asarray(a, jnp.float64) for a in (s1 / nf, s2 / nf, s3 / nf, s4 / nf)))
    cov_se = np.asarray(_safe_sqrt((moment - jnp.asarray(cov) ** 2) / nf), np.float64)
    return mean, cov, mean_se, cov_se


def _dataset(config: RunConfig, ts, names, roles, shift, pieces, kept, provenance):
    import jax
    import xarray as xr

    d = config.data
    s1, s2, s3, s4, n_used, n_failed = (np.stack([p[i] for p in pieces]) for i in range(6))
    n = int(n_used.sum())
    mean, cov, mean_se, cov_se = _statistics(shift, s1.sum(0), s2.sum(0), s3.sum(0), s4.sum(0), n)
    tnn = ("time", "name", "name2")
    data_vars = {
        "mean": (("time", "name"), mean, {"long_name": "sample mean over the paths"}),
        "cov": (tnn, cov, {"long_name": "sample covariance (unbiased) over the paths"}),
        "mean_se": (("time", "name"), mean_se, {"long_name": "Monte-Carlo standard error of mean"}),
        "cov_se": (tnn, cov_se, {"long_name": "Monte-Carlo standard error of cov"}),
        "shift": (("time", "name"), shift, {"long_name": "the point the moment sums are taken about"}),
        "piece_sum_z": (("piece", "time", "name"), s1),
        "piece_sum_zz": (("piece",) + tnn, s2),
        "piece_sum_zzz": (("piece",) + tnn, s3, {"long_name": "sum of z_i z_j^2"}),
        "piece_sum_zzzz": (("piece",) + tnn, s4, {"long_name": "sum of z_i^2 z_j^2"}),
        "piece_n_used": (("piece",), n_used),
        "piece_n_failed": (("piece",), n_failed),
    }
    if kept:
        data_vars["paths"] = (("path", "time", "name"), np.concatenate([k[0] for k in kept]))
        data_vars["failed"] = (("path",), np.concatenate([k[1] for k in kept]).astype(np.int8))
    done = min(len(pieces) * d["paths"]["chunk"], d["paths"]["n"])
    attrs = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "config": config.to_json(),
        "scene": d["scene"],
        "parameters": json.dumps(_all_parameters(config), sort_keys=True),
        "solver": d["solver"]["name"],
        "dt": d["solver"]["dt"],
        "t0": d["solver"]["t0"],
        "t1": d["solver"]["t1"],
        "seed": d["seed"],
        "key_impl": str(jax.random.key_impl(jax.random.key(d["seed"]))),
        "key_data": np.asarray(jax.random.key_data(jax.random.key(d["seed"]))).astype(np.int64).tolist(),
        "precision": d["precision"],
        "n_paths": d["paths"]["n"],
        "paths_done": done,
        "n_used": n,
        "n_failed": int(n_failed.sum()),
        "pieces_done": len(pieces),
        "pieces_total": math.ceil(d["paths"]["n"] / d["paths"]["chunk"]),
        "complete": int(done == d["paths"]["n"]),
        **provenance,
    }
    return xr.Dataset(
        data_vars,
        coords={"time": ts, "name": list(names), "name2": list(names), "role": ("name", list(roles))},
        attrs=attrs,
    )


def _all_parameters(config: RunConfig) -> dict[str, float]:
    from .scenes import get_scene

    cls = get_scene(config.data["scene"])
    values = {name: float(default) for name, default, *_ in cls.Parameters.describe()}
    return values | config.data["parameters"]


def _write(ds, path: Path):
    """Write ``ds`` to ``path`` atomically: a reader never sees a half-written file."""
    tmp = path.with_name(path.name + ".partial")
    ds.to_netcdf(tmp, engine="h5netcdf")
    os.replace(tmp, path)


def load_run(path):
    """The dataset stored at ``path``, read fully into memory (the file is closed)."""
    import xarray as xr

    with xr.open_dataset(path, engine="h5netcdf") as ds:
        return ds.load()


def _resume(path: Path, config: RunConfig):
    ds = load_run(path)
    if ds.attrs.get("format") != FORMAT:
        raise ConfigError(f"{path} exists and is not an nhsde run file; choose another output file.")
    if ds.attrs["config"] != config.to_json():
        old, new = json.loads(ds.attrs["config"]), config.data
        differ = sorted(k for k in set(old) | set(new) if old.get(k) != new.get(k))
        raise ConfigError(
            f"{path} holds a run of a different configuration (differs in: {', '.join(differ)}); "
            "delete it or choose another output file to start afresh."
        )
    pieces = [
        tuple(
            ds[v].values[k]
            for v in (
                "piece_sum_z",
                "piece_sum_zz",
                "piece_sum_zzz",
                "piece_sum_zzzz",
                "piece_n_used",
                "piece_n_failed",
            )
        )
        for k in range(ds.sizes["piece"])
    ]
    kept = []
    if "paths" in ds:
        chunk = config.data["paths"]["chunk"]
        kept = [
            (ds["paths"].values[i : i + chunk], ds["failed"].values[i : i + chunk].astype(bool))
            for i in range(0, ds.sizes["path"], chunk)
        ]
    provenance = {key: ds.attrs[key] for key in ("versions", "git_revision", "created")}
    now = _provenance()
    for key in ("versions", "git_revision"):
        if provenance[key] != now[key]:
            raise ConfigError(
                f"{path} was started with {key} {provenance[key]}, now {now[key]}; its paths could differ, "
                "so it cannot be resumed here: delete it or choose another output file."
            )
    return ds["shift"].values, pieces, kept, provenance


def run(config: RunConfig, out, *, on_piece: Callable[[int], None] | None = None, progress: bool = False):
    """Run (or resume) ``config``, writing ``out`` after every piece; returns the dataset written last.

    ``on_piece(k)`` is called after piece ``k`` is safely written (progress
    reports; an exception there interrupts the run as a kill would).
    """
    import diffrax as dfx

    from ._ensemble import Save
    from ._simulate import simulate

    if config.kind != "simulate":
        raise ValueError(f"run: this is a {config.kind!r} configuration; use run_fit.")
    _need_x64()
    out = Path(out)
    d = config.data
    system, y0, key, names = build(config)
    n_total, chunk = d["paths"]["n"], d["paths"]["chunk"]
    n_pieces = math.ceil(n_total / chunk)
    keep = d["statistics"]["keep_paths"]
    if out.exists():
        shift, pieces, kept, provenance = _resume(out, config)
    else:
        shift, pieces, kept, provenance = None, [], [], _provenance()
    roles = tuple(
        system.layout.roles[system.layout.index(n)] if n in system.layout.names else "observable" for n in names
    )
    ts = np.linspace(d["solver"]["t0"], d["solver"]["t1"], d["statistics"]["save_points"])
    for k in range(len(pieces), n_pieces):
        ens = simulate(
            system,
            y0,
            key,
            n_paths=min(chunk, n_total - k * chunk),
            first_path=k * chunk,
            t0=d["solver"]["t0"],
            t1=d["solver"]["t1"],
            dt=d["solver"]["dt"],
            solver=d["solver"]["name"],
            save=Save(names=names, n=d["statistics"]["save_points"], paths=True),
            on_failure="exclude",
            progress_meter=dfx.TqdmProgressMeter() if progress else None,
        )
        paths, failed = np.asarray(ens.paths), np.asarray(ens.failed)
        if shift is None:  # the first piece's mean: a point within the ensemble's spread
            good = paths[~failed].astype(np.float64)
            shift = good.mean(0) if len(good) else np.zeros(paths.shape[1:])
        pieces.append((*_piece_sums(paths, failed, shift), np.int64((~failed).sum()), np.int64(failed.sum())))
        if keep:
            kept.append((paths, failed))
        _write(_dataset(config, ts, names, roles, shift, pieces, kept, provenance), out)
        if on_piece is not None:
            on_piece(k)
    return _dataset(config, ts, names, roles, shift, pieces, kept, provenance)


# ----------------------------------------------------------------------------- fit


def observations_from_run(ds, names=None):
    """:class:`nhsde.fit.Observations` of a run file at all save times but the first (the initial state).

    With stored paths (``statistics.keep_paths``) the statistics' covariance is
    estimated in full; otherwise from the standard errors alone.
    """
    from .fit import Observations

    stored = list(ds["name"].values)
    names = stored if names is None else list(names)
    for name in names:
        if name not in stored:
            raise ConfigError(f"statistics.save: {name!r} is not in the data; it holds {', '.join(stored)}.")
    idx = [stored.index(n) for n in names]
    ts = ds["time"].values[1:]
    if "paths" in ds:
        good = ds["failed"].values == 0
        return Observations.from_paths(ts, ds["paths"].values[good][:, 1:][..., idx], names)
    ix = np.ix_(idx, idx)
    cov, cov_se = ds["cov"].values[1:][:, ix[0], ix[1]], ds["cov_se"].values[1:][:, ix[0], ix[1]]
    return Observations.from_statistics(
        ts, names, ds["mean"].values[1:, idx], cov, ds["mean_se"].values[1:, idx], cov_se, int(ds.attrs["n_used"])
    )


def run_fit(config: RunConfig, out=None):
    """Fit ``fit.vary`` to the run file ``fit.data`` through simulation; returns ``(FitResult, dataset)``.

    The model simulates ``paths.n`` paths with ``seed`` (use a seed other than
    the data's), the solver and ``dt`` of the file, from the scene's initial
    state, at the data's save times; ``parameters`` are the start values.
    """
    import xarray as xr

    from .fit import Simulated, estimate

    if config.kind != "fit":
        raise ValueError(f"run_fit: this is a {config.kind!r} configuration; use run.")
    _need_x64()
    d = config.data
    data_path = config.base / d["fit"]["data"]
    if not data_path.is_file():
        raise ConfigError(f"fit.data = {d['fit']['data']!r}: no such file {data_path}.")
    data = load_run(data_path)
    if data.attrs.get("format") != FORMAT:
        raise ConfigError(f"fit.data = {d['fit']['data']!r}: not an nhsde run file.")
    observed = observations_from_run(data, d["statistics"]["save"])
    system, y0, key, _ = build(config)
    model = Simulated(
        y0,
        key,
        n_paths=d["paths"]["n"],
        dt=d["solver"]["dt"],
        solver=d["solver"]["name"],
        t0=float(data["time"].values[0]),
    )
    result = estimate(system, observed, model, vary=tuple(d["fit"]["vary"]), max_steps=d["fit"]["max_steps"])
    ds = xr.Dataset(
        {
            "estimate": (("parameter",), result.values),
            "se": (("parameter",), result.se),
            "cov": (("parameter", "parameter2"), result.cov),
            "start": (("parameter",), result.init),
            "history": (("step", "column"), result.history),
        },
        coords={"parameter": list(result.names), "parameter2": list(result.names), "column": ["loss", *result.names]},
        attrs={
            "format": FIT_FORMAT,
            "format_version": FORMAT_VERSION,
            "config": config.to_json(),
            "chi2": result.chi2,
            "dof": result.dof,
            "steps": result.steps,
            "converged": int(result.converged),
            "observed_from_trajectories": int(observed.from_trajectories),
            "data_file": str(data_path),
            "data_config": data.attrs["config"],
            "data_git_revision": data.attrs["git_revision"],
            **_provenance(),
        },
    )
    if out is not None:
        _write(ds, Path(out))
    return result, ds
