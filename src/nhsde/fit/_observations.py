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

import bisect
import csv
import itertools
import math
import re
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

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
    return _sample_statistics(np.asarray(paths, np.float64))[2]


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


def _complex_refused(where: str, value) -> ValueError:
    value = complex(value) if isinstance(value, (complex, np.complexfloating)) else value
    return ValueError(
        f"{where} holds the complex number {value!r}; only real values can be fitted (its imaginary part would be "
        "lost): give the real part, or the real and imaginary parts as two components."
    )


def _real(name: str, values) -> np.ndarray:
    """``values`` as float64; complex values are refused (``np.asarray(z, float)`` would drop their imaginary part)."""
    if np.iscomplexobj(values):
        z = np.asarray(values).reshape(-1)
        raise _complex_refused(name, complex(z[int(np.argmax(np.imag(z) != 0))]) if z.size else values)
    return np.asarray(values, np.float64)


def _cell_number(cell, name: str) -> float:
    """One cell of an object column as a finite float; refused as ``_numbers`` says, naming the column."""
    if isinstance(cell, str):
        cell = cell.strip()
    if cell is None or (isinstance(cell, str) and not cell) or type(cell).__name__ in ("NAType", "NaTType"):
        raise ValueError(f"column {name!r} is missing.")
    if isinstance(cell, (complex, np.complexfloating)):
        raise _complex_refused(f"column {name!r}", cell)
    try:
        value = float(cell)
    except (TypeError, ValueError):
        try:
            complex(cell)
        except (TypeError, ValueError):
            raise ValueError(f"column {name!r} holds {cell!r}, not a number.") from None
        raise _complex_refused(f"column {name!r}", cell) from None
    if not math.isfinite(value):
        raise ValueError(f"column {name!r} is missing (or not finite: {cell!r}).")
    return value


def _numbers(columns: dict, name: str, row: Callable[[int], str]) -> np.ndarray:
    """Column ``name`` as finite float64 numbers; a missing, non-numeric or complex cell is refused, naming its row.

    A numeric column is checked at once; an object column (text, or numbers mixed with text) cell by cell."""
    cells = np.asarray(columns[name])
    if cells.dtype.kind == "c":
        bad = np.flatnonzero(np.imag(cells) != 0)
        i = int(bad[0]) if bad.size else 0
        raise _complex_refused(f"{row(i)}: column {name!r}", complex(cells[i]))
    if cells.dtype.kind in "biuf":
        out = cells.astype(np.float64, copy=False)
        bad = np.flatnonzero(~np.isfinite(out))
        if bad.size:
            i = int(bad[0])
            raise ValueError(f"{row(i)}: column {name!r} is missing (or not finite: {cells[i]!r}).")
        return out
    out = np.empty(len(cells))
    for i, cell in enumerate(cells):
        try:
            out[i] = _cell_number(cell, name)
        except ValueError as e:
            raise ValueError(f"{row(i)}: {e}") from None
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


def _labels(cells, row: Callable[[int], str]) -> np.ndarray:
    """Path labels: numbers as they are (a missing one refused), anything else as stripped text."""
    cells = np.asarray(cells)
    if cells.dtype.kind not in "biuf":
        return np.array([str(c).strip() for c in cells])
    missing = np.flatnonzero(np.isnan(cells)) if cells.dtype.kind == "f" else np.empty(0, np.int64)
    if len(missing):
        raise ValueError(f"{row(int(missing[0]))}: column 'path' is missing.")
    return cells


