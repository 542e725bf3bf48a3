"""``python -m jaxdmd`` (and the ``jaxdmd`` console script): see :func:`jaxdmd.run.main`."""

import sys

from jaxdmd.run import main

if __name__ == "__main__":
    sys.exit(main())
