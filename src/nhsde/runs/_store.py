"""The netCDF run file: its dataset, provenance, atomic writing, and the checks before a run resumes.

A run file (``format = "nhsde-run"``, read with ``xarray.open_dataset(path,
engine="h5netcdf")``) holds ``mean``, ``cov``, ``mean_se``, ``cov_se`` over
``time × name`` (``name2``), the ``shift`` the sums are taken about, the
float64 moment sums of every piece (``piece_sum_z``, ``piece_sum_zz``,
``piece_sum_zzz`` = Σ z_i z_j², ``piece_sum_zzzz`` = Σ z_i² z_j²,
``piece_n_used``, ``piece_n_failed`` over ``piece``), optionally every path
(``paths`` over ``path × time × name``, ``failed``), and as attributes the
validated configuration (JSON), the scene's parameters, solver, times, seed and
key data, counts, whether the run is complete, the package versions and the git
revision.  ``nhsde simulate SCENE`` adds ``d_mean_d_eps``, ``d_mean_d_nu``,
``d_cov_d_eps``, ``d_cov_d_nu``.
"""

from __future__ import annotations

import dataclasses
import datetime
import functools
import json
import math
import os
import subprocess
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import xarray as xr

from .._ensemble import Ensemble, MomentSums
from ._config import Built, ConfigError, RunConfig

__all__ = ["FIT_FORMAT", "FORMAT", "FORMAT_VERSION", "Pieces", "dataset", "git_revision", "load_run", "versions"]

FORMAT = "nhsde-run"
FIT_FORMAT = "nhsde-fit"
FORMAT_VERSION = 1

_SUMS = ("piece_sum_z", "piece_sum_zz", "piece_sum_zzz", "piece_sum_zzzz")


def versions() -> dict[str, str]:
    """Installed versions of nhsde and the packages its results depend on."""
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
    root = Path(__file__).resolve().parents[3]  # src/nhsde/runs/_store.py → the repository

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


