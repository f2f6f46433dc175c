"""Observed statistics: what a fit compares the model with.

A fit compares *statistics* — the mean ``m(t)`` and covariance ``K(t)`` of
named components at observation times — between data and model.  Their vector

    s = [m(t₁), K(t₁)ᵤ, m(t₂), K(t₂)ᵤ, …]        (ᵤ: upper triangle, row by row)

is asymptotically Gaussian with covariance ``Σ``; ``Σ`` is estimated from the
per-path influence functions ``ψ_p = [z_p − m, (z_p − m)(z_p − m)ᵀᵤ − Kᵤ]``
(``Σ = Cov(ψ)/n``) when trajectories are observed, and taken as
``diag(se²)`` when only measured statistics with standard errors are.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

__all__ = ["Observations", "statistic_labels", "statistic_size", "statistic_vector"]


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
    def from_statistics(cls, ts, names, mean, cov, mean_se, cov_se, n_paths: int) -> Observations:
        """Measured ``mean (T, k)``, ``cov (T, k, k)`` with standard errors, from ``n_paths`` paths.

        Arguments:
            ts: the observation times ``(T,)``.
            names: the ``k`` observed components.
            mean, cov: ``(T, k)`` and ``(T, k, k)``.
            mean_se, cov_se: their standard errors, same shapes.
            n_paths: the number of paths they were measured on.

        Returns:
            observations with ``Σ = diag(se²)`` (correlations between the statistics unknown and ignored).
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
        return cls(
            ts=ts,
            mean=mean,
            cov=cov,
            covariance=np.diag(se**2),
            names=tuple(str(n) for n in names),
            n_paths=n_paths,
            from_trajectories=False,
        )

    def statistics(self) -> np.ndarray:
        """The observed :func:`statistic_vector`."""
        return np.asarray(statistic_vector(self.mean, self.cov))

    @property
    def size(self) -> int:
        return statistic_size(len(self.ts), len(self.names))
