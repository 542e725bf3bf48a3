"""jaxdmd: discover dynamic models of power-system components from measured data.

The engine follows LLM-DMD (a language model, or the built-in offline proposer, writes candidate
equations as Python skeletons; jaxdmd checks, compiles and fits them in batches, keeps them in an
island archive, and extends the variable library when the search stalls).

jaxdmd works in float64 throughout: power-system states differ from their operating point by
1e-4 pu and less, which float32 cannot resolve. Importing jaxdmd therefore enables JAX's x64 mode.
"""

import os

# XLA:CPU's multi-threaded Eigen pool deadlocks here (0 % CPU, forever) on some batched solves
# inside diffrax while-loops on 2-core machines; reproduced with paper_protocol. One intra-op
# thread avoids it at a small cost. Set before JAX creates its CPU backend; a user's own
# XLA_FLAGS are kept and extended.
_XLA_FLAGS = ("--xla_cpu_multi_thread_eigen=false", "intra_op_parallelism_threads=1")
_flags = os.environ.get("XLA_FLAGS", "")
os.environ["XLA_FLAGS"] = " ".join(
    [_flags, *(f for f in _XLA_FLAGS if f.split("=")[0] not in _flags)]
).strip()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

__version__ = "0.1.0"
