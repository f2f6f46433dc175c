"""Bad input raises naming the argument and the allowed range; failures are reported, never averaged."""

import math
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhsde
from nhsde import StateLayout, StochasticSystem
from nhsde.scenes import BallOnVibratingPlane, get_scene

BALL = BallOnVibratingPlane()
KEY = jax.random.key(0)


def sim(**kw):
    args: dict[str, Any] = dict(n_paths=64, t1=1.0, dt=0.1)
    args.update(kw)
    system = args.pop("system", BALL.build())
    y0 = args.pop("y0", BALL.initial_state())
    return nhsde.simulate(system, y0, KEY, **args)


@pytest.mark.parametrize(
    "params, match",
    [
        (dict(eps=-1.0), r"eps=-1.0 .*≥ 0"),
        (dict(nu=-0.5), r"nu=-0.5 .*≥ 0"),
        (dict(eps=math.nan), r"eps=nan .*finite"),
        (dict(nu=math.inf), r"nu=inf .*finite"),
        (dict(radius=0.0), r"radius=0.0 .*> 0"),
    ],
)
def test_bad_parameters_are_refused(params, match):
    with pytest.raises(ValueError, match=match):
        BallOnVibratingPlane(**params)


def test_traced_bad_parameter_fails_at_run_time_with_its_name():
    def f(eps):
        return sim(system=BallOnVibratingPlane(eps=eps).build()).cov[-1, 0, 0]

    with pytest.raises(eqx.EquinoxRuntimeError, match="eps must be finite and ≥ 0"):
        jax.grad(f)(-1.0)
    assert np.isfinite(jax.grad(f)(1.0))


def test_unknown_parameter_is_refused():
    with pytest.raises(TypeError, match="mass"):
        BallOnVibratingPlane(mass=2.0)
    with pytest.raises(TypeError, match="no parameter 'mu'"):
        BALL.build().replace_params(mu=1.0)


@pytest.mark.parametrize(
    "kw, exc, match",
    [
        (dict(n_paths=0), ValueError, r"n_paths=0; must be ≥ 4"),
        (dict(n_paths=2), ValueError, r"n_paths=2; must be ≥ 4 \(a covariance and its standard error need 4\)"),
        (dict(n_paths=2**31), ValueError, r"first_path \+ n_paths = 2147483648 exceeds 2147483647"),
        (dict(first_path=2**38), ValueError, r"first_path \+ n_paths = .* exceeds 2147483647"),
        (dict(n_paths=True), TypeError, r"n_paths=True; expected a number"),
        (dict(dt=1e-9), ValueError, r"dt=1e-09 makes 1000000000 steps .* max_steps=10000000"),
        (dict(y0=jnp.zeros(4, jnp.float16)), TypeError, r"y0 has dtype float16"),
        (dict(y0=jnp.zeros(4, jnp.bfloat16)), TypeError, r"y0 has dtype bfloat16"),
        (dict(n_paths=2.5), ValueError, r"n_paths=2.5; must be a whole number"),
        (dict(dt=0.0), ValueError, r"dt=0.0; must be > 0"),
        (dict(dt=-0.1), ValueError, r"dt=-0.1; must be > 0"),
        (dict(dt=math.nan), ValueError, r"dt=nan; must be finite"),
        (dict(dt=0.3), ValueError, r"dt=0.3 must divide t1 − t0"),
        (dict(t1=0.0), ValueError, r"t1=0.0; must be > t0=0.0"),
        (dict(t1=1.0, t0=2.0), ValueError, r"t1=1.0; must be > t0=2.0"),
        (dict(y0=jnp.zeros(3)), ValueError, r"y0 has shape \(3,\); expected \(4,\) or \(64, 4\)"),
        (dict(y0=jnp.array([0.0, jnp.nan, 0, 0])), ValueError, r"y0 contains non-finite"),
        (dict(y0=[0.0, 1j, 0, 0]), TypeError, r"y0 has dtype complex128; expected real values"),
        (dict(solver="rk4"), ValueError, r"solver='rk4'; allowed: euler, milstein, heun, heun2, sra1, exponential"),
        (dict(solver=diffrax.Tsit5()), ValueError, r"solver='Tsit5': not an SDE solver"),
        (dict(solver=diffrax.ShOULD(0.01)), ValueError, r"solver='ShOULD': a Langevin solver"),
        (dict(solver=3), TypeError, r"solver=3; expected one of"),
        (dict(batching=nhsde.Batching), TypeError, r"expected nhsde.Batching"),
        (dict(steps=0.1, dt=None), TypeError, r"expected nhsde.FixedSteps"),
        (dict(steps=nhsde.FixedSteps(0.1)), TypeError, r"give the step once"),
        (dict(save=nhsde.Save(n=4)), ValueError, r"save.n=4: n − 1 must divide the 10 steps"),
        (dict(save=nhsde.Save(names=("z",))), ValueError, r"unknown name 'z'"),
        (dict(on_failure="ignore"), ValueError, r"on_failure='ignore'; allowed"),
        (dict(steps=nhsde.FixedSteps(0.1, brownian_dt=0.03), dt=None), ValueError, r"brownian_dt=0.03 must divide"),
        (dict(steps=nhsde.FixedSteps(0.01, max_steps=50), dt=None), ValueError, r"100 steps .* max_steps=50"),
        (dict(system="ball"), TypeError, r"expected a StochasticSystem"),
    ],
)
def test_bad_simulate_arguments_are_refused(kw, exc, match):
    with pytest.raises(exc, match=match):
        sim(**kw)


