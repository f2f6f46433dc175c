"""Throughput of ``nhsde.simulate`` against hand-written and off-the-shelf Euler–Maruyama.

Run from the repository root::

    python benchmarks/throughput.py                 # 4096 paths x 1000 steps, 5 repeats
    python benchmarks/throughput.py --quick         # small sizes, a smoke test
    python benchmarks/throughput.py --paths 8192 --steps 500 --repeats 3
    python benchmarks/throughput.py --device gpu    # on the GPU (pip install -e ".[gpu]"); fails clearly without one
    python benchmarks/throughput.py --device cpu    # on the CPU even where a GPU is present

Everything is measured in one process, float32, dt = 0.01, on the same SDE for
every implementation, on the backend ``--device`` names (default: the one JAX
picks, a GPU where there is one; the NumPy competitor always runs on the host),
for three scenes:

- ``ball``:   nhsde.scenes.BallOnVibratingPlane (linear, state (x, y, u_x, u_y));
- ``sleigh``: nhsde.scenes.ChaplyginSleigh      (nonlinear, state (x, y, θ, v, ω));
- ``chaplygin-ball``: nhsde.scenes.ChaplyginBall(drift=True), a rolling body
              (nonlinear, state (M, γ, α, x, y): angular momentum about the
              contact point, vertical and horizontal axis in the body, contact point).

The statistic is the fluctuation drift K_xx(t1) = Var x(t1) of the contact point
over the paths; the gradients are taken with respect to (eps, nu).  Implementations:

- ``nhsde``        ``nhsde.simulate(..., solver="euler", save=Save(n=2))`` inside a
                   ``jax.jit`` of ``(eps, nu) -> K_xx(t1)``; also the plain call to
                   ``simulate`` (its own ``eqx.filter_jit``, Python checks included),
                   ``jax.value_and_grad`` (reverse) and ``jax.jacfwd`` (forward mode);
- ``(a) scan``     hand-fused ``lax.scan`` Euler–Maruyama on an ``(n_paths, d)`` state,
                   noise ``normal(fold_in(key, step), (n_paths, m)) * sqrt(dt)``;
- ``(b) numpy``    vectorised NumPy Euler–Maruyama, ``default_rng().standard_normal``
                   per step (forward only);
- ``(c) diffrax``  ``diffrax.diffeqsolve`` vmapped over paths, ``VirtualBrownianTree``
                   (tol = dt/2), ``Euler()``, constant step dt, ``SaveAt(t1=True)``;
                   slow, so timed on fewer paths (``--c-paths``), compared per
                   trajectory-step.

The competitors re-write the scenes' drift and diffusion directly (from the
equations in ``src/nhsde/scenes/_ball.py``, ``_sleigh.py`` and ``_chaplygin_ball.py``), so they are
independent implementations; every implementation's K_xx(t1) is checked against
nhsde's within Monte-Carlo error (and, for the ball, against the exact value).

Timing: every function is compiled and run once first; then ``--repeats`` rounds
run all implementations in turn (round-robin, so a transient load on the machine
hits all of them alike), each call ended by ``jax.block_until_ready``; the table
reports the minimum (and the median) over the rounds.  Results also go to
``benchmarks/results/throughput.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics as pystats
import sys
import time
from pathlib import Path

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np

import nhsde
from nhsde.scenes import BallOnVibratingPlane, ChaplyginBall, ChaplyginSleigh, ball_covariances

DT = 0.01
DTYPE = jnp.float32

# ----------------------------------------------------------------------------- scenes
#
# Parameters other than (eps, nu) are the scenes' defaults, hard-coded here for the
# independent implementations:
#   ball:   radius r = 1, κ = 0.4  ⇒  δ = 1/(1 + κ) = 5/7
#           dx = u dt,  du = −2ε u dt + √ν δ dW                       (2 noise axes)
#   sleigh: m = 1, I = 1, a = 1  ⇒  J = I + m a² = 2
#           dx = v cos θ dt, dy = v sin θ dt, dθ = ω dt,
#           dv = (a ω² − 2ε v) dt + √ν/√m dW₁,
#           dω = (−(m a/J) v ω − 2ε ω) dt + √ν/√J dW₂
#   chaplygin-ball: m = R = 1 (D = m R² = 1), I = diag(0.3, 0.4, 0.5), A = (I + D E)⁻¹,
#           n = γ/|γ|,  ω = A M + D (n, A M)/(1 − D (n, A n)) A n   (Ĩ⁻¹M, Sherman–Morrison),
#           dM = (M × ω − 2ε ω) dt + √ν dW,   dγ = γ × ω dt,   dα = α × ω dt,
#           ṙ = −R n × ω,  dx = (α/|α|, ṙ) dt,  dy = (n × α/|α|, ṙ) dt       (3 noise axes)

BALL_DELTA = 1.0 / (1.0 + 0.4)
SLEIGH_M, SLEIGH_I, SLEIGH_A = 1.0, 1.0, 1.0
SLEIGH_J = SLEIGH_I + SLEIGH_M * SLEIGH_A**2
CB_D, CB_R = 1.0, 1.0
CB_A = tuple(1.0 / (i + CB_D) for i in (0.3, 0.4, 0.5))


def _chaplygin_ball(**params):
    return ChaplyginBall(drift=True, **params)


# x: index of the contact point's x in the state (the statistic is Var x(t1))
SCENES = {
    "ball": dict(make=BallOnVibratingPlane, eps=1.0, nu=1.0, y0=(0.0, 0.0, 0.0, 0.0), m=2, x=0),
    "sleigh": dict(make=ChaplyginSleigh, eps=0.1, nu=1.0, y0=(0.0, 0.0, 0.0, 1.0, 0.0), m=2, x=0),
    "chaplygin-ball": dict(
        make=_chaplygin_ball, eps=0.5, nu=1.0, y0=(0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0), m=3, x=9
    ),
}


# --- batched jnp (competitor a): y (n, d), dw (n, m) -> y_next
def ball_em_jnp(y, dw, eps, nu, dt):
    u = y[:, 2:]
    g = jnp.sqrt(nu) * BALL_DELTA
    return jnp.concatenate([y[:, :2] + u * dt, u - 2.0 * eps * u * dt + g * dw], axis=1)


def sleigh_em_jnp(y, dw, eps, nu, dt):
    x, yy, th, v, w = (y[:, i] for i in range(5))
    dv = SLEIGH_A * w**2 - 2.0 * eps * v
    dom = -(SLEIGH_M * SLEIGH_A / SLEIGH_J) * v * w - 2.0 * eps * w
    s = jnp.sqrt(nu)
    return jnp.stack(
        [
            x + v * jnp.cos(th) * dt,
            yy + v * jnp.sin(th) * dt,
            th + w * dt,
            v + dv * dt + s / math.sqrt(SLEIGH_M) * dw[:, 0],
            w + dom * dt + s / math.sqrt(SLEIGH_J) * dw[:, 1],
        ],
        axis=1,
    )


def cb_em_jnp(y, dw, eps, nu, dt):
    m, g, al = y[:, 0:3], y[:, 3:6], y[:, 6:9]
    a = jnp.asarray(CB_A, y.dtype)
    n = g / jnp.linalg.norm(g, axis=1, keepdims=True)
    am, an_ = a * m, a * n
    k = CB_D * jnp.sum(n * am, axis=1, keepdims=True) / (1.0 - CB_D * jnp.sum(n * an_, axis=1, keepdims=True))
    w = am + k * an_
    ua = al / jnp.linalg.norm(al, axis=1, keepdims=True)
    rdot = -CB_R * jnp.cross(n, w)
    xy = jnp.stack([jnp.sum(ua * rdot, axis=1), jnp.sum(jnp.cross(n, ua) * rdot, axis=1)], axis=1)
    return jnp.concatenate(
        [
            m + (jnp.cross(m, w) - 2.0 * eps * w) * dt + jnp.sqrt(nu) * dw,
            g + jnp.cross(g, w) * dt,
            al + jnp.cross(al, w) * dt,
            y[:, 9:11] + xy * dt,
        ],
        axis=1,
    )


# --- batched numpy (competitor b), in place on y (n, d) float32
def ball_em_numpy(y, dw, eps, nu, dt):
    u = y[:, 2:]
    g = np.float32(math.sqrt(nu) * BALL_DELTA)
    y[:, :2] += u * np.float32(dt)
    u *= np.float32(1.0 - 2.0 * eps * dt)
    dw *= g
    u += dw


def sleigh_em_numpy(y, dw, eps, nu, dt):
    th, v, w = y[:, 2], y[:, 3], y[:, 4]
    f = np.float32
    vdt = v * f(dt)
    x_inc, y_inc = vdt * np.cos(th), vdt * np.sin(th)
    dv = f(SLEIGH_A) * w * w - f(2.0 * eps) * v
    dom = f(-(SLEIGH_M * SLEIGH_A / SLEIGH_J)) * v * w - f(2.0 * eps) * w
    s = math.sqrt(nu)
    y[:, 0] += x_inc
    y[:, 1] += y_inc
    y[:, 2] += w * f(dt)
    y[:, 3] += dv * f(dt) + f(s / math.sqrt(SLEIGH_M)) * dw[:, 0]
    y[:, 4] += dom * f(dt) + f(s / math.sqrt(SLEIGH_J)) * dw[:, 1]


def _cross_np(u, v):
    """Row-wise cross product of (n, 3) float32 arrays (np.cross without its copies)."""
    out = np.empty_like(u)
    out[:, 0] = u[:, 1] * v[:, 2] - u[:, 2] * v[:, 1]
    out[:, 1] = u[:, 2] * v[:, 0] - u[:, 0] * v[:, 2]
    out[:, 2] = u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]
    return out


def cb_em_numpy(y, dw, eps, nu, dt):
    f = np.float32
    m, g, al = y[:, 0:3], y[:, 3:6], y[:, 6:9]
    a = np.asarray(CB_A, np.float32)
    n = g / np.sqrt(np.einsum("ij,ij->i", g, g))[:, None]
    am, an_ = a * m, a * n
    k = f(CB_D) * np.einsum("ij,ij->i", n, am) / (f(1.0) - f(CB_D) * np.einsum("ij,ij->i", n, an_))
    w = am + k[:, None] * an_
    ua = al / np.sqrt(np.einsum("ij,ij->i", al, al))[:, None]
    rdot = f(-CB_R) * _cross_np(n, w)
    x_inc = np.einsum("ij,ij->i", ua, rdot) * f(dt)
    y_inc = np.einsum("ij,ij->i", _cross_np(n, ua), rdot) * f(dt)
    m_inc = (_cross_np(m, w) - f(2.0 * eps) * w) * f(dt)
    g_inc, al_inc = _cross_np(g, w) * f(dt), _cross_np(al, w) * f(dt)
    dw *= f(math.sqrt(nu))
    m += m_inc
    m += dw
    g += g_inc
    al += al_inc
    y[:, 9] += x_inc
    y[:, 10] += y_inc


# --- per-path vector fields for diffrax (competitor c): f(t, y, args), y (d,)
def ball_drift_dfx(t, y, args):
    eps, nu = args
    u = y[2:]
    return jnp.concatenate([u, -2.0 * eps * u])


def ball_diffusion_dfx(t, y, args):
    eps, nu = args
    g = jnp.sqrt(nu) * BALL_DELTA
    return jnp.concatenate([jnp.zeros((2, 2), y.dtype), g * jnp.eye(2, dtype=y.dtype)])


def sleigh_drift_dfx(t, y, args):
    eps, nu = args
    th, v, w = y[2], y[3], y[4]
    return jnp.stack(
        [
            v * jnp.cos(th),
            v * jnp.sin(th),
            w,
            SLEIGH_A * w**2 - 2.0 * eps * v,
            -(SLEIGH_M * SLEIGH_A / SLEIGH_J) * v * w - 2.0 * eps * w,
        ]
    )


def sleigh_diffusion_dfx(t, y, args):
    eps, nu = args
    s = jnp.sqrt(nu)
    diag = jnp.stack([s / math.sqrt(SLEIGH_M), s / math.sqrt(SLEIGH_J)]).astype(y.dtype)
    return jnp.concatenate([jnp.zeros((3, 2), y.dtype), jnp.diag(diag)])


def cb_drift_dfx(t, y, args):
    eps, nu = args
    m, g, al = y[0:3], y[3:6], y[6:9]
    a = jnp.asarray(CB_A, y.dtype)
    n = g / jnp.linalg.norm(g)
    am, an_ = a * m, a * n
    w = am + CB_D * jnp.dot(n, am) / (1.0 - CB_D * jnp.dot(n, an_)) * an_
    ua = al / jnp.linalg.norm(al)
    rdot = -CB_R * jnp.cross(n, w)
    xy = jnp.stack([jnp.dot(ua, rdot), jnp.dot(jnp.cross(n, ua), rdot)])
    return jnp.concatenate([jnp.cross(m, w) - 2.0 * eps * w, jnp.cross(g, w), jnp.cross(al, w), xy])


def cb_diffusion_dfx(t, y, args):
    eps, nu = args
    return jnp.concatenate([jnp.sqrt(nu) * jnp.eye(3, dtype=y.dtype), jnp.zeros((8, 3), y.dtype)])


EM_JNP = {"ball": ball_em_jnp, "sleigh": sleigh_em_jnp, "chaplygin-ball": cb_em_jnp}
EM_NUMPY = {"ball": ball_em_numpy, "sleigh": sleigh_em_numpy, "chaplygin-ball": cb_em_numpy}
VF_DFX = {
    "ball": (ball_drift_dfx, ball_diffusion_dfx),
    "sleigh": (sleigh_drift_dfx, sleigh_diffusion_dfx),
    "chaplygin-ball": (cb_drift_dfx, cb_diffusion_dfx),
}


# ----------------------------------------------------------------------------- statistic


def var_and_se(x):
    """Unbiased variance of the samples ``x`` and its Monte-Carlo standard error."""
    n = x.shape[0]
    c = x - jnp.mean(x)
    var = jnp.sum(c * c) / (n - 1)
    m2 = jnp.mean(c * c)
    m4 = jnp.mean(c**4)
    se = jnp.sqrt(jnp.maximum(m4 - m2 * m2, 0.0) / n)
    return var, jax.lax.stop_gradient(se)


def var_and_se_numpy(x):
    x = x.astype(np.float64)
    c = x - x.mean()
    m2, m4 = np.mean(c * c), np.mean(c**4)
    return float(np.sum(c * c) / (len(x) - 1)), float(math.sqrt(max(m4 - m2 * m2, 0.0) / len(x)))


# ----------------------------------------------------------------------------- implementations
#
# Each forward function maps (theta = [eps, nu], key) -> (K_xx(t1), its standard error);
# gradient variants are built with has_aux so the standard error rides along.


def nhsde_stat(scene, n_paths, steps, chunk_size=None):
    cfg = SCENES[scene]
    y0 = jnp.asarray(cfg["y0"], DTYPE)
    batching = nhsde.Batching(chunk_size=chunk_size)

    def f(theta, key):
        system = cfg["make"](eps=theta[0], nu=theta[1]).build()
        ens = nhsde.simulate(
            system,
            y0,
            key,
            n_paths=n_paths,
            t1=steps * DT,
            dt=DT,
            solver="euler",
            save=nhsde.Save(n=2),
            batching=batching,
        )
        stats = nhsde.statistics.drift_statistics(ens)
        return stats.fluctuation[-1, 0, 0], jax.lax.stop_gradient(stats.fluctuation_se[-1, 0, 0])

    return f


def nhsde_direct(scene, n_paths, steps):
    """The plain user call: a prebuilt system, ``simulate`` (filter_jit inside), then the statistic."""
    cfg = SCENES[scene]
    system = cfg["make"](eps=cfg["eps"], nu=cfg["nu"]).build()
    y0 = jnp.asarray(cfg["y0"], DTYPE)

    def f(theta, key):
        del theta  # fixed in the prebuilt system
        ens = nhsde.simulate(
            system, y0, key, n_paths=n_paths, t1=steps * DT, dt=DT, solver="euler", save=nhsde.Save(n=2)
        )
        stats = nhsde.statistics.drift_statistics(ens)
        return stats.fluctuation[-1, 0, 0], stats.fluctuation_se[-1, 0, 0]

    return f


def scan_stat(scene, n_paths, steps):
    cfg = SCENES[scene]
    em = EM_JNP[scene]
    y0 = jnp.broadcast_to(jnp.asarray(cfg["y0"], DTYPE), (n_paths, len(cfg["y0"])))
    m = cfg["m"]
    sqrt_dt = math.sqrt(DT)

    def f(theta, key):
        eps, nu = theta[0], theta[1]

        def body(y, step):
            dw = jr.normal(jr.fold_in(key, step), (n_paths, m), DTYPE) * sqrt_dt
            return em(y, dw, eps, nu, DT), None

        y, _ = jax.lax.scan(body, y0, jnp.arange(steps))
        return var_and_se(y[:, cfg["x"]])

    return f


def numpy_stat(scene, n_paths, steps):
    cfg = SCENES[scene]
    em = EM_NUMPY[scene]
    m = cfg["m"]
    sqrt_dt = np.float32(math.sqrt(DT))

    def f(theta, seed):
        eps, nu = float(theta[0]), float(theta[1])
        rng = np.random.default_rng(seed)
        y = np.empty((n_paths, len(cfg["y0"])), np.float32)
        y[:] = np.asarray(cfg["y0"], np.float32)
        for _ in range(steps):
            dw = rng.standard_normal((n_paths, m), dtype=np.float32)
            dw *= sqrt_dt
            em(y, dw, eps, nu, DT)
        return var_and_se_numpy(y[:, cfg["x"]])

    return f


def diffrax_stat(scene, n_paths, steps):
    cfg = SCENES[scene]
    drift, diffusion = VF_DFX[scene]
    y0 = jnp.asarray(cfg["y0"], DTYPE)
    m = cfg["m"]
    t1 = steps * DT

    def f(theta, key):
        args = (theta[0], theta[1])

        def one(path_key):
            bm = dfx.VirtualBrownianTree(0.0, t1, tol=DT / 2, shape=(m,), key=path_key)
            terms = dfx.MultiTerm(dfx.ODETerm(drift), dfx.ControlTerm(diffusion, bm))
            sol = dfx.diffeqsolve(
                terms, dfx.Euler(), 0.0, t1, DT, y0, args, saveat=dfx.SaveAt(t1=True), max_steps=steps + 16
            )
            return sol.ys[0], sol.stats["num_steps"]

        ys, nsteps = jax.vmap(one)(jr.split(key, n_paths))
        var, se = var_and_se(ys[:, cfg["x"]])
        return var, (se, jnp.max(nsteps))

    return f


# ----------------------------------------------------------------------------- harness


def block(x):
    return jax.block_until_ready(x)


class Case:
    def __init__(self, scene, impl, mode, n_paths, steps, call, forward_of=None):
        self.scene, self.impl, self.mode = scene, impl, mode
        self.n_paths, self.steps = n_paths, steps
        self.call = call
        self.forward_of = forward_of  # (impl, mode) of the forward row this gradient row is compared with
        self.times: list[float] = []
        self.compile_s = math.nan
        self.out = None

    def warm(self):
        t = time.perf_counter()
        self.out = block(self.call())
        self.compile_s = time.perf_counter() - t

    def run(self):
        t = time.perf_counter()
        block(self.call())
        self.times.append(time.perf_counter() - t)

    @property
    def best(self):
        return min(self.times)

    @property
    def throughput(self):
        return self.n_paths * self.steps / self.best


def make_cases(scene, args):
    cfg = SCENES[scene]
    theta = jnp.asarray([cfg["eps"], cfg["nu"]], DTYPE)
    key = jr.key(0)
    key_a, key_c = jr.key(1), jr.key(2)
    n, steps, nc = args.paths, args.steps, args.c_paths
    cases = []

    def add(impl, mode, paths, call, forward_of=None):
        cases.append(Case(scene, impl, mode, paths, steps, call, forward_of))

    f = nhsde_stat(scene, n, steps)
    fwd = jax.jit(f)
    vg = jax.jit(jax.value_and_grad(f, has_aux=True))

    def f_aux(th, k):  # value and standard error ride along as aux of the Jacobian
        v, se = f(th, k)
        return v, (v, se)

    jf = jax.jit(jax.jacfwd(f_aux, has_aux=True))
    direct = nhsde_direct(scene, n, steps)
    add("nhsde", "forward", n, lambda: fwd(theta, key))
    add("nhsde simulate() call", "forward", n, lambda: direct(theta, key))
    add("nhsde", "value_and_grad", n, lambda: vg(theta, key), ("nhsde", "forward"))
    add("nhsde", "jacfwd", n, lambda: jf(theta, key), ("nhsde", "forward"))
    if n > 8192:  # the CPU's default chunk, beside the backend's default
        chunked = jax.jit(nhsde_stat(scene, n, steps, chunk_size=8192))
        add("nhsde, chunks of 8192", "forward", n, lambda: chunked(theta, key))

    g = scan_stat(scene, n, steps)
    add("(a) lax.scan", "forward", n, (lambda h: lambda: h(theta, key_a))(jax.jit(g)))
    add(
        "(a) lax.scan",
        "value_and_grad",
        n,
        (lambda h: lambda: h(theta, key_a))(jax.jit(jax.value_and_grad(g, has_aux=True))),
        ("(a) lax.scan", "forward"),
    )

    h = numpy_stat(scene, n, steps)
    theta_np = np.asarray(theta)
    add("(b) numpy", "forward", n, lambda: h(theta_np, 3))

    if nc > 0:
        c = diffrax_stat(scene, nc, steps)
        add("(c) diffrax", "forward", nc, (lambda h: lambda: h(theta, key_c))(jax.jit(c)))
        add(
            "(c) diffrax",
            "value_and_grad",
            nc,
            (lambda h: lambda: h(theta, key_c))(jax.jit(jax.value_and_grad(c, has_aux=True))),
            ("(c) diffrax", "forward"),
        )
    return cases


def value_se_grad(case):
    """(value, se, grad or None) from a case's first output."""
    out = case.out
    if case.mode == "forward":
        (v, aux), grad = out, None
    elif case.mode == "value_and_grad":
        (v, aux), grad = out
    else:  # jacfwd with has_aux: (jacobian, (value, se))
        grad, (v, aux) = out
    se = aux[0] if isinstance(aux, tuple) else aux
    grad = None if grad is None else [float(x) for x in np.asarray(grad)]
    return float(v), float(se), grad


