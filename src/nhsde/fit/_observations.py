"""Observed statistics: what a fit compares the model with.

A fit compares *statistics* — the mean ``m(t)`` and covariance ``K(t)`` of
named components at observation times — between data and model.  Their vector

    s = [m(t₁), K(t₁)ᵤ, m(t₂), K(t₂)ᵤ, …]        (ᵤ: upper triangle, row by row)

is asymptotically Gaussian with covariance ``Σ``; ``Σ`` is estimated from the
per-path influence functions ``ψ_p = [z_p − m, (z_p − m)(z_p − m)ᵀᵤ − Kᵤ]``
(``Σ = Cov(ψ)/n``) when trajectories are observed, and taken as
``diag(se²)`` when only measured statistics with standard errors are.

Data files (:meth:`Observations.from_csv`, :meth:`~Observations.from_dataframe`,
:meth:`~Observations.from_xarray`) come in two layouts:

- *per path* (long): columns ``path``, ``t`` and one column per observed
  component (a state or observable name), one row per path and time;
- *summary* (wide): one row per time, columns ``t``, ``n_paths`` (or the
  argument), ``mean_A``, ``se_mean_A`` per component ``A`` and ``cov_A_B``,
  ``se_cov_A_B`` per pair (either order; ``cov_A_A`` the variance).
"""

from __future__ import annotations

import csv
import itertools
import math
from collections.abc import Callable, Sequence
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np

__all__ = [
    "Observations",
    "gaussian_statistic_covariance",
    "statistic_labels",
    "statistic_size",
    "statistic_vector",
]

RESERVED = ("path", "t", "n_paths")
"""Columns of a data file that are not observed components."""