@pytest.mark.parametrize(
    "make, exc, match",
    [
        (lambda: nhsde.Batching(chunk_size=100), ValueError, r"chunk_size=100; must be a positive multiple of 64"),
        (lambda: nhsde.Batching(devices=jax.devices()[0]), TypeError, r"devices=.*expected a list of JAX devices"),
        (lambda: nhsde.Batching(devices=jax.devices()[:1] * 2), ValueError, r"lists a device twice"),
        (lambda: nhsde.Batching(devices=[]), ValueError, r"devices is empty"),
        (lambda: nhsde.Batching(checkpoint="no"), TypeError, r"checkpoint='no'; expected True, False or None"),
        (lambda: nhsde.Save(names="xy"), TypeError, r"Save\(names='xy'\); expected a tuple of names"),
        (lambda: nhsde.Save(names=()), ValueError, r"name at least one quantity"),
        (lambda: nhsde.Save(n=1), ValueError, r"Save\(n=1\); must be ≥ 2"),
        (lambda: nhsde.Save(paths="yes"), TypeError, r"Save\(paths='yes'\)"),
        (lambda: nhsde.FixedSteps(0.0), ValueError, r"dt=0.0; must be > 0"),
        (lambda: nhsde.FixedSteps(True), TypeError, r"dt=True; expected a number"),
        (lambda: nhsde.FixedSteps(0.1, brownian_dt=-1.0), ValueError, r"brownian_dt=-1.0; must be > 0"),
        (lambda: nhsde.FixedSteps(0.1, max_steps=0), ValueError, r"max_steps=0; must be ≥ 1"),
        (lambda: nhsde.AdaptiveSteps(0.1, rtol=math.nan), ValueError, r"rtol=nan; must be finite"),
    ],
)
def test_bad_options_are_refused_when_built(make, exc, match):
    with pytest.raises(exc, match=match):
        make()


def test_bad_key_is_refused():
    with pytest.raises(TypeError, match="key"):
        nhsde.simulate(BALL.build(), BALL.initial_state(), 0, n_paths=8, t1=1.0, dt=0.1)
    # legacy uint32 keys are accepted
    nhsde.simulate(BALL.build(), BALL.initial_state(), jax.random.PRNGKey(0), n_paths=8, t1=1.0, dt=0.1)


def test_unknown_scene_is_refused():
    with pytest.raises(ValueError, match="scene 'ball': unknown scene; known scenes: ball-on-vibrating-plane"):
        get_scene("ball")


def explosive():
    """dy = y² dt + dW from y0 = 1: a fraction of paths blows up before t = 1."""
    return StochasticSystem(
        drift_fn=lambda t, y, p: y**2,
        diffusion_fn=lambda t, y, p: p * jnp.ones((1, 1), y.dtype),
        params=jnp.float32(1.0),
        layout=StateLayout(("y",), ("independent_coordinate",)),
        noise_dim=1,
        additive_noise=True,
    )


def test_failed_paths_raise_by_default():
    with pytest.raises(nhsde.SimulationError, match=r"of 512 paths failed"):
        sim(system=explosive(), y0=jnp.ones(1, jnp.float32), n_paths=512, t1=1.0, dt=0.01)


