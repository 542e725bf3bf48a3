"""The search driven by the LLM proposer against a loopback server: failures, record, replay.

The server plays a generic model that knows no equation: it reads the target function's header
from the prompt and answers a random linear skeleton over those arguments (seeded by the
request's seed), with a JSON block asking for every variable the prompt's contract does not list.
"""

from __future__ import annotations

import itertools
import json
import random
import re

import jax
from llm_server import ChatServer, Received, Reply, completion
from test_llm import SECRET, make_config
from test_search import hidden_problem

from jaxdmd import search
from jaxdmd.pipeline import run_loop
from jaxdmd.proposers.llm import LLMProposer, ReplayProposer

CATALOG = ("u", "w", "z")


def generic_model(fail_every: int | None = None):
    """A handler answering generic linear skeletons; every ``fail_every``-th call fails."""
    calls = itertools.count()
    failures = itertools.cycle(
        [
            Reply(status=429, headers={"Retry-After": "0.05"}),
            Reply(status=500, body="oops"),
            Reply(status=200, body=b"", delay=1.5),  # past the request timeout
        ]
    )

    def handle(request: Received) -> Reply:
        if fail_every and next(calls) % fail_every == 0:
            return next(failures)
        body = request.body
        prompt = body["messages"][-1]["content"]
        args = re.findall(r"def equation\(([^)]*)\):\s*$", prompt)[-1].split(", ")[:-1]
        rng = random.Random(body.get("seed"))
        lines, k = [], 0
        for out in ("d_x", "d_y"):
            chosen = rng.sample(args, rng.randint(1, len(args)))
            terms = [f"p[{k + i}] * {a}" for i, a in enumerate(chosen)]
            k += len(chosen)
            lines.append(f"    {out} = " + " + ".join(terms))
        source = "\n".join([f"def equation({', '.join([*args, 'p'])}):", *lines])
        source += "\n    return d_x, d_y\n"
        wanted = [{"name": n} for n in CATALOG if n not in args]
        text = f"```python\n{source}```\n```json\n{json.dumps({'variables': wanted})}\n```"
        return completion([text])

    return handle


SETTINGS = search.SearchConfig(n_islands=3, prompts_per_round=2, samples_per_prompt=3, max_rounds=5)


def test_flaky_endpoint_run_completes_and_replays_without_the_server(tmp_path):
    problem, contract = hidden_problem(n=600)
    cache = tmp_path / "cache"
    state0 = search.init(problem, contract, jax.random.key(5), SETTINGS)
    sizes = []
    with ChatServer(generic_model(fail_every=3)) as server:
        proposer = LLMProposer(
            make_config(server.url, cache_dir=cache, round_timeout=20.0, max_retries=4)
        )
        original = proposer.propose

        def counted(requests):
            samples = original(requests)
            sizes.append(len(samples))
            return samples

        proposer.propose = counted  # type: ignore[method-assign]
        recorded = run_loop(state0, proposer)
    stats = proposer.stats.as_dict()
    # a third of the calls failed (429, 500, timeout); every sample still arrived: no round lost
    assert sizes == [6] * recorded.iteration
    assert stats["retries"] >= 2 * recorded.iteration
    assert SECRET not in json.dumps(stats)
    # the generic model asked for every catalog variable: the measured ones joined, z is missing
    assert {"u", "w"} <= set(recorded.contract.arguments)
    assert recorded.missing == ("z",)
    # the server is gone: the replayed run gives the same final state
    replayed = run_loop(state0, ReplayProposer(cache))
    assert search.state_to_dict(replayed) == search.state_to_dict(recorded)
    assert search.final_equations(replayed).source == search.final_equations(recorded).source
    for path in cache.rglob("*.json"):
        assert SECRET.encode() not in path.read_bytes()
