"""jaxdmd: discover dynamic models of power-system components from measured data.

The engine follows LLM-DMD (a language model, or the built-in offline proposer, writes candidate
equations as Python skeletons; jaxdmd checks, compiles and fits them in batches, keeps them in an
island archive, and extends the variable library when the search stalls).

jaxdmd works in float64 throughout: power-system states differ from their operating point by
1e-4 pu and less, which float32 cannot resolve. Importing jaxdmd therefore enables JAX's x64 mode.
"""

import jax

# XLA:CPU with asynchronous dispatch loses a completion wakeup now and then on these 2-core
# machines: an execution (seen with the vmapped diffrax simulation after several single runs)
# waits forever at 0 % CPU. Synchronous dispatch avoids it at no measured cost for jaxdmd's
# workloads, whose host code waits for every result anyway.
jax.config.update("jax_cpu_enable_async_dispatch", False)
jax.config.update("jax_enable_x64", True)

__version__ = "0.1.0"

from jaxdmd.data import Dataset  # noqa: E402  (after the configuration above)
from jaxdmd.pipeline import Discovery, DiscoveryConfig, discover, load  # noqa: E402

__all__ = ["Dataset", "Discovery", "DiscoveryConfig", "__version__", "discover", "load"]