def test_failed_paths_are_excluded_and_counted():
    ens = sim(
        system=explosive(),
        y0=jnp.ones(1, jnp.float32),
        n_paths=512,
        t1=1.0,
        dt=0.01,
        on_failure="exclude",
        save=nhsde.Save(paths=True),
    )
    failed = np.asarray(ens.failed)
    assert 0 < failed.sum() < 512
    assert int(ens.n_used) + failed.sum() == 512
    # a failed path keeps its last finite state (so reverse-mode gradients stay finite), and is left out
    assert np.all(np.isfinite(np.asarray(ens.paths)))
    good = np.asarray(ens.paths, np.float64)[~failed]
    assert np.all(np.isfinite(ens.mean)) and np.all(np.isfinite(ens.cov))
    np.testing.assert_allclose(ens.mean[:, 0], good[:, :, 0].mean(0), rtol=1e-4)


def test_failure_inside_a_transformation_is_an_error():
    def f(scale):
        return sim(system=explosive(), y0=jnp.ones(1, jnp.float32) * scale, n_paths=512, t1=1.0, dt=0.01).mean[-1, 0]

    with pytest.raises((eqx.EquinoxRuntimeError, jax.errors.JaxRuntimeError), match="some paths failed"):
        jax.jit(f)(jnp.float32(1.0))


def test_euler_beyond_its_stability_limit_is_refused_before_the_run():
    """The ball at ε·dt = 1.05 used to return k_uu = 4.8e7 (exact 0.0122) with 0 failed paths."""
    scene = BallOnVibratingPlane(eps=10.5, nu=1.0, drift=False)
    with pytest.raises(ValueError, match=r"dt=0.1: solver 'euler' is unstable .* solver='exponential'"):
        nhsde.simulate(scene.build(), scene.initial_state(), KEY, n_paths=64, t1=1.0, dt=0.1)
    # at ε·dt = 0.945 it runs, and the exponential solver runs at any step
    nhsde.simulate(scene.build(), scene.initial_state(), KEY, n_paths=64, t1=0.9, dt=0.09)
    nhsde.simulate(scene.build(), scene.initial_state(), KEY, n_paths=64, t1=1.0, dt=0.1, solver="exponential")


@pytest.mark.parametrize("on_failure", ["raise", "exclude"])
def test_an_ensemble_without_enough_successful_paths_raises_in_every_mode(on_failure):
    """All paths failed used to give NaN statistics without an error under on_failure='exclude'."""

    def doomed():  # dy = y³ dt from y0 = 10 blows up at t = 0.005
        return StochasticSystem(
            drift_fn=lambda t, y, p: y**3,
            diffusion_fn=lambda t, y, p: p * jnp.ones((1, 1), y.dtype),
            params=jnp.float32(1e-3),
            layout=StateLayout(("y",), ("independent_coordinate",)),
            noise_dim=1,
            additive_noise=True,
        )

    with pytest.raises(nhsde.SimulationError, match="paths"):
        sim(system=doomed(), y0=jnp.full(1, 10.0, jnp.float32), n_paths=64, t1=1.0, dt=0.01, on_failure=on_failure)
    with pytest.raises((eqx.EquinoxRuntimeError, jax.errors.JaxRuntimeError), match="fewer than 4 paths"):
        jax.jit(
            lambda s: (
                sim(
                    system=doomed(),
                    y0=jnp.full(1, 10.0, jnp.float32) * s,
                    n_paths=64,
                    t1=1.0,
                    dt=0.01,
                    on_failure="exclude",
                ).mean
            )
        )(jnp.float32(1.0))


def test_reverse_mode_with_excluded_paths_equals_forward_mode():
    """Reverse-mode gradients used to be NaN once any path was excluded, while forward mode was finite."""

    def mean_y(scale):
        system = explosive()
        system = StochasticSystem(
            drift_fn=lambda t, y, p: y**2,
            diffusion_fn=lambda t, y, p: p * jnp.ones((1, 1), y.dtype),
            params=scale,
            layout=system.layout,
            noise_dim=1,
            additive_noise=True,
        )
        ens = sim(system=system, y0=jnp.ones(1, jnp.float64), n_paths=256, t1=1.0, dt=0.01, on_failure="exclude")
        return ens.mean[-1, 0]

    scale = jnp.float64(1.0)
    forward, reverse = jax.jacfwd(mean_y)(scale), jax.grad(mean_y)(scale)
    assert np.isfinite(forward)
    np.testing.assert_allclose(reverse, forward, rtol=1e-10)


