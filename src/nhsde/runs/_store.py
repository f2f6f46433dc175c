"""The netCDF run file: its dataset, provenance, checksum, locked atomic writing, the checks before a run resumes.

A run file (``format = "nhsde-run"``, read with ``xarray.open_dataset(path,
engine="h5netcdf")``) holds ``mean``, ``cov``, ``mean_se``, ``cov_se`` over
``time × name`` (``name2``), the ``shift`` the sums are taken about, the
float64 moment sums of every piece (``piece_sum_z``, ``piece_sum_zz``,
``piece_sum_zzz`` = Σ z_i z_j², ``piece_sum_zzzz`` = Σ z_i² z_j²,
``piece_n_used``, ``piece_n_failed`` over ``piece``), optionally every path
(``paths`` over ``path × time × name``, ``failed``), and as attributes the
validated configuration (JSON), the scene's parameters, solver, times, seed and
key data, counts, whether the run is complete, the package versions, the
SHA-256 of the package's sources (``source``), for a scene of the user's
(``MODULE:CLASS`` or installed) the SHA-256 of its module's source
(``scene_source``), the git revision (information only) and a ``checksum``
(SHA-256 of the data variables, the coordinates and the other attributes).
``nhsde simulate SCENE`` adds ``d_mean_d_Q`` and ``d_cov_d_Q`` for ``Q`` the
friction ``eps`` and the scene's noise intensities (``nu``; ``kT`` in a bath).

Every file is serialised in memory, written to ``PATH.partial`` (created
afresh: a link there is replaced, never followed), synced and renamed to
``PATH``; the writer holds
``PATH.lock`` (``flock``) meanwhile, so a second process is refused.  An output
path is checked before any work; a file there that cannot be read, fails its
checksum, is of another kind or configuration, or has impossible counts, is
refused with its name, never merged.

Over several processes (``jax.distributed``) only process 0 checks, locks and
writes the output; the others read the file there to resume alike, and the
processes agree on the configuration, code, file and numbers
(:mod:`~nhsde.runs._distributed`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import fcntl
import functools
import hashlib
import json
import math
import os
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np

from .._ensemble import Ensemble, MomentSums
from ..scenes import scene_source_hash
from ._config import Built, ConfigError, RunConfig
from ._distributed import agree, digest, is_writer, several, to_host

if TYPE_CHECKING:
    import xarray as xr  # imported where used: `import nhsde.runs` leaves it (and pandas) until a run file

__all__ = [
    "FIT_FORMAT",
    "FORMAT",
    "FORMAT_VERSION",
    "Pieces",
    "checksum",
    "claim",
    "data_digest",
    "dataset",
    "git_revision",
    "load_run",
    "source_hash",
    "versions",
]

FORMAT = "nhsde-run"
FIT_FORMAT = "nhsde-fit"
FORMAT_VERSION = 3
"""3: the checksum covers the coordinates (``time``, ``name``, ``name2``, ``role``)."""
_PACKAGE = Path(__file__).resolve().parents[1]  # the nhsde package as imported

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


def source_hash(package: Path = _PACKAGE) -> str:
    """SHA-256 of the package's Python sources (``nhsde/**/*.py`` as imported): the code a run's numbers come from."""
    h = hashlib.sha256()
    for f in sorted(package.rglob("*.py")):
        data = f.read_bytes()
        h.update(f"{f.relative_to(package).as_posix()} {len(data)}\n".encode() + data)
    return h.hexdigest()


def provenance(config: RunConfig) -> dict:
    """Versions, sources (the package's and, for a scene of the user's, its module's), git revision, time."""
    scene = scene_source_hash(config.scene_class)
    return {
        "versions": json.dumps(versions(), sort_keys=True),
        "source": source_hash(),
        **({} if scene is None else {"scene_source": scene}),
        "git_revision": git_revision(),
        "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    }


def _float64(sums: MomentSums) -> MomentSums:
    """``sums`` in float64 (exact from float32), the count in int64, on this process's default device (through the
    host: over several processes ``simulate``'s results span the devices of all, a resumed file's only this one's)."""
    f64 = lambda a: jnp.asarray(np.asarray(to_host(a), np.float64))  # converted on the host: no program
    return MomentSums(
        shift=f64(sums.shift),
        s1=f64(sums.s1),
        s2=f64(sums.s2),
        s3=f64(sums.s3),
        s4=f64(sums.s4),
        count=jnp.asarray(np.asarray(to_host(sums.count), np.int64)),
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
        self.n_failed.append(int(to_host(ens.n_failed)))
        if keep_paths:
            assert ens.paths is not None
            self.paths.append(to_host(ens.paths))
            self.failed.append(to_host(ens.failed))

    def total(self) -> MomentSums:
        """The sums of all pieces, added in piece order (so bitwise alike however often the run resumed)."""
        return functools.reduce(MomentSums.add, self.sums)


def dataset(config: RunConfig, built: Built, pieces: Pieces, prov: dict, extra: dict | None = None) -> xr.Dataset:
    """The run file of ``config`` after ``pieces`` (its statistics from their summed moment sums)."""
    import xarray as xr

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
    ds = xr.Dataset(
        data_vars,
        coords={"time": ts, "name": names, "name2": names, "role": ("name", list(built.roles))},
        attrs=attrs,
    )
    return seal(ds)


def checksum(ds: xr.Dataset) -> str:
    """SHA-256 of ``ds``' data variables, coordinates and attributes (but ``checksum``): name, dtype, shape and bytes
    of each."""
    h = hashlib.sha256()
    items = [("var " + str(k), ds[k].values) for k in sorted(map(str, ds.data_vars))]
    items += [("coord " + str(k), ds[k].values) for k in sorted(map(str, ds.coords))]
    items += [("attr " + k, v) for k, v in sorted(ds.attrs.items()) if k != "checksum"]
    for name, value in items:
        a = np.array(value)
        if a.dtype.kind == "f":
            a[np.isnan(a)] = np.nan  # netCDF readers return their own NaN for a stored one
        elif a.dtype.kind == "O":
            a = a.astype(str)  # strings read back as objects: hash their characters, not the pointers
        h.update(f"{name} {a.dtype.str} {a.shape}\n".encode() + a.tobytes())
    return h.hexdigest()


def seal(ds: xr.Dataset) -> xr.Dataset:
    """``ds`` with its ``checksum`` attribute set."""
    ds.attrs["checksum"] = checksum(ds)
    return ds


def write(ds: xr.Dataset, path: Path):
    """Write ``ds`` to exactly ``path``, atomically: a reader never sees a half-written file.

    It is serialised in memory (so a failing disk never meets an open HDF5
    handle), written to ``PATH.partial`` (created afresh: a link there is
    replaced, never followed), synced, then renamed; after a failure (a full
    disk, the file-size limit) ``path`` still holds what it held, and the
    OSError names it and the cause.  Over several
    processes only process 0 writes; then the processes agree (a collective, so
    every process calls ``write`` alike): a failed write raises in all, as do
    numbers that differ between processes.
    """
    if not several():
        _write_here(ds, path)
        return
    error = None
    if is_writer():
        try:
            _write_here(ds, path)
        except OSError as e:
            error = e
    agree({"data": data_digest(ds)}, error)


def data_digest(ds: xr.Dataset) -> str:
    """SHA-256 of ``ds``' data variables and their coordinates: name, dtype, shape and bytes of each (NaNs alike)."""
    import xarray as xr

    return checksum(xr.Dataset({k: ds[k] for k in ds.data_vars}))


def _write_here(ds: xr.Dataset, path: Path):
    """:func:`write` in the process that writes."""
    tmp = path.with_name(path.name + ".partial")
    data = ds.to_netcdf(engine="h5netcdf")  # bytes: h5py writing to a failing disk can crash when its handle is freed
    try:
        tmp.unlink(missing_ok=True)
        with open(tmp, "xb") as f:  # "x": a new file, never through a link
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as e:
        tmp.unlink(missing_ok=True)
        if isinstance(e, OSError):
            raise OSError(f"cannot write {path} ({e.strerror or e}); it keeps what it held before") from e
        raise


def load_run(path) -> xr.Dataset:
    """The run (or fit) file at ``path``, read fully into memory (the file is closed) and checked against its checksum.

    A file that cannot be read (truncated, damaged) or does not match its
    checksum raises :class:`ConfigError` naming it.
    """
    import xarray as xr

    try:
        with xr.open_dataset(path, engine="h5netcdf") as ds:
            ds.load()
    except Exception as e:  # a damaged file fails inside h5py in many ways
        raise ConfigError(f"{path}: cannot be read as netCDF ({type(e).__name__}: {e}).") from None
    if "checksum" in ds.attrs and ds.attrs["checksum"] != checksum(ds):
        version = ds.attrs.get("format_version")
        if version in range(1, FORMAT_VERSION):
            raise ConfigError(
                f"{path} is of format version {version}, whose checksum this version of nhsde does not check "
                f"(format version {FORMAT_VERSION} covers the coordinates too); rerun it to read it here."
            )
        raise ConfigError(
            f"{path} is damaged or was edited: its contents (data, coordinates or attributes) do not "
            "match its checksum."
        )
    return ds


def _check_target(path: Path):
    """Refuse an output path that cannot become a file written there."""
    if path.is_dir():
        raise ConfigError(f"{path} is a directory; give the output a file name.")
    if not path.parent.is_dir():
        raise ConfigError(f"{path}: the directory {path.parent} does not exist.")
    if not os.access(path.parent, os.W_OK | os.X_OK):
        raise ConfigError(f"{path}: cannot write in the directory {path.parent} (permission denied).")
    if path.is_symlink() or (path.exists() and not path.is_file()):
        raise ConfigError(f"{path} exists and is not a regular file; choose another output file.")


def _existing(path: Path, config: RunConfig, fmt: str) -> xr.Dataset | None:
    """The file at the output ``path`` if any, after checking it is intact and of ``fmt`` and ``config``."""
    if not path.exists():
        return None
    ds = load_run(path)
    kind = "run" if fmt == FORMAT else "fit"
    if ds.attrs.get("format") != fmt or ds.attrs.get("format_version") != FORMAT_VERSION or "checksum" not in ds.attrs:
        raise ConfigError(
            f"{path} exists and is not an nhsde {kind} file of format version {FORMAT_VERSION}; "
            "it is left alone: delete it or choose another output file."
        )
    if ds.attrs["config"] != config.to_json():
        old, new = json.loads(ds.attrs["config"]), config.data
        differ = sorted(k for k in set(old) | set(new) if old.get(k) != new.get(k))
        raise ConfigError(
            f"{path} holds an nhsde {kind} of a different configuration (differs in: {', '.join(differ)}); "
            "delete it or choose another output file to start afresh."
        )
    return ds


@contextlib.contextmanager
def claim(path: Path, config: RunConfig, fmt: str = FORMAT) -> Iterator[xr.Dataset | None]:
    """Check the output ``path`` before any work and hold ``PATH.lock`` while writing; yields the file there, if any.

    Refused with :class:`ConfigError` naming the path: a directory, a missing
    or unwritable directory, a link or other non-file, a file that is damaged or
    not ``fmt`` of ``config``, and a path another process is writing.

    Over several processes (``jax.distributed``) only process 0 checks the path
    and holds the lock; the others only read the file there (they never create,
    lock or write anything).  Then the processes agree: an error in any of them,
    or a different configuration, code or file in any, is raised in all
    (:func:`~nhsde.runs._distributed.agree`).
    """
    if not several():
        with _claim_here(path, config, fmt) as found:
            yield found
        return
    with contextlib.ExitStack() as stack:
        found, error = None, None
        try:
            if is_writer():
                found = stack.enter_context(_claim_here(path, config, fmt))
            else:
                found = _existing(path, config, fmt)
        except (ConfigError, OSError) as e:
            error = e
        agree(
            {
                "config": digest(fmt, config.to_json()),
                "code": digest(json.dumps(versions(), sort_keys=True), source_hash()),
                "file": "none" if found is None else str(found.attrs.get("checksum")),
            },
            error,
        )
        yield found


@contextlib.contextmanager
def _claim_here(path: Path, config: RunConfig, fmt: str) -> Iterator[xr.Dataset | None]:
    """:func:`claim` in the process that writes."""
    _check_target(path)
    lock = path.with_name(path.name + ".lock")
    try:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)
    except OSError as e:
        raise ConfigError(f"{path}: cannot create its lock file {lock} ({e.strerror}).") from None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            held = os.path.samestat(os.fstat(fd), os.stat(lock))  # not removed meanwhile by a writer finishing
        except OSError:
            held = False
        if not held:
            raise ConfigError(
                f"{path} is being written by another process (it holds {lock}); "
                "wait for it to finish or choose another output file."
            )
        try:
            yield _existing(path, config, fmt)
        finally:
            lock.unlink(missing_ok=True)
    finally:
        os.close(fd)


_WHAT = {"scene_source": "the scene's module source (SHA-256)"}


def resume(ds: xr.Dataset, path: Path, config: RunConfig) -> tuple[Pieces, dict]:
    """The pieces and provenance of the run file ``ds`` at ``path`` (from :func:`claim`), after checking its counts
    and that the same code (package versions and sources, the scene's module's too) started it."""
    keys = ("versions", "source", "scene_source", "git_revision", "created")
    prov = {key: ds.attrs[key] for key in keys if key in ds.attrs}
    now = provenance(config)
    for key in ("versions", "source", "scene_source"):
        if prov.get(key) != now.get(key):
            raise ConfigError(
                f"{path} was started with {_WHAT.get(key, key)} {prov.get(key)}, now {now.get(key)}; "
                "its paths could differ, so it cannot be resumed here: delete it or choose another output file."
            )
    n, chunk = config.data["paths"]["n"], config.data["paths"]["chunk"]
    sizes = np.array([min(chunk, n - k * chunk) for k in range(ds.sizes["piece"])])
    used, failed = ds["piece_n_used"].values, ds["piece_n_failed"].values
    kept = sizes.sum() if config.data["statistics"]["keep_paths"] else 0
    if (
        len(sizes) > -(-n // chunk)
        or np.any(used < 0)
        or np.any(failed < 0)
        or not np.array_equal(used + failed, sizes)
        or ds.sizes.get("path", 0) != kept
    ):
        raise ConfigError(
            f"{path}: impossible counts: its paths used and failed do not add up to its {len(sizes)} pieces of "
            f"{n} paths in pieces of {chunk}; delete it or choose another output file."
        )
    shift = jnp.asarray(ds["shift"].values, jnp.float64)
    pieces = Pieces()
    for k in range(ds.sizes["piece"]):
        s1, s2, s3, s4 = (jnp.asarray(ds[v].values[k], jnp.float64) for v in _SUMS)
        count = jnp.asarray(ds["piece_n_used"].values[k], jnp.int64)
        pieces.sums.append(MomentSums(shift=shift, s1=s1, s2=s2, s3=s3, s4=s4, count=count))
        pieces.n_failed.append(int(ds["piece_n_failed"].values[k]))
    if "paths" in ds:
        for i in range(0, ds.sizes["path"], chunk):
            pieces.paths.append(ds["paths"].values[i : i + chunk])
            pieces.failed.append(ds["failed"].values[i : i + chunk].astype(bool))
    return pieces, prov
