"""``python -m perception.train``: see :mod:`perception.train.cli`."""

import sys

from perception.train.cli import main

if __name__ == "__main__":
    sys.exit(main())
