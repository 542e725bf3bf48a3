"""No surprises at import: what ``import jaxdmd`` changes in JAX's global configuration."""

from __future__ import annotations

import json
import os
import subprocess
import sys

PROBE = """
import json
import jax
from jax._src import xla_bridge
before = dict(jax.config.values)
import jaxdmd
after = dict(jax.config.values)
changed = {k: [before.get(k), v] for k, v in after.items() if before.get(k) != v}
print(json.dumps({"changed": changed, "backends": xla_bridge.backends_are_initialized()}))
"""


def test_import_changes_exactly_x64_and_cpu_dispatch_and_creates_no_backend():
    unset = ("JAX_ENABLE_X64", "JAX_CPU_ENABLE_ASYNC_DISPATCH")
    env = {k: v for k, v in os.environ.items() if k not in unset}
    done = subprocess.run(
        [sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=120, check=True,
        env=env,
    )  # fmt: skip
    seen = json.loads(done.stdout.strip().splitlines()[-1])
    assert seen["changed"] == {
        "jax_enable_x64": [False, True],
        "jax_cpu_enable_async_dispatch": [True, False],
    }
    # no backend yet: the dispatch flag (read when the CPU backend is created) takes effect
    assert seen["backends"] is False
