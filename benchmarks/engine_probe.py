"""Ray against Dask distributed as the engine of the tiled map: cluster start, the per-scan
pattern between two actors, and what a killed actor looks like to the driver.

    python benchmarks/engine_probe.py --engine ray
    /work/venv-dask/bin/python benchmarks/engine_probe.py --engine both --scans 200 --repeats 5 --checks

No mapping library is imported: the actors' work is trivial (sum the payload), so the figures are
the engine's own cost. Each repeat runs in a fresh child process (a fresh local cluster of 2
worker processes), and with ``--engine both`` the engines alternate (and swap order every repeat).

1. start: from ``ray.init`` / ``LocalCluster`` to two actors answering a call (the engine's own
   import is timed apart, as ``import``).
2. scans: for each scan the driver puts a ~1 MB float32 payload (80,000 x 3) once; each of the two
   actors gets ``step(payload, events)``, where ``events`` is the small int32 array (50 x 3) that the
   OTHER actor returned for the previous scan.
   Ray: object refs go straight in as arguments (Ray resolves them), the driver keeps at most
   ``--window`` scans in flight and waits for scan i only once scan i + window is submitted.
   Dask: an actor call does not resolve a Future given to it (the method gets the Future object) and
   an ActorFuture cannot be serialized at all, so the driver gathers both results of a scan and
   sends them along itself (lockstep). The payload goes inline in both calls (serialized twice):
   a scattered Future reaches the actor unresolved, and its ``.result()`` fails there.
   Per scan: the times between successive scan completions, as the driver sees them; driver CPU
   (this process, all its threads) and cluster CPU (all processes below this one, from /proc).
3. ``--checks``: what an actor call given futures receives, and what the driver gets when an actor
   is killed (Ray: ``ray.kill``; Dask: SIGKILL of the worker process that holds the actor).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import time

import numpy as np

N_POINTS = 80_000
N_EVENTS = 50


class Stepper:
    """One tile worker: sums the payload, returns a few 'events' for the other worker."""

    def __init__(self, index: int) -> None:
        self.index = index
        self.n = 0

    def ready(self) -> int:
        return os.getpid()

    def step(self, payload, events):
        s = float(payload.sum())
        got = 0 if events is None else int(events.shape[0])
        self.n += 1
        out = np.empty((N_EVENTS, 3), dtype=np.int32)
        out[:] = np.arange(N_EVENTS, dtype=np.int32)[:, None] + (int(s) % 1000 + got + self.index)
        return out

    def fetch(self, fut) -> str:
        try:
            return f"ok: {type(fut.result()).__name__}"
        except Exception as e:  # noqa: BLE001 - the class is what we report
            return f"{type(e).__name__}: {str(e)[:110]}"

    def describe(self, *args) -> list[str]:
        return [f"{type(a).__module__}.{type(a).__qualname__}" for a in args]


def tree_cpu() -> float:
    """CPU seconds (user + system) of every live process below this one, read from /proc."""
    if not os.path.isdir("/proc"):
        return float("nan")
    tick = os.sysconf("SC_CLK_TCK")
    parent: dict[int, int] = {}
    cpu: dict[int, float] = {}
    for name in os.listdir("/proc"):
        if not name.isdigit():
            continue
        try:
            with open(f"/proc/{name}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        parent[int(name)] = int(fields[1])
        cpu[int(name)] = (int(fields[11]) + int(fields[12])) / tick
    me = os.getpid()
    total = 0.0
    for pid, c in cpu.items():
        p = parent.get(pid, 0)
        while p > 1 and p != me:
            p = parent.get(p, 0)
        if p == me:
            total += c
    return total


def payloads(k: int = 4) -> list[np.ndarray]:
    rng = np.random.default_rng(7)
    return [rng.random((N_POINTS, 3), dtype=np.float32) for _ in range(k)]


def summary(times: list[float]) -> dict:
    t = sorted(times)
    return {
        "median_ms": 1e3 * statistics.median(t),
        "p90_ms": 1e3 * t[min(len(t) - 1, round(0.9 * (len(t) - 1)))],
        "mean_ms": 1e3 * sum(t) / len(t),
    }


# ---------------------------------------------------------------- Ray


def run_ray(args) -> dict:
    t = time.perf_counter()
    import ray

    t_import = time.perf_counter() - t

    t0 = time.perf_counter()
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, logging_level="ERROR")
    Actor = ray.remote(num_cpus=1)(Stepper)
    actors = [Actor.remote(i) for i in range(2)]
    ray.get([a.ready.remote() for a in actors])
    t_start = time.perf_counter() - t0

    data = payloads()
    out = {"engine": "ray", "version": ray.__version__, "import_s": t_import, "start_s": t_start}

    def scans(n: int) -> list[float]:
        done_at: list[float] = []
        pending: list[list] = []
        prev = [None, None]
        last = time.perf_counter()
        for i in range(n):
            ref = ray.put(data[i % len(data)])
            cur = [actors[k].step.remote(ref, prev[1 - k]) for k in range(2)]
            pending.append(cur)
            prev = cur
            if len(pending) > args.window:
                ray.get(pending.pop(0))
                now = time.perf_counter()
                done_at.append(now - last)
                last = now
        for cur in pending:
            ray.get(cur)
            now = time.perf_counter()
            done_at.append(now - last)
            last = now
        return done_at

    scans(args.warmup)
    out.update(measure(scans, args.scans))
    t = time.perf_counter()
    ray.shutdown()
    out["stop_s"] = time.perf_counter() - t
    return out


def checks_ray() -> dict:
    import ray

    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, logging_level="ERROR")
    Actor = ray.remote(num_cpus=1)(Stepper)
    a, b = Actor.remote(0), Actor.remote(1)
    ray.get([a.ready.remote(), b.ready.remote()])
    res: dict = {"engine": "ray", "version": ray.__version__}
    ref = ray.put(payloads(1)[0])
    ev = a.step.remote(ref, None)
    res["args_received"] = ray.get(b.describe.remote(ref, ev))
    # kill mid-run: a call in flight, then ray.kill, then a fresh call
    inflight = a.step.remote(ref, None)
    ray.kill(a)
    for what, r in (("in-flight call", inflight), ("call after kill", a.step.remote(ref, None))):
        t = time.perf_counter()
        try:
            ray.get(r, timeout=60)
            res[what] = "returned (no error)"
        except Exception as e:  # noqa: BLE001 - the class is what we report
            mro = [c.__name__ for c in type(e).__mro__[1:4]]
            res[what] = f"{type(e).__module__}.{type(e).__name__} (bases {mro}) after {time.perf_counter() - t:.3f}s"
    res["other actor still works"] = ray.get(b.step.remote(ref, None)).shape == (N_EVENTS, 3)
    # the same with SIGKILL of the actor's worker process (a crash rather than ray.kill)
    pid = ray.get(b.ready.remote())
    inflight = b.step.remote(ref, None)
    os.kill(pid, signal.SIGKILL)
    t = time.perf_counter()
    try:
        ray.get(inflight, timeout=60)
        ray.get(b.step.remote(ref, None), timeout=60)
        res["SIGKILL of the actor's process"] = "returned (no error)"
    except Exception as e:  # noqa: BLE001
        res["SIGKILL of the actor's process"] = (
            f"{type(e).__module__}.{type(e).__name__} after {time.perf_counter() - t:.3f}s"
        )
    ray.shutdown()
    return res


# ---------------------------------------------------------------- Dask


def dask_cluster():
    import logging

    from dask.distributed import Client, LocalCluster

    cluster = LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None, silence_logs=logging.ERROR
    )
    client = Client(cluster)
    workers = sorted(client.scheduler_info()["workers"])
    futs = [
        client.submit(Stepper, i, actor=True, workers=[w], allow_other_workers=False) for i, w in enumerate(workers)
    ]
    actors = [f.result() for f in futs]
    [a.ready().result() for a in actors]
    return cluster, client, actors, workers


def run_dask(args) -> dict:
    t = time.perf_counter()
    import dask
    import distributed

    t_import = time.perf_counter() - t

    t0 = time.perf_counter()
    cluster, client, actors, _ = dask_cluster()
    t_start = time.perf_counter() - t0

    data = payloads()
    out = {"engine": "dask", "version": f"dask {dask.__version__}, distributed {distributed.__version__}"}
    out.update(import_s=t_import, start_s=t_start)

    def scans(n: int) -> list[float]:
        done_at: list[float] = []
        prev = [None, None]
        last = time.perf_counter()
        for i in range(n):
            payload = data[i % len(data)]  # inline: a Future would reach the actor unresolved
            cur = [actors[k].step(payload, prev[1 - k]) for k in range(2)]
            prev = [c.result() for c in cur]
            now = time.perf_counter()
            done_at.append(now - last)
            last = now
        return done_at

    scans(args.warmup)
    out.update(measure(scans, args.scans))
    t = time.perf_counter()
    client.close()
    cluster.close()
    out["stop_s"] = time.perf_counter() - t
    return out


def checks_dask() -> dict:
    import dask
    import distributed

    cluster, client, (a, b), workers = dask_cluster()
    res: dict = {"engine": "dask", "version": f"dask {dask.__version__}, distributed {distributed.__version__}"}
    payload = payloads(1)[0]
    fut = client.scatter(payload, direct=True)
    res["args_received (scattered Future, task Future)"] = b.describe(fut, client.submit(np.ones, 3)).result()
    res["Future.result() inside the actor"] = b.fetch(fut).result()
    try:
        res["args_received (ActorFuture)"] = b.describe(a.step(payload, None)).result(timeout=10)
    except Exception as e:  # noqa: BLE001
        res["args_received (ActorFuture)"] = (
            f"{type(e).__module__}.{type(e).__name__}: {str(e)[:120]}"
            " (the client logs 'TypeError: Could not serialize object of type ActorFuture'; the call never runs)"
        )
    # kill mid-run: SIGKILL the worker process that holds actor a, with a call in flight
    pid = a.ready().result()
    inflight = a.step(payload, None)
    os.kill(pid, signal.SIGKILL)
    time.sleep(0.5)
    for what, call in (("in-flight call", lambda: inflight), ("call after kill", lambda: a.step(payload, None))):
        t = time.perf_counter()
        try:
            call().result(timeout=60)
            res[what] = "returned (no error)"
        except Exception as e:  # noqa: BLE001
            mro = [c.__name__ for c in type(e).__mro__[1:4]]
            msg = str(e).replace("\n", " ")[:160]
            res[what] = (
                f"{type(e).__module__}.{type(e).__name__} (bases {mro}) after {time.perf_counter() - t:.3f}s: {msg}"
            )
    try:
        res["other actor still works"] = b.step(payload, None).result(timeout=30).shape == (N_EVENTS, 3)
    except Exception as e:  # noqa: BLE001
        res["other actor still works"] = f"{type(e).__name__}: {e}"
    time.sleep(3)
    res["workers after kill"] = f"{len(client.scheduler_info()['workers'])} (nanny restarts the process; was {workers})"
    res["actor future status"] = "the actor is gone with its worker; the new process holds no actor"
    client.close()
    cluster.close()
    return res


# ---------------------------------------------------------------- driver


def measure(scans, n: int) -> dict:
    cpu0, tree0, t0 = time.process_time(), tree_cpu(), time.perf_counter()
    per = scans(n)
    wall = time.perf_counter() - t0
    cpu, tree = time.process_time() - cpu0, tree_cpu() - tree0
    out = {"scans": n, "wall_s": wall, "driver_cpu_s": cpu, "cluster_cpu_s": tree}
    out.update(summary(per))
    out["driver_cpu_ms_per_scan"] = 1e3 * cpu / n
    out["cluster_cpu_ms_per_scan"] = 1e3 * tree / n
    return out


def have_dask() -> bool:
    try:
        import dask.distributed  # noqa: F401
    except ImportError:
        return False
    return True


def child(args) -> None:
    if args.checks_only:
        res = checks_ray() if args.engine == "ray" else checks_dask()
    else:
        res = run_ray(args) if args.engine == "ray" else run_dask(args)
    print("RESULT " + json.dumps(res), flush=True)


def spawn(engine: str, args, checks: bool = False) -> dict | None:
    cmd = [sys.executable, os.path.abspath(__file__), "--child", "--engine", engine, "--scans", str(args.scans)]
    cmd += ["--warmup", str(args.warmup), "--window", str(args.window)] + (["--checks-only"] if checks else [])
    p = subprocess.run(cmd, check=False, capture_output=True, text=True, timeout=900)
    for line in p.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[7:])
    print(f"{engine}: child failed (rc {p.returncode})\n{p.stderr[-3000:]}", file=sys.stderr)
    return None


def report(rows: list[dict]) -> None:
    keys = [
        "start_s",
        "import_s",
        "median_ms",
        "p90_ms",
        "mean_ms",
        "driver_cpu_ms_per_scan",
        "cluster_cpu_ms_per_scan",
    ]
    keys += ["stop_s"]
    for engine in ("ray", "dask"):
        rs = [r for r in rows if r["engine"] == engine]
        if not rs:
            continue
        print(f"\n{engine} ({rs[0]['version']}), {len(rs)} repeats of {rs[0]['scans']} scans")
        for k in keys:
            v = [r[k] for r in rs]
            vals = " ".join(f"{x:.3g}" for x in v)
            print(f"  {k:26s} median {statistics.median(v):9.4g}  range {min(v):.4g}..{max(v):.4g}   [{vals}]")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--engine", choices=["ray", "dask", "both"], default="both")
    ap.add_argument("--scans", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--warmup", type=int, default=5, help="scans run before the timed ones")
    ap.add_argument("--window", type=int, default=4, help="Ray: scans in flight before the driver waits")
    ap.add_argument("--checks", action="store_true", help="also the future-argument and killed-actor checks")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--checks-only", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args)
        return

    engines = ["ray", "dask"] if args.engine == "both" else [args.engine]
    if "dask" in engines and not have_dask():
        print("dask.distributed is not installed: skipping Dask (pip install dask distributed)")
        engines.remove("dask")
    if "ray" in engines:
        try:
            import ray  # noqa: F401
        except ImportError:
            print("ray is not installed: skipping Ray")
            engines.remove("ray")
    if not engines:
        return

    rows = []
    for r in range(args.repeats):
        for engine in engines if r % 2 == 0 else engines[::-1]:
            res = spawn(engine, args)
            if res is None:
                continue
            rows.append(res)
            print(
                f"repeat {r} {engine:4s}: start {res['start_s']:.2f}s  scan median {res['median_ms']:.2f} ms"
                f"  p90 {res['p90_ms']:.2f} ms  driver CPU {res['driver_cpu_ms_per_scan']:.2f} ms/scan"
                f"  cluster CPU {res['cluster_cpu_ms_per_scan']:.2f} ms/scan",
                flush=True,
            )
    report(rows)
    if args.checks:
        for engine in engines:
            res = spawn(engine, args, checks=True)
            if res is not None:
                print(f"\nchecks, {engine} ({res.pop('engine')}, {res.pop('version')}):")
                for k, v in res.items():
                    print(f"  {k}: {v}")


if __name__ == "__main__":
    main()
