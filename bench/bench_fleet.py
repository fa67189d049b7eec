"""Fleet benchmark: bags/s and samples/s of ``fleet`` with 1 and 2 worker processes, the
scaling efficiency, and the peak memory of a worker against bag length.

The bags: bench_replay's simulated CRS A465 (6 joints, 1 kHz, measured torque, fv and fc
identified with config/crs_a465.yaml), ``--bags`` links to the same cached bag of
``--samples`` samples (separate paths, so separate tasks). Each configuration runs on a fresh
LocalCluster (single-threaded worker processes), warmed up by importing the package and by
one untimed fleet run of one bag per worker (a worker's first task loads the robot and warms
its caches); the time is run_fleet's wall time of the next run (map on the workers, reduce
and solve here), best of ``--repeat`` runs alternating 1 and 2 workers. Scaling efficiency =
speed-up / 2.

Memory: a fresh 1-worker cluster maps one bag of each length in ``--lengths``; the worker's
peak resident set size (VmHWM) above its size before the task.

    .venv/bin/python bench/bench_fleet.py [--samples 100000] [--bags 4] [--repeat 3]
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import checkout  # noqa: E402,F401  (this checkout's package, here and in subprocesses)

# One BLAS/OpenMP thread per process, set before numpy loads (the workers inherit it; Dask's
# nanny sets the same for its workers: distributed.nanny.pre-spawn-environ).
for _name in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ.setdefault(_name, '1')

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_replay import CONFIG, make_bag  # noqa: E402


def vmhwm_kib() -> int:
    """This process's peak resident set size (kiB)."""
    for line in open('/proc/self/status'):
        if line.startswith('VmHWM:'):
            return int(line.split()[1])
    return 0


def reset_peak() -> int:
    """Reset VmHWM to the current RSS (Linux: write 5 to clear_refs); the RSS then (kiB)."""
    with open('/proc/self/clear_refs', 'w') as f:
        f.write('5')
    return vmhwm_kib()


def warm_up() -> None:
    import identification_node.fleet.fleet  # noqa: F401


def cluster(workers: int):
    from distributed import Client, LocalCluster

    c = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                     host='127.0.0.1', dashboard_address='127.0.0.1:0')
    client = Client(c)
    client.run(warm_up)
    return client


def entries(bag: Path, count: int, folder: Path) -> list:
    from identification_node.fleet.fleet import FleetEntry

    out = []
    for k in range(count):
        link = folder / f'bag{k}'
        if not link.exists():
            link.symlink_to(bag.resolve(), target_is_directory=True)
        out.append(FleetEntry(str(link), 'crs', f'p{k % 2}', config=str(CONFIG)))
    return out


def timed_run(workers: int, fleet_entries: list) -> tuple[float, float, float, int]:
    """(wall s, map wall s: until the last map task is back, CPU s of the workers, samples
    used) of one fleet run."""
    from identification_node.fleet.fleet import run_fleet

    client = cluster(workers)
    mapped = []

    def progress(done: int, total: int) -> None:
        if done == total:
            mapped.append(time.perf_counter())
    try:
        run_fleet(fleet_entries[:workers], client)   # warm-up: first tasks load the robot
        cpu0 = client.run(time.process_time)
        start = time.perf_counter()
        result = run_fleet(fleet_entries, client, progress=progress)
        wall = time.perf_counter() - start
        cpu1 = client.run(time.process_time)
    finally:
        c = client.cluster
        client.close()
        c.close()
    if result.failed:
        raise SystemExit(f'bench: failed bags {result.failed}')
    cpu = sum(cpu1[w] - cpu0[w] for w in cpu1)
    return wall, mapped[0] - start, cpu, sum(s.used for s in result.groups.values())


def peak_memory(bag: Path) -> tuple[float, float]:
    """(RSS before, peak RSS above it) of a fresh worker mapping ``bag``, MiB."""
    from identification_node.fleet.fleet import FleetEntry, MapTask, run_task

    client = cluster(1)
    try:
        before = next(iter(client.run(reset_peak).values()))
        task = MapTask(FleetEntry(str(bag), 'crs', 'p', config=str(CONFIG)))
        stats = client.submit(run_task, task, pure=False).result()
        peak = next(iter(client.run(vmhwm_kib).values()))
    finally:
        c = client.cluster
        client.close()
        c.close()
    if not hasattr(stats, 'used'):
        raise SystemExit(f'bench: {stats}')
    return before / 1024, (peak - before) / 1024


