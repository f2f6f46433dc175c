"""Never silently wrong: the stability limit, the one failure channel and the standard errors hold when traced.

Each test is a row of the table of cases that used to go wrong silently under ``jit``, ``grad`` and ``vmap``.
"""

import functools
import os
import signal
import subprocess
import sys
import threading
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhsde
from nhsde import MomentSums, StateLayout, StochasticSystem
from nhsde.scenes import BallOnVibratingPlane
from nhsde.statistics import fluctuation_drift

KEY = jax.random.key(0)
RUNTIME_ERRORS = (eqx.EquinoxRuntimeError, jax.errors.JaxRuntimeError)


DOOMED = StochasticSystem(  # dy = y³ dt from y0 = 10 blows up at t = 0.005
    drift_fn=lambda t, y, p: y**3,
    diffusion_fn=lambda t, y, p: p * jnp.ones((1, 1), y.dtype),
    params=jnp.float32(1e-3),
    layout=StateLayout(("y",), ("independent_coordinate",)),
    noise_dim=1,
    additive_noise=True,
)


def k_xx(eps, dt=0.1, solver="euler", n_paths=64):
    """The README's statistic: K_xx(t1) of the ball, a function of a (possibly traced) friction."""
    scene = BallOnVibratingPlane(eps=eps, nu=1.0)
    ens = nhsde.simulate(scene.build(), scene.initial_state(), KEY, n_paths=n_paths, t1=1.0, dt=dt, solver=solver)
    return fluctuation_drift(ens)[-1, 0, 0]


def test_gradient_beyond_the_stability_limit_is_refused():
    """value_and_grad at ε·dt = 1.1 (Euler) used to return K_xx = 3.4e72 and gradients of 1e73."""
    with pytest.raises(Exception, match="stability limit") as info:
        jax.value_and_grad(k_xx)(11.0)
    assert "solver='exponential'" in str(info.value)


@pytest.mark.parametrize("solver", ["euler", "heun", "milstein", "heun2", "sra1"])
def test_the_stability_limit_is_inclusive_plain_and_jitted(solver):
    """Euler at exactly ε·dt = 1 gave k_uu = 9.6 against 0.0128; Heun2 exactly 0 (its noise response
    1 + λh/2 vanishes there, and |R(λh)| = 1); SRA1 26× the exact value."""
    with pytest.raises(ValueError, match=f"solver '{solver}' is unstable .* stability limit"):
        k_xx(10.0, solver=solver)
    if solver in ("euler", "heun2"):  # traced: the same limit inside the run (one compiled run per solver)
        with pytest.raises(RUNTIME_ERRORS, match="stability limit"):
            jax.jit(lambda e: k_xx(e, solver=solver))(10.0)


def test_one_unstable_point_under_vmap_names_the_stability_limit():
    """vmap over [1, 150] at dt = 0.01 used to say only 'some paths failed', or nothing at all."""
    with pytest.raises(RUNTIME_ERRORS, match="stability limit"):
        jax.vmap(lambda e: k_xx(e, dt=0.01))(jnp.array([1.0, 150.0]))


def test_stationary_variance_off_by_more_than_ten_percent_warns_with_the_factor_and_the_step():
    """Euler on u̇ = −2εu + noise: stationary variance factor 1/(1 − εh) (S0 (3.1), KP §9.8); εh = 1/2 gives 2."""
    with pytest.warns(
        nhsde.StationaryVarianceWarning, match=r"stationary variance 2× the exact one .* dt ≤ 0.0125 brings it within"
    ):
        k_xx(5.0)
    # 1/(1 − εh) ≤ 1.1 needs εh ≤ 1/11: dt = 0.1/8 is the first halving under it (εh = 0.0625: 1.067)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        k_xx(0.5)  # εh = 0.05: factor 1.053


