"""Work-precision report and stability cases (the same code as ``rtctl bench numerics``).

    python bench/numerics.py [--out DIR] [--json] [--quick]
"""

import sys

from rtctl.numerics.cli import main

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
