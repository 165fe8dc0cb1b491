import os
import sys

# tests/naive.py and friends are imported as plain modules by the tests.
sys.path.insert(0, os.path.dirname(__file__))
