"""Work in other processes (:mod:`jaxdmd.workers`): results, progress and failures come back;
the DE loop's searches give the same archives side by side as one after the other."""

from __future__ import annotations

import dataclasses
import os

import jax
import numpy as np
import pytest

import jaxdmd
from jaxdmd import search, workers
from jaxdmd.data import Dataset
from jaxdmd.pipeline import DiscoveryConfig
from jaxdmd.search import SearchConfig


def _count(n: int, *, progress) -> dict[str, object]:
    for i in range(n):
        progress(i)
    return {"pid": os.getpid(), "blas": os.environ.get("OPENBLAS_NUM_THREADS")}


def _fail(text: str, *, progress) -> None:
    progress("before")
    raise ValueError(text)


def _die(code: int, *, progress) -> None:
    os._exit(code)


def _chatty(*, progress) -> int:
    print("a print in the task")  # must not corrupt the message stream
    return 7


def test_a_worker_returns_its_value_and_its_progress_in_order():
    seen: list[object] = []
    value = workers.start(_count, 5, on_progress=seen.append).result()
    assert seen == [0, 1, 2, 3, 4]
    assert value["pid"] != os.getpid()  # it ran in another process
    assert value["blas"] == "1"
    assert workers.start(_chatty).result() == 7


def test_a_worker_that_raises_or_dies_is_a_worker_error_that_says_why():
    seen: list[object] = []
    with pytest.raises(workers.WorkerError, match="ValueError: no such generator"):
        workers.start(_fail, "no such generator", on_progress=seen.append).result()
    assert seen == ["before"]
    with pytest.raises(workers.WorkerError, match="exit status 3"):
        workers.start(_die, 3).result()


def _recordings(n: int = 3) -> list[Dataset]:
    """d a/dt = 2 (w - 1), d w/dt = 0.3 u - 0.8 (w - 1) with a little noise."""
    t = np.linspace(0.0, 4.0, 401)
    out = []
    for k in range(n):
        rng = np.random.default_rng(k)
        u = np.where(t < 0.5, 0.0, 1.0 + 0.5 * k)
        w, a = np.ones_like(t), np.zeros_like(t)
        for i in range(t.size - 1):
            h = t[i + 1] - t[i]
            a[i + 1] = a[i] + h * 2 * (w[i] - 1)
            w[i + 1] = w[i] + h * (0.3 * u[i] - 0.8 * (w[i] - 1))
        clean = {"a": a, "w": w}
        noisy = {s: x + 0.002 * np.ptp(x) * rng.normal(size=t.shape) for s, x in clean.items()}
        roles = {"a": "state", "w": "state", "u": "input"}
        out.append(Dataset.create(t, {**noisy, "u": u}, roles, events=(0.5,), label=f"r{k}"))
    return out


def test_searches_side_by_side_in_worker_processes_give_the_archives_of_one_after_the_other(
    tmp_path, monkeypatch
):
    config = DiscoveryConfig(
        search=SearchConfig(n_islands=2, prompts_per_round=2, samples_per_prompt=2, max_rounds=3),
        algebraic=False, selection=None, refit_window=None, searches=3,
    )  # fmt: skip
    train = _recordings()
    alone = jaxdmd.discover(
        train, (), dataclasses.replace(config, jobs=1), key=jax.random.key(3),
        checkpoints=tmp_path / "alone",
    )  # fmt: skip
    messages: list[str] = []

    class Seen:
        def loop_started(self, name, state):
            messages.append(f"start {name}")

        def round(self, name, state, report):
            messages.append(f"{name} {report.round}")

        def message(self, text):
            messages.append(text)

    together = jaxdmd.discover(
        train, (), dataclasses.replace(config, jobs=3), key=jax.random.key(3),
        checkpoints=tmp_path / "together", observer=Seen(),
    )  # fmt: skip
    # two at once: the third search runs here after the first, whose own choice is then made
    # in a worker
    two = jaxdmd.discover(
        train, (), dataclasses.replace(config, jobs=2), key=jax.random.key(3),
        checkpoints=tmp_path / "two",
    )  # fmt: skip
    for name in ("de", "de2", "de3"):
        a = (tmp_path / "alone" / f"{name}_state.json").read_text()
        assert a == (tmp_path / "together" / f"{name}_state.json").read_text(), name
        assert a == (tmp_path / "two" / f"{name}_state.json").read_text(), name
    for other in (together, two):
        assert other.de.source == alone.de.source
        assert other.de.params == alone.de.params
        # each search's own choice, wherever it was made
        assert other.report["de"]["searches"] == alone.report["de"]["searches"]
    # every search's start and rounds were shown, those of the workers too
    for name in ("DE", "DE2", "DE3"):
        assert f"start {name}" in messages
        assert f"{name} 1" in messages
    assert not any("worker process failed" in m for m in messages)

    # resumed, the three searches are done at once: their choices still take at most jobs - 1
    # workers at a time beside this process (before, both choices' workers started together).
    # The workers here are stand-ins that compute in this process and count as running until
    # waited for, so that the count does not depend on how fast a process starts
    running: list[bool] = []
    counts: list[int] = []

    class Stand:
        def __init__(self, fn, args):
            self.fn, self.args, self.index, self.value = fn, args, len(running), None
            counts.append(sum(running))
            running.append(True)

        def wait(self):
            if running[self.index]:
                self.value = self.fn(*self.args, progress=lambda message: None)
                running[self.index] = False

        def result(self):
            self.wait()
            return self.value

        def stop(self):
            running[self.index] = False

    monkeypatch.setattr(workers, "start", lambda fn, *args, **kw: Stand(fn, args))
    resumed = jaxdmd.discover(
        train, (), dataclasses.replace(config, jobs=2), key=jax.random.key(3),
        checkpoints=tmp_path / "two",
    )  # fmt: skip
    assert counts == [0, 0]
    assert resumed.de.source == two.de.source and resumed.de.params == two.de.params
    assert resumed.report["de"]["searches"] == two.report["de"]["searches"]


