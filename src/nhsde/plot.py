"""Matplotlib helpers: drift curves with error bands, densities against theory, Poincaré sections.

matplotlib is imported only when a function here is called, so the rest of
nhsde does not need it (``pip install nhsde[plot]``).  Every function draws on
``ax`` (a new figure's axes if ``None``) and returns the axes it drew on.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

__all__ = [
    "band",
    "confidence_ellipse",
    "density",
    "drift_curves",
    "figure_dir",
    "poincare_section",
    "save",
    "sweep",
]


def figure_dir() -> Path:
    """Where :func:`save` writes: ``$NHSDE_NOTEBOOK_OUT``, else ``notebooks/_output`` from the repository
    root, else ``_output`` in the current directory (created if missing)."""
    out = Path(
        os.environ.get("NHSDE_NOTEBOOK_OUT") or ("notebooks/_output" if Path("notebooks").is_dir() else "_output")
    )
    out.mkdir(parents=True, exist_ok=True)
    return out


def save(fig, name: str, *, dpi: int = 120) -> Path:
    """Write ``fig`` as ``figure_dir()/name``; show it inline in Jupyter, close it otherwise."""
    import matplotlib.pyplot as plt

    path = figure_dir() / name
    fig.savefig(path, dpi=dpi, bbox_inches="tight")
    print(f"saved {path}")
    if "ipykernel" in sys.modules:
        plt.show()
    else:
        plt.close(fig)
    return path


def _axes(ax, n=1, **subplots):
    if ax is not None:
        return ax
    import matplotlib.pyplot as plt

    # constrained layout: the labels fit the figure on a plain savefig
    _, axes = plt.subplots(1, n, figsize=(4.5 * n, 3.6), squeeze=False, layout="constrained", **subplots)
    return axes[0] if n > 1 else axes[0, 0]


def band(
    ax,
    ts,
    value,
    se,
    *,
    n_se: float = 2.0,
    label: str | None = None,
    color=None,
    theory=None,
    theory_ts=None,
    theory_label: str = "theory",
):
    """``value ± n_se·se`` against ``ts`` as markers on a shaded band; ``theory`` (at ``theory_ts``, default
    ``ts``) as a line."""
    ax = _axes(ax)
    ts, value, se = (np.asarray(a, np.float64) for a in (ts, value, se))
    if not ts.shape == value.shape == se.shape:
        raise ValueError(f"band: ts {ts.shape}, value {value.shape} and se {se.shape} must have one shape.")
    (line,) = ax.plot(ts, value, "o", ms=3.5, color=color, label=label)
    ax.fill_between(
        ts, value - n_se * se, value + n_se * se, color=line.get_color(), alpha=0.25, lw=0, label=f"±{n_se:g} SE"
    )
    if theory is not None:
        tt = ts if theory_ts is None else np.asarray(theory_ts, np.float64)
        ax.plot(tt, np.asarray(theory, np.float64), "-", color="k", lw=1.2, label=theory_label)
    return ax


def drift_curves(stats, *, theory: Callable | None = None, axes=None, n_se: float = 2.0):
    """Systematic drift ``m_{q''}(t)`` and fluctuation drift ``K_{q''}(t)`` (diagonal) with error bands, S0 (6.7).

    Arguments:
        stats: a :class:`nhsde.statistics.DriftStatistics` with standard errors (from Monte Carlo).
        theory: ``theory(ts) -> (mean (T, k), cov (T, k, k))``, drawn as lines at 200 times.
        axes: two matplotlib axes (systematic, fluctuation); default a new figure.
        n_se: the half-width of the bands in standard errors.

    Returns:
        the two axes.
    """
    axes = _axes(axes, 2)
    ts = np.asarray(stats.ts, np.float64)
    tt = np.linspace(ts[0], ts[-1], 200)
    th_mean = th_cov = None
    if theory is not None:
        th_mean, th_cov = (np.asarray(a, np.float64) for a in theory(tt))
    for i, name in enumerate(stats.names):
        color = f"C{i}"
        band(axes[0], ts, stats.systematic[:, i], stats.systematic_se[:, i], n_se=n_se, label=f"m[{name}]", color=color)
        band(
            axes[1],
            ts,
            stats.fluctuation[:, i, i],
            stats.fluctuation_se[:, i, i],
            n_se=n_se,
            label=f"K[{name},{name}]",
            color=color,
        )
        if th_mean is not None and th_cov is not None:
            axes[0].plot(tt, th_mean[:, i], "-", color=color, lw=1)
            axes[1].plot(tt, th_cov[:, i, i], "-", color=color, lw=1)
    axes[0].set_title("systematic drift")
    axes[1].set_title("fluctuation drift")
    for ax in axes:
        ax.set_xlabel("t")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    return axes


def density(
    ax,
    samples,
    pdf: Callable,
    *,
    bins: int = 40,
    range: tuple[float, float] | None = None,
    n_se: float = 2.0,
    label: str = "samples",
    theory_label: str = "theory",
):
    """Histogram of ``samples`` against the density ``pdf`` with the band a histogram of that many samples fills.

    A bin with probability ``p`` holds ``n p ± √(n p (1 − p))`` samples, so the
    shaded band is ``n_se`` such errors about the theory; bin probabilities are
    ``pdf`` integrated over each bin (Simpson, 16 panels).

    Arguments:
        ax: matplotlib axes (``None``: a new figure).
        samples: the values (any shape; non-finite ones dropped).
        pdf: the density, vectorised over a 1-d array.
        bins, range: as for ``numpy.histogram``.
        n_se: the half-width of the band in standard errors.
        label, theory_label: legend entries.

    Returns:
        the axes.
    """
    ax = _axes(ax)
    x = np.asarray(samples, np.float64).ravel()
    x = x[np.isfinite(x)]
    if x.size < 2:
        raise ValueError(f"density: {x.size} finite samples; need at least 2.")
    edges = np.histogram_bin_edges(x, bins=bins, range=range)
    counts, _ = np.histogram(x, bins=edges)
    width = np.diff(edges)
    sub = edges[:-1, None] + width[:, None] * np.linspace(0, 1, 17)
    f = np.asarray(pdf(sub.ravel()), np.float64).reshape(sub.shape)
    p = width / 48 * (f[:, 0] + 4 * f[:, 1:-1:2].sum(1) + 2 * f[:, 2:-1:2].sum(1) + f[:, -1])
    n = x.size
    spread = n_se * np.sqrt(n * p * np.clip(1 - p, 0, 1)) / (n * width)
    steps = np.repeat(edges, 2)[1:-1]  # the band follows the bins
    ax.fill_between(
        steps,
        np.repeat(np.maximum(p / width - spread, 0.0), 2),
        np.repeat(p / width + spread, 2),
        color="0.8",
        lw=0,
        label=f"±{n_se:g} SE of a histogram",
    )
    ax.stairs(counts / (n * width), edges, color="C1", lw=1.5, label=label)
    xs = np.linspace(edges[0], edges[-1], 400)
    ax.plot(xs, np.asarray(pdf(xs), np.float64), "k-", lw=1.2, label=theory_label)
    ax.legend(fontsize=8)
    return ax


def poincare_section(ax, points, *, labels=("q", "p"), s: float = 1.0, colors=None):
    """Points of a Poincaré section: ``points`` is a list of ``(n_i, 2)`` arrays, one per orbit (NaN rows skipped)."""
    ax = _axes(ax)
    if isinstance(points, np.ndarray) and points.ndim == 2:
        points = [points]
    for i, orbit in enumerate(points):
        orbit = np.asarray(orbit, np.float64)
        if orbit.ndim != 2 or orbit.shape[1] != 2:
            raise ValueError(f"poincare_section: orbit {i} has shape {orbit.shape}; expected (n, 2).")
        orbit = orbit[np.all(np.isfinite(orbit), axis=1)]
        color = None if colors is None else colors[i % len(colors)]
        ax.scatter(orbit[:, 0], orbit[:, 1], s=s, color=color, lw=0)
    ax.set_xlabel(labels[0])
    ax.set_ylabel(labels[1])
    return ax


def confidence_ellipse(ax, mean, cov, *, n_sigma: float = 2.0, **kwargs):
    """The ellipse ``(θ − mean)ᵀ cov⁻¹ (θ − mean) = n_sigma²`` of a two-parameter estimate."""
    from matplotlib.patches import Ellipse

    ax = _axes(ax)
    mean, cov = np.asarray(mean, np.float64), np.asarray(cov, np.float64)
    if mean.shape != (2,) or cov.shape != (2, 2):
        raise ValueError(f"confidence_ellipse: mean {mean.shape} and cov {cov.shape} must be (2,) and (2, 2).")
    w, v = np.linalg.eigh(cov)
    angle = np.degrees(np.arctan2(v[1, 1], v[0, 1]))
    kwargs.setdefault("fill", False)
    center = (float(mean[0]), float(mean[1]))
    ax.add_patch(Ellipse(center, 2 * n_sigma * np.sqrt(w[1]), 2 * n_sigma * np.sqrt(w[0]), angle=angle, **kwargs))
    ax.autoscale_view()
    return ax


_GREEK = {"eps": r"\varepsilon", "nu": r"\nu", "alpha": r"\alpha", "beta": r"\beta", "gamma": r"\gamma"}


def _symbol(name: str) -> str:
    """A parameter or state name as mathtext: ``eps`` → ε, ``x_dot`` → x_dot (upright, escaped)."""
    return _GREEK.get(name, r"\mathrm{" + name.replace("_", r"\_") + "}")


def _sweep_label(ds, variable: str) -> str:
    """``E[x](t = 10)``, ``Var[x]``, ``Cov[x, y]`` or ``∂E[x]/∂ε`` of a sweep's statistic, for an axis."""
    kind, *names = str(ds.attrs.get("statistic", "")).split() or ["", ""]
    if kind not in ("mean", "cov") or not names:
        return str(ds[variable].attrs.get("long_name", variable))
    quantity = ", ".join(map(_symbol, names))
    if kind == "mean":
        stat = rf"\mathrm{{E}}[{quantity}]"
    else:
        stat = rf"\mathrm{{Var}}[{_symbol(names[0])}]" if len(set(names)) == 1 else rf"\mathrm{{Cov}}[{quantity}]"
    at = f"(t = {float(ds.attrs['t1']):g})" if "t1" in ds.attrs else ""
    if variable.startswith("d_value_d_"):
        return rf"$\partial {stat}{at} / \partial {_symbol(variable.removeprefix('d_value_d_'))}$"
    return f"${stat}{at}$"


