"""The language-model proposers (the paper's M-Agent): which samples to ask for, and from where.

:class:`LLMProposer` answers a round's prompt requests with ``request.n_samples`` samples each
from an OpenAI-compatible chat endpoint (DeepSeek, OpenAI, vLLM, Ollama and the llama.cpp
server all speak it) at temperature 1.2 (the paper's tau). It names every sample (a
:class:`~jaxdmd.proposers.cache.RequestIdentity`), takes what the cache already holds, plans the
HTTP calls for the rest, has :class:`~jaxdmd.proposers.chat_client.ChatClient` make them, records
the answers, and turns answers into samples in request order. Answers are raw, untrusted text;
the skeleton checker downstream decides what is usable. This module only drops what is clearly
unusable (no content, a body that is not a chat completion, no ``def``, code cut off at
``max_tokens``) and says why in :attr:`LLMProposer.stats`.

With ``cache_dir`` every sample's request and answer is recorded on disk (:mod:`.cache`) and
reused instead of calling the endpoint; :class:`ReplayProposer` answers from such a record with
no endpoint at all. The API key is never stored, logged or shown: not in the cache, the stats,
the exceptions or any ``repr``.

The parts live in their own modules and are re-exported here, so that
``from jaxdmd.proposers.llm import ...`` reaches all of them:

* :mod:`.llm_config`: :class:`LLMConfig` (settings, from arguments or the environment),
  :class:`LLMStats` and the errors (:class:`LLMError`, :class:`LLMUnavailable`,
  :class:`LLMRequestError`, :class:`LLMConfigError`, :class:`CacheMiss`);
* :mod:`.chat_client`: the HTTP client (timeouts, retries with backoff, ``Retry-After``, the
  parsing of answers) and its pure helpers (:func:`derive_seed`, :func:`backoff_delay`,
  :func:`parse_retry_after`);
* :mod:`.llm_cli`: the command-line options, :func:`add_llm_arguments` and
  :func:`proposer_from_args`.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import httpx

from jaxdmd.prompts import PromptRequest
from jaxdmd.proposers import Sample
from jaxdmd.proposers.cache import (
    AnswerCache,
    CachedAnswer,
    CacheEntry,
    RequestIdentity,
    prompt_key,
    public_url,
)
from jaxdmd.proposers.chat_client import (
    RETRYABLE_STATUS,
    Call,
    ChatClient,
    backoff_delay,
    derive_seed,
    parse_retry_after,
)
from jaxdmd.proposers.llm_cli import add_llm_arguments, proposer_from_args
from jaxdmd.proposers.llm_config import (
    ENV_API_KEY,
    ENV_API_KEY_FALLBACK,
    ENV_BASE_URL,
    ENV_MODEL,
    PAPER_TEMPERATURE,
    CacheMiss,
    LLMConfig,
    LLMConfigError,
    LLMError,
    LLMRequestError,
    LLMStats,
    LLMUnavailable,
)

__all__ = [  # the proposers here; the rest re-exported (see the module docstring)
    "ENV_API_KEY",
    "ENV_API_KEY_FALLBACK",
    "ENV_BASE_URL",
    "ENV_MODEL",
    "PAPER_TEMPERATURE",
    "RETRYABLE_STATUS",
    "CacheMiss",
    "LLMConfig",
    "LLMConfigError",
    "LLMError",
    "LLMProposer",
    "LLMRequestError",
    "LLMStats",
    "LLMUnavailable",
    "ReplayProposer",
    "add_llm_arguments",
    "backoff_delay",
    "derive_seed",
    "parse_retry_after",
    "proposer_from_args",
    "unusable_reason",
]

logger = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------------
# turning recorded or fresh answers into samples


def unusable_reason(content: str | None, finish_reason: str | None) -> str | None:
    """Why an answer is clearly unusable (``empty``, ``truncated``, ``no_code``), or None."""
    if content is None or not content.strip():
        return "empty"
    if finish_reason == "length":
        return "truncated"
    if "def " not in content:
        return "no_code"
    return None


@dataclass(frozen=True)
class _Slot:
    """Sample ``sample`` of prompt request number ``position``."""

    position: int
    island: int
    sample: int


def _collect(
    slots: Sequence[tuple[_Slot, str]],
    answers: Mapping[str, CachedAnswer],
    origins: Mapping[str, str],
    stats: LLMStats,
) -> list[Sample]:
    """Samples in request order from answers by key; drops are counted in ``stats``."""
    samples = []
    for slot, key in slots:
        answer = answers.get(key)
        if answer is None:  # lost this round (already counted in stats.lost)
            continue
        if answer.status == "failed":
            stats.dropped["recorded_failure"] += 1
            continue
        if answer.status == "bad_body":
            stats.dropped["bad_body"] += 1
            continue
        reason = unusable_reason(answer.content, answer.finish_reason)
        if reason is not None:
            stats.dropped[reason] += 1
            logger.debug("dropped sample %d of request %d: %s", slot.sample, slot.position, reason)
            continue
        samples.append(Sample(text=answer.content or "", island=slot.island, origin=origins[key]))
    stats.samples_returned += len(samples)
    return samples


# --------------------------------------------------------------------------------------------
# the live proposer


class LLMProposer:
    """A :class:`~jaxdmd.proposers.Proposer` that asks an OpenAI-compatible chat endpoint.

    ``propose`` is synchronous (it runs its own event loop) and returns one
    :class:`~jaxdmd.proposers.Sample` per usable answer, in request order, with
    ``island = request.island`` and ``origin = config.model``. Counts and token usage accumulate
    in :attr:`stats`.

    Args:
        config: endpoint and behaviour settings.
        transport_factory: makes the httpx async transport of each round instead of the network
            (e.g. ``lambda: httpx.MockTransport(handler)``); a client closes its transport
            after each round, hence a factory.
        jitter_seed: seed of the backoff jitter (the jitter needs no reproducibility).
    """

    def __init__(
        self,
        config: LLMConfig,
        *,
        transport_factory: Callable[[], httpx.AsyncBaseTransport] | None = None,
        jitter_seed: int | None = None,
    ) -> None:
        self.config = config
        self.stats = LLMStats()
        self._cache = AnswerCache(config.cache_dir) if config.cache_dir is not None else None
        self._client = ChatClient(
            config,
            self.stats,
            store=self._store,
            transport_factory=transport_factory,
            jitter_seed=jitter_seed,
        )

    def __repr__(self) -> str:
        return f"LLMProposer({self.config!r})"

    # -- public ------------------------------------------------------------------------------

    def propose(self, requests: Sequence[PromptRequest]) -> list[Sample]:
        """Ask for ``n_samples`` answers to each request; return the usable ones.

        Raises:
            LLMUnavailable: no request of the round got an answer.
            LLMRequestError: the endpoint refused a request (bad key, unknown model, ...).
            CacheMiss: in replay mode, a sample is not in the record.
        """
        started = time.monotonic()
        self.stats.rounds += 1
        slots: list[tuple[_Slot, str]] = []
        identities: dict[str, RequestIdentity] = {}
        by_request: dict[int, list[RequestIdentity]] = {}
        for position, request in enumerate(requests):
            for sample in range(request.n_samples):
                identity = self._identity(request, sample)
                slots.append((_Slot(position, request.island, sample), identity.key))
                if identity.key not in identities:
                    identities[identity.key] = identity
                    by_request.setdefault(position, []).append(identity)
        self.stats.samples_requested += len(slots)

        answers: dict[str, CachedAnswer] = {}
        pending: dict[int, list[RequestIdentity]] = {}
        for position, group in by_request.items():
            for identity in group:
                answer = self._cache.get(identity) if self._cache is not None else None
                if answer is not None and (answer.status == "ok" or self.config.replay):
                    answers[identity.key] = answer
                    self.stats.cache_hits += 1
                    self.stats.cached_prompt_tokens += answer.usage.get("prompt_tokens", 0)
                    self.stats.cached_completion_tokens += answer.usage.get("completion_tokens", 0)
                elif self.config.replay:
                    raise CacheMiss(
                        f"replay: no recorded answer in {self.config.cache_dir} for "
                        f"{identity.describe()}; record it first with a live run using this cache "
                        "directory, or check that the prompts, seed and endpoint settings are "
                        "those of the recorded run"
                    )
                else:
                    pending.setdefault(position, []).append(identity)

        if pending:
            calls = self._plan_calls(requests, pending)
            answers.update(self._client.run(calls))

        origins = {key: self.config.model for key in identities}
        samples = _collect(slots, answers, origins, self.stats)
        elapsed = time.monotonic() - started
        self.stats.seconds += elapsed
        logger.info(
            "LLM round %d: %d of %d samples usable (%d from cache), %d retries, "
            "%d+%d tokens so far, %.1f s",
            self.stats.rounds,
            len(samples),
            len(slots),
            len(identities) - sum(len(group) for group in pending.values()),
            self.stats.retries,
            self.stats.prompt_tokens,
            self.stats.completion_tokens,
            elapsed,
        )
        return samples

    # -- request building --------------------------------------------------------------------

    def _identity(self, request: PromptRequest, sample: int) -> RequestIdentity:
        if not request.messages:
            raise ValueError(
                f"prompt request for island {request.island} (seed {request.seed}) has no "
                "messages: render it with jaxdmd.prompts before asking a language model"
            )
        return RequestIdentity.build(
            base_url=self.config.base_url,
            model=self.config.model,
            messages=request.messages,
            temperature=self.config.temperature,
            max_tokens=self.config.max_tokens,
            seed=request.seed,
            sample=sample,
            extra=self.config.extra_body,
        )

    def _plan_calls(
        self, requests: Sequence[PromptRequest], pending: Mapping[int, list[RequestIdentity]]
    ) -> list[Call]:
        per_call = self.config.n_per_request if self._client.n_supported else 1
        calls = []
        for position, group in pending.items():
            request = requests[position]
            for start in range(0, len(group), per_call):
                chunk = group[start : start + per_call]
                calls.append(
                    Call(
                        messages=[dict(m) for m in request.messages],
                        seed=request.seed,
                        identities=chunk,
                    )
                )
        return calls

    # -- the cache ---------------------------------------------------------------------------

    def _store(self, identity: RequestIdentity, answer: CachedAnswer) -> None:
        if self._cache is None or self.config.replay:
            return
        try:
            self._cache.put(identity, answer)
        except OSError as exc:
            logger.warning("cannot write LLM cache entry in %s: %s", self.config.cache_dir, exc)
        else:
            self.stats.cache_writes += 1


# --------------------------------------------------------------------------------------------
# replay without an endpoint


class ReplayProposer:
    """Answers prompt requests from a recorded cache directory, never calling an endpoint.

    Entries are found by (messages, request seed, sample index); if the record holds answers
    from several endpoint settings for the same prompt, narrow them with ``model``,
    ``base_url``, ``temperature`` or ``max_tokens``. Recorded failures and unusable answers
    are dropped again (with their reason in :attr:`stats`), so replaying a recorded run gives
    the same samples. A sample missing from the record raises :class:`CacheMiss`.
    """

    def __init__(
        self,
        cache_dir: str | os.PathLike[str],
        *,
        model: str | None = None,
        base_url: str | None = None,
        temperature: float | None = None,
        max_tokens: int | None = None,
    ) -> None:
        self.cache = AnswerCache(cache_dir)
        if not self.cache.directory.is_dir():
            raise LLMConfigError(f"replay: {self.cache.directory} is not a directory")
        self.model = model
        self.base_url = public_url(base_url) if base_url else None
        self.temperature = temperature
        self.max_tokens = max_tokens
        self.stats = LLMStats()
        self._index: dict[str, list[CacheEntry]] | None = None

    def __repr__(self) -> str:
        return f"ReplayProposer({str(self.cache.directory)!r}, model={self.model!r})"

    def _matches(self, entry: CacheEntry) -> bool:
        endpoint = entry.endpoint
        return (
            (self.model is None or endpoint.model == self.model)
            and (self.base_url is None or endpoint.base_url == self.base_url)
            and (self.temperature is None or endpoint.temperature == float(self.temperature))
            and (self.max_tokens is None or endpoint.max_tokens == int(self.max_tokens))
        )

    def _lookup(self, request: PromptRequest, sample: int) -> CacheEntry:
        key = prompt_key(request.messages, request.seed, sample)
        for fresh in (False, True):
            if self._index is None or fresh:
                self._index = self.cache.index_by_prompt()
            candidates = [e for e in self._index.get(key, []) if self._matches(e)]
            if candidates:
                break
        endpoints = {e.endpoint for e in candidates}
        if not candidates:
            first = next(
                (
                    m.get("content", "")
                    for m in reversed(request.messages)
                    if m.get("role") == "user"
                ),
                "",
            )
            raise CacheMiss(
                f"replay: {self.cache.directory} ({len(self.cache)} entries) holds no answer for "
                f"sample {sample} of the request for island {request.island} with seed "
                f"{request.seed} ({len(request.messages)} messages, the user message starting "
                f"{first[:50]!r}, prompt key {key[:12]})"
                + (f" from model {self.model!r}" if self.model else "")
                + "; replay needs the same prompts, seeds and sample counts as the recorded run"
            )
        if len(endpoints) > 1:
            listing = "; ".join(sorted(str(e) for e in endpoints))
            raise LLMConfigError(
                f"replay: {self.cache.directory} holds answers to the same prompt from several "
                f"endpoint settings ({listing}); choose one with --model, --llm or --temperature"
            )
        return candidates[0]

    def propose(self, requests: Sequence[PromptRequest]) -> list[Sample]:
        """The recorded samples for ``requests``; raises :class:`CacheMiss` for a missing one."""
        started = time.monotonic()
        self.stats.rounds += 1
        slots: list[tuple[_Slot, str]] = []
        answers: dict[str, CachedAnswer] = {}
        origins: dict[str, str] = {}
        for position, request in enumerate(requests):
            for sample in range(request.n_samples):
                entry = self._lookup(request, sample)
                slots.append((_Slot(position, request.island, sample), entry.key))
                answers[entry.key] = entry.answer
                origins[entry.key] = entry.model
                self.stats.cache_hits += 1
                self.stats.cached_prompt_tokens += entry.answer.usage.get("prompt_tokens", 0)
                self.stats.cached_completion_tokens += entry.answer.usage.get(
                    "completion_tokens", 0
                )
        self.stats.samples_requested += len(slots)
        samples = _collect(slots, answers, origins, self.stats)
        self.stats.seconds += time.monotonic() - started
        logger.info(
            "replay round %d: %d of %d samples usable", self.stats.rounds, len(samples), len(slots)
        )
        return samples