def statistic_size(n_times: int, n_names: int) -> int:
    """Length of :func:`statistic_vector`: per time ``k`` means and ``k(k+1)/2`` covariances."""
    return n_times * (n_names + n_names * (n_names + 1) // 2)


def statistic_vector(mean, cov):
    """``s`` of ``mean (T, k)`` and ``cov (T, k, k)``: per time the mean, then ``K``'s upper triangle."""
    i, j = np.triu_indices(mean.shape[-1])
    return jnp.concatenate([mean, cov[:, i, j]], axis=-1).reshape(-1)


def statistic_labels(ts, names) -> list[str]:
    """Human-readable names of the entries of :func:`statistic_vector`."""
    i, j = np.triu_indices(len(names))
    per_time = [f"mean[{n}]" for n in names] + [f"cov[{names[a]},{names[b]}]" for a, b in zip(i, j)]
    return [f"{label} at t={float(t):g}" for t in np.asarray(ts) for label in per_time]


def statistic_covariance(paths) -> np.ndarray:
    """``Σ`` of :func:`statistic_vector` of the sample moments of ``paths (n, T, k)``, float64."""
    z = np.asarray(paths, np.float64)
    n = z.shape[0]
    z = z - z.mean(0)
    cov = np.einsum("pti,ptj->tij", z, z) / (n - 1)
    i, j = np.triu_indices(z.shape[-1])
    psi = np.concatenate([z, z[..., i] * z[..., j] - cov[:, i, j]], axis=-1).reshape(n, -1)
    return psi.T @ psi / (n * (n - 1))


def gaussian_statistic_covariance(cross, n_paths: int) -> np.ndarray:
    """``Σ`` of :func:`statistic_vector` of the sample moments of ``n_paths`` Gaussian paths, exactly.

    ``cross (T, T, k, k)``: ``cross[a, b, i, j] = Cov(z_i(t_a), z_j(t_b))``.  For jointly Gaussian paths
    the sample means and the unbiased sample covariances are uncorrelated, and (Wishart moments)

        Cov(m̂_i(a), m̂_j(b)) = C_ij(a, b)/n,
        Cov(K̂_ij(a), K̂_kl(b)) = [C_ik(a, b) C_jl(a, b) + C_il(a, b) C_jk(a, b)]/(n − 1).
    """
    c = np.asarray(cross, np.float64)
    t, k = c.shape[0], c.shape[-1]
    if c.shape != (t, t, k, k):
        raise ValueError(f"cross has shape {c.shape}; expected (T, T, k, k).")
    i, j = np.triu_indices(k)
    mean_part = c / n_paths
    cov_part = (c[:, :, i[:, None], i[None, :]] * c[:, :, j[:, None], j[None, :]]) + (
        c[:, :, i[:, None], j[None, :]] * c[:, :, j[:, None], i[None, :]]
    )
    cov_part = cov_part / (n_paths - 1)
    m, q = k, len(i)
    block = np.zeros((t, t, m + q, m + q))
    block[:, :, :m, :m] = mean_part
    block[:, :, m:, m:] = cov_part
    return block.transpose(0, 2, 1, 3).reshape(t * (m + q), t * (m + q))


def _numbers(columns: dict, name: str, row: Callable[[int], str]) -> np.ndarray:
    """Column ``name`` as finite float64 numbers; a missing or non-numeric cell is refused, naming its row."""
    out = np.empty(len(columns[name]))
    for i, cell in enumerate(columns[name]):
        if cell is None or (isinstance(cell, str) and not cell):
            raise ValueError(f"{row(i)}: column {name!r} is missing.")
        try:
            value = float(cell)
        except (TypeError, ValueError):
            raise ValueError(f"{row(i)}: column {name!r} holds {cell!r}, not a number.") from None
        if not math.isfinite(value):
            raise ValueError(f"{row(i)}: column {name!r} is missing (or not finite: {cell!r}).")
        out[i] = value
    return out


def _check_components(found: Sequence[str], names, system, where: str) -> tuple[str, ...]:
    """The components to use: ``names`` (each among ``found``) or all of ``found``, each offered by ``system``."""
    found = tuple(found)
    if names is not None:
        names = tuple(str(n) for n in names)
        missing = [n for n in names if n not in found]
        if missing:
            raise ValueError(f"names={names}: {where} has no component {missing[0]!r}; it holds {found}.")
        found = names
    if not found:
        raise ValueError(f"{where} holds no observed component.")
    if system is not None:
        offered = system.observable_names()
        for name in found:
            if name not in offered:
                raise ValueError(
                    f"{where}: column {name!r} is not a state component or observable of the system; "
                    f"it offers {', '.join(offered)}."
                )
    return found


def _per_path_table(columns: dict, row: Callable[[int], str], where: str, names, system):
    """``(ts, paths (n, T, k), names)`` of a per-path table: columns ``path``, ``t`` and the components."""
    if "n_paths" in columns:
        raise ValueError(f"{where}: unknown column 'n_paths' in a per-path table (columns path, t, components).")
    names = _check_components([c for c in columns if c not in RESERVED], names, system, where)
    if "t" not in columns:
        raise ValueError(f"{where}: no column 't' (the observation time of each row).")
    t = _numbers(columns, "t", row)
    z = np.stack([_numbers(columns, n, row) for n in names], axis=-1)
    labels = [str(p) for p in columns["path"]]
    path_ids, first, path_index = np.unique(labels, return_index=True, return_inverse=True)
    ts, time_index = np.unique(t, return_inverse=True)
    rows = np.full((len(path_ids), len(ts)), -1)
    for i, (p, j) in enumerate(zip(path_index, time_index)):
        if rows[p, j] >= 0:
            raise ValueError(
                f"{row(i)}: path {labels[i]!r} at t={ts[j]:g} again (first in {row(int(rows[p, j]))}); "
                "each path holds one row per time."
            )
        rows[p, j] = i
    holes = np.argwhere(rows < 0)
    if len(holes):
        p, j = holes[0]
        raise ValueError(
            f"{where}: path {str(path_ids[p])!r} (from {row(int(first[p]))}) has no row at t={ts[j]:g}, which "
            f"{int(np.sum(rows[:, j] >= 0))} other paths have; ragged paths cannot be fitted: give every path "
            "every time, or leave that time out of the file."
        )
    return ts, z[rows], names


def _summary_table(columns: dict, row: Callable[[int], str], where: str, names, system, n_paths):
    """The arguments of :meth:`Observations.from_statistics` from a summary table (one row per time)."""
    found = [c[len("mean_") :] for c in columns if c.startswith("mean_")]
    pair_of: dict[str, tuple[str, str]] = {}
    for a, b in itertools.combinations_with_replacement(found, 2):
        for label in {f"cov_{a}_{b}", f"cov_{b}_{a}"}:
            if label in pair_of and set(pair_of[label]) != {a, b}:
                raise ValueError(
                    f"{where}: column {label!r} could be the covariance of {pair_of[label]} or of {(a, b)}; "
                    "rename the components so that no name joined with '_' reads as another pair."
                )
            pair_of[label] = (a, b)
    known = {"t", "n_paths"} | {f"{se}mean_{a}" for a in found for se in ("", "se_")}
    known |= set(pair_of) | {"se_" + label for label in pair_of}
    for column in columns:
        if column not in known:
            raise ValueError(
                f"{where}: unknown column {column!r}; a summary table has t, n_paths, and mean_A, se_mean_A, "
                f"cov_A_B, se_cov_A_B for its components {tuple(found)} (a per-path table has a column 'path')."
            )
    names = _check_components(found, names, system, where)
    if "t" not in columns:
        raise ValueError(f"{where}: no column 't' (the observation time of each row).")
    t = _numbers(columns, "t", row)
    order = np.argsort(t, kind="stable")
    repeated = np.flatnonzero(np.diff(t[order]) == 0)
    if len(repeated):
        i, j = order[repeated[0]], order[repeated[0] + 1]
        raise ValueError(f"{row(int(j))}: t={t[j]:g} again (first in {row(int(i))}); a summary has one row per time.")

    def column(label: str) -> np.ndarray:
        if label not in columns:
            raise ValueError(f"{where}: no column {label!r}; a summary table needs it for the components {names}.")
        return _numbers(columns, label, row)[order]

    def pair(prefix: str, a: str, b: str) -> np.ndarray:
        labels = [f"{prefix}cov_{x}_{y}" for x, y in {(a, b), (b, a)} if f"{prefix}cov_{x}_{y}" in columns]
        if len(labels) > 1:
            raise ValueError(f"{where}: columns {labels[0]!r} and {labels[1]!r} both give cov({a}, {b}); keep one.")
        return column(labels[0] if labels else f"{prefix}cov_{a}_{b}")

    k = len(names)
    mean, mean_se = (np.stack([column(f"{se}mean_{a}") for a in names], -1) for se in ("", "se_"))
    cov, cov_se = np.empty((len(t), k, k)), np.empty((len(t), k, k))
    for i, j in itertools.combinations_with_replacement(range(k), 2):
        cov[:, i, j] = cov[:, j, i] = pair("", names[i], names[j])
        cov_se[:, i, j] = cov_se[:, j, i] = pair("se_", names[i], names[j])
    if "n_paths" in columns:
        counts = np.unique(_numbers(columns, "n_paths", row))
        if len(counts) != 1 or (n_paths is not None and counts[0] != n_paths):
            given = "" if n_paths is None else f" and n_paths={n_paths} was given"
            raise ValueError(f"{where}: column 'n_paths' holds {counts.tolist()}{given}; give one number of paths.")
        n_paths = counts[0]
    if n_paths is None:
        raise ValueError(
            f"{where}: how many paths the statistics are from is unknown; add a column 'n_paths' or give n_paths=."
        )
    if n_paths != int(n_paths):
        raise ValueError(f"{where}: n_paths={n_paths} must be a whole number.")
    return t[order], names, mean, cov, mean_se, cov_se, int(n_paths)


class Observations(eqx.Module):
    """Observed means and covariances of ``names`` at times ``ts``, with the covariance ``Σ`` of their vector.

    Build with :meth:`from_paths` (trajectories: ``Σ`` in full, cross-time
    correlations included) or :meth:`from_statistics` (measured statistics
    with standard errors: ``Σ = diag(se²)``, correlations unknown and ignored).
    """

    ts: np.ndarray
    mean: np.ndarray
    cov: np.ndarray
    covariance: np.ndarray  # Σ of statistic_vector(mean, cov)
    names: tuple[str, ...] = eqx.field(static=True)
    n_paths: int = eqx.field(static=True)
    from_trajectories: bool = eqx.field(static=True)
    correlations: str = eqx.field(static=True, default="paths")
    """Where ``Σ``'s correlations come from: ``"paths"``, ``"given"``, ``"model"`` (at a fit's estimate), or
    ``"unknown"`` (a summary's standard errors alone: ``Σ`` diagonal)."""

    def __check_init__(self):
        t, k = len(self.ts), len(self.names)
        if np.shape(self.mean) != (t, k) or np.shape(self.cov) != (t, k, k):
            raise ValueError(
                f"Observations: mean {np.shape(self.mean)} and cov {np.shape(self.cov)} must be "
                f"({t}, {k}) and ({t}, {k}, {k}) for {t} times and names {self.names}."
            )
        if np.any(np.diff(self.ts) <= 0):
            raise ValueError(f"Observations: ts={np.asarray(self.ts).tolist()} must increase strictly.")
        size = statistic_size(t, k)
        if np.shape(self.covariance) != (size, size):
            raise ValueError(
                f"Observations: covariance has shape {np.shape(self.covariance)}; expected ({size}, {size})."
            )
        var = np.diag(self.covariance)
        if not np.all(np.isfinite(self.covariance)) or np.any(var <= 0):
            bad = statistic_labels(self.ts, self.names)[int(np.argmin(np.where(np.isfinite(var), var, -1.0)))]
            raise ValueError(
                f"Observations: the statistic {bad} has zero (or non-finite) variance, so it carries no "
                "likelihood; leave out that time (e.g. the deterministic initial state) or that component."
            )

    @classmethod
    def from_paths(cls, ts, paths, names) -> Observations:
        """Trajectories ``paths (n_paths, len(ts), len(names))`` observed at ``ts``.

        Arguments:
            ts: the observation times ``(T,)``.
            paths: ``(n_paths, T, k)`` finite values, more paths than the statistics they give plus 2.
            names: the ``k`` observed components (state names of the fitted system).

        Returns:
            the sample means and covariances with their full covariance ``Σ`` (cross-time correlations included).

        Examples:
            >>> import numpy as np
            >>> from nhsde import fit
            >>> paths = np.random.default_rng(0).normal(size=(200, 2, 1))
            >>> observed = fit.Observations.from_paths([1.0, 2.0], paths, ("x",))
            >>> observed.size, observed.covariance.shape, observed.n_paths
            (4, (4, 4), 200)
        """
        ts = np.asarray(ts, np.float64)
        names = tuple(str(n) for n in names)
        z = np.asarray(paths, np.float64)
        if z.ndim != 3 or z.shape[1:] != (len(ts), len(names)):
            raise ValueError(f"paths has shape {z.shape}; expected (n_paths, {len(ts)}, {len(names)}).")
        if not np.all(np.isfinite(z)):
            raise ValueError("paths contains non-finite values; drop the failed paths first.")
        n = z.shape[0]
        size = statistic_size(len(ts), len(names))
        if n <= size + 2:
            raise ValueError(
                f"{n} paths cannot estimate the {size}×{size} covariance of the statistics; "
                f"observe more than {size + 2} paths, or fewer times or components."
            )
        c = z - z.mean(0)
        return cls(
            ts=ts,
            mean=z.mean(0),
            cov=np.einsum("pti,ptj->tij", c, c) / (n - 1),
            covariance=statistic_covariance(z),
            names=names,
            n_paths=n,
            from_trajectories=True,
        )

    @classmethod
    def from_statistics(cls, ts, names, mean, cov, mean_se, cov_se, n_paths: int, *, covariance=None) -> Observations:
        """Measured ``mean (T, k)``, ``cov (T, k, k)`` with standard errors, from ``n_paths`` paths.

        Arguments:
            ts: the observation times ``(T,)``.
            names: the ``k`` observed components.
            mean, cov: ``(T, k)`` and ``(T, k, k)``.
            mean_se, cov_se: their standard errors, same shapes.
            n_paths: the number of paths they were measured on.
            covariance: the full covariance ``Σ`` of the statistic vector (:func:`statistic_labels` names its
                entries), correlations across times included, if known; its diagonal must be the ``se²``.

        Returns:
            observations with ``Σ = covariance``, else ``Σ = diag(se²)`` with correlations ``"unknown"``: then
            :func:`~nhsde.fit.estimate` takes the correlations from the model at its estimate where the model
            can give them, and otherwise warns and inflates the errors by ``χ²/dof``.
        """
        ts = np.asarray(ts, np.float64)
        mean, cov, mean_se, cov_se = (np.asarray(a, np.float64) for a in (mean, cov, mean_se, cov_se))
        if mean_se.shape != mean.shape or cov_se.shape != cov.shape:
            raise ValueError(
                f"mean_se {mean_se.shape} and cov_se {cov_se.shape} must match mean {mean.shape} and cov {cov.shape}."
            )
        n_paths = int(n_paths)
        if n_paths < 2:
            raise ValueError(f"n_paths={n_paths}; must be ≥ 2.")
        se = np.asarray(statistic_vector(mean_se, cov_se))
        if covariance is not None:
            covariance = np.asarray(covariance, np.float64)
            if covariance.shape != (se.size, se.size) or not np.allclose(covariance, covariance.T, rtol=1e-10):
                raise ValueError(
                    f"covariance has shape {covariance.shape}; expected a symmetric ({se.size}, {se.size}) matrix."
                )
            off = np.flatnonzero(~np.isclose(np.diag(covariance), se**2, rtol=1e-6, atol=0))
            if off.size:
                label = statistic_labels(ts, names)[off[0]]
                raise ValueError(
                    f"covariance: its diagonal at {label} is {np.diag(covariance)[off[0]]:g}, but the standard "
                    f"error given there squares to {se[off[0]] ** 2:g}."
                )
        return cls(
            ts=ts,
            mean=mean,
            cov=cov,
            covariance=np.diag(se**2) if covariance is None else covariance,
            names=tuple(str(n) for n in names),
            n_paths=n_paths,
            from_trajectories=False,
            correlations="unknown" if covariance is None else "given",
        )

    def with_correlations(self, covariance, source: str = "model") -> Observations:
        """These observations with ``Σ = D R D``: ``R`` the correlations of ``covariance``, ``D`` this ``Σ``'s
        standard errors (so the data keep their own errors and gain correlations across times)."""
        covariance = np.asarray(covariance, np.float64)
        scale = np.sqrt(np.diag(covariance))
        se = np.sqrt(np.diag(self.covariance))
        r = covariance / np.outer(scale, scale)
        return Observations(
            ts=self.ts,
            mean=self.mean,
            cov=self.cov,
            covariance=se[:, None] * r * se[None, :],
            names=self.names,
            n_paths=self.n_paths,
            from_trajectories=self.from_trajectories,
            correlations=source,
        )

    @classmethod
    def _from_table(cls, columns: dict, row: Callable[[int], str], where: str, names, system, n_paths):
        """A per-path table (it has a column ``path``) or a summary table (one row per time)."""
        if not columns or not len(next(iter(columns.values()))):
            raise ValueError(f"{where} holds no data rows.")
        if "path" in columns:
            if n_paths is not None:
                raise ValueError(f"n_paths={n_paths}: {where} is a per-path table; its paths are counted.")
            ts, paths, names = _per_path_table(columns, row, where, names, system)
            return cls.from_paths(ts, paths, names)
        return cls.from_statistics(*_summary_table(columns, row, where, names, system, n_paths))

    @classmethod
    def from_csv(cls, file, *, names=None, n_paths: int | None = None, system=None) -> Observations:
        """Observations from a CSV file, per path or summary (the layouts of this module), read without pandas.

        The first line names the columns; empty lines and lines starting with ``#`` are skipped.  Unknown columns,
        missing or non-numeric values, repeated times and ragged paths (a path without a time others have) are
        refused, naming the line or column.

        Arguments:
            file: the CSV file.
            names: the components to use (default: every component column).
            n_paths: for a summary without an ``n_paths`` column, the number of paths it was measured on.
            system: a :class:`~nhsde.StochasticSystem` whose state or observable names every component must be.

        Returns:
            :meth:`from_paths` of a per-path file, :meth:`from_statistics` of a summary.

        Examples:
            >>> import pathlib, tempfile
            >>> from nhsde import fit
            >>> rows = ["t,n_paths,mean_x,se_mean_x,cov_x_x,se_cov_x_x", "1,400,0.01,0.05,1.02,0.07",
            ...         "2,400,-0.03,0.07,2.1,0.15"]
            >>> file = pathlib.Path(tempfile.mkdtemp()) / "summary.csv"
            >>> _ = file.write_text("\\n".join(rows))
            >>> observed = fit.Observations.from_csv(file)
            >>> observed.names, observed.ts.tolist(), observed.n_paths
            (('x',), [1.0, 2.0], 400)
        """
        path = Path(file)
        try:
            with open(path, newline="", encoding="utf-8") as f:
                records = [(reader.line_num, r) for reader in [csv.reader(f)] for r in reader]
        except (OSError, UnicodeDecodeError, csv.Error) as e:
            raise ValueError(f"{path}: cannot be read as a CSV file ({e}).") from None
        records = [(n, r) for n, r in records if r and any(c.strip() for c in r) and not r[0].lstrip().startswith("#")]
        if not records:
            raise ValueError(f"{path}: empty; the first line must name the columns.")
        (_, header), body = records[0], records[1:]
        header = [h.strip() for h in header]
        for i, name in enumerate(header):
            if not name or name in header[:i]:
                raise ValueError(
                    f"{path}: column {i + 1} of the header is {'empty' if not name else f'{name!r} again'}."
                )
        for n, r in body:
            if len(r) != len(header):
                raise ValueError(f"{path}, line {n}: {len(r)} fields; the header names {len(header)} columns.")
        columns = {name: [r[i].strip() for _, r in body] for i, name in enumerate(header)}
        return cls._from_table(columns, lambda i: f"{path}, line {body[i][0]}", str(path), names, system, n_paths)

    @classmethod
    def from_dataframe(cls, df, *, names=None, n_paths: int | None = None, system=None) -> Observations:
        """Observations from a pandas ``DataFrame`` in either layout (as :meth:`from_csv`; a named index, such as
        ``Dataset.to_dataframe()``'s ``(path, t)``, counts as columns).  nhsde does not import pandas.

        Arguments:
            df: the table.
            names, n_paths, system: as for :meth:`from_csv`.
        """
        if not hasattr(df, "columns") or not hasattr(df, "reset_index"):
            raise TypeError(f"df={type(df).__name__}; expected a pandas DataFrame.")
        if any(n is not None for n in df.index.names):
            df = df.reset_index()
        labels = [str(c) for c in df.columns]
        repeated = [c for i, c in enumerate(labels) if c in labels[:i]]
        if repeated:
            raise ValueError(f"df: column {repeated[0]!r} appears twice.")
        columns = {str(c): df[c].to_numpy() for c in df.columns}
        index = df.index
        return cls._from_table(columns, lambda i: f"df row {index[i]!r}", "df", names, system, n_paths)

    @classmethod
    def from_xarray(cls, ds, *, names=None, n_paths: int | None = None, system=None) -> Observations:
        """Observations from an xarray ``Dataset``.

        Run-file layout (:func:`nhsde.runs.run`): ``paths`` over ``path × time × name`` (paths flagged in
        ``failed`` are dropped), or ``mean``, ``cov``, ``mean_se``, ``cov_se`` over ``time × name (× name2)``
        with ``n_paths`` (argument, else the attribute ``n_used``) and, where known, ``covariance``: the
        statistics' full covariance over ``statistic × statistic2`` (:meth:`from_statistics`).  Any other
        dataset is read as the table ``ds.to_dataframe()`` (:meth:`from_dataframe`), e.g. variables ``x``,
        ``u_x`` over ``(path, t)``.
        A run file starts at its deterministic initial state: select the later times, ``ds.isel(time=slice(1, None))``.

        Arguments:
            ds: the dataset.
            names, n_paths, system: as for :meth:`from_csv`.
        """
        if not hasattr(ds, "data_vars") or not hasattr(ds, "to_dataframe"):
            raise TypeError(f"ds={type(ds).__name__}; expected an xarray Dataset.")
        summary = ("mean", "cov", "mean_se", "cov_se")
        if "paths" not in ds and not all(v in ds for v in summary):
            return cls.from_dataframe(ds.to_dataframe(), names=names, n_paths=n_paths, system=system)
        stored = [str(n) for n in ds["name"].values]
        names = _check_components(stored, names, system, "ds")
        idx = [stored.index(n) for n in names]
        ts = ds["time"].values
        if "paths" in ds:
            if n_paths is not None:
                raise ValueError(f"n_paths={n_paths}: ds holds paths; they are counted.")
            paths = ds["paths"].transpose("path", "time", "name").values[..., idx]
            good = ds["failed"].values == 0 if "failed" in ds else np.ones(len(paths), bool)
            return cls.from_paths(ts, paths[good], names)
        mean, mean_se = (ds[v].transpose("time", "name").values[:, idx] for v in ("mean", "mean_se"))
        cov, cov_se = (ds[v].transpose("time", "name", "name2").values[:, idx][:, :, idx] for v in ("cov", "cov_se"))
        if n_paths is None:
            if "n_used" not in ds.attrs:
                raise ValueError("ds: how many paths the statistics are from is unknown; give n_paths=.")
            n_paths = int(ds.attrs["n_used"])
        covariance = None
        if "covariance" in ds:  # Σ over statistic × statistic2, of all the stored names
            if list(names) != stored:
                raise ValueError(f"names={names}: ds holds the statistics' covariance of all of {tuple(stored)}.")
            covariance = ds["covariance"].values
        return cls.from_statistics(ts, names, mean, cov, mean_se, cov_se, n_paths, covariance=covariance)

    def statistics(self) -> np.ndarray:
        """The observed :func:`statistic_vector`."""
        return np.asarray(statistic_vector(self.mean, self.cov))

    @property
    def size(self) -> int:
        return statistic_size(len(self.ts), len(self.names))
