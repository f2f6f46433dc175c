"""The one scene contract (``nhsde.scenes.AbstractScene``), checked for every registered scene.

- ``∂/∂ν`` of the noise amplitude at ``ν = 0`` raises (``sqrt_intensity``), finite and nonzero at ``ν > 0``;
- ``SCENES`` is exactly the set of concrete scenes defined in ``nhsde.scenes``, concrete scenes are final,
  the deterministic rolling bodies are another kind;
- ``initial_state()`` fits ``build()``'s state and every listed observable is observable;
- a new scene from its ``T``, ``R``, constraint and noise alone, against its mean-energy balance.
"""

import importlib
import inspect
import pkgutil
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhsde
import nhsde.scenes as S
from nhsde import AbstractParameters, parameter, sqrt_intensity, validated

CLI_NAMES = {
    "ball-on-vibrating-plane",
    "chaplygin-sleigh",
    "chaplygin-sleigh-from-spec",
    "vertical-rolling-disk",
    "rolling-disk",
    "contact-oscillator",
    "beghin-plate",
    "ball-from-lagrangian",
    "bead-on-rotating-rod",
    "body-on-vibrating-plane",
    "chaplygin-ball",
}
SINGULAR = "derivative with respect to a noise intensity nu at nu = 0 is singular"


def _concrete(cls) -> bool:
    return not any(getattr(cls, a, ()) for a in ("__abstractmethods__", "__abstractvars__", "__abstractclassvars__"))


def _variants(cls):
    """The default scene and each boolean option flipped."""
    flags = [
        name
        for name, p in inspect.signature(cls.__init__).parameters.items()
        if p.kind is inspect.Parameter.KEYWORD_ONLY and isinstance(p.default, bool)
    ]
    defaults = {name: inspect.signature(cls.__init__).parameters[name].default for name in flags}
    return [cls()] + [cls(**{name: not defaults[name]}) for name in flags]


@pytest.mark.parametrize("name", sorted(S.SCENES))
def test_noise_intensity_derivative(name):
    """Every noise amplitude goes through ``sqrt_intensity``: ``∂b/∂ν`` at ``ν = 0`` raises, at ``ν > 0`` it is
    finite and nonzero (``ν`` is a leaf of ``params``, not closed over)."""
    cls = S.SCENES[name]
    assert cls.intensities, name
    y0 = cls().initial_state()
    for intensity in cls.intensities:

        def amplitude(nu, intensity=intensity):
            system = cls(**{intensity: nu}).build()
            return system.diffusion(0.0, y0, validated(system.params))

        with pytest.raises(eqx.EquinoxRuntimeError, match=SINGULAR):
            jax.jacfwd(amplitude)(jnp.asarray(0.0))
        d = np.asarray(jax.jacfwd(amplitude)(jnp.asarray(0.5)))
        assert np.all(np.isfinite(d)) and np.max(np.abs(d)) > 0, (name, intensity)


def test_registry_is_the_set_of_concrete_scenes():
    found = set()
    for info in pkgutil.iter_modules(S.__path__):
        module = importlib.import_module(f"{S.__name__}.{info.name}")
        for obj in vars(module).values():
            if isinstance(obj, type) and issubclass(obj, S.AbstractScene) and _concrete(obj):
                found.add(obj)
    assert set(S.SCENES.values()) == found
    assert CLI_NAMES <= set(S.SCENES) and len(S.SCENES) == len(found)
    for name, cls in S.SCENES.items():
        assert cls.name == name and cls.description() and getattr(S, cls.__name__) is cls
        assert S.get_scene(name) is cls
    with pytest.raises(ValueError, match="scene 'ball': unknown scene; known scenes: .*chaplygin-ball"):
        S.get_scene("ball")
    with pytest.raises(TypeError):
        S.SCENES["x"] = S.ChaplyginSleigh  # pyright: ignore[reportIndexIssue]


def test_concrete_scenes_are_final_and_rolling_bodies_another_kind():
    with pytest.raises(TypeError, match="concrete scenes are final"):

        class Sleigh(S.ChaplyginSleigh):
            pass

    with pytest.raises(TypeError, match="concrete scenes are final"):

        class Body(S.RollingBody):
            pass

    for cls in (S.RollingBody, S.FlatBaseOnSphere, S.Rattleback):
        assert issubclass(cls, S.AbstractRollingBodyScene) and not issubclass(cls, S.AbstractScene)
        assert cls not in S.SCENES.values()
    assert not issubclass(S.Rattleback, S.RollingBody)
    rattleback = S.Rattleback()
    assert rattleback.params is rattleback.rolling.params and rattleback.layout.size == 6


