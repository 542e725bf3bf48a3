"""The entry point of a worker process (:mod:`jaxdmd.workers`): ``python -m jaxdmd._worker``."""

import sys

from jaxdmd.workers import serve

sys.exit(serve())
