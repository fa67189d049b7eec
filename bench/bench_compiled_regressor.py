"""What a compiled regressor stage would buy: pinocchio's C++ ``computeJointTorqueRegressor``
in a C++ loop over each batch of samples, in place of model/robot.py's
``joint_torque_regressors`` (one binding call per sample). A prototype, measured, not shipped.

Builds once, in bench/.cache/compiled_regressor/, a shared library from the C++ source below
against the venv's pinocchio (headers and library of the pin wheel) and Eigen's headers (the
cmeel-eigen wheel, fetched by pip into the cache), and loads it with ctypes; the model goes to
it through pinocchio's own binary serialization. It first checks that the compiled call gives
pinocchio's Python results to the bit on random samples of bench_replay's arm, then measures,
alternating the Python call and the compiled one in this process:

- RobotModel.regressor alone on 50,000 random samples, us per sample;
- bench_replay.py's pipelines on its bag: ours on one process, ours on ``--workers``
  processes (the smoother pinned) and ours auto on them (the shipped smoother), each as
  samples/s and against the naive pipeline of the same run.

``--run SCRIPT [ARGS...]`` instead runs another benchmark (e.g. bench_pipeline_runs.py) as its
own ``__main__`` with the compiled call in place; compare with the same command run plainly.

    .venv/bin/python bench/bench_compiled_regressor.py [--samples 100000] [--repeat 3]
        [--workers N] [--run SCRIPT ARGS...]

Needs g++ and, for the first build, PyPI.
"""
from __future__ import annotations

import argparse
import ctypes
import os
import runpy
import shutil
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

from checkout import ROOT  # noqa: E402  (this checkout's package, here and in subprocesses)

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')  # as bench_replay.py

import numpy as np  # noqa: E402

BUILD = ROOT / 'bench' / '.cache' / 'compiled_regressor'
EIGEN = 'cmeel-eigen==3.4.1'    # the Eigen pinocchio's and eigenpy's wheels are built with
# pinocchio's exported compile definitions (lib/cmake/pinocchio/pinocchioTargets.cmake)
DEFINES = ['BOOST_MPL_LIMIT_LIST_SIZE=30', 'BOOST_MPL_LIMIT_VECTOR_SIZE=30',
           'BOOST_MPL_CFG_NO_PREPROCESSED_HEADERS', 'BOOST_FUSION_INVOKE_MAX_ARITY=12',
           'PINOCCHIO_ENABLE_TEMPLATE_INSTANTIATION']
SOURCE = r'''
#include <pinocchio/multibody.hpp>
#include <pinocchio/serialization.hpp>
#include <pinocchio/algorithm/regressor.hpp>

struct Handle { pinocchio::Model model; pinocchio::Data *data; };

extern "C" {
void *regressor_open(const char *path) {
  Handle *h = new Handle();
  h->model.loadFromBinary(std::string(path));
  h->data = new pinocchio::Data(h->model);
  return h;
}

// out (N, nv, 10 (njoints - 1)) row-major: pinocchio's Python result per sample, stacked
void regressor_batch(void *handle, long N, const double *Q, const double *V, const double *A,
                     double *out) {
  Handle *h = static_cast<Handle *>(handle);
  const long nq = h->model.nq, nv = h->model.nv, p = 10 * (h->model.njoints - 1);
  typedef Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor> RowMajor;
  for (long k = 0; k < N; ++k) {
    pinocchio::computeJointTorqueRegressor(
        h->model, *h->data, Eigen::Map<const Eigen::VectorXd>(Q + k * nq, nq),
        Eigen::Map<const Eigen::VectorXd>(V + k * nv, nv),
        Eigen::Map<const Eigen::VectorXd>(A + k * nv, nv));
    Eigen::Map<RowMajor>(out + k * nv * p, nv, p) = h->data->jointTorqueRegressor;
  }
}
}
'''