def solve_times(bag: Path, repeat: int) -> tuple[float, float]:
    """(s, s): segments.identification of the runs' 3 groups (two periods of 2 bags, the total
    of 4) with a new consistent solver per group, and with one solver for all (run_fleet's),
    best of ``repeat`` alternating, in this process (the client)."""
    from identification_node.fleet import fleet
    from identification_node.replay import segments

    entry = fleet.FleetEntry(str(bag), 'crs', 'p', config=str(CONFIG))
    stats = fleet.run_task(fleet.MapTask(entry))
    groups = [stats + stats, stats + stats, stats + stats + stats + stats]
    settings = fleet.entry_settings(entry)
    robot = fleet.entry_robot(entry, settings)
    segments.identification(stats, settings, robot)    # imports, caches
    best = [float('inf'), float('inf')]
    for _ in range(repeat):
        for k in (0, 1):
            start = time.perf_counter()
            solver = segments.consistent_solver(settings, robot) if k else None
            for g in groups:
                segments.identification(g, settings, robot, solver=solver)
            best[k] = min(best[k], time.perf_counter() - start)
    return best[0], best[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--samples', type=int, default=100000)
    parser.add_argument('--bags', type=int, default=4)
    parser.add_argument('--repeat', type=int, default=3)
    parser.add_argument('--lengths', type=int, nargs='+', default=[50000, 100000])
    args = parser.parse_args()
    import logging
    logging.getLogger('distributed').setLevel(logging.ERROR)

    bag = make_bag(args.samples)
    runs: dict[int, list] = {1: [], 2: []}
    with tempfile.TemporaryDirectory() as tmp:
        fleet_entries = entries(bag, args.bags, Path(tmp))
        samples = 0
        for r in range(args.repeat):
            for workers in (1, 2):
                wall, mapped, cpu, samples = timed_run(workers, fleet_entries)
                runs[workers].append((wall, mapped, cpu))
                print(f'run {r + 1}: {workers} worker(s) {wall:.2f} s (map {mapped:.2f} s, '
                      f'reduce and solve {wall - mapped:.2f} s), workers\' CPU {cpu:.2f} s '
                      f'({cpu / mapped:.2f} cores busy while mapping; load average '
                      f'{os.getloadavg()[0]:.2f})', flush=True)
    best = {w: min(runs[w]) for w in runs}
    print(f'\n{args.bags} bags of {args.samples} samples ({samples} samples used in all), '
          f'best of {args.repeat}:')
    print('| workers | wall (s) | map (s) | bags/s | samples/s |')
    print('|---:|---:|---:|---:|---:|')
    for workers in (1, 2):
        w, m, _ = best[workers]
        print(f'| {workers} | {w:.2f} | {m:.2f} | {args.bags / w:.2f} | {samples / w:,.0f} |')
    speedup = best[1][0] / best[2][0]
    print(f'speed-up 1 -> 2 workers (best runs): {speedup:.2f}x, scaling efficiency '
          f'{speedup / 2:.0%}; map alone {best[1][1] / best[2][1]:.2f}x')
    pairs = sorted(a[0] / b[0] for a, b in zip(runs[1], runs[2]))
    print('speed-up of each alternating pair (1-worker run / the 2-worker run after it): '
          + ', '.join(f'{x:.2f}x' for x in pairs) + f'; median {statistics.median(pairs):.2f}x')
    # Amdahl with the load-independent parts: the workers' CPU and the client's serial part
    cpu = {w: statistics.median(r[2] for r in runs[w]) for w in runs}
    serial = statistics.median(r[0] - r[1] for w in runs for r in runs[w])
    print(f'workers\' CPU (median): {cpu[1]:.2f} s with 1 worker, {cpu[2]:.2f} s with 2; '
          f'reduce and solve on the client (median) {serial:.2f} s: on 2 idle cores '
          f'{(cpu[1] + serial) / (cpu[2] / 2 + serial):.2f}x (CPU-time model)')
    per_group, shared = solve_times(bag, args.repeat)
    print(f'the client\'s solves of the 3 groups (2 periods, the total), physically '
          f'consistent: {shared:.2f} s with one solver per robot against {per_group:.2f} s '
          f'with one per group ({per_group / shared:.2f}x; best of {args.repeat} alternating)')
    print('\nworker memory while mapping one bag:')
    print('| bag samples | worker RSS before (MiB) | peak above it (MiB) |')
    print('|---:|---:|---:|')
    for n in args.lengths:
        before, peak = peak_memory(make_bag(n))
        print(f'| {n} | {before:.1f} | {peak:.1f} |', flush=True)


if __name__ == '__main__':
    main()
