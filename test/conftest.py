"""Test configuration: single-threaded BLAS (threads only spin on this 2-core machine)."""
import os

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')


def pytest_configure(config):
    # @pytest.mark.slow: tests that start clusters or process many bags
    config.addinivalue_line('markers', 'slow: long-running test (clusters, many bags)')