def _items(n: int, *, progress) -> list[int]:
    return list(range(n))


def test_a_later_sequence_is_the_workers_result_or_if_it_failed_the_fallbacks():
    later = workers.Later(workers.start(_items, 3), lambda: [9])
    assert len(later) == 3 and list(later) == [0, 1, 2] and later[-1] == 2
    failed = workers.Later(workers.start(_die, 3), lambda: [9])
    assert list(failed) == [9] and bool(failed)


def test_jobs_must_be_positive():
    with pytest.raises(ValueError, match="jobs"):
        DiscoveryConfig(jobs=0)


def test_work_started_ahead_is_used_only_for_the_state_equations_it_was_started_for():
    """discover starts the AE refits in a worker before the closed selection has chosen the
    state equations: the worker's result is used when they stay as they were, the work runs
    here (and the worker is stopped) when they changed, and here (with a message) when the
    worker failed."""
    from jaxdmd.pipeline import _ahead_or_here
    from jaxdmd.prompts import Contract, Variable

    contract = Contract(loop="DE", targets=("x",), states=(Variable("x", "state"),))
    source = "def equation(x, p):\n    dx_ = p[0] * x\n    return dx_\n"
    de = search.Equations(contract, source, (-1.0,), (0.0,), 0.0)
    changed = dataclasses.replace(de, params=(-1.5,))

    class Messages:
        def __init__(self):
            self.texts = []

        def message(self, text):
            self.texts.append(text)

    def here():
        return "here"

    observer = Messages()
    same = workers.start(_items, 2)
    assert _ahead_or_here((dataclasses.replace(de), same), de, here, observer) == [0, 1]
    slow = workers.start(_sleep, 60.0)
    assert _ahead_or_here((de, slow), changed, here, observer) == "here"
    with pytest.raises(workers.WorkerError):  # stopped, not waited for
        slow.result()
    assert _ahead_or_here(None, de, here, observer) == "here" and not observer.texts
    assert _ahead_or_here((de, workers.start(_die, 3)), de, here, observer) == "here"
    assert observer.texts and "exit status 3" in observer.texts[0]


def _sleep(seconds: float, *, progress) -> None:
    import time

    time.sleep(seconds)


_HEAP_PATTERN = """
import sys
import numpy as np
from jaxdmd.workers import map_large_blocks
if not map_large_blocks():
    print("no mallopt"); sys.exit(0)
def rss():
    return int(open("/proc/self/statm").read().split()[1]) * 4096
base = rss()
a = np.ones((4 << 20) // 8)
del a  # glibc would now raise its mmap threshold above 4 MB
blocks, pins = [], []
for _ in range(50):  # 2 MB arrays, each followed by a small one that pins the heap's top
    blocks.append(np.ones((2 << 20) // 8))
    pins.append(np.ones(1000))
held = rss()
del blocks
print(base, held, rss())
"""


@pytest.mark.skipif(not os.path.exists("/proc/self/statm"), reason="reads /proc (Linux)")
def test_with_large_blocks_mapped_freed_arrays_leave_the_process():
    """In jaxdmd's own processes (:func:`workers.map_large_blocks`) an array of a few MB,
    freed, gives its memory back to the system even where the allocator had raised its mmap
    threshold above it and small blocks pin the heap (without the call this process keeps the
    100 MB below: glibc serves the 2 MB arrays from the heap)."""
    import subprocess
    import sys

    out = subprocess.run(
        [sys.executable, "-c", _HEAP_PATTERN], capture_output=True, text=True, check=True,
        env={**os.environ, "PYTHONPATH": os.path.dirname(os.path.dirname(jaxdmd.__file__))},
    ).stdout.split()  # fmt: skip
    if out == ["no", "mallopt"]:
        pytest.skip("the C library has no mallopt (not glibc)")
    base, held, after = map(int, out)
    assert held - base > 80e6  # the arrays were resident
    assert after - base < 0.2 * (held - base)