@pytest.mark.parametrize(
    "params, exc, match",
    [
        (dict(eps=[0.5, 2.0]), ValueError, r"parameter eps has shape \(2,\); eps is one number"),
        (dict(eps=True), TypeError, r"parameter eps=True; expected a real number"),
        (dict(nu="1"), TypeError, r"parameter nu='1'; expected a real number"),
        (dict(eps=None), TypeError, r"parameter eps=None; expected a real number"),
    ],
)
def test_parameters_of_the_wrong_kind_are_refused(params, exc, match):
    with pytest.raises(exc, match=match):
        BallOnVibratingPlane(**params)


def test_parameter_ranges_are_checked_in_the_state_precision():
    """radius = 1e-50 is 0 in float32: the error names the radius, not the state."""
    scene = BallOnVibratingPlane(radius=1e-50)
    with pytest.raises(ValueError, match=r"parameter radius=0.0 is not allowed; radius must be finite and > 0"):
        nhsde.simulate(scene.build(), scene.initial_state().astype(jnp.float32), KEY, n_paths=64, t1=1.0, dt=0.1)


def test_float32_time_keeps_its_step_at_large_t0():
    """At t0 = 1e5 float32 rounds t + dt − t to 0.0078 or 0.0156: the solver now steps over (0, dt) exactly."""
    scene = BallOnVibratingPlane(eps=1.0, nu=1.0, drift=False)
    ens = nhsde.simulate(
        scene.build(), scene.initial_state().astype(jnp.float32), KEY, n_paths=4096, t0=1e5, t1=1e5 + 8.0, dt=0.01
    )
    exact = (1 / 1.4) ** 2 / (4 * (1 - 1.0 * 0.01))  # Euler's own stationary k_uu
    assert abs(float(ens.cov[-1, 0, 0]) - exact) <= 4 * float(ens.cov_se[-1, 0, 0])


def test_memory_does_not_grow_with_paths():
    """2¹² chunks of 128 paths need no more temporaries than 2⁴ chunks, to less than one bit per extra path
    (they used to hold the initial states and a failure flag per path: 17–33 bytes)."""
    system, y0 = BALL.build(), BALL.initial_state()

    def temp_bytes(n_paths):
        def run(y):
            return nhsde.simulate(
                system, y, KEY, n_paths=n_paths, t1=1.0, dt=0.1, batching=nhsde.Batching(128, jax.devices()[:1])
            ).mean

        return jax.jit(run).lower(y0).compile().memory_analysis().temp_size_in_bytes

    small, large = temp_bytes(128 * 2**4), temp_bytes(128 * 2**12)
    assert large <= small + 128 * (2**12 - 2**4) // 8, (small, large)


def test_chunks_larger_than_the_paths_simulate_no_padding():
    small = sim(batching=nhsde.Batching(chunk_size=64))
    huge = sim(batching=nhsde.Batching(chunk_size=2**20))
    assert np.array_equal(small.cov, huge.cov) and int(huge.n_used) + int(huge.n_failed) == 64


def test_whole_numbers_are_real_parameters():
    """eps=0 used to be an integer leaf: a type-promotion error from inside JAX under strict promotion."""
    scene = BallOnVibratingPlane(eps=2, nu=1)
    assert jnp.issubdtype(scene.params.eps.dtype, jnp.floating)
    ens = nhsde.simulate(scene.build(), scene.initial_state(), KEY, n_paths=64, t1=1.0, dt=0.1)
    assert np.all(np.isfinite(ens.cov))


