"""A small scriptable chat-completions server on 127.0.0.1, for testing the LLM proposer.

The server speaks just enough of the OpenAI-compatible protocol (``POST .../chat/completions``)
and answers every request with whatever the test's handler returns: normal completions,
429 with ``Retry-After``, 500, slow answers, garbage bodies. Its answers are toy skeletons the
tests write themselves; nothing here knows any real equation.

    with ChatServer(handler) as server:
        config = LLMConfig(base_url=server.url, model="toy")
        ...
        server.received  # every request, in arrival order
"""

from __future__ import annotations

import json
import socket
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any


@dataclass
class Reply:
    """What the server answers: status, body (dict -> JSON, str/bytes as is), headers, delay."""

    status: int = 200
    body: dict[str, Any] | str | bytes = b""
    headers: dict[str, str] = field(default_factory=dict)
    delay: float = 0.0


@dataclass(frozen=True)
class Received:
    """One request the server got."""

    index: int
    path: str
    headers: dict[str, str]
    raw: bytes
    body: Any  # parsed JSON, or None


Handler = Callable[[Received], Reply]


def toy_skeleton(seed: int | None, i: int = 0) -> str:
    """A made-up skeleton whose constant depends on the seed, so answers can be told apart."""
    c = (seed or 0) % 1000
    return f"def equation(x, p):\n    return p[0] * x + p[1] * {c + i}\n"


def completion(
    contents: Sequence[str | None],
    *,
    finish_reason: str = "stop",
    usage: tuple[int, int] = (100, 20),
    model: str = "toy",
) -> Reply:
    """A 200 chat completion with one choice per content."""
    return Reply(
        body={
            "id": "cmpl-test",
            "object": "chat.completion",
            "model": model,
            "choices": [
                {
                    "index": i,
                    "message": {"role": "assistant", "content": c},
                    "finish_reason": finish_reason,
                }
                for i, c in enumerate(contents)
            ],
            "usage": {
                "prompt_tokens": usage[0],
                "completion_tokens": usage[1] * len(contents),
                "total_tokens": usage[0] + usage[1] * len(contents),
            },
        }
    )


def skeletons(request: Received) -> Reply:
    """The default handler: ``n`` toy skeletons derived from the request's seed."""
    body = request.body if isinstance(request.body, dict) else {}
    n = int(body.get("n", 1))
    return completion([toy_skeleton(body.get("seed"), i) for i in range(n)])


def closed_port() -> int:
    """A port on 127.0.0.1 where nothing listens (bound, then closed)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class ChatServer:
    """A threaded HTTP server on a free loopback port, answering through ``handler``."""

    def __init__(self, handler: Handler = skeletons) -> None:
        self.handler = handler
        self.received: list[Received] = []
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self._server: ThreadingHTTPServer | None = None
        self._thread: threading.Thread | None = None

    @property
    def port(self) -> int:
        assert self._server is not None, "server not started"
        return self._server.server_address[1]

    @property
    def url(self) -> str:
        """The base URL to give the proposer (``.../v1``)."""
        return f"http://127.0.0.1:{self.port}/v1"

    def start(self) -> ChatServer:
        owner = self

        class _RequestHandler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"

            def log_message(self, format: str, *args: Any) -> None:  # silence
                pass

            def do_POST(self) -> None:
                length = int(self.headers.get("Content-Length", "0"))
                raw = self.rfile.read(length)
                try:
                    body = json.loads(raw)
                except ValueError:
                    body = None
                with owner._lock:
                    received = Received(
                        index=len(owner.received),
                        path=self.path,
                        headers={k.lower(): v for k, v in self.headers.items()},
                        raw=raw,
                        body=body,
                    )
                    owner.received.append(received)
                if not self.path.rstrip("/").endswith("/chat/completions"):
                    reply = Reply(404, {"error": {"message": f"no route {self.path}"}})
                else:
                    reply = owner.handler(received)
                if reply.delay and owner._stopping.wait(reply.delay):
                    return
                payload = reply.body
                if isinstance(payload, dict):
                    data = json.dumps(payload).encode()
                    ctype = "application/json"
                else:
                    data = payload.encode() if isinstance(payload, str) else payload
                    ctype = "text/plain"
                try:
                    self.send_response(reply.status)
                    self.send_header("Content-Type", reply.headers.get("Content-Type", ctype))
                    self.send_header("Content-Length", str(len(data)))
                    for name, value in reply.headers.items():
                        if name.lower() != "content-type":
                            self.send_header(name, value)
                    self.end_headers()
                    self.wfile.write(data)
                except (BrokenPipeError, ConnectionResetError):
                    pass  # the client gave up (timeout): fine

        server = ThreadingHTTPServer(("127.0.0.1", 0), _RequestHandler)
        server.daemon_threads = True
        self._server = server
        self._thread = threading.Thread(
            target=server.serve_forever, kwargs={"poll_interval": 0.02}, daemon=True
        )
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stopping.set()
        if self._server is not None:
            self._server.shutdown()
            self._server.server_close()
        if self._thread is not None:
            self._thread.join(timeout=5)

    def __enter__(self) -> ChatServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
