"""jaxdmd: discover dynamic models of power-system components from measured data.

The engine follows LLM-DMD (a language model, or the built-in offline proposer, writes candidate
equations as Python skeletons; jaxdmd checks, compiles and fits them in batches, keeps them in an
island archive, and extends the variable library when the search stalls).

What ``import jaxdmd`` changes in JAX's global configuration, for every JAX program in the
process, and nothing else (``tests/test_import.py`` checks it):

* ``jax_enable_x64 = True``. jaxdmd works in float64 throughout: power-system states differ from
  their operating point by 1e-4 pu and less, which float32 cannot resolve.
* ``jax_cpu_enable_async_dispatch = False``. XLA:CPU with asynchronous dispatch loses a
  completion wakeup now and then on 2-core machines: an execution (seen with the vmapped diffrax
  simulation after several single runs) waits forever at 0 % CPU. Synchronous dispatch avoids it
  at no measured cost for jaxdmd's workloads, whose host code waits for every result anyway.

The second setting cannot be confined to the simulator (a context manager around the diffrax
calls would do nothing): JAX reads the flag once, when it creates the CPU backend (the
``asynchronous=`` argument of ``make_cpu_client`` in ``jax._src.xla_bridge``), not when it
dispatches a computation. Measured with jax 0.10.2, a 3 s jitted CPU computation returns from
its call after 0.2 ms (asynchronous) when the flag is switched off after the backend exists, and
after 3 s (synchronous) when it is switched off before; switching it back on after creation
leaves dispatch synchronous. Hence: it takes effect only if ``import jaxdmd`` comes before the
process's first JAX computation (importing jaxdmd creates no backend), and then it holds for the
whole process. To keep asynchronous dispatch, call
``jax.config.update("jax_cpu_enable_async_dispatch", True)`` after ``import jaxdmd`` and before
the first computation (at the risk of the hang described above).
"""

import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_cpu_enable_async_dispatch", False)

__version__ = "0.1.0"

from jaxdmd.data import Dataset  # noqa: E402  (after the configuration above)
from jaxdmd.pipeline import Discovery, DiscoveryConfig, discover, load  # noqa: E402

__all__ = ["Dataset", "Discovery", "DiscoveryConfig", "__version__", "discover", "load"]
