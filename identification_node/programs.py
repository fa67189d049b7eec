"""The console entry points (setup.py, ``python -m identification_node``): each sets this
package's process-wide environment before numpy loads, then runs its program. Importing the
package changes nothing in the process."""
from __future__ import annotations

import os


def _environment() -> None:
    # The matrices here are small (tens of columns): threaded BLAS only spins on the few
    # cores a robot computer shares with its controllers. A user's choice wins.
    os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')


def identification_node() -> int:
    """``ros2 run identification_node identification_node``."""
    _environment()
    from .ros.node import main
    return main()


def simulated_arm() -> int:
    """``ros2 run identification_node simulated_arm``."""
    _environment()
    from .ros.sim_node import main
    return main()


def payload_forwarder() -> int:
    """``ros2 run identification_node payload_forwarder``: ~/payload to a controller."""
    _environment()
    from .ros.payload_forwarder import main
    return main()


def identification_cli() -> int:
    """``identification_cli VERB ...`` / ``python -m identification_node VERB ...``."""
    _environment()
    from .cli import main
    return main()
