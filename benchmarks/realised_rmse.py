"""Realised RMSE of ``to_accuracy`` against the RMSE it was asked for, estimator by estimator, over many keys.

    python benchmarks/realised_rmse.py [--scenes sleigh,chaplygin-ball,body] [--estimators NAME,...]
                                       [--keys 20] [--rel 1e-2] [--dt H] [--out FILE]
    python benchmarks/realised_rmse.py --merge FILE [FILE ...] [--out FILE]

For each scene of :mod:`benchmarks.estimators` with an exact value (the sleigh ``E[H](2)``, closed form;
Chaplygin's ball ``E[H](4)``, the stationary ``3ν/(8ε)``; the body on the vibrating plane ``E[H](1)``, against
the recorded reference ``BODY_REFERENCE`` whose own SE 6.6e-4 is accounted for) and for each estimator alone
(``to_accuracy(..., estimators=(E,))``, absolute ``rmse = rel·|exact|``, the case's ``t1``, statistic, ``save`` and
``y0``, the default coarsest step) it runs ``--keys`` keys ``jax.random.key(1000 + i)`` and records per key the
value, SE, bias estimate, realised error, path-steps (pilots included), seconds (compiling included) and choice.
Estimators (``--estimators``): ``plain-euler``, ``plain-weak2``, ``richardson-euler``, ``richardson-weak2``,
``multilevel-euler``, ``multilevel-weak2``, ``multilevel-weak2-anti``, ``control-variate``, ``qmc``, ``qmc-weak2``,
``qmc-anti`` (antithetic points), ``plain-heun2``, ``richardson-heun2``, ``multilevel-heun2``, ``qmc-heun2`` (Heun's
method, the body's first pilot), ``mlqmc``, ``mlqmc-weak2`` (``MultilevelQuasiMonteCarlo``),
``multilevel-weak2-control``, ``qmc-weak2-control``, ``mlqmc-weak2-control`` (the linearised control variate inside)
(``weak2`` is ``PlatenWeak2(increments='gaussian')``).

Per cell, over the runs that returned (float64):

- realised RMSE/ε = √(Σ errors²/n)/ε.  If every run's MSE is ≤ ε² (and its error about Gaussian), Σ errors²/ε²
  is stochastically below χ²_n (a split of the MSE into bias² and variance only narrows it: for a fixed MSE the
  variance of Σ errors² is largest with no bias), so RMSE/ε ≤ √(χ²_{n,0.99}/n) (≈ 1.37 for n = 20) at 99 %.  For
  the body the reference's error δ (SE σ_ref) is common to every run: the bound is the 99 % quantile of
  √(Σ(x_i + δ)²/n)/ε with x_i ~ N(0, ε²), δ ~ N(0, σ_ref²), by simulation;
- mean error / SE of the mean (√(Σ SE_i²)/n, with σ_ref added in quadrature for the body): |z| ≫ 3 is a bias
  the runs' SEs do not cover;
- coverage: the fraction of runs with |error| ≤ 2·(reported SE) (about 95 % if the SE is right and the bias small;
  for the body the reference's σ_ref is added to each SE in quadrature).

An estimator that does not apply (``to_accuracy`` raises ``ValueError``: no alternative reaches the target) is
recorded with the exception text, key by key (whether it applies can depend on the key: a pilot whose paths grow
huge but stay finite); the statistics are over the keys that returned.
Writes ``--out`` (default benchmarks/results/realised_rmse.json) after every scene × estimator and prints a
markdown table at the end.  ``--dt H`` gives ``to_accuracy`` that coarsest step instead of its default (a
supplementary run where the default fails); ``--merge`` only merges result files (e.g. one per scene, run as
separate processes) into ``--out`` and prints their table.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import pathlib
import platform
import subprocess
import sys
import time
import traceback

import jax

jax.config.update("jax_enable_x64", True)
import numpy as np  # noqa: E402
from scipy import stats  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).parent))
from estimators import BODY_REFERENCE, CASES  # noqa: E402

import nhsde  # noqa: E402
from nhsde.statistics import (  # noqa: E402
    ControlVariate,
    MartingaleControlVariate,
    Multilevel,
    MultilevelQuasiMonteCarlo,
    PlainMonteCarlo,
    QuasiMonteCarlo,
    Richardson,
    to_accuracy,
)

OUT = pathlib.Path(__file__).parent / "results"
GAUSS = nhsde.PlatenWeak2(increments="gaussian")
SCENES = ("sleigh", "chaplygin-ball", "body")


def estimator_objects():
    """The estimators by name, each alone given to ``to_accuracy``."""
    return {
        "plain-euler": PlainMonteCarlo("euler"),
        "plain-weak2": PlainMonteCarlo(GAUSS),
        "richardson-euler": Richardson("euler"),
        "richardson-weak2": Richardson(GAUSS),
        "multilevel-euler": Multilevel("euler"),
        "multilevel-weak2": Multilevel(GAUSS),
        "multilevel-weak2-anti": Multilevel(GAUSS, antithetic=True),
        "control-variate": ControlVariate(),
        "qmc": QuasiMonteCarlo(),
        "qmc-weak2": QuasiMonteCarlo(GAUSS),
        "qmc-anti": QuasiMonteCarlo(antithetic=True),
        "plain-heun2": PlainMonteCarlo("heun2"),
        "richardson-heun2": Richardson("heun2"),
        "multilevel-heun2": Multilevel("heun2"),
        "qmc-heun2": QuasiMonteCarlo("heun2"),
        "mlqmc": MultilevelQuasiMonteCarlo(),
        "mlqmc-weak2": MultilevelQuasiMonteCarlo(GAUSS),
        "multilevel-weak2-control": Multilevel(GAUSS, control=True),
        "qmc-weak2-control": QuasiMonteCarlo(GAUSS, control=True),
        "mlqmc-weak2-control": MultilevelQuasiMonteCarlo(GAUSS, control=True),
        "martingale-weak2": MartingaleControlVariate(GAUSS),
        "multilevel-weak2-martingale": Multilevel(GAUSS, control="martingale"),
    }


def chi2_bound(n: int, level: float = 0.99) -> float:
    """√(χ²_{n,level}/n): the bound on realised RMSE/ε over n runs each of MSE ≤ ε²."""
    return math.sqrt(stats.chi2.ppf(level, n) / n)


def bound_with_reference(n: int, ref_ratio: float, level: float = 0.99, draws: int = 400_000, seed: int = 0) -> float:
    """99 % quantile of √(Σ(x_i + δ)²/n)/ε, x_i ~ N(0, ε²) independent, δ ~ N(0, (ref_ratio·ε)²) common to all."""
    if ref_ratio == 0:
        return chi2_bound(n, level)
    rng = np.random.default_rng(seed)
    x = rng.standard_normal((draws, n)) + ref_ratio * rng.standard_normal((draws, 1))
    return float(np.quantile(np.sqrt(np.mean(x**2, axis=1)), level))


def one_run(case, estimator, key_index, eps, dt=None):
    """One ``to_accuracy`` call: a dict of what it returned (or the exception)."""
    start = time.perf_counter()
    try:
        r = to_accuracy(
            case["system"],
            case["y0"],
            jax.random.key(key_index),
            t1=case["t1"],
            statistic=case["target"],
            rmse=eps,
            save=case["save"],
            dt=dt,
            estimators=(estimator,),
        )
    except Exception as e:  # recorded, never hidden
        return dict(
            key=key_index,
            ok=False,
            exception=type(e).__name__,
            message=str(e)[:2000],
            traceback=traceback.format_exc()[-1500:],
            seconds=time.perf_counter() - start,
        )
    value, se = r.value()
    chosen = next((a for a in r.alternatives if a.name == r.choice), None)
    return dict(
        key=key_index,
        ok=True,
        value=value,
        se=se,
        bias=r.bias,
        path_steps=r.cost.path_steps,
        pilot_path_steps=r.pilot_cost.path_steps,
        predicted_path_steps=r.predicted.path_steps,
        seconds=r.cost.seconds,
        compile_seconds=r.cost.compile_seconds,
        choice=r.choice,
        reason=r.reason,
        h0=r.pilot[0].dts[0] if r.pilot else math.nan,
        dt=None if chosen is None else chosen.dt,
        n_paths=None if chosen is None else list(chosen.n_paths),
        note=None if chosen is None else chosen.note,
    )


def summarise(runs, exact, eps, ref_se):
    """Realised RMSE/ε with its 99 % bound, mean error in SEs of the mean, coverage, mean cost."""
    ok = [r for r in runs if r["ok"]]
    out = dict(n_runs=len(runs), n_ok=len(ok), n_failed=len(runs) - len(ok))
    if not ok:
        return out
    n = len(ok)
    errors = np.array([r["value"] - exact for r in ok])
    ses = np.array([r["se"] for r in ok])
    rmse = float(np.sqrt(np.mean(errors**2)))
    se_mean = float(np.sqrt(np.sum(ses**2) / n**2 + ref_se**2))
    warm = [r["seconds"] for r in ok[1:]] or [ok[0]["seconds"]]
    out.update(
        realised_rmse=rmse,
        ratio=rmse / eps,
        bound99=bound_with_reference(n, ref_se / eps),
        mean_error=float(np.mean(errors)),
        mean_error_in_se=float(np.mean(errors) / se_mean),
        coverage=float(np.mean(np.abs(errors) <= 2 * np.sqrt(ses**2 + ref_se**2))),
        mean_se_over_eps=float(np.mean(ses) / eps),
        mean_abs_bias_over_eps=float(np.mean(np.abs([r["bias"] for r in ok])) / eps),
        mean_error_over_eps=float(np.mean(errors) / eps),
        sd_error_over_eps=float(np.std(errors, ddof=1) / eps) if n > 1 else math.nan,
        mean_bias_over_eps=float(np.mean([r["bias"] for r in ok]) / eps),
        mean_path_steps=float(np.mean([r["path_steps"] for r in ok])),
        mean_seconds=float(np.mean([r["seconds"] for r in ok])),
        mean_seconds_after_first=float(np.mean(warm)),
        first_seconds=ok[0]["seconds"],
        choices=sorted({f"{r['choice']} dt={r['dt']:.4g}" for r in ok}),
        h0s=sorted({r["h0"] for r in ok}),
        retried=sum("priced again" in r["reason"] for r in ok),
    )
    out["passes"] = out["ratio"] <= out["bound99"]
    return out


def label(cell):
    """The estimator's name, with the coarsest step where one was given."""
    return cell["estimator"] + (f" (dt={cell['dt']:g})" if cell.get("dt") else "")