def build() -> Path:
    """The prototype's shared library, built on first use."""
    lib = BUILD / 'libcompiled_regressor.so'
    if lib.is_file():
        return lib
    if shutil.which('g++') is None:
        print('bench_compiled_regressor.py: skipped, it needs g++ to build its prototype')
        raise SystemExit(0)
    BUILD.mkdir(parents=True, exist_ok=True)
    eigen = BUILD / 'eigen'
    if not eigen.is_dir():
        got = subprocess.run([sys.executable, '-m', 'pip', 'download', '-q', '--no-deps',
                              EIGEN, '-d', str(BUILD)], capture_output=True, text=True)
        if got.returncode:
            raise SystemExit(f'bench_compiled_regressor.py: pip could not fetch {EIGEN} '
                             "(Eigen's headers, for the prototype's build)")
        wheel = next(BUILD.glob('cmeel_eigen-*.whl'))
        with zipfile.ZipFile(wheel) as z:
            z.extractall(eigen)
    import cmeel   # the prefix of the cmeel wheels (pin, boost) in this venv
    prefix = Path(cmeel.__path__[0]).parent / 'cmeel.prefix'
    source = BUILD / 'compiled_regressor.cpp'
    source.write_text(SOURCE)
    print('building the prototype (about 30 s) ...', flush=True)
    done = subprocess.run(
        ['g++', '-O3', '-DNDEBUG', '-fPIC', '-shared', '-std=c++17', '-w',
         *(f'-D{d}' for d in DEFINES), f'-I{prefix / "include"}',
         f'-I{eigen / "cmeel.prefix" / "include" / "eigen3"}', str(source),
         '-o', str(lib) + '.tmp', f'-L{prefix / "lib"}', '-lpinocchio_default',
         '-lboost_serialization', f'-Wl,-rpath,{prefix / "lib"}'],
        capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(f'the prototype did not build:\n{done.stderr[-3000:]}')
    os.replace(str(lib) + '.tmp', lib)
    return lib


class Compiled:
    """The prototype as a drop-in for robot.joint_torque_regressors."""

    def __init__(self, lib: Path):
        self.lib = ctypes.CDLL(str(lib))
        self.lib.regressor_open.restype = ctypes.c_void_p
        self.lib.regressor_open.argtypes = [ctypes.c_char_p]
        self.lib.regressor_batch.argtypes = [ctypes.c_void_p, ctypes.c_long] + [
            ctypes.c_void_p] * 4
        self._open: dict[int, tuple] = {}   # id(model): (model kept alive, handle)

    def _handle(self, model) -> int:
        entry = self._open.get(id(model))
        if entry is None:
            with tempfile.TemporaryDirectory() as tmp:
                path = os.path.join(tmp, 'model.bin')
                model.saveToBinary(path)
                entry = self._open[id(model)] = (model, self.lib.regressor_open(path.encode()))
        return entry[1]

    def __call__(self, model, data, Q, V, A) -> np.ndarray:
        Q, V, A = (np.ascontiguousarray(x, dtype=float) for x in (Q, V, A))
        out = np.empty((len(Q), model.nv, 10 * (model.njoints - 1)))
        self.lib.regressor_batch(self._handle(model), len(Q), Q.ctypes.data, V.ctypes.data,
                                 A.ctypes.data, out.ctypes.data)
        return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--samples', type=int, default=100_000)
    parser.add_argument('--repeat', type=int, default=3)
    parser.add_argument('--workers', type=int, default=2)
    parser.add_argument('--run', nargs=argparse.REMAINDER,
                        help='SCRIPT ARGS...: run that benchmark with the compiled call')
    args = parser.parse_args()
    from identification_node.model import robot as robot_module

    if args.run and not Path(args.run[0]).is_file():
        raise SystemExit(f'--run: no script {args.run[0]}')
    python = robot_module.joint_torque_regressors
    compiled = Compiled(build())
    if args.run:
        robot_module.joint_torque_regressors = compiled
        sys.argv = args.run
        runpy.run_path(args.run[0], run_name='__main__')
        return

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import bench_replay as br

    robot = br._settings().load_robot()
    rng = np.random.default_rng(0)
    q, qd, qdd = (rng.uniform(-1.0, 1.0, (50_000, robot.dof)) for _ in range(3))
    want = robot.regressor(q, qd, qdd)
    robot_module.joint_torque_regressors = compiled
    got = robot.regressor(q, qd, qdd)
    robot_module.joint_torque_regressors = python
    if not np.array_equal(want, got):
        raise SystemExit(f'the compiled regressor differs: {np.abs(want - got).max()}')

    def timed(call) -> float:
        times = []
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            call()
            times.append(time.perf_counter() - t0)
        return min(times)

    alone = {}
    for name, fn in (('python', python), ('compiled', compiled)) * 2:
        robot_module.joint_torque_regressors = fn
        alone[name] = min(alone.get(name, np.inf),
                          timed(lambda: robot.regressor(q, qd, qdd)) / len(q) * 1e6)
    robot_module.joint_torque_regressors = python
    print(f'RobotModel.regressor on {len(q)} random samples of the {robot.dof}-joint arm: '
          f'{alone["python"]:.2f} us per sample with the Python call, '
          f'{alone["compiled"]:.2f} compiled ({alone["compiled"] / alone["python"]:.2f}x); '
          'equal to the bit')

    def with_call(fn, run):
        def call(bag):
            robot_module.joint_torque_regressors = fn
            try:
                return run(bag)
            finally:
                robot_module.joint_torque_regressors = python
        return call

    bag = br.make_bag(args.samples)
    w = args.workers
    kinds = {'ours': br.run_ours,
             f'ours, {w} workers': lambda b: br.run_parallel(b, w),
             f'ours auto, {w} workers': lambda b: br.run_parallel(b, w, automatic=True)}
    runs = {'naive': (br.run_naive, bag)}
    for name, run in kinds.items():
        runs[name] = (with_call(python, run), bag)
        runs[name + ' (compiled)'] = (with_call(compiled, run), bag)
    best = br.throughput(runs, args.repeat)
    n0, wall0, _ = best['naive']
    print(f'{args.samples} samples of bench_replay\'s bag, best of {args.repeat} interleaved '
          'runs:')
    for name, (n, wall, cpu) in best.items():
        line = (f'  {name:32s} {n / wall:9.0f} samples/s  {wall:6.3f} s wall  {cpu:6.3f} s '
                f'CPU of this process  {n / wall / (n0 / wall0):5.2f}x naive')
        if name.endswith('(compiled)'):
            base = best[name[:-len(' (compiled)')]]
            line += f'  {base[1] / wall:.2f}x the Python call'
        print(line)


if __name__ == '__main__':
    main()
