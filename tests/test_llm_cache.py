"""Recording and replaying language-model answers; the API key never reaches the disk."""

from __future__ import annotations

import json
import logging
import threading
from pathlib import Path

import pytest
from llm_server import ChatServer, Handler, Received, Reply, completion, toy_skeleton
from test_llm import SECRET, make_config, make_requests, user_text

from jaxdmd.proposers.cache import AnswerCache, CachedAnswer, RequestIdentity, public_url
from jaxdmd.proposers.llm import (
    CacheMiss,
    LLMConfigError,
    LLMProposer,
    LLMRequestError,
    ReplayProposer,
)


def eventful() -> Handler:
    """Mostly good answers; request 1 fails once (even seeds), request 2 always, 3 is prose."""
    seen: set[tuple[str, int]] = set()
    lock = threading.Lock()

    def handler(received: Received) -> Reply:
        text = user_text(received)
        which = int(text.split()[1]) % 10  # the request's position within its round
        seed = received.body["seed"]
        if which == 2:
            return Reply(500, "always broken")
        if which == 1 and seed % 2 == 0:
            with lock:
                first = (text, seed) not in seen
                seen.add((text, seed))
            if first:
                return Reply(503, "try again", {"Retry-After": "0"})
        if which == 3:
            return completion(["Sorry, I cannot help with that."])
        return completion([toy_skeleton(seed)])

    return handler


def rounds() -> list[list]:
    return [make_requests(n_requests=4, n_samples=2, seed0=10 * r) for r in range(2)]


def test_recorded_run_replays_identically_without_the_server(tmp_path: Path) -> None:
    cache_dir = tmp_path / "cache"
    with ChatServer(eventful()) as server:
        url = server.url
        recorder = LLMProposer(make_config(url, cache_dir=cache_dir, max_retries=1))
        recorded = [recorder.propose(requests) for requests in rounds()]
    assert [len(samples) for samples in recorded] == [4, 4]  # request 2 lost, request 3 prose
    assert recorder.stats.lost["retries_exhausted"] == 2 * 2
    assert recorder.stats.dropped["no_code"] == 2 * 2
    assert recorder.stats.cache_writes == 16
    assert len(AnswerCache(cache_dir)) == 16
    assert not list(cache_dir.rglob("*.tmp"))

    # the server is gone: replay by exact key ...
    replayer = LLMProposer(make_config(url, cache_dir=cache_dir, replay=True))
    assert [replayer.propose(requests) for requests in rounds()] == recorded
    assert replayer.stats.cache_hits == 16 and replayer.stats.attempts == 0
    assert replayer.stats.dropped["recorded_failure"] == 4
    assert replayer.stats.cached_prompt_tokens == recorder.stats.prompt_tokens

    # ... and by prompt alone, knowing nothing of the endpoint
    replay = ReplayProposer(cache_dir)
    assert [replay.propose(requests) for requests in rounds()] == recorded
    assert replay.stats.samples_returned == 8 and replay.stats.dropped["no_code"] == 4


def test_cached_answers_are_used_instead_of_the_endpoint(tmp_path: Path) -> None:
    requests = make_requests(n_requests=2, n_samples=2)
    with ChatServer() as server:
        first = LLMProposer(make_config(server.url, cache_dir=tmp_path))
        samples = first.propose(requests)
        assert len(server.received) == 4
        second = LLMProposer(make_config(server.url, cache_dir=tmp_path))
        assert second.propose(requests) == samples
        assert len(server.received) == 4
        assert second.stats.cache_hits == 4 and second.stats.prompt_tokens == 0
        assert second.stats.cached_prompt_tokens == first.stats.prompt_tokens
        # a different temperature is a different request
        third = LLMProposer(make_config(server.url, cache_dir=tmp_path, temperature=0.7))
        third.propose(requests)
        assert len(server.received) == 8


def test_recorded_failures_are_asked_again_in_a_live_run(tmp_path: Path) -> None:
    requests = make_requests(n_requests=1, n_samples=1)
    with ChatServer(lambda r: Reply(500, "down")) as server:
        proposer = LLMProposer(make_config(server.url, cache_dir=tmp_path, max_retries=0))
        with pytest.raises(Exception, match="no answer"):
            proposer.propose(requests)
    with ChatServer() as server:
        proposer = LLMProposer(make_config(server.url, cache_dir=tmp_path))
        assert len(proposer.propose(requests)) == 1
        assert len(server.received) == 1


