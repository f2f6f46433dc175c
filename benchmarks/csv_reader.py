"""Reading a large per-path CSV: ``Observations.from_csv`` against ``pandas.read_csv`` on the same file.

Writes a per-path file (columns ``path, t, x, u_x``, 10 times per path, values written to 17 digits) of about
``--mb`` megabytes, in two layouts: path by path (as files are written; the reader's fast path) and its rows
shuffled (the general path: paths and times found by hashing).  Then measures on each

- the peak resident memory each reader adds (``VmHWM`` after the read less ``VmRSS`` before it, the peak reset
  through ``/proc/self/clear_refs``), each in a fresh process with its imports done;
- the time of each, in one process, alternating, the best of ``--repeat`` reads (and the median of the
  ratios of the reads paired in turn, less sensitive to a machine that others load);

and prints the ratios to the file's size and to pandas' time (targets: memory ≤ 3× the file, time ≤ 2× pandas).

    python benchmarks/csv_reader.py              # about 50 MB
    python benchmarks/csv_reader.py --mb 220     # the size of the report that asked for it
"""

import argparse
import json
import pathlib
import subprocess
import sys
import tempfile
import time
from typing import Any

import numpy as np

TIMES = 10

CHILD = """
import json, pathlib, sys
import numpy as np, pandas as pd
from nhsde import fit
which, file, warm = sys.argv[1], pathlib.Path(sys.argv[2]), pathlib.Path(sys.argv[3])
read = (lambda f: pd.read_csv(f)) if which == "pandas" else fit.Observations.from_csv
read(warm)  # imports and first-call work before the measurement

def status(key):
    for line in open("/proc/self/status"):
        if line.startswith(key):
            return int(line.split()[1]) * 1024
pathlib.Path("/proc/self/clear_refs").write_text("5")  # reset the peak (VmHWM) to the present RSS
before = status("VmRSS:")
out = read(file)
print(json.dumps(dict(growth=status("VmHWM:") - before)))
"""


def write_per_path(file: pathlib.Path, megabytes: float, seed: int = 0, shuffle: bool = False) -> int:
    """A per-path CSV of about ``megabytes`` MB, path by path or its rows shuffled; returns its number of paths."""
    import pandas as pd

    rng = np.random.default_rng(seed)
    n_paths = max(64, int(megabytes * 1e6 / 63 / TIMES))  # about 63 bytes a row
    ts = np.arange(1, TIMES + 1) / TIMES
    order = rng.permutation(n_paths * TIMES) if shuffle else None
    with open(file, "w") as f:
        f.write("path,t,x,u_x\n")
        if order is not None:
            z = rng.normal(size=(n_paths, TIMES, 2)) * np.sqrt(ts)[None, :, None]
            table = pd.DataFrame(
                {
                    "path": np.repeat(np.arange(n_paths), TIMES)[order],
                    "t": np.tile(ts, n_paths)[order],
                    "x": z[..., 0].reshape(-1)[order],
                    "u_x": z[..., 1].reshape(-1)[order],
                }
            )
            table.to_csv(f, header=False, index=False, float_format="%.17g")
            return n_paths
        for start in range(0, n_paths, 20_000):
            paths = np.arange(start, min(n_paths, start + 20_000))
            z = rng.normal(size=(len(paths), TIMES, 2)) * np.sqrt(ts)[None, :, None]
            table = pd.DataFrame(
                {
                    "path": np.repeat(paths, TIMES),
                    "t": np.tile(ts, len(paths)),
                    "x": z[..., 0].reshape(-1),
                    "u_x": z[..., 1].reshape(-1),
                }
            )
            table.to_csv(f, header=False, index=False, float_format="%.17g")
    return n_paths


def growth(which: str, file: pathlib.Path, warm: pathlib.Path) -> int:
    out = subprocess.run([sys.executable, "-c", CHILD, which, str(file), str(warm)], capture_output=True, text=True)
    if out.returncode:
        raise RuntimeError(out.stderr.strip())
    return json.loads(out.stdout.strip().splitlines()[-1])["growth"]


def measure(file: pathlib.Path, warm: pathlib.Path, repeat: int) -> dict[str, Any]:
    import pandas as pd

    from nhsde import fit

    size = file.stat().st_size
    memory = {which: growth(which, file, warm) for which in ("pandas", "nhsde")}
    fit.Observations.from_csv(warm)
    seconds: dict[str, list[float]] = {"pandas": [], "nhsde": []}
    for _ in range(repeat):
        for which, read in (("pandas", pd.read_csv), ("nhsde", fit.Observations.from_csv)):
            start = time.perf_counter()
            read(file)
            seconds[which].append(time.perf_counter() - start)
    best = {which: min(s) for which, s in seconds.items()}
    return dict(
        file_mb=size / 1e6,
        seconds=best,
        memory_growth_mb={which: m / 1e6 for which, m in memory.items()},
        memory_ratio_to_file=memory["nhsde"] / size,
        time_ratio_to_pandas=best["nhsde"] / best["pandas"],
        paired_time_ratio_median=float(np.median(np.divide(seconds["nhsde"], seconds["pandas"]))),
    )


def main():
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--mb", type=float, default=50.0, help="the file's size in MB (default 50)")
    parser.add_argument("--repeat", type=int, default=5, help="timed reads of each (default 5, best kept)")
    args = parser.parse_args()
    results = []
    with tempfile.TemporaryDirectory() as folder:
        warm = pathlib.Path(folder) / "warm.csv"
        write_per_path(warm, 0.05, seed=1)
        for layout in ("path by path", "shuffled"):
            file = pathlib.Path(folder) / "paths.csv"
            n_paths = write_per_path(file, args.mb, shuffle=layout == "shuffled")
            result: dict[str, Any] = dict(layout=layout, paths=n_paths, times=TIMES)
            result.update(measure(file, warm, args.repeat))
            results.append(result)
            file.unlink()
            print(f"{layout}: {result['file_mb']:.1f} MB, {n_paths} paths × {TIMES} times")
            for which in ("pandas", "nhsde"):
                name = "pandas.read_csv" if which == "pandas" else "Observations.from_csv"
                mb = result["memory_growth_mb"][which]
                print(
                    f"{name:>24}: {result['seconds'][which]:6.2f} s, peak memory growth {mb:7.1f} MB "
                    f"({mb / result['file_mb']:.2f}× the file)"
                )
            print(
                f"  from_csv memory / file size: {result['memory_ratio_to_file']:.2f} (target ≤ 3); "
                f"from_csv / read_csv time: {result['time_ratio_to_pandas']:.2f} (target ≤ 2; paired median "
                f"{result['paired_time_ratio_median']:.2f})"
            )
    print(json.dumps(results))


if __name__ == "__main__":
    main()
