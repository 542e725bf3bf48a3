"""The LLM proposer against a real HTTP server on 127.0.0.1 (tests/llm_server.py).

The server's answers are toy skeletons written here; no language model is involved.
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import random
import threading
import time
from datetime import UTC, datetime, timedelta
from email.utils import format_datetime
from typing import Any

import httpx
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from llm_server import ChatServer, Received, Reply, closed_port, completion, toy_skeleton

from jaxdmd.prompts import Contract, PromptRequest, Variable
from jaxdmd.proposers import Proposer
from jaxdmd.proposers.llm import (
    LLMConfig,
    LLMProposer,
    LLMRequestError,
    LLMUnavailable,
    backoff_delay,
    derive_seed,
    parse_retry_after,
    unusable_reason,
)

SECRET = "sk-test-SECRET-0123456789"
CONTRACT = Contract(loop="DE", targets=("x",), states=(Variable("x", "state"),))


def make_requests(n_requests: int = 2, n_samples: int = 3, seed0: int = 0) -> list[PromptRequest]:
    """Prompt requests with hand-written messages (the proposer sends them as they are)."""
    return [
        PromptRequest(
            contract=CONTRACT,
            examples=(),
            header="def equation(x, p):",
            messages=(
                {"role": "system", "content": "You complete Python functions."},
                {"role": "user", "content": f"request {seed0 + i}\ndef equation(x, p):"},
            ),
            n_samples=n_samples,
            island=i,
            seed=seed0 + i,
        )
        for i in range(n_requests)
    ]


def make_config(url: str, **overrides: Any) -> LLMConfig:
    """Small timeouts and backoff, so failure tests take fractions of a second."""
    settings: dict[str, Any] = dict(
        base_url=url,
        model="toy-model",
        api_key=SECRET,
        api_key_source="$TEST_KEY",
        request_timeout=1.0,
        connect_timeout=0.5,
        round_timeout=10.0,
        max_retries=3,
        backoff_base=0.02,
        backoff_cap=0.1,
        retry_after_cap=1.0,
        trust_env=False,
    )
    settings.update(overrides)
    return LLMConfig(**settings)


def user_text(received: Received) -> str:
    return received.body["messages"][-1]["content"]


def test_normal_round_returns_n_samples_with_island_and_origin() -> None:
    requests = make_requests(n_requests=2, n_samples=3)
    with ChatServer() as server:
        proposer: Proposer = LLMProposer(make_config(server.url))
        assert isinstance(proposer, LLMProposer)
        samples = proposer.propose(requests)
    assert len(samples) == 6
    assert [s.island for s in samples] == [0, 0, 0, 1, 1, 1]
    assert {s.origin for s in samples} == {"toy-model"}
    expected = [toy_skeleton(derive_seed(r.seed, k)) for r in requests for k in range(3)]
    assert [s.text for s in samples] == expected

    assert len(server.received) == 6
    seeds = set()
    for got in server.received:
        assert got.path == "/v1/chat/completions"
        assert got.headers["authorization"] == f"Bearer {SECRET}"
        body = got.body
        assert body["model"] == "toy-model"
        assert body["temperature"] == 1.2
        assert body["stream"] is False
        assert "n" not in body
        assert body["messages"] in [list(r.messages) for r in requests]
        seeds.add(body["seed"])
    assert len(seeds) == 6

    stats = proposer.stats.as_dict()
    assert stats["calls"] == 6 and stats["attempts"] == 6 and stats["retries"] == 0
    assert stats["samples_requested"] == 6 and stats["samples_returned"] == 6
    assert stats["prompt_tokens"] == 600 and stats["completion_tokens"] == 120
    assert stats["total_tokens"] == 720
    assert stats["dropped"] == {} and stats["failures"] == {}


def test_n_per_request_uses_n_and_falls_back_when_ignored() -> None:
    requests = make_requests(n_requests=2, n_samples=3)
    with ChatServer() as server:
        proposer = LLMProposer(make_config(server.url, n_per_request=3))
        samples = proposer.propose(requests)
    assert len(samples) == 6 and len(server.received) == 2
    assert all(got.body["n"] == 3 for got in server.received)

    def one_choice_only(received: Received) -> Reply:
        return completion([toy_skeleton(received.body.get("seed"))])

    with ChatServer(one_choice_only) as server:
        proposer = LLMProposer(make_config(server.url, n_per_request=3))
        samples = proposer.propose(requests)
        assert len(samples) == 6
        # first call of each request asks n=3 (maybe both before the fallback), then singles
        assert len(server.received) <= 6
        assert sum(1 for got in server.received if "n" not in got.body) >= 4
        again = proposer.propose(make_requests(n_requests=1, n_samples=2, seed0=10))
        assert len(again) == 2
        assert all("n" not in got.body for got in server.received[-2:])


def test_flaky_endpoint_multi_round_loses_no_round_and_counts_retries() -> None:
    """30 % of first attempts fail (429 / 500 / too slow), by a seeded schedule per request."""
    attempts: dict[tuple[str, int], int] = {}
    lock = threading.Lock()

    def schedule(key: tuple[str, int]) -> str | None:
        rng = random.Random(hashlib.sha256(repr(key).encode()).digest())
        if rng.random() >= 0.3:
            return None
        return rng.choice(["429", "500", "slow"])

    def flaky(received: Received) -> Reply:
        key = (user_text(received), received.body["seed"])
        with lock:
            attempts[key] = attempts.get(key, 0) + 1
            first = attempts[key] == 1
        kind = schedule(key) if first else None
        if kind == "429":
            return Reply(429, {"error": {"message": "slow down"}}, {"Retry-After": "0.05"})
        if kind == "500":
            return Reply(500, {"error": {"message": "internal error"}})
        if kind == "slow":
            return Reply(delay=2.0, body=completion(["def equation(x, p): return p[0]"]).body)
        return completion([toy_skeleton(received.body["seed"])])

    rounds = [make_requests(n_requests=4, n_samples=3, seed0=100 * r) for r in range(3)]
    expected: dict[str, int] = {}
    for requests in rounds:
        for r in requests:
            for k in range(r.n_samples):
                kind = schedule((r.messages[-1]["content"], derive_seed(r.seed, k)))
                if kind is not None:
                    expected[kind] = expected.get(kind, 0) + 1
    assert 5 <= sum(expected.values()) <= 20  # the schedule really injects ~30 % failures

    started = time.monotonic()
    with ChatServer(flaky) as server:
        proposer = LLMProposer(make_config(server.url, request_timeout=0.4), jitter_seed=0)
        for requests in rounds:
            samples = proposer.propose(requests)
            assert len(samples) == 12
            assert [s.island for s in samples] == [i for i in range(4) for _ in range(3)]
    assert time.monotonic() - started < 10

    stats = proposer.stats
    assert stats.rounds == 3 and stats.samples_returned == 36
    assert stats.retries == sum(expected.values())
    assert stats.attempts == 36 + stats.retries
    assert stats.failures["http_429"] == expected.get("429", 0)
    assert stats.failures["http_500"] == expected.get("500", 0)
    assert stats.failures["timeout"] == expected.get("slow", 0)
    assert sum(stats.lost.values()) == 0


def test_closed_port_raises_llm_unavailable_quickly() -> None:
    port = closed_port()
    url = f"http://127.0.0.1:{port}/v1"
    proposer = LLMProposer(make_config(url, max_retries=2))
    started = time.monotonic()
    with pytest.raises(LLMUnavailable) as info:
        proposer.propose(make_requests(n_requests=3, n_samples=2))
    elapsed = time.monotonic() - started
    assert elapsed < 3.0
    message = str(info.value)
    assert f"127.0.0.1:{port}/v1/chat/completions" in message
    assert "3 attempts" in message and "last error" in message
    assert SECRET not in message
    assert proposer.stats.failures["connect"] >= 3


def test_endpoint_that_never_answers_in_time_raises_within_round_timeout() -> None:
    with ChatServer(lambda r: Reply(delay=5.0, body=completion(["def f(p): return p"]).body)) as s:
        proposer = LLMProposer(
            make_config(s.url, request_timeout=0.3, max_retries=20, round_timeout=1.0)
        )
        started = time.monotonic()
        with pytest.raises(LLMUnavailable, match=r"no answer from http://127\.0\.0\.1"):
            proposer.propose(make_requests(n_requests=2, n_samples=2))
        assert time.monotonic() - started < 3.0  # 21 attempts of 0.3 s would take > 6 s


def test_round_timeout_goes_on_with_the_answers_it_got() -> None:
    def half_slow(received: Received) -> Reply:
        if "request 1" in user_text(received) or "request 3" in user_text(received):
            return Reply(delay=5.0, body=completion(["def f(x, p): return p[0]"]).body)
        return completion([toy_skeleton(received.body["seed"])])

    with ChatServer(half_slow) as server:
        proposer = LLMProposer(make_config(server.url, request_timeout=3.0, round_timeout=0.6))
        started = time.monotonic()
        samples = proposer.propose(make_requests(n_requests=4, n_samples=1))
        assert time.monotonic() - started < 2.5
    assert [s.island for s in samples] == [0, 2]
    assert proposer.stats.lost["round_timeout"] == 2


@pytest.mark.parametrize("status", [401, 403])
def test_bad_key_fails_fast_without_retries_or_leaking_the_key(status: int) -> None:
    def refuse(received: Received) -> Reply:
        message = f"Incorrect API key provided: {SECRET}. You can find your key at ..."
        return Reply(status, {"error": {"message": message, "type": "invalid_request_error"}})

    with ChatServer(refuse) as server:
        proposer = LLMProposer(make_config(server.url, concurrency=1))
        started = time.monotonic()
        with pytest.raises(LLMRequestError) as info:
            proposer.propose(make_requests(n_requests=3, n_samples=2))
        assert time.monotonic() - started < 2.0
        assert len(server.received) == 1
    error = info.value
    assert error.status == status
    text = f"{error} {error!r} {error.args}"
    assert SECRET not in text
    assert "***" in str(error) and str(status) in str(error) and "$TEST_KEY" in str(error)
    assert proposer.stats.retries == 0


def test_unknown_model_404_fails_fast_with_a_hint() -> None:
    def unknown_model(received: Received) -> Reply:
        return Reply(404, {"error": {"message": f"model {received.body['model']} not found"}})

    with ChatServer(unknown_model) as server:
        proposer = LLMProposer(make_config(server.url, model="no-such-model"))
        with pytest.raises(LLMRequestError, match="404") as info:
            proposer.propose(make_requests(n_requests=1, n_samples=1))
    assert "no-such-model" in str(info.value) and "/v1" in str(info.value)


def test_no_api_key_gives_a_hint_about_the_variables() -> None:
    with ChatServer(lambda r: Reply(401, {"error": "missing key"})) as server:
        proposer = LLMProposer(make_config(server.url, api_key=None))
        with pytest.raises(LLMRequestError, match="JAXDMD_LLM_API_KEY"):
            proposer.propose(make_requests(n_requests=1, n_samples=1))
        assert "authorization" not in server.received[0].headers


def _rate_limited_once(retry_after: str) -> Any:
    seen: list[float] = []

    def handler(received: Received) -> Reply:
        seen.append(time.monotonic())
        if len(seen) == 1:
            return Reply(429, {"error": {"message": "rate limit"}}, {"Retry-After": retry_after})
        return completion([toy_skeleton(received.body["seed"])])

    return handler, seen


def test_retry_after_seconds_is_honoured() -> None:
    handler, seen = _rate_limited_once("0.3")
    with ChatServer(handler) as server:
        # a backoff this large would make the test slow: Retry-After must take its place
        proposer = LLMProposer(make_config(server.url, backoff_base=5.0, backoff_cap=5.0))
        samples = proposer.propose(make_requests(n_requests=1, n_samples=1))
    assert len(samples) == 1 and len(seen) == 2
    assert 0.3 <= seen[1] - seen[0] < 1.5
    assert proposer.stats.retries == 1 and proposer.stats.failures["http_429"] == 1


def test_retry_after_is_capped() -> None:
    handler, _ = _rate_limited_once("3600")
    with ChatServer(handler) as server:
        proposer = LLMProposer(make_config(server.url, retry_after_cap=0.2))
        started = time.monotonic()
        samples = proposer.propose(make_requests(n_requests=1, n_samples=1))
    assert len(samples) == 1 and time.monotonic() - started < 1.5


def test_persistent_server_errors_lose_samples_but_the_round_goes_on() -> None:
    def broken_for_island_1(received: Received) -> Reply:
        if "request 1" in user_text(received):
            return Reply(503, "upstream unavailable")
        return completion([toy_skeleton(received.body["seed"])])

    with ChatServer(broken_for_island_1) as server:
        proposer = LLMProposer(make_config(server.url, max_retries=2))
        samples = proposer.propose(make_requests(n_requests=2, n_samples=2))
    assert [s.island for s in samples] == [0, 0]
    assert proposer.stats.lost["retries_exhausted"] == 2
    assert proposer.stats.failures["http_503"] == 6 and proposer.stats.retries == 4


GARBAGE: dict[str, Reply] = {
    "good": completion(["```python\ndef equation(x, p):\n    return p[0] * x\n```"]),
    "not json": Reply(200, "<html><body>502 Bad Gateway</body></html>"),
    "no choices": Reply(200, {"error": {"message": "overloaded"}}),
    "prose": completion(["The derivative is proportional to x."]),
    "empty": completion([""]),
    "null": completion([None]),
    "truncated": completion(["def equation(x, p):\n    return p[0] * "], finish_reason="length"),
}


def test_unusable_answers_are_dropped_with_reasons() -> None:
    requests = [
        PromptRequest(
            contract=CONTRACT,
            examples=(),
            header="def equation(x, p):",
            messages=({"role": "user", "content": name},),
            n_samples=1,
            island=i,
            seed=i,
        )
        for i, name in enumerate(GARBAGE)
    ]
    with ChatServer(lambda received: GARBAGE[user_text(received)]) as server:
        proposer = LLMProposer(make_config(server.url))
        samples = proposer.propose(requests)
    assert [s.text for s in samples] == [GARBAGE["good"].body["choices"][0]["message"]["content"]]
    assert proposer.stats.as_dict()["dropped"] == {
        "bad_body": 2,
        "empty": 2,
        "no_code": 1,
        "truncated": 1,
    }
    assert proposer.stats.retries == 0


def test_concurrency_is_bounded() -> None:
    state = {"now": 0, "peak": 0}
    lock = threading.Lock()

    def counting(received: Received) -> Reply:
        with lock:
            state["now"] += 1
            state["peak"] = max(state["peak"], state["now"])
        time.sleep(0.05)
        with lock:
            state["now"] -= 1
        return completion([toy_skeleton(received.body["seed"])])

    with ChatServer(counting) as server:
        proposer = LLMProposer(make_config(server.url, concurrency=2))
        assert len(proposer.propose(make_requests(n_requests=4, n_samples=2))) == 8
    assert state["peak"] == 2


def test_propose_works_inside_a_running_event_loop() -> None:
    with ChatServer() as server:
        proposer = LLMProposer(make_config(server.url))

        async def main() -> int:
            return len(proposer.propose(make_requests(n_requests=1, n_samples=2)))

        assert asyncio.run(main()) == 2


def test_an_in_process_transport_can_replace_the_network() -> None:
    def handler(request: httpx.Request) -> httpx.Response:
        body = json.loads(request.content)
        return httpx.Response(200, json=completion([toy_skeleton(body["seed"])]).body)

    proposer = LLMProposer(
        make_config("http://in-process/v1"),
        transport_factory=lambda: httpx.MockTransport(handler),
    )
    for _ in range(2):  # a fresh transport each round
        assert len(proposer.propose(make_requests(n_requests=1, n_samples=2))) == 2


def test_requests_without_messages_are_refused() -> None:
    proposer = LLMProposer(make_config("http://127.0.0.1:9/v1"))
    request = PromptRequest(contract=CONTRACT, examples=(), header="def equation(x, p):")
    with pytest.raises(ValueError, match="no messages"):
        proposer.propose([request])


def test_parse_retry_after() -> None:
    now = datetime(2025, 1, 1, 12, 0, 0, tzinfo=UTC)
    assert parse_retry_after("0.2") == pytest.approx(0.2)
    assert parse_retry_after(" 7 ") == 7.0
    assert parse_retry_after("-3") == 0.0
    assert parse_retry_after(format_datetime(now + timedelta(seconds=10), usegmt=True), now) == 10
    assert parse_retry_after(format_datetime(now - timedelta(seconds=10), usegmt=True), now) == 0
    assert parse_retry_after("soon") is None
    assert parse_retry_after("") is None
    assert parse_retry_after(None) is None
    assert parse_retry_after("nan") is None


@settings(max_examples=200, deadline=None)
@given(
    retry=st.integers(0, 60),
    base=st.floats(0, 10),
    cap=st.floats(0, 100),
    seed=st.integers(0, 2**32),
)
def test_backoff_is_bounded_and_jittered(retry: int, base: float, cap: float, seed: int) -> None:
    delay = backoff_delay(retry, base, cap, random.Random(seed))
    ceiling = min(cap, base * 2.0**retry)
    assert ceiling / 2 <= delay <= ceiling + 1e-12


def test_unusable_reason() -> None:
    assert unusable_reason(None, "stop") == "empty"
    assert unusable_reason("  \n", "stop") == "empty"
    assert unusable_reason("def f(p):\n  return p", "length") == "truncated"
    assert unusable_reason("x = p[0]", "stop") == "no_code"
    assert unusable_reason("def f(p):\n  return p", None) is None


def test_derive_seed_is_stable_and_distinct() -> None:
    assert derive_seed(3, 1) == derive_seed(3, 1)
    seeds = {derive_seed(s, k) for s in range(20) for k in range(20)}
    assert len(seeds) == 400 and all(0 <= s < 2**31 for s in seeds)
