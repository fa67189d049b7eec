"""``fleet MANIFEST``: identification of many bags of many robots on a Dask cluster.

MANIFEST is a CSV with header ``bag,robot,period`` (optional ``urdf``, ``config``; paths
relative to its folder), or a folder of bags, grouped by the robot description they carry
(period: the UTC day of each bag); ``--config`` applies to the bags whose row names no
parameter file. Each bag (or ``--segment`` seconds of it) is mapped to its
sufficient statistics on the cluster, they are reduced per robot and period and per robot,
and solved (fleet.py), physically consistent as ``identify`` unless
``--no-physical-consistency``; the flags test the unconstrained estimates. The default
cluster is a LocalCluster with one single-threaded worker process per core (``--workers
N``); ``--scheduler tcp://HOST:PORT`` uses a running one
(``dask scheduler`` / ``dask worker``). Progress goes to stderr. Prints per robot the estimate
over the periods with standard deviations, the flags (parameters moved by more than
``--sigma`` standard deviations between periods, robots that are outliers against the fleet),
the bags that failed and those holding the same messages as another (counted once); exit 2
when nothing was identified; ``--json`` prints the same as one object, ``--report DIR`` writes
fleet.md and figures.
"""
from __future__ import annotations

import argparse
import json
import sys

from identification_node.results.text import text_table


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('manifest', help='manifest CSV (bag,robot,period[,urdf][,config]) or '
                        'a folder of rosbag2 bags')
    parser.add_argument('--scheduler', metavar='ADDR',
                        help='address of a running dask scheduler, tcp://HOST:PORT (default: '
                        'a local cluster)')
    parser.add_argument('--workers', type=int, metavar='N',
                        help='worker processes of the local cluster (default: one per core)')
    parser.add_argument('--report', metavar='DIR', help='write fleet.md and PNG figures')
    parser.add_argument('--json', action='store_true', help='print one JSON object')
    parser.add_argument('--config', help='parameter YAML file (as for the node) for the bags '
                        'whose manifest row names none, and for a folder of bags')
    parser.add_argument('--sigma', type=float, default=5.0, metavar='K',
                        help='flag changes of more than K standard deviations (default 5)')
    parser.add_argument('--segment', type=float, metavar='S',
                        help='map each S seconds of a bag as its own task (long bags); '
                        'rounded to a multiple of 10 s, cut at multiples of 10 s of the stamps')
    parser.add_argument('--timeout', type=float, default=5.0, metavar='S',
                        help='seconds to wait for --scheduler (default 5)')
    parser.add_argument('--no-physical-consistency', action='store_true',
                        help='report the unconstrained least-squares estimates only (as '
                        'identify; config physical_consistency: false)')
    parser.add_argument('--joint-states-topic', default='/joint_states')
    parser.add_argument('--currents-topic', default='/motor_currents')


def format_fleet(doc: dict) -> str:
    """Per robot: one row per base parameter, its estimate +- stddev in each period."""
    lines = []
    for robot, periods in doc['robots'].items():
        docs = list(periods.values())
        rows = [tuple(['samples'] + [str(d['num_samples']) for d in docs])]
        for i, p in enumerate(docs[0]['base_parameters']):
            rows.append(tuple([p['name']] + [_pm(d['base_parameters'][i]) for d in docs]))
        lines += [f'{robot} ({len(periods)} period(s); SI units):'] + text_table(
            tuple(['parameter'] + list(periods)), rows) + ['']
    lines.append(f"flags (> {doc['sigma']:g} standard deviations):" if doc['flags']
                 else 'flags: none')
    for f in doc['flags']:
        where = f"period {f['period']} (since {f['since']})" if f['kind'] == 'drift' \
            else 'against the fleet'
        lines.append(f"  {f['robot']} {f['parameter']}: {f['kind']}, {where}, "
                     f"{f['change_sigma']:.1f} sigma")
    for f in doc['failed']:
        lines.append(f"failed: {f['bag']}: {f['error']}")
    for d in doc.get('duplicates', []):
        lines.append(f"counted once: {d['bag']} holds the messages of {d['duplicate_of']}")
    return '\n'.join(lines)


def _pm(p: dict) -> str:
    sd = 'inf' if p['stddev'] is None else f"{p['stddev']:.2g}"
    return f"{p['estimate']:.6g} +- {sd}"


def run(args: argparse.Namespace) -> int:
    from dataclasses import replace
    from pathlib import Path

    from identification_node.fleet import fleet
    from identification_node.errors import IdentificationError

    if not args.sigma > 0:
        raise IdentificationError(f'--sigma must be > 0, got {args.sigma}')
    if args.segment is not None and not args.segment > 0:
        raise IdentificationError(f'--segment must be > 0 s, got {args.segment}')
    if args.workers is not None and args.workers < 1:
        raise IdentificationError(f'--workers must be >= 1, got {args.workers}')
    if args.report:
        from identification_node.results.report import check_writable
        check_writable(args.report)
    source = Path(args.manifest)
    if source.is_dir():
        entries, failed = fleet.scan_directory(source, args.config)
    elif source.is_file():
        entries, failed = fleet.read_manifest(source), []
    else:
        raise IdentificationError(f'{source} is neither a manifest file nor a folder of bags')
    if args.config:
        entries = [replace(e, config=e.config or args.config) for e in entries]
    client = fleet.connect(args.scheduler, args.workers, args.timeout)
    try:
        unit = 'segments' if args.segment else 'bags'
        result = fleet.run_fleet(
            entries, client, args.segment, args.joint_states_topic, args.currents_topic,
            progress=lambda done, total: fleet.print_progress(done, total, unit),
            physical_consistency=not args.no_physical_consistency)
    finally:
        cluster = None if args.scheduler else client.cluster
        client.close()
        if cluster is not None:
            cluster.close()
    result.failed[:0] = failed
    doc = fleet.fleet_document(result, args.sigma)
    if args.report:
        from identification_node.fleet.report import write_fleet_report
        doc['report'] = {k: str(p) for k, p in write_fleet_report(args.report, doc).items()}
    if args.json:
        print(json.dumps(doc, indent=2))
    else:
        print(format_fleet(doc))
        if args.report:
            print(f"\nreport: {doc['report']['report']}")
    for f in doc['failed']:
        print(f"fleet: skipped {f['bag']}: {f['error']}", file=sys.stderr)
    for d in doc['duplicates']:
        print(f"warning: fleet: {d['bag']} holds the same messages as {d['duplicate_of']}: "
              'counted once', file=sys.stderr)
    if not doc['robots'] and not doc['totals']:
        print(f'error: fleet: nothing identified: all {len(doc["failed"])} bag(s) failed',
              file=sys.stderr)
        return 2
    return 0