ESTIMATOR_CALLS = {
    "multilevel_monte_carlo": lambda **kw: nhsde.statistics.multilevel_monte_carlo(
        BALL.build(), BALL.initial_state(), KEY, t1=1.0, statistic=("mean", "x"), n_paths=(64,), **kw
    ),
    "extrapolate": lambda **kw: nhsde.statistics.extrapolate(
        BALL.build(), BALL.initial_state(), KEY, t1=1.0, n_paths=64, **kw
    ),
    "control_variate": lambda **kw: nhsde.statistics.control_variate(
        BALL.build(), BALL.initial_state(), KEY, t1=1.0, n_paths=64, **kw
    ),
    "quasi_monte_carlo": lambda **kw: nhsde.statistics.quasi_monte_carlo(
        BALL.build(), BALL.initial_state(), KEY, t1=1.0, n_paths=64, **kw
    ),
    "multilevel_quasi_monte_carlo": lambda **kw: nhsde.statistics.multilevel_quasi_monte_carlo(
        BALL.build(), BALL.initial_state(), KEY, t1=1.0, statistic=("mean", "x"), n_points=(64,), **kw
    ),
    "to_accuracy": lambda **kw: nhsde.statistics.to_accuracy(
        BALL.build(), BALL.initial_state(), KEY, t1=1.0, statistic=("mean", "x"), rmse=0.1, **kw
    ),
}


@pytest.mark.parametrize("name", list(ESTIMATOR_CALLS))
@pytest.mark.parametrize(
    "kw, exc, match",
    [
        (dict(dt=0.25, steps=nhsde.FixedSteps(0.25)), TypeError, r"dt=0.25 and steps=.*: give the step once"),
        (dict(steps=nhsde.AdaptiveSteps(0.25)), ValueError, r"compares solves on fixed step grids; use dt=h"),
        (dict(steps=0.25), TypeError, r"steps=0.25; expected nhsde.FixedSteps\(h\)"),
        (dict(dt=nhsde.FixedSteps(0.25)), TypeError, r"dt=FixedSteps\(dt=0.25\); give a number"),
        (dict(dt=-1.0), ValueError, r"dt=-1.0; must be > 0"),
    ],
)
def test_every_estimator_takes_its_step_by_one_rule(name, kw, exc, match):
    """``dt=h`` or ``steps=FixedSteps(h)``, once, the same messages everywhere (``run_options``), refused
    before any solve."""
    with pytest.raises(exc, match=match):
        ESTIMATOR_CALLS[name](**kw)


@pytest.mark.parametrize("name", ["simulate", *ESTIMATOR_CALLS])
@pytest.mark.parametrize(
    "kw, exc, match",
    [
        (dict(t0=1.0, dt=0.25), ValueError, r"t1=1.0; must be > t0=1.0"),
        (dict(t0="start", dt=0.25), TypeError, r"t0='start'; expected a number"),
        (dict(dt=0.3), ValueError, r"dt=0.3 must divide t1 − t0 = 1.0 into a whole number of steps"),
        (dict(dt=2.0), ValueError, r"dt=2.0 is larger than t1 − t0 = 1.0"),
        (dict(steps=nhsde.FixedSteps(0.25, max_steps=2)), ValueError, r"makes 4 steps .* max_steps=2"),
        (dict(dt=0.25, save="x"), TypeError, r"save='x'; expected nhsde.Save\(...\)"),
        (dict(dt=0.25, batching=3), TypeError, r"batching=3; expected nhsde.Batching\(...\)"),
    ],
)
def test_simulate_and_every_estimator_check_the_run_options_by_one_rule(name, kw, exc, match):
    """The span, the step and its budget, what is saved and the batching are checked in one place
    (``RunOptions``), with the same messages in ``simulate`` and every estimator, before any solve."""
    call = ESTIMATOR_CALLS.get(name) or (
        lambda **kw: nhsde.simulate(BALL.build(), BALL.initial_state(), KEY, n_paths=64, t1=1.0, **kw)
    )
    with pytest.raises(exc, match=match):
        call(**kw)


@pytest.mark.parametrize("name", [n for n in ESTIMATOR_CALLS if n != "to_accuracy"])
def test_every_estimator_but_to_accuracy_needs_a_step(name):
    with pytest.raises(TypeError, match=rf"{name} needs a step: dt=h or steps=nhsde.FixedSteps\(h\)"):
        ESTIMATOR_CALLS[name]()


def test_a_step_given_as_fixed_steps_is_the_same_step():
    """``steps=FixedSteps(h)`` gives bitwise the estimate of ``dt=h`` (extrapolation, whose two solves share it)."""
    by_dt = ESTIMATOR_CALLS["extrapolate"](dt=0.25)
    by_steps = ESTIMATOR_CALLS["extrapolate"](steps=nhsde.FixedSteps(0.25))
    np.testing.assert_array_equal(np.asarray(by_dt.cov), np.asarray(by_steps.cov))
