"""`experiment synthetic` on a Dask LocalCluster against one worker (issue 13, item 3).

Starts a LocalCluster (``--n-workers`` processes, one thread each), runs the command line twice,
``--workers 1`` and ``--scheduler <the cluster's address>``, and compares the two ``trials.csv``
byte for byte with the ``time_ms`` column removed. Prints both wall times.

    PYTHONPATH=src python benchmarks/cluster.py --trials 1000 --out results/cluster
"""

from __future__ import annotations

import argparse
import csv
import io
import os
import subprocess
import sys
import time
from pathlib import Path


def strip_time(path: Path) -> str:
    rows = list(csv.reader(io.StringIO(path.read_text())))
    k = rows[0].index("time_ms")
    return "\n".join(",".join(r[:k] + r[k + 1:]) for r in rows)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=1000)
    ap.add_argument("--methods", default="opencv-ippe-lm,opencv-sqpnp")
    ap.add_argument("--sigmas", default="0:5:0.5")
    ap.add_argument("--n-workers", type=int, default=2)
    ap.add_argument("--out", default="results/cluster")
    a = ap.parse_args()
    import distributed

    out = Path(a.out)
    base = [sys.executable, "-m", "cutterpose.cli", "experiment", "synthetic", "--methods",
            a.methods, "--trials", str(a.trials), "--sigmas", a.sigmas, "--no-progress"]
    src = str(Path(__file__).resolve().parents[1] / "src")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        p for p in (src, os.environ.get("PYTHONPATH", "")) if p))
    os.environ["PYTHONPATH"] = env["PYTHONPATH"]  # the cluster's worker processes
    times = {}
    t0 = time.perf_counter()
    subprocess.run(base + ["--out", str(out / "one"), "--workers", "1"], check=True, env=env,
                   stdout=subprocess.DEVNULL)
    times["one"] = time.perf_counter() - t0
    with distributed.LocalCluster(n_workers=a.n_workers, processes=True, threads_per_worker=1,
                                  dashboard_address=None, silence_logs=40) as cluster:
        t0 = time.perf_counter()
        subprocess.run(base + ["--out", str(out / "dask"), "--scheduler",
                               cluster.scheduler_address], check=True, env=env,
                       stdout=subprocess.DEVNULL)
        times["dask"] = time.perf_counter() - t0
    one, dask = strip_time(out / "one" / "trials.csv"), strip_time(out / "dask" / "trials.csv")
    n = one.count("\n")
    same = one == dask
    print(f"trials.csv rows: {n}; identical without time_ms: {same}")
    print(f"wall time: --workers 1 {times['one']:.1f} s, --scheduler (LocalCluster of "
          f"{a.n_workers} processes) {times['dask']:.1f} s")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
