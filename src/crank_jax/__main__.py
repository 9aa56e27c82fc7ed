"""`python -m crank_jax ...` is `crank-jax ...`."""

import sys

from .cli import main

sys.exit(main())
