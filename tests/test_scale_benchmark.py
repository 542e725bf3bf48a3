"""benchmarks/scale.py: its long recordings and its memory of a process tree."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from benchmark_scripts import load_script

scale = load_script("scale.py", "scale_benchmark")


def _source(path: Path) -> Path:
    """A cached source as ``scale.source`` writes it: one state that ends far from its start."""
    t = np.linspace(0.0, 1.0, 101)
    x = np.where(t < 0.2, 0.0, 1.0 - np.exp(-(t - 0.2) / 0.1))  # settles at 1 after a step
    u = np.ones_like(t)
    meta = {"names": ["x", "u"], "roles": ["state", "input"], "events": [[0.2, 0.3]]}
    np.savez(path, t=t, values=np.stack([x, u], axis=1)[None], meta=np.array(json.dumps(meta)))
    return path


def test_long_recordings_mark_each_join_as_an_event(tmp_path: Path) -> None:
    (ds,) = scale.recordings(_source(tmp_path / "source.npz"), 250, "long")
    t = np.asarray(ds.t)
    period = 1.01
    assert t.shape == (250,) and np.allclose(np.diff(t), 0.01)
    joins = [period, 2 * period]  # the copies' first samples: the state jumps there
    for join in joins:
        k = int(np.argmin(np.abs(t - join)))
        assert t[k] == pytest.approx(join)
        assert any(e == pytest.approx(join) for e in ds.events)
    faults = [e + k * period for k in range(3) for e in (0.2, 0.3)]
    assert sorted(ds.events) == pytest.approx(sorted(joins + faults))


def test_tree_memory_counts_a_child_process() -> None:
    """A child that holds 300 MB shows in the tree's peak (it would not in this process's
    own resident set)."""
    hold = (
        "import numpy as np, sys, time; a = np.ones(300 * 2**20 // 8); "
        "print('ready', flush=True); time.sleep(2.0)"
    )
    with scale.TreeMemory(every=0.05) as memory:
        child = subprocess.Popen([sys.executable, "-c", hold], stdout=subprocess.PIPE, text=True)
        assert child.stdout is not None and child.stdout.readline().strip() == "ready"
        time.sleep(0.5)
        during = memory.window()
        child.wait()
    assert memory.processes >= 2
    assert during >= 250 and memory.pss_mb >= 250 and memory.rss_mb >= 250
