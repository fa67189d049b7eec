"""The console entry points (setup.py, ``python -m identification_node``): each sets this
package's process-wide environment before numpy loads, then runs its program. Importing the
package changes nothing in the process."""
from __future__ import annotations

import importlib
import os


def _run(module: str) -> int:
    """``main()`` of ``module`` (relative to this package) after setting the environment."""
    # The matrices here are small (tens of columns): threaded BLAS only spins on the few
    # cores a robot computer shares with its controllers. A user's choice wins.
    os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
    return importlib.import_module(module, __package__).main()


def identification_node() -> int:
    """``ros2 run identification_node identification_node``."""
    return _run('.ros.node')


def simulated_arm() -> int:
    """``ros2 run identification_node simulated_arm``."""
    return _run('.ros.sim_node')


def payload_forwarder() -> int:
    """``ros2 run identification_node payload_forwarder``: ~/payload to a controller."""
    return _run('.ros.payload_forwarder')


def identification_cli() -> int:
    """``identification_cli VERB ...`` / ``python -m identification_node VERB ...``."""
    return _run('.cli')
