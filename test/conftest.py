"""Test configuration: single-threaded BLAS (threads only spin on this 2-core machine)."""
import os

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