def test_all_paths_failed_under_jit_fails_every_output():
    """With on_failure='exclude' under jit, cov came back NaN and cov_se 0; only mean carried the guard."""
    doomed = DOOMED

    def run(scale):
        ens = nhsde.simulate(
            doomed, jnp.full(1, 10.0, jnp.float32) * scale, KEY, n_paths=64, t1=1.0, dt=0.01, on_failure="exclude"
        )
        return ens.mean, ens.cov, ens.mean_se, ens.cov_se

    for pick in range(4):
        with pytest.raises(RUNTIME_ERRORS, match="fewer than 4 paths succeeded"):
            jax.block_until_ready(jax.jit(lambda s, i=pick: run(s)[i])(jnp.float32(1.0)))


def test_reverse_mode_with_excluded_paths_equals_forward_mode_on_every_moment():
    """dy = y² dt + s dW from y0 = 1 blows up on some paths: the gradients of the survivors' covariance agree."""

    def cov_y(scale):
        system = StochasticSystem(
            drift_fn=lambda t, y, p: y**2,
            diffusion_fn=lambda t, y, p: p * jnp.ones((1, 1), y.dtype),
            params=scale,
            layout=StateLayout(("y",), ("independent_coordinate",)),
            noise_dim=1,
            additive_noise=True,
        )
        ens = nhsde.simulate(system, jnp.ones(1, jnp.float64), KEY, n_paths=256, t1=1.0, dt=0.01, on_failure="exclude")
        return ens.cov[-1, 0, 0] + ens.mean[-1, 0]

    scale = jnp.float64(1.0)
    forward, reverse = jax.jacfwd(cov_y)(scale), jax.grad(cov_y)(scale)
    assert np.isfinite(forward)
    np.testing.assert_allclose(reverse, forward, rtol=1e-10)


def test_covariance_standard_errors_are_never_zero_for_a_non_degenerate_sample():
    """At 4 paths the fourth-moment estimate went negative and was clipped: cov_se was exactly 0.

    The variance of the unbiased covariance is (μ₂₂ − σ²)/n + (σ_ii σ_jj + σ_ij²)/(n(n − 1)); for Gaussian
    data (μ₂₂ = σ_ii σ_jj + 2σ_ij²) it is (σ_ii σ_jj + σ_ij²)/(n − 1), which the estimate must approach.
    """

    def cov_se(z, valid):
        return MomentSums.zeros(jnp.zeros((1, 2))).add_paths(z, valid).statistics()[3]

    rng = np.random.default_rng(0)
    counts = np.repeat([4, 5, 8], 50)  # 50 samples of each size, padded to 64 rows: one compiled program for all
    z = rng.standard_normal((len(counts), 64, 1, 2)) * (np.arange(64)[None, :] < counts[:, None])[..., None, None]
    small = jax.jit(jax.vmap(cov_se))(jnp.asarray(z), jnp.arange(64)[None, :] < jnp.asarray(counts)[:, None])
    assert np.all(np.asarray(small) > 0)
    # large n: the estimate of Var(s_01) against the Gaussian closed form with σ = [[1, ρ], [ρ, 1]]
    rho, n = 0.6, 64 * 1024  # the relative error of the estimate is about 1.2 % here: 5 % is 4 of them
    z = rng.multivariate_normal([0, 0], [[1, rho], [rho, 1]], size=n)[:, None, :]
    cov_se = jax.jit(cov_se)(jnp.asarray(z), jnp.ones(n, bool))
    np.testing.assert_allclose(float(cov_se[0, 0, 1]) ** 2, (1 + rho**2) / (n - 1), rtol=0.05)
    np.testing.assert_allclose(float(cov_se[0, 0, 0]) ** 2, 2 / (n - 1), rtol=0.05)


# Bounds on hangs, not measurements: a loaded 2-core machine may take minutes to import and compile; a run that
# honours Ctrl-C stops within seconds of the signal, a run that ignores it never does.
READY_WITHIN_S = 600
STOPPED_WITHIN_S = 120
# The child's SIGINT disposition is set, not inherited: a suite started as `nohup … &` from a non-interactive shell
# passes SIGINT ignored to its children, and a run is right to honour that.
WITH_DEFAULT_SIGINT = (
    "import os, signal, sys; signal.signal(signal.SIGINT, signal.SIG_DFL); os.execv(sys.argv[1], sys.argv[1:])"
)