def machine_info():
    proc = platform.processor()
    model = ""
    try:
        with open("/proc/cpuinfo") as fh:
            model = next((ln.split(":", 1)[1].strip() for ln in fh if ln.startswith("model name")), "")
    except OSError:
        pass
    try:
        load = os.getloadavg()
    except OSError:
        load = None
    import subprocess

    import jaxlib

    repo = Path(__file__).resolve().parents[1]

    def git(*a):
        try:
            return subprocess.run(["git", *a], cwd=repo, capture_output=True, text=True, timeout=10).stdout.strip()
        except (OSError, subprocess.SubprocessError):
            return ""

    return {
        "git_head": git("rev-parse", "--short", "HEAD"),
        "src_modified_vs_head": bool(git("status", "--porcelain", "--", "src")),
        "cpu_count": os.cpu_count(),
        "platform.processor()": proc,
        "cpu_model": model,
        "platform": platform.platform(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "jaxlib": jaxlib.__version__,
        "diffrax": dfx.__version__ if hasattr(dfx, "__version__") else "?",
        "equinox": eqx.__version__ if hasattr(eqx, "__version__") else "?",
        "numpy": np.__version__,
        "nhsde": nhsde.__version__,
        "jax_devices": [str(d) for d in jax.devices()],
        "XLA_FLAGS": os.environ.get("XLA_FLAGS", ""),
        "loadavg_at_start": load,
    }


def fmt_rate(x):
    return f"{x:.3g}" if x < 1e3 else f"{x:,.0f}"


def select_device(device: str | None) -> str:
    """Make ``device`` (``"cpu"``, ``"gpu"`` or ``None``: JAX's choice) the backend every JAX competitor runs on;
    returns the backend's name.  Must run before anything else uses JAX.  Without a GPU, ``"gpu"`` exits (status 1)
    saying so."""
    if device == "cpu":
        jax.config.update("jax_platforms", "cpu")  # before the backends start: a GPU, if any, stays unused
    elif device == "gpu":
        try:
            gpus = jax.devices("gpu")
        except RuntimeError as e:
            sys.exit(
                f"--device gpu: JAX finds no GPU here ({e}). Run on a machine with an NVIDIA GPU and its driver, "
                'with the CUDA build of jaxlib: pip install -e ".[gpu]" (jax[cuda12]).'
            )
        jax.config.update("jax_default_device", gpus[0])
        if jax.default_backend() != "gpu":
            sys.exit(f"--device gpu: JAX's default backend is {jax.default_backend()!r}, not the GPU {gpus[0]}.")
    elif device is not None:
        raise ValueError(f"device={device!r}; expected 'cpu', 'gpu' or None.")
    return jax.default_backend()


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--paths", type=int, default=4096, help="paths for nhsde, (a), (b) (default 4096)")
    p.add_argument("--steps", type=int, default=1000, help="Euler steps of dt=0.01 (default 1000)")
    p.add_argument("--repeats", type=int, default=5, help="timed rounds; the minimum is reported (default 5)")
    p.add_argument("--c-paths", type=int, default=256, help="paths for (c) plain diffrax (default 256; 0 skips)")
    p.add_argument("--scenes", default="ball,sleigh,chaplygin-ball", help="comma-separated: ball,sleigh,chaplygin-ball")
    p.add_argument("--quick", action="store_true", help="smoke test: 512 paths, 200 steps, 2 repeats, 64 (c) paths")
    p.add_argument("--json", default=str(Path(__file__).resolve().parent / "results" / "throughput.json"))
    p.add_argument(
        "--device",
        choices=("cpu", "gpu"),
        help="the JAX backend: cpu, or gpu (fails clearly without one); default JAX's choice",
    )
    args = p.parse_args(argv)
    backend = select_device(args.device)
    if args.quick:
        args.paths, args.steps, args.repeats, args.c_paths = 512, 200, 2, 64
    if args.paths % 64:
        p.error("--paths must be a multiple of 64 (nhsde's Brownian block).")
    scenes = [s.strip() for s in args.scenes.split(",") if s.strip()]
    for s in scenes:
        if s not in SCENES:
            p.error(f"unknown scene {s!r}; choose from {', '.join(SCENES)}")

    info = machine_info()
    info["backend"] = backend
    if len(jax.devices()) > 1:
        print(f"note: nhsde shards over all {len(jax.devices())} devices, the other competitors use one")
    print("machine:")
    for k, v in info.items():
        print(f"  {k}: {v}")
    print(
        f"config: float32, dt={DT}, {args.paths} paths x {args.steps} steps (t1={args.steps * DT:g}); "
        f"(c) on {args.c_paths} paths; {args.repeats} timed rounds (min reported)\n"
    )

    all_rows, sanity, targets = [], {}, {}
    for scene in scenes:
        cases = make_cases(scene, args)
        print(f"[{scene}] compiling / warming up ...", flush=True)
        for c in cases:
            c.warm()
            print(f"  {c.impl:24s} {c.mode:15s} first call {c.compile_s:7.2f} s", flush=True)
        for r in range(args.repeats):
            for c in cases:
                c.run()
        by = {(c.impl, c.mode): c for c in cases}
        ref = by[("nhsde", "forward")]

        # ---- sanity: every implementation's K_xx(t1) against nhsde's
        v_ref, se_ref, _ = value_se_grad(ref)
        cfg = SCENES[scene]
        exact = None
        if scene == "ball":
            kxx = lambda th: ball_covariances(args.steps * DT, th[0], th[1], BALL_DELTA)[0]  # noqa: E731
            th64 = np.asarray([cfg["eps"], cfg["nu"]], np.float32)
            exact = {"value": float(kxx(th64)), "grad": [float(x) for x in jax.grad(kxx)(jnp.asarray(th64))]}
        print(f"\n[{scene}] sanity: K_xx(t1) = Var x(t1)  (± one Monte-Carlo standard error)")
        if exact:
            print(
                f"  exact (continuous SDE)         {exact['value']:.5f}   d/d(eps, nu) = "
                f"({exact['grad'][0]:+.4f}, {exact['grad'][1]:+.4f})"
            )
        san = {"exact": exact, "rows": []}
        for c in cases:
            v, se, grad = value_se_grad(c)
            z = (v - v_ref) / math.sqrt(se**2 + se_ref**2) if c is not ref else 0.0
            # nhsde's own rows share the key with the reference: identical paths, z must be ~0
            ok = abs(z) < 4.0
            gtxt = "" if grad is None else f"   d/d(eps, nu) = ({grad[0]:+.4f}, {grad[1]:+.4f})"
            extra = ""
            if c.impl.startswith("(c)") and isinstance(c.out, tuple):
                aux = c.out[1] if c.mode == "forward" else c.out[0][1]
                extra = f"   [diffrax steps taken: {int(aux[1])}]"
            print(
                f"  {c.impl:24s} {c.mode:15s} {v:.5f} ± {se:.5f}  z={z:+5.2f} {'ok' if ok else 'MISMATCH'}{gtxt}{extra}"
            )
            san["rows"].append(
                dict(impl=c.impl, mode=c.mode, paths=c.n_paths, value=v, se=se, z_vs_nhsde=z, consistent=ok, grad=grad)
            )
        sanity[scene] = san

        # ---- table
        print(f"\n[{scene}] throughput ({args.steps} steps; traj-steps/s = paths x steps / best time)")
        hdr = (
            f"  {'implementation':24s} {'mode':15s} {'paths':>6s} {'best s':>9s} {'median s':>9s} "
            f"{'traj-steps/s':>14s} {'time vs nhsde fwd':>18s} {'grad / own fwd':>15s}"
        )
        print(hdr)
        print("  " + "-" * (len(hdr) - 2))
        for c in cases:
            # time per trajectory-step relative to nhsde forward (> 1: slower than nhsde forward)
            per_fwd = ref.throughput / c.throughput
            own = by[c.forward_of] if c.forward_of else None
            grad_ratio = (own.throughput / c.throughput) if own else None
            row = dict(
                scene=scene,
                impl=c.impl,
                mode=c.mode,
                paths=c.n_paths,
                steps=c.steps,
                best_s=c.best,
                median_s=pystats.median(c.times),
                times_s=c.times,
                first_call_s=c.compile_s,
                traj_steps_per_s=c.throughput,
                time_per_traj_step_vs_nhsde_forward=per_fwd,
                grad_time_over_own_forward=grad_ratio,
            )
            all_rows.append(row)
            print(
                f"  {c.impl:24s} {c.mode:15s} {c.n_paths:6d} {c.best:9.4f} {row['median_s']:9.4f} "
                f"{fmt_rate(c.throughput):>14s} {per_fwd:18.2f} "
                f"{'' if grad_ratio is None else f'{grad_ratio:.2f}':>15s}"
            )

        # ---- targets
        t = {}
        a = by.get(("(a) lax.scan", "forward"))
        b = by.get(("(b) numpy", "forward"))
        cc = by.get(("(c) diffrax", "forward"))
        vg = by[("nhsde", "value_and_grad")]
        t["nhsde_time_over_scan (<= 1.5)"] = a.throughput / ref.throughput
        t["nhsde_speedup_over_numpy (> 1)"] = ref.throughput / b.throughput
        if cc:
            t["nhsde_speedup_over_diffrax (>= 15)"] = ref.throughput / cc.throughput
        t["nhsde_value_and_grad_over_forward (<= 3)"] = ref.throughput / vg.throughput
        met = {
            "nhsde_time_over_scan (<= 1.5)": lambda x: x <= 1.5,
            "nhsde_speedup_over_numpy (> 1)": lambda x: x > 1.0,
            "nhsde_speedup_over_diffrax (>= 15)": lambda x: x >= 15.0,
            "nhsde_value_and_grad_over_forward (<= 3)": lambda x: x <= 3.0,
        }
        print(f"\n[{scene}] targets")
        targets[scene] = {}
        for k, x in t.items():
            ok = bool(met[k](x))
            targets[scene][k] = {"ratio": x, "met": ok}
            print(f"  {k:44s} {x:8.2f}   {'MET' if ok else 'NOT MET'}")
        # extra context: reverse mode against the hand-fused loop's reverse mode
        avg = by[("(a) lax.scan", "value_and_grad")]
        print(f"  {'(nhsde vg time / (a) vg time)':44s} {avg.throughput / vg.throughput:8.2f}   (info)")
        print(flush=True)

    out = {
        "machine": info,
        "config": {
            "dtype": "float32",
            "dt": DT,
            "paths": args.paths,
            "steps": args.steps,
            "repeats": args.repeats,
            "c_paths": args.c_paths,
            "quick": args.quick,
            "device": args.device or backend,
        },
        "rows": all_rows,
        "sanity": sanity,
        "targets": targets,
        "loadavg_at_end": os.getloadavg(),
    }
    path = Path(args.json)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=2))
    print(f"load average at end: {os.getloadavg()}")
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
