"""Work in other processes: independent searches side by side on the machine's cores.

The DE loop runs several independent searches (:class:`jaxdmd.pipeline.DiscoveryConfig`'s
``searches``); on a machine with more than one core they run at once, each in its own Python
process (:func:`start`): a fresh interpreter (``python -m jaxdmd._worker``), not a fork of
this one, so that no user script is imported again and no thread of JAX's is copied. The
call and its arguments travel pickled on the worker's stdin; the worker sends back
length-prefixed pickled messages on its stdout: any number of ``("progress", value)``, then
one ``("result", value)`` or ``("error", text)``. Its stderr is kept for the error message.

Every process that searches, this one included (:func:`one_blas_thread`), uses one BLAS
thread: two processes on two cores that each start a BLAS thread per core run at a third of
their speed (measured: 204 s instead of 72 s for the benchmark's three searches), and a search
gives the same archive to the last bit however many run at once.
"""

from __future__ import annotations

import contextlib
import os
import pickle
import struct
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from typing import Any

_LENGTH = struct.Struct("<Q")

#: the BLAS libraries' thread counts in a worker (read when NumPy loads them)
_ONE_THREAD = {
    name: "1"
    for name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS")
}


def _path() -> str:
    """This process's module path, for the worker: it imports what this process imports."""
    return os.pathsep.join(os.path.abspath(p) if p else os.getcwd() for p in sys.path)


class WorkerError(RuntimeError):
    """A worker process failed: it raised, or ended without a result."""


def cores() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


@contextlib.contextmanager
def one_blas_thread() -> Iterator[None]:
    """This process's BLAS libraries limited to one thread while the block runs."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        yield


class Worker:
    """``fn(*args, progress=report)`` running in a worker process; ``report(value)`` there
    calls ``on_progress(value)`` here (from a thread of this process that reads the worker's
    messages). :meth:`result` waits for the return value and raises :class:`WorkerError` if
    the worker failed. ``fn``, ``args`` and every value sent back must pickle. A worker runs
    to its end unless :meth:`stop` ends it (or this process ends: its result then has
    nowhere to go)."""

    def __init__(
        self, fn: Callable[..., Any], args: tuple[Any, ...],
        on_progress: Callable[[Any], None] | None = None,
    ) -> None:  # fmt: skip
        payload = pickle.dumps((fn, args), protocol=pickle.HIGHEST_PROTOCOL)
        self._process = subprocess.Popen(
            [sys.executable, "-m", "jaxdmd._worker"],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            env={**os.environ, **_ONE_THREAD, "PYTHONPATH": _path()},
        )  # fmt: skip
        self._stderr: list[bytes] = []
        self._errors = threading.Thread(target=self._drain, daemon=True)
        self._errors.start()
        self._outcome: tuple[str, Any] = ("error", "the worker ended without a result")
        self._on_progress = on_progress
        self._reader = threading.Thread(target=self._read, daemon=True)
        try:
            assert self._process.stdin is not None
            self._process.stdin.write(payload)
            self._process.stdin.close()
        except OSError as err:  # the worker could not even read its task
            self._outcome = ("error", f"could not send the task: {err}")
        self._reader.start()

    def _drain(self) -> None:
        stream = self._process.stderr
        assert stream is not None
        with stream:
            for line in stream:
                self._stderr.append(line)
                del self._stderr[:-40]  # the last lines are the ones that say why

    def _read(self) -> None:
        stream = self._process.stdout
        assert stream is not None
        try:
            while True:
                head = stream.read(_LENGTH.size)
                if len(head) < _LENGTH.size:
                    return
                (n,) = _LENGTH.unpack(head)
                kind, value = pickle.loads(stream.read(n))
                if kind == "progress":
                    if self._on_progress is not None:
                        self._on_progress(value)
                else:
                    self._outcome = (kind, value)
        except Exception as err:  # a broken stream, or a progress callback that raised
            self._outcome = ("error", f"{type(err).__name__}: {err}")
        finally:
            stream.close()

    def result(self) -> Any:
        self._reader.join()
        code = self._process.wait()
        self._errors.join()
        kind, value = self._outcome
        if kind == "result" and code == 0:
            return value
        tail = b"".join(self._stderr).decode(errors="replace").strip().splitlines()[-5:]
        detail = [str(value)] if kind == "error" else []
        raise WorkerError("; ".join([*detail, f"exit status {code}", *tail]))

    def wait(self) -> None:
        """Wait until the worker process has ended (its result, or its failure, is then
        there)."""
        self._process.wait()

    def stop(self) -> None:
        """End the worker now (its result is then an error)."""
        if self._process.poll() is None:
            self._process.kill()


def start(
    fn: Callable[..., Any], *args: Any, on_progress: Callable[[Any], None] | None = None
) -> Worker:
    """Start ``fn(*args, progress=...)`` in a worker process (see :class:`Worker`)."""
    return Worker(fn, args, on_progress)


class Later(Sequence[Any]):
    """A worker's result, a sequence, used as one before it is there: :meth:`Worker.result` is
    waited for when the sequence is first used (its length, an item, an iteration). If the
    worker failed, ``fallback()`` computes the sequence here instead."""

    def __init__(self, worker: Worker, fallback: Callable[[], Sequence[Any]]) -> None:
        self._worker, self._fallback = worker, fallback
        self._items: list[Any] | None = None

    def _resolved(self) -> list[Any]:
        if self._items is None:
            try:
                self._items = list(self._worker.result())
            except WorkerError:
                self._items = list(self._fallback())
        return self._items

    def __len__(self) -> int:
        return len(self._resolved())

    def __getitem__(self, index: Any) -> Any:
        return self._resolved()[index]


# glibc's ``mallopt`` parameter: the size from which a block is mapped on its own
_M_MMAP_THRESHOLD = -3

#: the block size (bytes) from which :func:`map_large_blocks` has the allocator map each block
#: on its own
LARGE_BLOCK = 1 << 20


def map_large_blocks(threshold: int = LARGE_BLOCK) -> bool:
    """Have the C library's allocator map every block of ``threshold`` bytes or more on its
    own, so that freeing it gives its memory back to the system: what jaxdmd's own processes
    (the command line, :mod:`jaxdmd._worker`, the benchmarks' children) call at their start.

    glibc by default raises that threshold, up to 32 MB, each time a mapped block is freed:
    later arrays of a few MB then come from the heap, and the holes they leave there stay
    resident. At four recordings of 1e5 samples that held the main process about 180 MB above
    what it used (docs/benchmarks.md, session 42). Arrays of the benchmark's length (1001
    samples, below 1 MB) are not affected. A library function never calls this: the policy
    is the whole process's. Returns whether the allocator took it (False where the C library
    has no ``mallopt``: not glibc)."""
    import ctypes

    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, int(threshold)))


def serve() -> int:
    """The worker's side: read the task from stdin, run it, send the messages."""
    map_large_blocks()
    out = sys.stdout.buffer
    sys.stdout = sys.stderr  # a print in the task must not corrupt the message stream
    lock = threading.Lock()

    def send(kind: str, value: Any) -> None:
        data = pickle.dumps((kind, value), protocol=pickle.HIGHEST_PROTOCOL)
        with lock:
            out.write(_LENGTH.pack(len(data)) + data)
            out.flush()

    try:
        fn, args = pickle.loads(sys.stdin.buffer.read())
        value = fn(*args, progress=lambda v: send("progress", v))
    except BaseException as err:  # every failure goes back as a message
        import traceback

        traceback.print_exc()
        send("error", f"{type(err).__name__}: {err}")
        return 1
    send("result", value)
    return 0
