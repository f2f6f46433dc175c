"""nhsde.plot: what each helper draws, and that nhsde itself does not import matplotlib."""

import subprocess
import sys

import matplotlib

matplotlib.use("Agg")

import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np
import pytest
from matplotlib.patches import Ellipse
from scipy import stats

import nhsde
from nhsde import plot
from nhsde.scenes import BallOnVibratingPlane, ball_covariances


def test_core_does_not_import_matplotlib():
    code = "import sys, nhsde, nhsde.plot, nhsde.fit; assert 'matplotlib' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)


def test_band_spans_the_standard_errors():
    ts, value, se = np.linspace(0, 1, 5), np.arange(5.0), np.full(5, 0.5)
    ax = plot.band(None, ts, value, se, theory=value + 0.1, label="mc")
    (poly,) = ax.collections
    vertices = poly.get_paths()[0].vertices
    assert np.isclose(vertices[:, 1].min(), -1.0) and np.isclose(vertices[:, 1].max(), 5.0)
    assert [line.get_label() for line in ax.lines] == ["mc", "theory"]
    with pytest.raises(ValueError, match="must have one shape"):
        plot.band(ax, ts, value, se[:3])
    plt.close("all")


def test_drift_curves_of_the_ball_against_the_closed_form(tmp_path):
    scene = BallOnVibratingPlane(eps=0.6)
    ens = nhsde.simulate(
        scene.build(),
        scene.initial_state(),
        jax.random.key(0),
        n_paths=256,
        t1=2.0,
        dt=0.01,
        solver="sra1",
        save=nhsde.Save(n=11),
    )
    delta = float(scene.params.delta)

    def theory(ts):
        kxx = np.asarray(ball_covariances(jnp.asarray(ts), 0.6, 1.0, delta)[0])
        return np.zeros((len(ts), 2)), kxx[:, None, None] * np.eye(2)

    axes = plot.drift_curves(nhsde.statistics.drift_statistics(ens), theory=theory)
    assert len(axes) == 2
    # fluctuation panel: markers of K[x,x], K[y,y] and the theory line ending at k_xx(t1)
    lines = axes[1].lines
    np.testing.assert_allclose(lines[0].get_ydata(), ens.cov[:, 0, 0])
    np.testing.assert_allclose(lines[-1].get_ydata()[-1], ball_covariances(2.0, 0.6, 1.0, delta)[0], rtol=1e-12)
    axes[0].figure.savefig(tmp_path / "drift.png")
    assert (tmp_path / "drift.png").stat().st_size > 1000
    plt.close("all")


def test_density_band_is_the_binomial_error_of_the_theory():
    x = np.random.default_rng(0).normal(size=20000)
    ax = plot.density(None, x, stats.norm.pdf, bins=20, range=(-4, 4))
    (stairs,) = [p for p in ax.patches]
    heights = stairs.get_data().values
    edges = np.linspace(-4, 4, 21)
    p = np.diff(stats.norm.cdf(edges))  # exact bin probabilities: Simpson must reproduce them
    band_poly = ax.collections[0].get_paths()[0].vertices[:, 1]
    assert np.isclose(band_poly.max(), (p / 0.4 + 2 * np.sqrt(20000 * p * (1 - p)) / (20000 * 0.4)).max(), rtol=1e-6)
    z = (heights * 20000 * 0.4 - 20000 * p) / np.sqrt(20000 * p * (1 - p))
    assert np.all(np.abs(z) < 4), z  # normal samples fit their own density
    plt.close("all")


def test_poincare_section_and_confidence_ellipse():
    orbits = [np.c_[np.cos(np.arange(50.0)), np.sin(np.arange(50.0))], np.array([[0.5, 0.5], [np.nan, 1.0]])]
    ax = plot.poincare_section(None, orbits, labels=("θ", "p_θ"))
    assert [len(c.get_offsets()) for c in ax.collections] == [50, 1]
    assert ax.get_xlabel() == "θ"
    with pytest.raises(ValueError, match="orbit 0 has shape"):
        plot.poincare_section(ax, [np.zeros((3, 3))])
    cov = np.array([[4.0, 0.0], [0.0, 1.0]])
    plot.confidence_ellipse(ax, [1.0, 2.0], cov, n_sigma=2.0)
    (ellipse,) = [p for p in ax.patches if isinstance(p, Ellipse)]
    assert np.isclose(ellipse.width, 8.0) and np.isclose(ellipse.height, 4.0)
    assert np.isclose(ellipse.angle % 180, 0.0)
    plt.close("all")


def test_save_writes_the_figure_where_the_notebooks_are_told(tmp_path, monkeypatch):
    monkeypatch.setenv("NHSDE_NOTEBOOK_OUT", str(tmp_path / "figures"))
    fig, ax = plt.subplots()
    ax.plot([0, 1], [1, 0])
    path = plot.save(fig, "line.png")
    assert path == tmp_path / "figures" / "line.png" and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not plt.fignum_exists(fig.number)  # closed outside Jupyter
    monkeypatch.delenv("NHSDE_NOTEBOOK_OUT")
    monkeypatch.chdir(tmp_path)
    assert plot.figure_dir().resolve() == (tmp_path / "_output").resolve()