def _started_solving(command, tmp_path) -> tuple[subprocess.Popen, list[str], threading.Thread]:
    """Start ``command`` with SIGINT at its default disposition; return once its progress meter reports the compiled
    solve running (diffrax's tqdm bar, drawn from inside the compiled loop), with the stderr read so far and the
    thread that reads it (to the end of the child's stderr)."""
    child = subprocess.Popen(
        [sys.executable, "-c", WITH_DEFAULT_SIGINT, *command],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=dict(os.environ, NHSDE_COMPILATION_CACHE="off"),
        cwd=tmp_path,
    )
    err: list[str] = []
    ready = threading.Event()

    def read():
        assert child.stderr is not None
        while chunk := child.stderr.read1(4096):  # pyright: ignore[reportAttributeAccessIssue]
            err.append(chunk.decode(errors="replace"))
            if "%|" in "".join(err[-2:]):  # tqdm's bar: the solve runs
                ready.set()
        ready.set()  # the child ended: the caller sees it in poll()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    if not ready.wait(READY_WITHIN_S):
        child.kill()
        raise AssertionError(f"no progress within {READY_WITHIN_S} s (a hang bound): {''.join(err)[-2000:]}")
    assert child.poll() is None, "".join(err)
    return child, err, reader


def test_ctrl_c_stops_a_long_cli_run_within_seconds(tmp_path):
    """A `nhsde simulate` estimated at hours used to ignore SIGINT until the solve ended."""
    command = [sys.executable, "-m", "nhsde.runs", "simulate", "ball-on-vibrating-plane", "--progress"]
    command += ["--paths", "4096", "--t1", "100000", "--dt", "0.01"]
    child, err, reader = _started_solving(command, tmp_path)
    child.send_signal(signal.SIGINT)
    child.wait(timeout=STOPPED_WITHIN_S)
    reader.join(timeout=STOPPED_WITHIN_S)  # the child's last words
    text = "".join(err)
    assert child.returncode == 130, text
    assert text.strip().splitlines()[-1].startswith("nhsde simulate: interrupted"), text


def test_ctrl_c_stops_a_long_solve_from_python(tmp_path):
    """From Python the KeyboardInterrupt used to arrive only when the solve ended."""
    script = (
        "import diffrax, jax, nhsde\n"
        "scene = nhsde.scenes.BallOnVibratingPlane()\n"
        "try:\n"
        "    nhsde.simulate(scene.build(), scene.initial_state(), jax.random.key(0), n_paths=4096, t1=1e5, dt=0.01,\n"
        "                   progress_meter=diffrax.TqdmProgressMeter())\n"
        "except KeyboardInterrupt:\n"
        "    print('interrupted', flush=True)\n"
    )
    child, err, _ = _started_solving([sys.executable, "-c", script], tmp_path)
    child.send_signal(signal.SIGINT)
    out, _ = child.communicate(timeout=STOPPED_WITHIN_S)
    assert out.decode().strip() == "interrupted", "".join(err)


def test_cli_warns_on_a_terminal_when_started_with_sigint_ignored():
    """Started as `nohup … &` (SIGINT ignored, inherited), the command cannot be stopped by Ctrl-C: it says so, on a
    terminal only (a pipe or a log file gets nothing)."""
    import pty

    script = (
        "import signal, sys; signal.signal(signal.SIGINT, signal.SIG_IGN)\n"
        "from nhsde.runs import main; sys.exit(main(['scenes']))"
    )
    for terminal in (True, False):
        primary, secondary = pty.openpty() if terminal else os.pipe()
        child = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.DEVNULL, stderr=secondary)
        os.close(secondary)
        chunks = []
        while True:
            try:
                chunk = os.read(primary, 4096)
            except OSError:  # a pty's reader sees EIO once the child closed it
                break
            if not chunk:
                break
            chunks.append(chunk)
        os.close(primary)
        assert child.wait(timeout=STOPPED_WITHIN_S) == 0
        assert ("Ctrl-C cannot stop this run" in b"".join(chunks).decode()) is terminal