def _codes(labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(codes, sorted distinct labels)`` of integer labels, by a table where their range is small (else hashing)."""
    low, high = int(labels.min()), int(labels.max())
    if high - low > 4 * len(labels):
        import pandas as pd

        codes, distinct = pd.factorize(labels, sort=True)
        return codes, np.asarray(distinct)
    present = np.zeros(high - low + 1, bool)
    present[labels - low] = True
    code_of = np.cumsum(present) - 1
    return code_of[labels - low], np.flatnonzero(present) + low


def _in_blocks(labels: np.ndarray, t: np.ndarray) -> int | None:
    """The number of times per path where the rows come as files are written: path by path, labels (numbers)
    increasing, each path's times increasing and the same for every path; ``None`` otherwise."""
    if labels.dtype.kind not in "iuf" or not len(t):
        return None
    change = np.flatnonzero(labels[1:] != labels[0])
    n_times = int(change[0]) + 1 if change.size else len(t)
    if len(t) % n_times:
        return None
    blocks, times = labels.reshape(-1, n_times), t.reshape(-1, n_times)
    if np.any(np.diff(times[0]) <= 0) or np.any(np.diff(blocks[:, 0]) <= 0):
        return None
    return None if np.any(times != times[0]) or np.any(blocks != blocks[:, :1]) else n_times


def _per_path_table(columns: dict, row: Callable[[int], str], where: str, names, system):
    """``(ts, paths (n, T, k), names)`` of a per-path table: columns ``path``, ``t`` and the components."""
    if "n_paths" in columns:
        raise ValueError(f"{where}: unknown column 'n_paths' in a per-path table (columns path, t, components).")
    names = _check_components([c for c in columns if c not in RESERVED], names, system, where)
    if "t" not in columns:
        raise ValueError(f"{where}: no column 't' (the observation time of each row).")
    import pandas as pd  # a table's reader has it: a CSV file, a DataFrame, a Dataset's to_dataframe()

    t = _numbers(columns, "t", row)
    values = [_numbers(columns, n, row) for n in names]
    labels = _labels(columns["path"], row)
    n_times = _in_blocks(labels, t)
    if n_times is not None:  # every path every time once, in order: the table is the paths
        n_paths = len(t) // n_times
        paths = np.empty((len(names), n_times, n_paths))  # (k, T, n): each value over the paths contiguous
        for j, v in enumerate(values):
            paths[j] = v.reshape(n_paths, n_times).T
        return np.array(t[:n_times]), paths.transpose(2, 1, 0), names
    path_index, path_ids = _codes(labels) if labels.dtype.kind in "iu" else pd.factorize(labels, sort=True)
    time_index, ts = pd.factorize(t, sort=True)
    path_ids, ts = np.asarray(path_ids), np.asarray(ts, np.float64)
    n_paths = len(path_ids)
    cell = time_index.astype(np.int64) * n_paths + path_index  # (time, path) of each row, flat
    del t, path_index, time_index
    if len(cell) == len(ts) * n_paths:  # every (path, time) once unless one is missing, and then another repeats
        paths = np.full((len(names), len(ts), n_paths), np.nan)  # (k, T, n): each value over the paths contiguous
        for j, v in enumerate(values):
            paths[j].reshape(-1)[cell] = v
        if not np.isnan(paths[0]).any():  # the values are finite: nothing missing
            return ts, paths.transpose(2, 1, 0), names
    counts = np.bincount(cell, minlength=len(ts) * n_paths)
    if counts.max() > 1:
        order = np.argsort(cell, kind="stable")
        again = np.flatnonzero(cell[order[1:]] == cell[order[:-1]])
        k = again[np.argmin(order[1:][again])]  # the earliest row that repeats a (path, time)
        i, before = int(order[k + 1]), int(order[k])
        j, p = divmod(int(cell[i]), n_paths)
        raise ValueError(
            f"{row(i)}: path {str(path_ids[p])!r} at t={ts[j]:g} again (first in {row(before)}); "
            "each path holds one row per time."
        )
    holes = np.flatnonzero(counts.reshape(len(ts), n_paths).T.reshape(-1) == 0)  # the first path first
    p, j = divmod(int(holes[0]), len(ts))
    first, present = int(np.argmax(cell % n_paths == p)), int(np.sum(counts[j * n_paths : (j + 1) * n_paths] > 0))
    raise ValueError(
        f"{where}: path {str(path_ids[p])!r} (from {row(first)}) has no row at t={ts[j]:g}, which {present} "
        "other paths have; ragged paths cannot be fitted: give every path every time, or leave that time out "
        "of the file."
    )


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

    def column(label: str, what: str | None = None) -> np.ndarray:
        """The column in time order; ``what`` (a variance, a standard error) must be ≥ 0."""
        if label not in columns:
            raise ValueError(f"{where}: no column {label!r}; a summary table needs it for the components {names}.")
        values = _numbers(columns, label, row)
        negative = np.flatnonzero(values < 0) if what else np.empty(0, np.int64)
        if len(negative):
            i = int(negative[0])
            raise ValueError(f"{row(i)}: column {label!r} holds {values[i]:g}, a negative {what}; it must be ≥ 0.")
        return values[order]

    def pair(prefix: str, a: str, b: str) -> np.ndarray:
        labels = [f"{prefix}cov_{x}_{y}" for x, y in {(a, b), (b, a)} if f"{prefix}cov_{x}_{y}" in columns]
        if len(labels) > 1:
            raise ValueError(f"{where}: columns {labels[0]!r} and {labels[1]!r} both give cov({a}, {b}); keep one.")
        what = "standard error" if prefix else "variance" if a == b else None
        return column(labels[0] if labels else f"{prefix}cov_{a}_{b}", what)

    k = len(names)
    mean = np.stack([column(f"mean_{a}") for a in names], -1)
    mean_se = np.stack([column(f"se_mean_{a}", "standard error") for a in names], -1)
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


def _zero_variance_note(ts, names, covariance) -> str:
    """What a fit leaves out: the statistics of zero variance, which carry no information ("" where none)."""
    per = statistic_size(1, len(names))
    zero = (np.diag(covariance) == 0).reshape(len(ts), per)
    if not zero.any():
        return ""
    labels = statistic_labels(ts, names)
    whole = zero.all(1)
    parts = [f"every statistic at t={t:g}" for t in np.asarray(ts)[whole]]
    parts += [labels[j * per + a] for j in np.flatnonzero(~whole) for a in np.flatnonzero(zero[j])]
    shown = ", ".join(parts[:6]) + (f" and {len(parts) - 6} more" if len(parts) > 6 else "")
    return f"left out {int(zero.sum())} statistics of zero variance, which carry no information: {shown}"


def _chunk_rows(width: int) -> int:
    """Paths per block of influence functions: about 1 Mi numbers (8 MiB)."""
    return max(1, (1 << 20) // max(1, width))


def _sample_statistics(z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(mean, cov, Σ)`` of the sample moments of ``z (n, T, k)`` (float64).

    ``Σ = Σ_p ψ_p ψ_pᵀ/(n(n − 1))`` with ``ψ = [c, c_i c_j − K_ij]`` (``c = z − mean``), summed by blocks of paths
    (the influence functions of all paths are never held at once), each statistic's values over the paths
    contiguous."""
    n, t, k = z.shape
    mean = z.mean(0)
    c = np.subtract(z.transpose(2, 1, 0), mean.T[:, :, None], order="C")  # (k, T, n)
    pairs = list(zip(*np.triu_indices(k)))
    per = k + len(pairs)
    cov_upper = np.stack([np.einsum("tp,tp->t", c[i], c[j]) for i, j in pairs]) / (n - 1)  # (pairs, T)
    step = _chunk_rows(per * t)
    buffer = np.empty(per * t * min(step, n))
    gram = np.zeros((per * t, per * t))
    for start in range(0, n, step):
        b = c[:, :, start : start + step]
        psi = buffer[: b.size // k * per].reshape(per, t, b.shape[-1])
        psi[:k] = b
        for a, (i, j) in enumerate(pairs):
            np.multiply(b[i], b[j], out=psi[k + a])
            psi[k + a] -= cov_upper[a][:, None]
        flat = psi.reshape(per * t, -1)
        gram += flat @ flat.T
    order = (np.arange(per)[None, :] * t + np.arange(t)[:, None]).reshape(-1)  # statistic-major to time-major
    cov = np.empty((t, k, k))
    for a, (i, j) in enumerate(pairs):
        cov[:, i, j] = cov[:, j, i] = cov_upper[a]
    return mean, cov, gram[np.ix_(order, order)] / (n * (n - 1))


def _csv_layout(path: Path) -> tuple[list[str] | None, int, list[int]]:
    """``(header, its last line, the comment lines after it)`` of a CSV file (lines counted from 1).

    The header is the first record that is neither blank nor a comment (its first cell starting with ``#``).
    Comment lines after it are looked for only where the rest of the file holds a ``#`` at all."""
    with open(path, newline="", encoding="utf-8-sig") as f:
        reader = csv.reader(f)
        for record in reader:
            if record and any(c.strip() for c in record) and not record[0].lstrip().startswith("#"):
                header, lines = [h.strip() for h in record], reader.line_num
                break
        else:
            return None, 0, []
    with open(path, "rb") as f:
        for _ in range(lines):
            f.readline()
        start = f.tell()
        if not any(b"#" in block for block in iter(lambda: f.read(1 << 20), b"")):
            return header, lines, []
        f.seek(start)
        return header, lines, [n for n, line in enumerate(f, lines + 1) if line.lstrip().startswith(b"#")]


def _skipped_lines(path: Path, after: int) -> list[int]:
    """The lines after line ``after`` that the parser passes over: blank (white space only) or comments."""
    with open(path, "rb") as f:
        return [n for n, line in enumerate(f, 1) if n > after and (not line.strip() or line.lstrip()[:1] == b"#")]


def _fields_on(path: Path, line: int) -> int:
    """The number of fields of the record ending on line ``line``."""
    with open(path, newline="", encoding="utf-8-sig") as f:
        reader = csv.reader(f)
        for record in reader:
            if reader.line_num >= line:
                return len(record)
    return 0


def _read_csv(path: Path) -> tuple[dict, Callable[[int], str]]:
    """The columns of a CSV file as arrays, blank rows dropped, and ``row(i)``: ``"FILE, line N"`` of row ``i``.

    pandas' C parser reads every column but ``path`` as float64; where that fails (a cell that is not a number,
    an empty one) the file is read again with each column as numbers or text, for the checks to name the cell.
    A row with more fields than the header is refused here."""
    try:
        header, lines, comments = _csv_layout(path)
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise ValueError(f"{path}: cannot be read as a CSV file ({e}).") from None
    if header is None:
        raise ValueError(f"{path}: empty; the first line must name the columns.")
    for i, name in enumerate(header):
        if not name or name in header[:i]:
            raise ValueError(f"{path}: column {i + 1} of the header is {'empty' if not name else f'{name!r} again'}.")
    skipped: list[list[int]] = []

    def line(p: int) -> int:  # the line of the parser's row p: the lines after the header but those skipped
        if not skipped:
            skipped.append(_skipped_lines(path, lines))
        n = lines + 1 + p
        while (m := lines + 1 + p + bisect.bisect_right(skipped[0], n)) != n:
            n = m
        return n

    import pandas as pd

    options: dict[str, Any] = dict(
        header=None,
        names=header,
        skiprows=sorted({*range(lines), *(n - 1 for n in comments)}) if comments else lines,
        index_col=False,
        na_filter=False,
        encoding="utf-8-sig",
        engine="c",
    )
    numbers: dict[Any, str] = {name: "float64" for name in header if name != "path"}
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                df = pd.read_csv(path, dtype=numbers, **options)
            except (pd.errors.ParserError, pd.errors.EmptyDataError):
                raise
            except ValueError:  # a cell that is not a number: read as text where need be, for the checks to name it
                df = pd.read_csv(path, **options)
    except pd.errors.EmptyDataError:
        return {name: np.empty(0) for name in header}, lambda i: f"{path}, line {line(i)}"
    except pd.errors.ParserError as e:
        fields = re.search(r"Expected \d+ fields in line (\d+), saw (\d+)", str(e))
        if fields is None:
            raise ValueError(f"{path}: cannot be read as a CSV file ({e}).") from None
        raise ValueError(
            f"{path}, line {fields[1]}: {fields[2]} fields; the header names {len(header)} columns."
        ) from None
    except (OSError, UnicodeDecodeError) as e:
        raise ValueError(f"{path}: cannot be read as a CSV file ({e}).") from None
    if any(issubclass(w.category, pd.errors.ParserWarning) and "Length of header" in str(w.message) for w in caught):
        n = line(0)  # the first row has more fields than the header names: the parser dropped them
        raise ValueError(f"{path}, line {n}: {_fields_on(path, n)} fields; the header names {len(header)} columns.")
    columns = {name: df[name].to_numpy() for name in header}
    del df
    if all(c.dtype == object for c in columns.values()):  # an empty record (",,") is text in every column
        blank = np.logical_and.reduce([np.char.strip(c.astype(str)) == "" for c in columns.values()])
        if blank.any():
            kept = np.flatnonzero(~blank)
            return {name: c[kept] for name, c in columns.items()}, lambda i: f"{path}, line {line(int(kept[i]))}"
    return columns, lambda i: f"{path}, line {line(i)}"


class Observations(eqx.Module):
    """Observed means and covariances of ``names`` at times ``ts``, with the covariance ``Σ`` of their vector.

    Build with :meth:`from_paths` (trajectories: ``Σ`` in full, cross-time
    correlations included) or :meth:`from_statistics` (measured statistics
    with standard errors: ``Σ = diag(se²)``, correlations unknown and ignored).

    A statistic of zero variance (every path the same there: a deterministic start; a standard error of 0) carries
    no information: its row and column of ``Σ`` are zero, a fit passes it by (:attr:`used`) and :attr:`note` says so.
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
        labels = statistic_labels(self.ts, self.names)
        finite = np.all(np.isfinite(self.covariance), axis=1)
        if not finite.all():
            bad = labels[int(np.argmin(finite))]
            raise ValueError(f"Observations: the covariance of the statistic {bad} is not finite.")
        var = np.diag(self.covariance)
        if np.any(var < 0):
            a = int(np.argmin(var))
            raise ValueError(f"Observations: the statistic {labels[a]} has variance {var[a]:g}; it must be ≥ 0.")
        zero = var == 0
        if zero.all():
            raise ValueError(
                f"Observations: every statistic of {self.names} has zero variance (every path the same), so none "
                "carries information to fit."
            )
        tied = np.flatnonzero(zero & np.any(self.covariance != 0, axis=1))
        if tied.size:
            raise ValueError(
                f"Observations: the statistic {labels[tied[0]]} has zero variance but covariances with others; "
                "a covariance matrix cannot."
            )

    @classmethod
    def from_paths(cls, ts, paths, names) -> Observations:
        """Trajectories ``paths (n_paths, len(ts), len(names))`` observed at ``ts``.

        Statistics with zero variance (a component the same on every path at a time, such as a deterministic
        initial state) carry no information: a fit leaves them out, and :attr:`note` says so.

        Arguments:
            ts: the observation times ``(T,)``.
            paths: ``(n_paths, T, k)`` finite real values, more paths than the informative statistics they give
                plus 2.
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
        ts = _real("ts", ts)
        names = tuple(str(n) for n in names)
        z = _real("paths", paths)
        if z.ndim != 3 or z.shape[1:] != (len(ts), len(names)):
            raise ValueError(f"paths has shape {z.shape}; expected (n_paths, {len(ts)}, {len(names)}).")
        if not np.all(np.isfinite(z)):
            raise ValueError("paths contains non-finite values; drop the failed paths first.")
        n = z.shape[0]
        same = np.all(z == z[:1], axis=0)  # (T, k): a component every path has alike at a time
        i, j = np.triu_indices(len(names))
        zero = np.concatenate([same, same[:, i] | same[:, j]], axis=-1).reshape(-1)
        size = int(np.sum(~zero))
        if n <= size + 2:
            raise ValueError(
                f"{n} paths cannot estimate the {size}×{size} covariance of the statistics; "
                f"observe more than {size + 2} paths, or fewer times or components."
            )
        mean, cov, covariance = _sample_statistics(z)
        covariance[zero, :] = covariance[:, zero] = 0.0  # exactly: the rounding of z − mean is no information
        return cls(
            ts=ts,
            mean=mean,
            cov=cov,
            covariance=covariance,
            names=names,
            n_paths=n,
            from_trajectories=True,
        )

    @classmethod
    def from_statistics(cls, ts, names, mean, cov, mean_se, cov_se, n_paths: int, *, covariance=None) -> Observations:
        """Measured ``mean (T, k)``, ``cov (T, k, k)`` with standard errors, from ``n_paths`` paths.

        A standard error of 0 marks a statistic without information (a deterministic value): a fit leaves it out,
        and :attr:`note` says so.

        Arguments:
            ts: the observation times ``(T,)``.
            names: the ``k`` observed components.
            mean, cov: ``(T, k)`` and ``(T, k, k)``, real; the variances (``cov``'s diagonal) ≥ 0.
            mean_se, cov_se: their standard errors, same shapes, ≥ 0.
            n_paths: the number of paths they were measured on.
            covariance: the full covariance ``Σ`` of the statistic vector (:func:`statistic_labels` names its
                entries), correlations across times included, if known; its diagonal must be the ``se²``.

        Returns:
            observations with ``Σ = covariance``, else ``Σ = diag(se²)`` with correlations ``"unknown"``: then
            :func:`~nhsde.fit.estimate` takes the correlations from the model at its estimate where the model
            can give them, and otherwise warns and inflates the errors by ``χ²/dof``.
        """
        ts = _real("ts", ts)
        names = tuple(str(n) for n in names)
        mean, cov, mean_se, cov_se = (
            _real(label, a) for label, a in zip(("mean", "cov", "mean_se", "cov_se"), (mean, cov, mean_se, cov_se))
        )
        t, k = len(ts), len(names)
        if mean.shape != (t, k) or cov.shape != (t, k, k):
            raise ValueError(
                f"mean {mean.shape} and cov {cov.shape} must be ({t}, {k}) and ({t}, {k}, {k}) for {t} times and "
                f"names {names}."
            )
        if mean_se.shape != mean.shape or cov_se.shape != cov.shape:
            raise ValueError(
                f"mean_se {mean_se.shape} and cov_se {cov_se.shape} must match mean {mean.shape} and cov {cov.shape}."
            )
        for label, a in (("mean", mean), ("cov", cov), ("mean_se", mean_se), ("cov_se", cov_se)):
            if not np.all(np.isfinite(a)):
                raise ValueError(
                    f"{label} holds non-finite values ({a[~np.isfinite(a)][0]}); every entry must be finite."
                )
        n_paths = int(n_paths)
        if n_paths < 2:
            raise ValueError(f"n_paths={n_paths}; must be ≥ 2.")
        labels = statistic_labels(ts, names)
        per = statistic_size(1, k)
        variances = np.diagonal(cov, axis1=1, axis2=2)
        if np.any(variances < 0):
            a, b = np.unravel_index(int(np.argmin(variances)), variances.shape)
            raise ValueError(
                f"cov: the variance cov[{names[b]},{names[b]}] at t={ts[a]:g} is {variances[a, b]:g}; "
                "a variance must be ≥ 0."
            )
        se = np.asarray(statistic_vector(mean_se, cov_se))
        if np.any(se < 0):
            a = int(np.argmin(se))
            label = "mean_se" if a % per < k else "cov_se"
            raise ValueError(f"{label}: the standard error of {labels[a]} is {se[a]:g}; a standard error must be ≥ 0.")
        if covariance is not None:
            covariance = _real("covariance", covariance)
            if covariance.shape != (se.size, se.size) or not np.allclose(covariance, covariance.T, rtol=1e-10):
                raise ValueError(
                    f"covariance has shape {covariance.shape}; expected a symmetric ({se.size}, {se.size}) matrix."
                )
            off = np.flatnonzero(~np.isclose(np.diag(covariance), se**2, rtol=1e-6, atol=0))
            if off.size:
                label = labels[off[0]]
                raise ValueError(
                    f"covariance: its diagonal at {label} is {np.diag(covariance)[off[0]]:g}, but the standard "
                    f"error given there squares to {se[off[0]] ** 2:g}."
                )
            covariance = np.array(covariance)
            zero = se == 0
            covariance[zero, :] = covariance[:, zero] = 0.0
        return cls(
            ts=ts,
            mean=mean,
            cov=cov,
            covariance=np.diag(se**2) if covariance is None else covariance,
            names=names,
            n_paths=n_paths,
            from_trajectories=False,
            correlations="unknown" if covariance is None else "given",
        )

    @property
    def used(self) -> np.ndarray:
        """Indices of the statistics a fit uses: those of nonzero variance."""
        return np.flatnonzero(np.diag(self.covariance) > 0)

    @property
    def note(self) -> str:
        """What a fit leaves out: the statistics of zero variance, which carry no information ("" where none)."""
        return _zero_variance_note(self.ts, self.names, self.covariance)

    def with_correlations(self, covariance, source: str = "model") -> Observations:
        """These observations with ``Σ = D R D``: ``R`` the correlations of ``covariance``, ``D`` this ``Σ``'s
        standard errors (so the data keep their own errors and gain correlations across times); the statistics of
        zero variance stay left out."""
        covariance = np.asarray(covariance, np.float64)
        used = np.ix_(self.used, self.used)
        scale = np.sqrt(np.diag(covariance))[self.used]
        se = np.sqrt(np.diag(self.covariance))[self.used]
        out = np.zeros_like(self.covariance)
        out[used] = se[:, None] * (covariance[used] / np.outer(scale, scale)) * se[None, :]
        return Observations(
            ts=self.ts,
            mean=self.mean,
            cov=self.cov,
            covariance=out,
            names=self.names,
            n_paths=self.n_paths,
            from_trajectories=self.from_trajectories,
            correlations=source,
        )

    @classmethod
    def _from_table(cls, columns: dict, row: Callable[[int], str], where: str, names, system, n_paths):
        """A per-path table (it has a column ``path``) or a summary table (one row per time).

        ``columns`` is emptied once read: what it held need not outlive the reading of a large file."""
        if not columns or not len(next(iter(columns.values()))):
            raise ValueError(f"{where} holds no data rows.")
        if "path" in columns:
            if n_paths is not None:
                raise ValueError(f"n_paths={n_paths}: {where} is a per-path table; its paths are counted.")
            ts, paths, names = _per_path_table(columns, row, where, names, system)
            columns.clear()
            return cls.from_paths(ts, paths, names)
        return cls.from_statistics(*_summary_table(columns, row, where, names, system, n_paths))

    @classmethod
    def from_csv(cls, file, *, names=None, n_paths: int | None = None, system=None) -> Observations:
        """Observations from a CSV file, per path or summary (the layouts of this module), read by pandas' C parser.

        The first line names the columns; empty lines and lines starting with ``#`` are skipped, and a UTF-8
        byte-order mark (Excel's) is dropped.  Unknown columns, missing, non-numeric or complex values, negative
        variances or standard errors, repeated times and ragged paths (a path without a time others have) are
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
        columns, row = _read_csv(path)
        return cls._from_table(columns, row, str(path), names, system, n_paths)

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
        A run file starts at its deterministic initial state, whose statistics of zero variance a fit leaves out.

        Arguments:
            ds: the dataset.
            names, n_paths, system: as for :meth:`from_csv`.
        """
        if not hasattr(ds, "data_vars") or not hasattr(ds, "to_dataframe"):
            raise TypeError(f"ds={type(ds).__name__}; expected an xarray Dataset.")
        if not len(ds.data_vars):
            raise ValueError(
                "ds holds no data variables; expected paths over path × time × name, or mean, cov, mean_se, cov_se "
                "over time × name (× name2), or component variables over (path, t) or t."
            )
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
