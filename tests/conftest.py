import os
import sys

# Single-threaded BLAS, as the rtctl command sets it: the models' matrices are small, and two
# BLAS threads on a busy 2-core machine made one discretization 100x slower (9.5 s vs 0.085 s).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

# tests/naive.py and friends are imported as plain modules by the tests.
sys.path.insert(0, os.path.dirname(__file__))