def test_derivatives_alone_beyond_the_stability_limit_are_refused():
    """jit(grad(k_xx)) at ε·dt = 25·0.05 used to return 4.7e9 silently: the check rode on the primal output alone,
    which XLA removes when only derivatives are returned; jit(vmap(jacfwd)) over ε = (1, 25, 2) likewise."""
    f = functools.partial(k_xx, dt=0.05)
    with pytest.raises(RUNTIME_ERRORS, match="stability limit"):
        jax.jit(jax.grad(f))(25.0)
    with pytest.raises(RUNTIME_ERRORS, match="stability limit"):
        jax.jit(jax.vmap(jax.jacfwd(f)))(jnp.asarray([1.0, 25.0, 2.0]))
    assert np.isfinite(float(jax.jit(jax.grad(f))(2.0)))  # before the limit: a derivative


def test_traced_parameter_range_message_under_jit_and_filter_jit():
    """jax.jit(k_xx)(-1.0): JAX wraps a run-time check's message in its own error (equinox.filter_jit in its own
    frame); the library's message is in it, with the cause and the range."""
    with pytest.raises(eqx.EquinoxRuntimeError, match="parameter eps must be finite and ≥ 0"):
        eqx.filter_jit(k_xx)(jnp.asarray(-1.0))
    with pytest.raises(jax.errors.JaxRuntimeError, match="parameter eps must be finite and ≥ 0"):
        jax.jit(k_xx)(-1.0)


def test_cli_run_where_every_path_overflows_prints_one_line(tmp_path):
    """nu = 1e30 in float32: every path's fourth moments overflow; this used to be a 46-line traceback."""
    env = dict(os.environ, NHSDE_COMPILATION_CACHE="off")
    command = [sys.executable, "-m", "nhsde.runs", "simulate", "ball-on-vibrating-plane"]
    command += ["--paths", "64", "--t1", "0.1", "--dt", "0.01", "--set", "nu=1e30"]
    out = subprocess.run(command, capture_output=True, text=True, env=env, cwd=tmp_path, timeout=300)
    assert out.returncode == 1, out.stderr
    assert out.stderr.strip().splitlines() == [
        "nhsde simulate: moment_sensitivities: 64 of 64 paths failed (or their tangents were not finite): fewer than 4 "
        "paths succeeded (the others failed on a non-finite state, a blow-up, an angle past its precision's "
        "resolution, or a solver error); statistics and their standard errors need ≥ 4; nu = 1e+30 is "
        "beyond 4.29e+09, where fourth moments overflow in float32: the scale is the likely cause, not the step; "
        "rescale the units (or use float64 states)."
    ]  # (the advice was "try a smaller dt or a stiffer-stable solver": the cause is the scale, not the step)


def test_a_huge_initial_state_is_named_as_the_cause_not_the_step():
    scene = BallOnVibratingPlane(nu=1.0)
    with pytest.raises(nhsde.SimulationError, match="initial state = 1e.30 is beyond .* the scale is the likely"):
        nhsde.simulate(scene.build(), jnp.full(4, 1e30, jnp.float32), KEY, n_paths=64, t1=0.1, dt=0.01)
    doomed = DOOMED  # at an ordinary scale: the step is advised
    with pytest.raises(nhsde.SimulationError, match="try a smaller dt"):
        nhsde.simulate(doomed, jnp.full(1, 10.0, jnp.float32), KEY, n_paths=64, t1=1.0, dt=0.01)