def test_replay_miss_is_a_clear_error(tmp_path: Path) -> None:
    with ChatServer() as server:
        LLMProposer(make_config(server.url, cache_dir=tmp_path)).propose(make_requests(1, 1))
    with pytest.raises(CacheMiss, match=r"1 entries.*island 0 with seed 99"):
        ReplayProposer(tmp_path).propose(make_requests(1, 1, seed0=99))
    with pytest.raises(CacheMiss, match="seed 0"):
        ReplayProposer(tmp_path).propose(make_requests(1, 2))  # sample 1 was never asked
    config = make_config("http://127.0.0.1:9/v1", cache_dir=tmp_path, replay=True)
    with pytest.raises(CacheMiss, match="sample 0 of the request with seed 99"):
        LLMProposer(config).propose(make_requests(1, 1, seed0=99))
    with pytest.raises(LLMConfigError, match="not a directory"):
        ReplayProposer(tmp_path / "nowhere")


def test_replay_of_several_models_needs_a_choice(tmp_path: Path) -> None:
    requests = make_requests(n_requests=1, n_samples=1)
    with ChatServer() as server:
        for model in ("model-a", "model-b"):
            LLMProposer(make_config(server.url, model=model, cache_dir=tmp_path)).propose(requests)
    with pytest.raises(LLMConfigError, match=r"model-a.*model-b"):
        ReplayProposer(tmp_path).propose(requests)
    samples = ReplayProposer(tmp_path, model="model-b").propose(requests)
    assert [s.origin for s in samples] == ["model-b"]


def test_api_key_never_reaches_disk_stats_logs_or_errors(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.DEBUG)
    with ChatServer(eventful()) as server:
        # credentials in the URL are not stored either
        url = server.url.replace("http://", "http://user:pw-SECRET-pw@")
        config = make_config(url, cache_dir=tmp_path, max_retries=1)
        proposer = LLMProposer(config)
        proposer.propose(make_requests(n_requests=4, n_samples=2))
        assert any(r.headers.get("authorization") for r in server.received)

    def refuse(received: Received) -> Reply:
        return Reply(401, {"error": {"message": f"bad key {SECRET}"}})

    with ChatServer(refuse) as server:
        config_401 = make_config(server.url, cache_dir=tmp_path)
        with pytest.raises(LLMRequestError) as info:
            LLMProposer(config_401).propose(make_requests(1, 1, seed0=50))

    blobs = [path.read_bytes() for path in tmp_path.rglob("*") if path.is_file()]
    assert blobs
    texts = [
        *(blob.decode() for blob in blobs),
        json.dumps(proposer.stats.as_dict()),
        repr(config),
        str(config),
        repr(proposer),
        repr(config_401),
        str(info.value),
        repr(info.value),
        caplog.text,
    ]
    for text in texts:
        assert SECRET not in text
        assert "pw-SECRET-pw" not in text
    stored = json.loads(blobs[0])
    assert stored["request"]["base_url"].startswith("http://127.0.0.1:")
    assert "api_key=None" not in repr(config) and "api_key='***'" in repr(config)


def test_identity_covers_the_request_and_not_the_credentials() -> None:
    base = dict(
        base_url="https://api.example.com/v1/",
        model="m",
        messages=[{"role": "user", "content": "hi"}],
        temperature=1.2,
        max_tokens=100,
        seed=1,
        sample=0,
    )
    key = RequestIdentity.build(**base).key
    with_creds = {**base, "base_url": "https://me:secret@api.example.com/v1?key=abc"}
    assert RequestIdentity.build(**with_creds).key == key
    changes = {
        "base_url": "https://api.other.com/v1",
        "model": "n",
        "messages": [{"role": "user", "content": "hi!"}],
        "temperature": 1.0,
        "max_tokens": 101,
        "seed": 2,
        "sample": 1,
    }
    for name, value in changes.items():
        assert RequestIdentity.build(**{**base, name: value}).key != key, name
    assert RequestIdentity.build(**base, extra={"top_p": 0.9}).key != key
    assert public_url("https://me:secret@api.example.com:8443/v1/?key=abc") == (
        "https://api.example.com:8443/v1"
    )


def test_cache_entries_round_trip_and_bad_files_are_skipped(tmp_path: Path) -> None:
    cache = AnswerCache(tmp_path)
    identity = RequestIdentity.build(
        base_url="http://h/v1",
        model="m",
        messages=[{"role": "user", "content": "x"}],
        temperature=1.2,
        max_tokens=10,
        seed=0,
        sample=0,
    )
    answer = CachedAnswer(status="ok", content="def f(p): return p", finish_reason="stop")
    path = cache.put(identity, answer)
    assert cache.get(identity) == answer
    assert path.parent.parent == tmp_path and path.name == f"{identity.key}.json"
    (path.parent / "broken.json").write_text("{not json")
    assert [e.answer for e in cache.entries()] == [answer]
