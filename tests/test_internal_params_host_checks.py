"""Parameter checks that move to the host where the values are known there (so that the compiled programs have no
host callback and enter JAX's persistent compilation cache), and stay in the programs where they are traced: every
check holds under jit, grad and vmap with the same message."""

import equinox as eqx
import jax
import jax.numpy as jnp
import pytest

import nhsde
from nhsde._params import checked_on_host, differentiated_nonzero, parameters_checked_on_host, validated
from nhsde._simulate import simulate_run

SINGULAR = "the derivative with respect to a noise intensity nu at nu = 0 is singular"
RAISED = (eqx.EquinoxRuntimeError, jax.errors.JaxRuntimeError)  # eager and eqx.filter_jit; jax.jit
SCENE = nhsde.scenes.BallOnVibratingPlane()
SYSTEM = SCENE.build()


def k_xx(nu, eps=1.0):
    system = SYSTEM.replace_params(eps=eps, nu=nu)
    ens = nhsde.simulate(system, SCENE.initial_state(), jax.random.key(0), n_paths=64, t1=1.0, dt=0.1)
    return ens.cov[-1, 0, 0]


def k_xx_forward_only(nu, eps=1.0):
    """:func:`k_xx` as the estimators solve it in forward mode of concrete values (``forward_only``)."""
    system = SYSTEM.replace_params(eps=eps, nu=nu)
    run = nhsde.RunOptions(t1=1.0, steps=nhsde.FixedSteps(0.1), save=nhsde.Save())
    ens = simulate_run(system, SCENE.initial_state(), jax.random.key(0), run, n_paths=64, forward_only=True)
    return ens.cov[-1, 0, 0]


def test_a_derivative_in_nu_at_nu_0_raises_concrete_under_jit_and_in_forward_mode():
    with pytest.raises(eqx.EquinoxRuntimeError, match=SINGULAR):
        jax.grad(k_xx)(0.0)
    with pytest.raises(RAISED, match=SINGULAR):
        jax.jit(jax.grad(k_xx))(0.0)
    # the estimators' forward mode of concrete values: ν = 0 is differentiated, so the check stays in the program
    with pytest.raises(eqx.EquinoxRuntimeError, match=SINGULAR):
        jax.jacfwd(k_xx_forward_only)(jnp.asarray(0.0))
    # at ν > 0 the forward mode's program has no check (checked on the host), and equals reverse mode
    forward = jax.jacfwd(k_xx_forward_only)(jnp.asarray(0.5))
    assert jnp.allclose(forward, jax.grad(k_xx)(0.5), rtol=1e-10)


def test_only_differentiated_parameters_known_on_the_host_and_nonzero_pass():
    assert differentiated_nonzero(SYSTEM.params)  # nothing differentiated
    with_zero = SYSTEM.replace_params(nu=0.0, eps=1.0)
    assert differentiated_nonzero(with_zero)  # ν = 0 but not differentiated
    seen = []

    def record(eps, nu):
        seen.append(differentiated_nonzero(SYSTEM.replace_params(eps=eps, nu=nu)))
        return eps * nu

    jax.jacfwd(record, argnums=(0, 1))(1.0, 0.5)
    jax.jacfwd(record, argnums=(0, 1))(1.0, 0.0)  # ν = 0, differentiated
    jax.jacfwd(record, argnums=0)(1.0, 0.0)  # ν = 0, only ε differentiated
    jax.jit(jax.jacfwd(record, argnums=(0, 1)))(1.0, 0.5)  # under jit: not known on the host
    assert seen == [True, False, True, False]


def test_range_checks_of_traced_parameters_survive_a_trace_with_host_checked_parameters():
    """A program traced in ``checked_on_host`` leaves the range checks out; the same function traced outside keeps
    them (the setting is in the jit cache key), with the message naming the parameter and its range."""
    eps_of = jax.jit(lambda eps: validated(SYSTEM.params.replace(eps=eps)).eps)
    with checked_on_host():
        assert parameters_checked_on_host()
        assert float(eps_of(-1.0)) == -1.0  # the caller's promise: no check in the program
    assert not parameters_checked_on_host()
    with pytest.raises(RAISED, match="parameter eps must be finite and ≥ 0"):
        eps_of(-1.0)
    with pytest.raises(RAISED, match="parameter eps must be finite and ≥ 0"):
        jax.vmap(eps_of)(jnp.array([1.0, -1.0]))


def test_without_the_jax_state_every_check_stays_in_the_programs(monkeypatch):
    """Where JAX offers no config state to key programs on (its private API changed), ``checked_on_host`` does
    nothing: the programs keep their checks (and stay out of the persistent cache), and the answers are the same."""
    import nhsde._params as params

    def sensitivities():
        return nhsde.statistics.moment_sensitivities(
            SYSTEM, SCENE.initial_state(), jax.random.key(2), wrt=("eps", "nu"), n_paths=64, t1=1.0, dt=0.1
        )

    keyed = sensitivities()
    monkeypatch.setattr(params, "_CHECKED_ON_HOST", None)
    with checked_on_host():
        assert not parameters_checked_on_host()
    unkeyed = sensitivities()
    for a, b in ((keyed.cov, unkeyed.cov), (keyed.d_cov, unkeyed.d_cov), (keyed.d_cov_se, unkeyed.d_cov_se)):
        assert jnp.allclose(a, b, rtol=1e-12, atol=1e-12)
    with pytest.raises(RAISED, match="parameter eps must be finite and ≥ 0"):
        jax.jit(lambda eps: k_xx(1.0, eps))(-1.0)