@pytest.mark.parametrize("name", sorted(S.SCENES))
def test_initial_state_and_observables(name):
    for scene in _variants(S.SCENES[name]):
        system, y0 = scene.build(), scene.initial_state()
        assert system.params is scene.params
        assert y0.shape == (system.state_dim,), (name, y0.shape, system.layout.names)
        names = scene.observable_names()
        assert set(system.layout.names) <= set(names)
        values = system.observe(names)(jnp.zeros((), y0.dtype), y0, system.params)
        assert values.shape == (len(names),) and bool(jnp.all(jnp.isfinite(values))), (name, names, values)


# A new scene from its mechanics alone (user code, ≤ 30 lines): Rosenberg's nonholonomic particle, a unit mass
# with ż = y ẋ, friction R = ε|q̇|² and random forces √ν V on each coordinate.


class ParticleParameters(AbstractParameters):
    eps: jnp.ndarray = parameter(default=0.5, lower=0.0, doc="friction ε")
    nu: jnp.ndarray = parameter(default=0.8, lower=0.0, doc="noise intensity ν")


class NonholonomicParticle(S.AbstractSpecScene):
    """A unit mass with ż = y ẋ, friction and random forces."""

    name: ClassVar[str] = "nonholonomic-particle"
    Parameters: ClassVar[type[ParticleParameters]] = ParticleParameters
    coordinates: ClassVar[tuple[str, ...]] = ("x", "y", "z")
    dependent: ClassVar[tuple[str, ...]] = ("z",)
    terms: ClassVar[dict] = dict(
        kinetic_energy=lambda q, v, pi, t, p: 0.5 * v @ v,
        constraints=lambda q, pi, t, p: jnp.stack([-q[1], jnp.zeros_like(q[1]), jnp.ones_like(q[1])])[None],
        dissipation=lambda q, v, pi, t, p: p.eps * v @ v,
        noise_force=lambda q, v, pi, t, p: sqrt_intensity(p.nu) * jnp.eye(3, dtype=q.dtype),
    )

    params: ParticleParameters
    route: str = eqx.field(static=True)

    def __init__(self, *, route: str = "reduced", **params):
        self.params, self.route = ParticleParameters(**params), route

    def configuration(self):
        return jnp.array([0.0, 0.5, 0.0]), jnp.array([1.0, 0.4, 0.5])  # ż = y ẋ


def _kinetic_energy(scene, t1, dt, n_paths=64):
    velocities = ("x_dot", "y_dot", "z_dot")
    ens = nhsde.simulate(
        scene.build(),
        scene.initial_state(),
        jax.random.key(0),
        n_paths=n_paths,
        t1=t1,
        dt=dt,
        save=nhsde.Save(names=velocities, n=5, paths=True),
    )
    v = np.asarray(ens.paths, np.float64)
    return np.asarray(ens.ts), 0.5 * np.sum(v**2, axis=-1)


@pytest.mark.parametrize("route", ["reduced", "multipliers"])
def test_a_new_scene_from_its_spec(route):
    """Without friction and noise ``T`` is conserved (the reaction does no work); with them, Itô on the two free
    velocities gives ``dE[T]/dt = −4ε E[T] + ν``, so ``E[T] = T₀ e^{−4εt} + ν(1 − e^{−4εt})/(4ε)``."""
    assert NonholonomicParticle.name not in S.SCENES
    _, energy = _kinetic_energy(NonholonomicParticle(route=route, eps=0.0, nu=0.0), t1=2.0, dt=1e-2)
    np.testing.assert_allclose(energy, 0.705, rtol=2e-3)  # Euler: O(dt)

    eps, nu = 0.5, 0.8
    ts, energy = _kinetic_energy(NonholonomicParticle(route=route, eps=eps, nu=nu), t1=1.0, dt=1e-2, n_paths=512)
    decay = np.exp(-4 * eps * ts)
    exact = 0.705 * decay + nu * (1 - decay) / (4 * eps)
    se = energy.std(0) / np.sqrt(energy.shape[0])
    assert np.all(np.abs(energy.mean(0) - exact)[1:] <= 4 * se[1:] + 1e-2 * exact[1:]), (energy.mean(0), exact, se)