def _fixed_text(ds) -> str:
    """The parameters a sweep holds fixed, and its paths: the figure's title."""
    import json

    fixed = json.loads(ds.attrs.get("parameters", "{}"))
    parts = [f"${_symbol(k)} = {v:g}$" for k, v in fixed.items()]
    if "n_paths" in ds.attrs:
        parts.append(f"{int(ds.attrs['n_paths'])} paths")
    return ", ".join(parts)


def sweep(ds, variable: str = "value", *, ax=None, n_se: float = 2.0, cmap: str = "viridis"):
    """A statistic of :func:`nhsde.sweep` over its grid: markers on a band of ``± n_se`` standard errors
    over one parameter, a heat map over two.

    Arguments:
        ds: the dataset :func:`nhsde.sweep` returns (with ``statistic=``, for ``value``).
        variable: what to draw: ``value`` or a derivative ``d_value_d_eps``, …; its ``_se`` gives the band.
        ax: matplotlib axes (``None``: a new figure).
        n_se: the half-width of the band in standard errors (one parameter).
        cmap: the colour map of the heat map (two parameters).

    Returns:
        the axes.
    """
    if variable not in ds:
        have = ", ".join(v for v in map(str, ds.data_vars) if not v.endswith("_se"))
        raise ValueError(f"sweep: ds has no {variable!r} (sweep(..., statistic=...) adds value); it has {have}.")
    dims = [str(d) for d in ds[variable].dims]
    if set(dims) & {"time", "name", "name2"}:
        raise ValueError(f"sweep: {variable!r} varies over {dims}; draw a statistic over the grid alone (value, …).")
    value = ds[variable]
    label = _sweep_label(ds, variable)
    ax = _axes(ax)
    ax.set_title(_fixed_text(ds), fontsize=8)
    if len(dims) == 1:
        band(ax, ds[dims[0]].values, value.values, ds[variable + "_se"].values, n_se=n_se, label=label)
        ax.set_xlabel(f"${_symbol(dims[0])}$")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    elif len(dims) == 2:
        x, y = ds[dims[1]].values, ds[dims[0]].values
        mesh = ax.pcolormesh(x, y, value.values, shading="nearest", cmap=cmap)
        ax.figure.colorbar(mesh, ax=ax, label=label)
        ax.set_xlabel(f"${_symbol(dims[1])}$")
        ax.set_ylabel(f"${_symbol(dims[0])}$")
    else:
        raise ValueError(f"sweep: {variable!r} varies over {dims}; select one or two parameters (ds.isel(...)).")
    return ax