@pytest.mark.parametrize("solver, factor", [("euler", 2.0), ("heun2", 2 / 3)])
def test_the_warned_variance_factor_is_what_the_solver_delivers(solver, factor):
    """At εh = 1/2 on the ball: Euler–Maruyama's stationary k_uu is 1/(1 − εh) = 2 times the exact one, weak order 2's
    (1 + λh/2)²h / (1 − R²) · 2|λ| = 2/3 (R = 1 + λh + (λh)²/2, λh = −1); simulated, within 4 standard errors."""
    scene = BallOnVibratingPlane(eps=10.0, nu=1.0, drift=False)
    with pytest.warns(nhsde.StationaryVarianceWarning, match=rf"stationary variance {factor:.3g}× the exact one"):
        ens = nhsde.simulate(scene.build(), scene.initial_state(), KEY, n_paths=4096, t1=1.0, dt=0.05, solver=solver)
    exact = float(nhsde.scenes.ball_covariances(1.0, 10.0, 1.0, 5 / 7)[2])  # k_uu at 2εt = 20: stationary
    assert abs(float(ens.cov[-1, 0, 0]) - factor * exact) < 4 * float(ens.cov_se[-1, 0, 0])


def test_a_blow_up_with_finite_values_fails_its_paths_plain_and_under_jit_grad():
    """Beghin's servo plate (S1 (3.4)): β̈ = (R b/(b² + k²)) β̇² + …, a Riccati blow-up once a kick makes β̇ large.
    At ν = 1e3 the Milstein paths grew doubly exponentially to 1e56 and stayed there (α − β rounded to nothing), so
    simulate returned finite means of 1e54, and value_and_grad numbers 0.45 % from the plain call's."""
    scene = nhsde.scenes.BeghinPlate(eps=1.0, nu=1e3)
    system, y0 = scene.build(), scene.initial_state()

    def mean_rate(eps):
        run = system.replace_params(eps=eps)
        ens = nhsde.simulate(run, y0, KEY, n_paths=16, t1=0.25, dt=0.0125, solver="milstein")
        return ens.mean[-1, 2]

    with pytest.raises(nhsde.SimulationError, match="paths failed .*a blow-up"):
        mean_rate(1.0)
    with pytest.raises(RUNTIME_ERRORS, match="a blow-up"):
        jax.block_until_ready(jax.jit(jax.grad(mean_rate))(1.0))


@pytest.mark.parametrize("switched_on", [False, True], ids=["noise on", "noise switched on from 0"])
def test_a_kick_from_rest_is_not_a_blow_up(switched_on):
    """From u = 0 a step's noise multiplies the state's size without bound, and a small first draw makes the next
        step's ratio large: du = −u dt + σ(t) dW keeps every path, its variance ∫₀¹ e^(−2(1−s)) σ(s)² ds within 4
        standard errors.  Measured against the state before, without the largest size and the first kick's exemption,
    σ = 1e3 lost 1 path in 1024 and σ = sin t (zero at the start) 1 in 800."""
    sigma = (lambda t: jnp.sin(t)) if switched_on else (lambda t: 1e3 + 0 * t)
    system = StochasticSystem(
        drift_fn=lambda t, y, p: -p * y,
        diffusion_fn=lambda t, y, p: sigma(t) * jnp.ones((1, 1), y.dtype),
        params=jnp.asarray(1.0),
        layout=StateLayout(("u",), ("velocity",)),
        noise_dim=1,
        additive_noise=True,
    )
    ens = nhsde.simulate(system, jnp.zeros(1), KEY, n_paths=4096, t1=1.0, dt=0.01)
    assert ens.n_failed == 0
    s = np.linspace(0.0, 1.0, 100_001)
    exact = np.trapezoid(np.exp(-2 * (1 - s)) * np.asarray(sigma(s)) ** 2, s)  # Euler's O(h) bias: below 4 se
    assert abs(float(ens.cov[-1, 0, 0]) - exact) < 4 * float(ens.cov_se[-1, 0, 0])