def provenance() -> dict:
    return {
        "versions": json.dumps(versions(), sort_keys=True),
        "git_revision": git_revision(),
        "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    }


def _float64(sums: MomentSums) -> MomentSums:
    """``sums`` in float64 (exact from float32), the count in int64."""
    f64 = functools.partial(jnp.asarray, dtype=jnp.float64)
    return MomentSums(
        shift=f64(sums.shift),
        s1=f64(sums.s1),
        s2=f64(sums.s2),
        s3=f64(sums.s3),
        s4=f64(sums.s4),
        count=jnp.asarray(sums.count, jnp.int64),
    )


@dataclasses.dataclass
class Pieces:
    """What a run keeps of its pieces: float64 moment sums about one shift, failure counts, paths on request."""

    sums: list[MomentSums] = dataclasses.field(default_factory=list)
    n_failed: list[int] = dataclasses.field(default_factory=list)
    paths: list[np.ndarray] = dataclasses.field(default_factory=list)
    failed: list[np.ndarray] = dataclasses.field(default_factory=list)

    @property
    def shift(self):
        """The point every piece's sums are taken about: the first piece's (``None`` before it)."""
        return self.sums[0].shift if self.sums else None

    def add(self, ens: Ensemble, keep_paths: bool):
        self.sums.append(_float64(ens.sums))
        self.n_failed.append(int(ens.n_failed))
        if keep_paths:
            assert ens.paths is not None
            self.paths.append(np.asarray(ens.paths))
            self.failed.append(np.asarray(ens.failed))

    def total(self) -> MomentSums:
        """The sums of all pieces, added in piece order (so bitwise alike however often the run resumed)."""
        return functools.reduce(MomentSums.add, self.sums)


def dataset(config: RunConfig, built: Built, pieces: Pieces, prov: dict, extra: dict | None = None) -> xr.Dataset:
    """The run file of ``config`` after ``pieces`` (its statistics from their summed moment sums)."""
    d = config.data
    stack = lambda get: np.stack([np.asarray(get(s)) for s in pieces.sums])
    s1, s2, s3, s4 = (stack(lambda s, f=f: getattr(s, f)) for f in ("s1", "s2", "s3", "s4"))
    n_used, n_failed = stack(lambda s: s.count).astype(np.int64), np.asarray(pieces.n_failed, np.int64)
    mean, cov, mean_se, cov_se = (np.asarray(a, np.float64) for a in pieces.total().statistics())
    tnn = ("time", "name", "name2")
    data_vars = {
        "mean": (("time", "name"), mean, {"long_name": "sample mean over the paths"}),
        "cov": (tnn, cov, {"long_name": "sample covariance (unbiased) over the paths"}),
        "mean_se": (("time", "name"), mean_se, {"long_name": "Monte-Carlo standard error of mean"}),
        "cov_se": (tnn, cov_se, {"long_name": "Monte-Carlo standard error of cov"}),
        "shift": (("time", "name"), np.asarray(pieces.shift), {"long_name": "the point the moment sums are about"}),
        "piece_sum_z": (("piece", "time", "name"), s1),
        "piece_sum_zz": (("piece", *tnn), s2),
        "piece_sum_zzz": (("piece", *tnn), s3, {"long_name": "sum of z_i z_j^2"}),
        "piece_sum_zzzz": (("piece", *tnn), s4, {"long_name": "sum of z_i^2 z_j^2"}),
        "piece_n_used": (("piece",), n_used),
        "piece_n_failed": (("piece",), n_failed),
    }
    if pieces.paths:
        data_vars["paths"] = (("path", "time", "name"), np.concatenate(pieces.paths))
        data_vars["failed"] = (("path",), np.concatenate(pieces.failed).astype(np.int8))
    data_vars |= extra or {}
    key = jax.random.key(d["seed"])
    done = min(len(pieces.sums) * d["paths"]["chunk"], d["paths"]["n"])
    attrs = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "config": config.to_json(),
        "scene": d["scene"],
        "parameters": json.dumps(config.parameters(), sort_keys=True),
        "solver": d["solver"]["name"],
        "dt": d["solver"]["dt"],
        "t0": d["solver"]["t0"],
        "t1": d["solver"]["t1"],
        "seed": d["seed"],
        "key_impl": str(jax.random.key_impl(key)),
        "key_data": np.asarray(jax.random.key_data(key)).astype(np.int64).tolist(),
        "precision": d["precision"],
        "n_paths": d["paths"]["n"],
        "paths_done": done,
        "n_used": int(n_used.sum()),
        "n_failed": int(n_failed.sum()),
        "pieces_done": len(pieces.sums),
        "pieces_total": math.ceil(d["paths"]["n"] / d["paths"]["chunk"]),
        "complete": int(done == d["paths"]["n"]),
        **prov,
    }
    ts = np.linspace(d["solver"]["t0"], d["solver"]["t1"], d["statistics"]["save_points"])
    names = list(built.names)
    return xr.Dataset(
        data_vars,
        coords={"time": ts, "name": names, "name2": names, "role": ("name", list(built.roles))},
        attrs=attrs,
    )


def write(ds: xr.Dataset, path: Path):
    """Write ``ds`` to exactly ``path``, atomically: a reader never sees a half-written file."""
    tmp = path.with_name(path.name + ".partial")
    ds.to_netcdf(tmp, engine="h5netcdf")
    os.replace(tmp, path)


def load_run(path) -> xr.Dataset:
    """The run (or fit) file at ``path``, read fully into memory (the file is closed)."""
    with xr.open_dataset(path, engine="h5netcdf") as ds:
        return ds.load()


def resume(path: Path, config: RunConfig) -> tuple[Pieces, dict]:
    """The pieces and provenance stored at ``path``, after checking it is this run, started by this code."""
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
    prov = {key: ds.attrs[key] for key in ("versions", "git_revision", "created")}
    now = provenance()
    for key in ("versions", "git_revision"):
        if prov[key] != now[key]:
            raise ConfigError(
                f"{path} was started with {key} {prov[key]}, now {now[key]}; its paths could differ, "
                "so it cannot be resumed here: delete it or choose another output file."
            )
    shift = jnp.asarray(ds["shift"].values, jnp.float64)
    pieces = Pieces()
    for k in range(ds.sizes["piece"]):
        s1, s2, s3, s4 = (jnp.asarray(ds[v].values[k], jnp.float64) for v in _SUMS)
        count = jnp.asarray(ds["piece_n_used"].values[k], jnp.int64)
        pieces.sums.append(MomentSums(shift=shift, s1=s1, s2=s2, s3=s3, s4=s4, count=count))
        pieces.n_failed.append(int(ds["piece_n_failed"].values[k]))
    if "paths" in ds:
        chunk = config.data["paths"]["chunk"]
        for i in range(0, ds.sizes["path"], chunk):
            pieces.paths.append(ds["paths"].values[i : i + chunk])
            pieces.failed.append(ds["failed"].values[i : i + chunk].astype(bool))
    return pieces, prov