def table(cells):
    """Markdown table of the cells."""
    lines = [
        "| scene | estimator | RMSE/ε | 99 % bound | mean err / SE | mean err/ε (bias est./ε) | SD err/ε (mean SE/ε) "
        "| coverage (±2 SE) | mean path-steps | mean s (first) | chosen / notes |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for c in cells:
        s = c["summary"]
        if not s.get("n_ok"):
            msg = c["runs"][0]["message"].splitlines()[0][:140] if c["runs"] else c.get("skipped", "")
            exc = c["runs"][0]["exception"] if c["runs"] else ""
            lines.append(f"| {c['scene']} | {label(c)} | – | – | – | – | – | – | – | – | {exc}: {msg} |")
            continue
        notes = "; ".join(s["choices"][:3])
        if s["n_failed"]:
            failed = [r for r in c["runs"] if not r["ok"]]
            first = failed[0]["message"].splitlines()[0][:90]
            notes += f"; {s['n_failed']}/{s['n_runs']} raised ({failed[0]['exception']}: {first})"
        if s["retried"]:
            notes += f"; {s['retried']} retried from dt/2"
        if len(s["h0s"]) > 1 or s["h0s"][0] != c["default_h0"]:
            notes += f"; h0 {','.join(f'{h:g}' for h in s['h0s'])}"
        mark = "" if s["passes"] else " **fail**"
        lines.append(
            f"| {c['scene']} | {label(c)} | {s['ratio']:.2f}{mark} | {s['bound99']:.2f} | "
            f"{s['mean_error_in_se']:+.1f} | {s['mean_error_over_eps']:+.2f} ({s['mean_bias_over_eps']:+.2f}) | "
            f"{s['sd_error_over_eps']:.2f} ({s['mean_se_over_eps']:.2f}) | {s['coverage']:.2f} | "
            f"{s['mean_path_steps']:.3g} | "
            f"{s['mean_seconds_after_first']:.1f} ({s['first_seconds']:.0f}) | {notes} (n={s['n_ok']}) |"
        )
    return "\n".join(lines)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    names = list(estimator_objects())
    parser.add_argument("--scenes", default=",".join(SCENES), help=f"comma-separated, from {', '.join(SCENES)}")
    parser.add_argument("--estimators", default=",".join(names), help=f"comma-separated, from {', '.join(names)}")
    parser.add_argument("--keys", type=int, default=20, help="keys per cell: jax.random.key(1000 + i)")
    parser.add_argument("--rel", type=float, default=1e-2, help="target RMSE relative to |exact|")
    parser.add_argument("--out", default=str(OUT / "realised_rmse.json"))
    parser.add_argument("--append", action="store_true", help="keep the cells already in --out (other scenes)")
    parser.add_argument(
        "--dt", type=float, help="the coarsest step given to to_accuracy (default: none, its own default)"
    )
    parser.add_argument("--merge", nargs="+", help="only merge these result files into --out and print the table")
    args = parser.parse_args()
    if args.merge:
        records = [json.loads(pathlib.Path(f).read_text()) for f in args.merge]
        by_cell = {}  # a later file's cell replaces an earlier one of the same scene, estimator and dt
        for c in (c for r in records for c in r["cells"]):
            c["summary"] = summarise(c["runs"], c["exact"], c["rmse"], c["reference_se"])  # this version's
            by_cell[(c["scene"], c["estimator"], c.get("dt"))] = c
        cells = list(by_cell.values())
        merged = dict(sources=args.merge, machines=[r["machine"] for r in records], cells=cells, table=table(cells))
        pathlib.Path(args.out).write_text(json.dumps(merged, indent=2, default=str))
        print(merged["table"] + f"\nwrote {args.out}")
        return
    scenes = [s.strip() for s in args.scenes.split(",") if s.strip()]
    chosen = [s.strip() for s in args.estimators.split(",") if s.strip()]
    bad = [s for s in scenes if s not in SCENES] + [e for e in chosen if e not in names]
    if bad:
        parser.error(f"unknown {bad}")
    path = pathlib.Path(args.out)
    path.parent.mkdir(exist_ok=True)
    revision = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    machine = dict(
        cpu_count=os.cpu_count(),
        platform=platform.platform(),
        versions=dict(jax=jax.__version__, nhsde=nhsde.__version__),
        git=revision,
        date=time.strftime("%Y-%m-%d %H:%M %Z"),
        loadavg_start=os.getloadavg(),
    )
    cells = []
    if args.append and path.exists():
        cells = json.loads(path.read_text()).get("cells", [])
    record = dict(machine=machine, args=vars(args), cells=cells)
    objects = estimator_objects()
    for scene in scenes:
        case = CASES[scene]()
        exact, ref_se = BODY_REFERENCE if case["exact"] is None else (case["exact"], 0.0)
        eps = args.rel * abs(exact)
        print(f"\n[{scene}] exact {exact:.6g} (ref SE {ref_se:.2g}), rmse ε = {eps:.3g}", flush=True)
        for name in chosen:
            est = objects[name]
            cell = dict(
                scene=scene,
                estimator=name,
                repr=repr(est),
                exact=exact,
                reference_se=ref_se,
                rmse=eps,
                rel=args.rel,
                default_h0=case["t1"] / 4 if args.dt is None else args.dt,
                dt=args.dt,
                runs=[],
            )
            cells[:] = [c for c in cells if not (c["scene"] == scene and c["estimator"] == name)]
            cells.append(cell)
            for i in range(args.keys):
                run = one_run(case, est, 1000 + i, eps, args.dt)
                cell["runs"].append(run)
                if run["ok"]:
                    print(
                        f"  {name:<22} key {1000 + i}: error/ε {(run['value'] - exact) / eps:+.2f}, SE/ε "
                        f"{run['se'] / eps:.2f}, bias/ε {run['bias'] / eps:+.2f}, {run['path_steps']:.3g} "
                        f"path-steps, {run['seconds']:.1f} s; {run['choice']} dt={run['dt']:.4g}",
                        flush=True,
                    )
                else:
                    print(f"  {name:<22} key {1000 + i}: {run['exception']}: {run['message'][:300]}", flush=True)
                cell["summary"] = summarise(cell["runs"], exact, eps, ref_se)
                machine["loadavg_now"] = os.getloadavg()
                path.write_text(json.dumps(record, indent=2, default=str))
            cell["summary"] = summarise(cell["runs"], exact, eps, ref_se)
            s = cell["summary"]
            if s.get("n_ok"):
                print(
                    f"  => {name}: RMSE/ε {s['ratio']:.2f} (99 % bound {s['bound99']:.2f}), mean error "
                    f"{s['mean_error_in_se']:+.1f} SE, coverage {s['coverage']:.2f}",
                    flush=True,
                )
            path.write_text(json.dumps(record, indent=2, default=str))
    machine["loadavg_end"] = os.getloadavg()
    record["table"] = table(cells)
    path.write_text(json.dumps(record, indent=2, default=str))
    print("\n" + record["table"] + f"\nwrote {path}")


if __name__ == "__main__":
    main()