def test_an_angle_past_its_precision_fails_its_path_plain_and_under_jit_grad():
    """A sleigh with its knife under the centre of mass (a = 0) turning at θ̇ = Ω (ν = 0, ε = 1e-3), read through
    cos θ and sin θ; Euler steps h give θ̇ₙ = Ω rⁿ (r = 1 − 2εh) and θ_N = h Ω (1 − r^N)/(1 − r).  In float32 an
    angle resolves to ``eps·|θ|``: at 8e3 rad (below 10⁻³/eps = 8.4e3) the paths run and θ_N is the closed form
    within N roundings of 8e3; at 9e3 rad they fail, plain and under ``jit(grad)``.  Unchecked, a vertical disk kicked
    by ν = 1e30 turned 1e14 rad in 0.25 s in float64, and grad and jacfwd of its statistics parted by 10×."""
    system = nhsde.scenes.ChaplyginSleigh(eps=1e-3, nu=0.0, offset=0.0, drift=True).build()
    assert system.layout.angles == ("theta",)
    h, n = 0.01, 100

    def heading(eps, rate):
        y0 = jnp.asarray([0.0, 0.0, 0.0, 0.0, rate], jnp.float32)
        ens = nhsde.simulate(system.replace_params(eps=eps), y0, KEY, n_paths=64, t1=n * h, dt=h, solver="euler")
        return ens.mean[-1, 2]

    eps = jnp.asarray(1e-3, jnp.float32)
    r = 1 - 2e-3 * h
    assert abs(float(heading(eps, 8e3)) - h * 8e3 * (1 - r**n) / (1 - r)) < n * float(jnp.spacing(jnp.float32(8e3)))
    with pytest.raises(nhsde.SimulationError, match="64 of 64 paths failed.*an angle past its precision's resolution"):
        heading(eps, 9e3)
    with pytest.raises(RUNTIME_ERRORS, match="paths (failed|succeeded) .*an angle past"):
        jax.block_until_ready(jax.jit(jax.grad(heading))(eps, 9e3))


def test_exponential_euler_with_more_noise_channels_than_its_rank_keeps_the_noise():
    """The vertical disk in a bath (soft contact): six channels drive four velocities, so ``PᵀP`` of the exponential
    solver's noise factor is singular.  Its solve gave a non-finite factor: every covariance 0, and ``grad`` nan,
    silently.  The velocities are linear with additive noise, so the solver is exact at any step: at t = 1/4 their
    covariance is ``∫₀ᵗ e^(As) b bᵀ e^(Aᵀs) ds`` (Simpson's rule here) within 4 standard errors, and ``grad`` equals
    forward mode's derivative."""
    import scipy.linalg

    scene = nhsde.scenes.VerticalRollingDiskInBath(eps=1.0, kT=0.5)
    system, y0 = scene.build(), scene.initial_state().astype(jnp.float64)
    a = np.asarray(system.linear_drift(system.params))[4:, 4:]
    b = np.asarray(system.diffusion_fn(0.0, y0, system.params))[4:]
    s = np.linspace(0.0, 0.25, 1001)
    flows = [scipy.linalg.expm(a * si) @ b for si in s]
    weights = np.r_[1, np.tile([4, 2], 499), 4, 1] * (s[1] - s[0]) / 3
    exact = sum(w * f @ f.T for w, f in zip(weights, flows))

    def covariance(eps):  # two programs in all: jvp (values and forward derivative) and grad
        ens = nhsde.simulate(
            system.replace_params(eps=eps), y0, KEY, n_paths=16384, t1=0.25, dt=0.0625, solver="exponential"
        )
        return ens.cov[-1, 4, 4], (ens.cov[-1], ens.cov_se[-1])

    (_, (cov, cov_se)), (forward, _) = jax.jvp(covariance, (1.0,), (1.0,))
    z = (np.diagonal(cov)[4:] - np.diagonal(exact)) / np.diagonal(cov_se)[4:]
    assert np.all(np.abs(z) < 4), z
    grad, _ = jax.grad(covariance, has_aux=True)(1.0)
    assert np.isfinite(grad) and abs(grad - forward) <= 1e-9 * abs(forward), (grad, forward)
