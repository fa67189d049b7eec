"""The console entry points (setup.py, ``python -m identification_node``): each sets this
package's process-wide environment before numpy loads, then runs its program. Importing the
package changes nothing in the process."""
from __future__ import annotations

import os
from typing import Sequence


def _environment() -> None:
    # The matrices here are small (tens of columns): threaded BLAS only spins on the few
    # cores a robot computer shares with its controllers. A user's choice wins.
    os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')


def _program(verb: str, script: str, argv: Sequence[str] | None) -> int:
    """The CLI verb ``verb`` as the program ``script`` (its --help, then ROS arguments)."""
    _environment()
    from identification_node.cli import run_program
    return run_program(verb, f'ros2 run identification_node {script}', argv)


def identification_node(argv: Sequence[str] | None = None) -> int:
    """``ros2 run identification_node identification_node [--help] [--ros-args ...]``."""
    return _program('node', 'identification_node', argv)


def simulated_arm(argv: Sequence[str] | None = None) -> int:
    """``ros2 run identification_node simulated_arm [--help] [--ros-args ...]``."""
    return _program('sim', 'simulated_arm', argv)


def payload_forwarder(argv: Sequence[str] | None = None) -> int:
    """``ros2 run identification_node payload_forwarder``: ~/payload to a controller."""
    return _program('forward_payload', 'payload_forwarder', argv)


def parameter_forwarder(argv: Sequence[str] | None = None) -> int:
    """``ros2 run identification_node parameter_forwarder``: quantities to node parameters."""
    return _program('forward_parameters', 'parameter_forwarder', argv)


def identification_cli(argv: Sequence[str] | None = None) -> int:
    """``identification_cli VERB ...`` / ``python -m identification_node VERB ...``."""
    _environment()
    from identification_node.cli import main
    return main(argv)
