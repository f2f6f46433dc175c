"""The spec scenes' vector fields alone: drift and diffusion of 4096 states under ``jit(vmap)``, float32.

    python benchmarks/spec_fields.py                      # this checkout
    PYTHONPATH=/path/to/other/checkout/src python benchmarks/spec_fields.py   # another revision, to alternate with

Prints one JSON line, ``{scene: median ms of 30 warm calls}``, for every registered spec scene (default route) and
the docs' user scene (``tests/data/knife_edge.py``).  Alternate revisions in fresh processes and read ratios only:
absolute times on a shared machine mean little.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from nhsde.scenes import SCENES
from nhsde.scenes._spec_scene import AbstractSpecScene

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "data"))
from knife_edge import KnifeEdge  # noqa: E402  the docs' "Your own scene"


def fields_ms(scene, n: int = 4096, repeats: int = 30) -> float:
    system = scene.build()
    y = jnp.broadcast_to(scene.initial_state(), (n, system.state_dim)).astype(jnp.float32)
    y = y + 0.01 * jax.random.normal(jax.random.key(0), y.shape, jnp.float32)
    params = jax.tree_util.tree_map(
        lambda x: x.astype(jnp.float32) if jnp.issubdtype(x.dtype, jnp.floating) else x, system.params
    )
    t = jnp.zeros((), jnp.float32)
    both = jax.jit(lambda y, p: jax.vmap(lambda z: (system.drift_fn(t, z, p), system.diffusion_fn(t, z, p)))(y))
    jax.block_until_ready(both(y, params))
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(both(y, params))
        times.append(time.perf_counter() - start)
    return round(1e3 * float(np.median(times)), 3)


if __name__ == "__main__":
    scenes = {name: cls() for name, cls in sorted(SCENES.items()) if issubclass(cls, AbstractSpecScene)}
    scenes["user knife edge"] = KnifeEdge()
    print(json.dumps({name: fields_ms(scene) for name, scene in scenes.items()}))
