"""Property-based fuzzing of the public entry points (hypothesis).

The property: every call either returns a result whose statistics are finite and whose failures are counted, or
raises ``ValueError``/``TypeError``/``SimulationError`` with a message naming the argument; never another exception
type from inside JAX, never a hang (each example has a deadline), never a non-finite statistic without an error.
The examples that once failed are kept as explicit regression tests in ``test_errors.py``.
"""

import collections

import diffrax
import jax
import jax.numpy as jnp
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

import nhsde
from nhsde.scenes import SCENES, BallOnVibratingPlane

OUTCOMES: collections.Counter = collections.Counter()
FUZZ = settings(
    max_examples=90,
    deadline=60_000,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)

numbers = st.one_of(
    st.sampled_from([0, 1, 2, 64, 100, 2**31, 2**63 - 1, -1, 0.5, 1e-9, 1e300, -0.0]),
    st.floats(allow_nan=True, allow_infinity=True, width=64),
    st.integers(min_value=-(2**70), max_value=2**70),
    st.booleans(),
    st.text(max_size=3),
    st.none(),
    st.lists(st.floats(-2, 2), max_size=3),
)


def _names_the_argument(message: str, names) -> bool:
    return any(name in message for name in names)


def _check(call, names):
    """Run ``call``; classify and check its outcome against the property."""
    try:
        ens = call()
    except nhsde.SimulationError:  # a numerical failure, reported: the paths failed, no statistic returned
        OUTCOMES["reported failure"] += 1
        return
    except (ValueError, TypeError) as e:
        OUTCOMES["clear error"] += 1
        assert _names_the_argument(str(e), names), f"{type(e).__name__}: {e} (names none of {names})"
        return
    OUTCOMES["result"] += 1
    stats = (ens.mean, ens.cov, ens.mean_se, ens.cov_se)
    assert all(bool(jnp.all(jnp.isfinite(s))) for s in stats), "non-finite statistic without an error"
    assert int(ens.n_used) >= 4 and int(ens.n_failed) >= 0, "failures must be counted"


BALL = BallOnVibratingPlane(drift=False)
SYSTEM, Y0 = BALL.build(), BALL.initial_state()
SOLVERS = ["euler", "milstein", "heun", "heun2", "sra1", "exponential", "rk4", diffrax.ShARK(), diffrax.Tsit5(), 3]


@FUZZ
@given(
    n_paths=st.one_of(st.sampled_from([64, 128]), numbers),
    t1=st.one_of(st.sampled_from([0.5, 1.0]), numbers),
    dt=st.one_of(st.sampled_from([0.05, 0.1, 0.5]), numbers),
    t0=st.one_of(st.just(0.0), numbers),
    solver=st.sampled_from(SOLVERS),
    first_path=st.one_of(st.just(0), numbers),
    on_failure=st.sampled_from(["raise", "exclude", "ignore", 0]),
)
def test_simulate_arguments(n_paths, t1, dt, t0, solver, first_path, on_failure):
    def call():
        return nhsde.simulate(
            SYSTEM,
            Y0,
            jax.random.key(0),
            n_paths=n_paths,
            t1=t1,
            dt=dt,
            t0=t0,
            solver=solver,
            first_path=first_path,
            on_failure=on_failure,
        )

    _check(call, ("n_paths", "t1", "dt", "t0", "solver", "first_path", "on_failure", "steps"))


@FUZZ
@given(
    names=st.one_of(st.none(), st.text(max_size=3), st.lists(st.sampled_from(["u_x", "u_y", "omega_x", "z", ""]))),
    n=st.one_of(st.none(), numbers),
    paths=st.one_of(st.booleans(), numbers),
    chunk_size=st.one_of(st.none(), st.sampled_from([64, 128, 4096]), numbers),
    checkpoint=st.one_of(st.none(), st.booleans(), numbers),
    devices=st.sampled_from([None, "one", "twice", "empty", "list"]),
    steps=st.sampled_from(["fixed", "brownian", "adaptive", "budget"]),
)
def test_option_objects(names, n, paths, chunk_size, checkpoint, devices, steps):
    device_choice = {
        "one": jax.devices()[0],
        "twice": jax.devices()[:1] * 2,
        "empty": [],
        "list": jax.devices()[:1],
        None: None,
    }[devices]
    step_choice = {
        "fixed": lambda: nhsde.FixedSteps(0.1),
        "brownian": lambda: nhsde.FixedSteps(0.1, brownian_dt=0.03),
        "adaptive": lambda: nhsde.AdaptiveSteps(0.1),
        "budget": lambda: nhsde.FixedSteps(0.001, max_steps=100),
    }[steps]

    def call():
        return nhsde.simulate(
            SYSTEM,
            Y0,
            jax.random.key(0),
            n_paths=64,
            t1=1.0,
            steps=step_choice(),
            save=nhsde.Save(names=names, n=n, paths=paths),
            batching=nhsde.Batching(chunk_size=chunk_size, devices=device_choice, checkpoint=checkpoint),
            solver="sra1",
        )

    _check(
        call,
        (
            "names",
            "Save",
            "save",
            "save.n",
            "n −",
            "paths",
            "chunk_size",
            "checkpoint",
            "devices",
            "brownian_dt",
            "max_steps",
        ),
    )


@settings(FUZZ, max_examples=60)
@given(
    scene=st.sampled_from(sorted(SCENES)),
    parameter=st.sampled_from(["eps", "nu", "mass", "radius", "inertia", "offset", "unknown"]),
    value=numbers,
)
def test_scene_parameters(scene, parameter, value):
    cls = SCENES[scene]

    def call():
        built = cls(**{parameter: value})
        system = built.build()
        return nhsde.simulate(
            system, built.initial_state(), jax.random.key(0), n_paths=64, t1=0.2, dt=0.05, on_failure="exclude"
        )

    _check(call, (parameter,))


def test_fuzz_report():
    """The counted report (run after the fuzz tests above; any other outcome failed its example already)."""
    if not OUTCOMES:
        pytest.skip("run with the fuzz tests above")
    print(
        f"\nfuzz: {sum(OUTCOMES.values())} inputs: {OUTCOMES['clear error']} clear errors, "
        f"{OUTCOMES['reported failure']} reported numerical failures, {OUTCOMES['result']} finite results; "
        "0 silent non-finite statistics, 0 foreign exceptions, 0 hangs"
    )
