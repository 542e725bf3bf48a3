"""The language-model proposer (the paper's M-Agent) over the OpenAI-compatible HTTP protocol.

:class:`LLMProposer` sends each prompt request's chat messages to
``POST {base_url}/chat/completions`` (DeepSeek, OpenAI, vLLM, Ollama and the llama.cpp server
all speak it) and asks for ``request.n_samples`` answers at temperature 1.2 (the paper's tau).
Answers are raw, untrusted text; the skeleton checker downstream decides what is usable. This
module only drops what is clearly unusable (no content, a body that is not a chat completion,
no ``def``, code cut off at ``max_tokens``) and says why in :attr:`LLMProposer.stats`.

Failures are normal and handled here, so that a search loop sees either samples or one clear
error:

* every HTTP attempt has a timeout (``request_timeout``), every round a deadline
  (``round_timeout``); a round that runs out of time goes on with the answers it got;
* 429, 408, 5xx, connection errors and timeouts are retried with exponential backoff and
  jitter, honouring ``Retry-After`` (seconds or HTTP-date, capped at ``retry_after_cap``);
* an endpoint that answers nothing in a round (down, wrong port, everything failing) raises one
  :class:`LLMUnavailable` naming the URL, the attempts and the last error, never a hang;
* other 4xx answers (401 bad key, 404 unknown model or wrong URL, 400 bad request) fail fast with
  :class:`LLMRequestError`.

With ``cache_dir`` every sample's request and answer is recorded on disk (:mod:`.cache`) and
reused instead of calling the endpoint; :class:`ReplayProposer` answers from such a record with
no endpoint at all. The API key is never stored, logged or shown: not in the cache, the stats,
the exceptions or any ``repr``.

Command-line integration: :func:`add_llm_arguments` and :func:`proposer_from_args`.
"""

from __future__ import annotations

import argparse
import asyncio
import concurrent.futures
import email.utils
import hashlib
import logging
import os
import random
import time
from collections import Counter
from collections.abc import Callable, Coroutine, Mapping, Sequence
from dataclasses import dataclass, field, fields
from datetime import UTC, datetime
from typing import Any, TypeVar

import httpx

from jaxdmd.prompts import PromptRequest
from jaxdmd.proposers import Proposer, Sample
from jaxdmd.proposers.cache import (
    AnswerCache,
    CachedAnswer,
    CacheEntry,
    RequestIdentity,
    prompt_key,
    public_url,
)

logger = logging.getLogger(__name__)

ENV_BASE_URL = "JAXDMD_LLM_BASE_URL"
ENV_MODEL = "JAXDMD_LLM_MODEL"
ENV_API_KEY = "JAXDMD_LLM_API_KEY"
ENV_API_KEY_FALLBACK = "OPENAI_API_KEY"

PAPER_TEMPERATURE = 1.2
"""The sampling temperature tau of the M-Agent in the paper."""

RETRYABLE_STATUS = frozenset({408, 409, 425, 429, 500, 502, 503, 504, 520, 522, 524, 529})
"""HTTP statuses that are retried; any other 5xx is retried too, any other 4xx fails fast."""

T = TypeVar("T")


# --------------------------------------------------------------------------------------------
# errors


class LLMError(RuntimeError):
    """Base class of the language-model proposer's errors."""


class LLMUnavailable(LLMError):
    """The endpoint answered no request of a round (down, unreachable or failing every time)."""


class LLMRequestError(LLMError):
    """The endpoint refused a request (a 4xx other than 429/408): retrying would not help."""

    def __init__(self, message: str, status: int) -> None:
        super().__init__(message)
        self.status = status


class LLMConfigError(LLMError, ValueError):
    """The language-model settings are incomplete or inconsistent."""


class CacheMiss(LLMError):
    """Replay was asked for a sample that the record does not hold."""


# --------------------------------------------------------------------------------------------
# configuration


@dataclass(frozen=True, kw_only=True)
class LLMConfig:
    """Settings of an OpenAI-compatible chat-completions endpoint and of how it is used.

    Attributes:
        base_url: the API root, e.g. ``https://api.deepseek.com/v1``; requests go to
            ``{base_url}/chat/completions`` (a URL already ending in ``/chat/completions`` is
            used as is).
        model: the model name the endpoint knows, e.g. ``deepseek-chat``.
        api_key: sent as ``Authorization: Bearer``; None for local servers. Never shown.
        api_key_source: name of the environment variable the key came from (for messages).
        temperature: sampling temperature; the paper's M-Agent uses 1.2.
        max_tokens: the answer budget; an answer cut at this length is dropped as truncated.
        n_per_request: samples asked per HTTP call with the ``n`` field. 1 (default) sends
            one call per sample, concurrently, which every server supports; >1 saves prompt
            tokens where ``n`` is supported (OpenAI, vLLM). A server that answers fewer choices
            than asked is asked again for the rest, one sample per call.
        concurrency: at most this many HTTP calls in flight.
        request_timeout: seconds for one HTTP attempt, from connecting to the last byte.
        connect_timeout: seconds to establish a connection (bounded by ``request_timeout``).
        round_timeout: seconds for a whole ``propose`` call including retries; what has not
            arrived by then is given up, and the round goes on with what it got.
        max_retries: retries of one call after its first attempt.
        backoff_base, backoff_cap: exponential backoff ``min(cap, base * 2**retry)`` with
            equal jitter (half fixed, half uniform) between retries without ``Retry-After``.
        retry_after_cap: the longest ``Retry-After`` that is honoured (longer ones are capped).
        send_seed: send a per-sample ``seed`` (derived from the request seed and the sample
            index); servers that support it (OpenAI, vLLM, llama.cpp, Ollama) become more
            reproducible, the others ignore it.
        extra_body: more JSON fields for the request body (e.g. ``{"top_p": 0.95}``); they are
            part of the cache key.
        cache_dir: record every request and answer here and reuse recorded answers.
        replay: answer from ``cache_dir`` only, never calling the endpoint; a missing sample
            raises :class:`CacheMiss`.
        trust_env: let httpx read proxy settings and certificates from the environment.
    """

    base_url: str
    model: str
    api_key: str | None = None
    api_key_source: str = ""
    temperature: float = PAPER_TEMPERATURE
    max_tokens: int = 2048
    n_per_request: int = 1
    concurrency: int = 4
    request_timeout: float = 120.0
    connect_timeout: float = 10.0
    round_timeout: float = 900.0
    max_retries: int = 4
    backoff_base: float = 1.0
    backoff_cap: float = 30.0
    retry_after_cap: float = 60.0
    send_seed: bool = True
    extra_body: Mapping[str, Any] = field(default_factory=dict)
    cache_dir: str | os.PathLike[str] | None = None
    replay: bool = False
    trust_env: bool = True

    def __post_init__(self) -> None:
        if not self.base_url or not str(self.base_url).strip():
            raise LLMConfigError(
                f"no endpoint URL: pass base_url=... or set {ENV_BASE_URL} "
                "(e.g. https://api.deepseek.com/v1 or http://127.0.0.1:8000/v1)"
            )
        try:
            scheme = httpx.URL(self.base_url).scheme
        except (httpx.InvalidURL, TypeError, ValueError) as exc:
            raise LLMConfigError(
                f"invalid endpoint URL {public_url(self.base_url)}: {exc}"
            ) from None
        if scheme not in ("http", "https"):
            raise LLMConfigError(
                f"endpoint URL {public_url(self.base_url)!r} must start with http:// or https://"
            )
        if not self.model or not str(self.model).strip():
            raise LLMConfigError(
                f"no model name for {public_url(self.base_url)}: pass model=... or set {ENV_MODEL} "
                "(e.g. deepseek-chat, gpt-4o-mini, or the name the local server serves)"
            )
        positive = {
            "max_tokens": self.max_tokens,
            "n_per_request": self.n_per_request,
            "concurrency": self.concurrency,
            "request_timeout": self.request_timeout,
            "connect_timeout": self.connect_timeout,
            "round_timeout": self.round_timeout,
        }
        for name, value in positive.items():
            if not value > 0:
                raise LLMConfigError(f"{name} must be positive, got {value!r}")
        non_negative = {
            "temperature": self.temperature,
            "max_retries": self.max_retries,
            "backoff_base": self.backoff_base,
            "backoff_cap": self.backoff_cap,
            "retry_after_cap": self.retry_after_cap,
        }
        for name, value in non_negative.items():
            if not value >= 0:
                raise LLMConfigError(f"{name} must be >= 0, got {value!r}")
        if self.replay and self.cache_dir is None:
            raise LLMConfigError("replay=True needs cache_dir (the directory of a recorded run)")

    def __repr__(self) -> str:
        parts = []
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name == "api_key":
                parts.append(f"api_key={'***' if value else None!r}")
            elif f.name == "base_url":
                parts.append(f"base_url={public_url(value)!r}")
            else:
                parts.append(f"{f.name}={value!r}")
        return f"LLMConfig({', '.join(parts)})"

    __str__ = __repr__

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None, **overrides: Any) -> LLMConfig:
        """Settings from the environment, with keyword overrides taking precedence.

        Reads ``JAXDMD_LLM_BASE_URL``, ``JAXDMD_LLM_MODEL`` and ``JAXDMD_LLM_API_KEY`` (falling
        back to ``OPENAI_API_KEY``). ``environ`` defaults to ``os.environ``.
        """
        env = os.environ if environ is None else environ
        values: dict[str, Any] = {
            "base_url": env.get(ENV_BASE_URL, ""),
            "model": env.get(ENV_MODEL, ""),
        }
        for var in (ENV_API_KEY, ENV_API_KEY_FALLBACK):
            if env.get(var):
                values["api_key"] = env[var]
                values["api_key_source"] = var
                break
        if overrides.get("api_key") and "api_key_source" not in overrides:
            overrides = {**overrides, "api_key_source": "the api_key argument"}
        values.update({k: v for k, v in overrides.items() if v is not None})
        return cls(**values)

    @property
    def chat_url(self) -> str:
        """The full URL of the chat-completions endpoint, without user info (see :attr:`auth`)."""
        url = httpx.URL(self.base_url)
        path = url.path.rstrip("/")
        if not path.endswith("/chat/completions"):
            path += "/chat/completions"
        return str(url.copy_with(path=path, username=None, password=None))

    @property
    def url_auth(self) -> httpx.BasicAuth | None:
        """Basic-auth credentials given in the URL (``http://user:password@host/...``), if any."""
        url = httpx.URL(self.base_url)
        if not url.username and not url.password:
            return None
        return httpx.BasicAuth(url.username, url.password)

    @property
    def public_chat_url(self) -> str:
        """:attr:`chat_url` without credentials or query: safe to show."""
        return public_url(self.chat_url)


# --------------------------------------------------------------------------------------------
# statistics


@dataclass
class LLMStats:
    """Counts and token usage of a proposer, cumulative over its rounds.

    ``failures`` counts failed HTTP attempts by kind (``connect``, ``timeout``, ``transport``,
    ``http_429``, ``http_500``, ...); ``lost`` counts samples given up by reason
    (``retries_exhausted``, ``round_timeout``); ``dropped`` counts answers that arrived but are
    clearly unusable, by reason (``empty``, ``truncated``, ``no_code``, ``bad_body``,
    ``recorded_failure``). Token counts of answers taken from the cache are kept apart
    (``cached_*``): they cost nothing this time.
    """

    rounds: int = 0
    samples_requested: int = 0
    samples_returned: int = 0
    calls: int = 0
    attempts: int = 0
    retries: int = 0
    cache_hits: int = 0
    cache_writes: int = 0
    prompt_tokens: int = 0
    completion_tokens: int = 0
    cached_prompt_tokens: int = 0
    cached_completion_tokens: int = 0
    seconds: float = 0.0
    failures: Counter[str] = field(default_factory=Counter)
    lost: Counter[str] = field(default_factory=Counter)
    dropped: Counter[str] = field(default_factory=Counter)

    @property
    def total_tokens(self) -> int:
        """Prompt plus completion tokens billed by the endpoint in this session."""
        return self.prompt_tokens + self.completion_tokens

    def as_dict(self) -> dict[str, Any]:
        """A JSON-ready copy, for the run's summary."""
        out: dict[str, Any] = {}
        for f in fields(self):
            value = getattr(self, f.name)
            out[f.name] = dict(sorted(value.items())) if isinstance(value, Counter) else value
        out["seconds"] = round(self.seconds, 3)
        out["total_tokens"] = self.total_tokens
        return out


# --------------------------------------------------------------------------------------------
# small pure helpers


def derive_seed(seed: int, sample: int) -> int:
    """The seed sent for sample ``sample`` of a request with seed ``seed`` (31-bit, stable)."""
    digest = hashlib.sha256(f"jaxdmd-llm:{int(seed)}:{int(sample)}".encode()).digest()
    return int.from_bytes(digest[:4], "big") & 0x7FFFFFFF


def backoff_delay(retry: int, base: float, cap: float, rng: random.Random) -> float:
    """Delay before retry ``retry`` (0-based): equal jitter on ``min(cap, base * 2**retry)``."""
    ceiling = min(cap, base * 2.0 ** min(retry, 62))
    return ceiling / 2.0 + rng.uniform(0.0, ceiling / 2.0)


def parse_retry_after(value: str | None, now: datetime | None = None) -> float | None:
    """Seconds to wait from a ``Retry-After`` header (delta-seconds or HTTP-date), or None.

    Dates in the past give 0; unparsable values give None (the caller falls back to backoff).
    """
    if value is None:
        return None
    text = value.strip()
    if not text:
        return None
    try:
        seconds = float(text)
    except ValueError:
        pass
    else:
        return max(0.0, seconds) if seconds == seconds else None  # reject NaN
    try:
        when = email.utils.parsedate_to_datetime(text)
    except (TypeError, ValueError, IndexError):
        return None
    if when is None:
        return None
    if when.tzinfo is None:
        when = when.replace(tzinfo=UTC)
    current = now if now is not None else datetime.now(UTC)
    return max(0.0, (when - current).total_seconds())


def unusable_reason(content: str | None, finish_reason: str | None) -> str | None:
    """Why an answer is clearly unusable (``empty``, ``truncated``, ``no_code``), or None."""
    if content is None or not content.strip():
        return "empty"
    if finish_reason == "length":
        return "truncated"
    if "def " not in content:
        return "no_code"
    return None


def _message_content(choice: Any) -> tuple[str | None, str | None]:
    """(content, finish_reason) of one choice; tolerant of content given as a list of parts."""
    if not isinstance(choice, Mapping):
        return None, None
    finish = choice.get("finish_reason")
    message = choice.get("message")
    content: Any = message.get("content") if isinstance(message, Mapping) else None
    if content is None and isinstance(choice.get("text"), str):  # legacy completions shape
        content = choice["text"]
    if isinstance(content, list):
        content = "".join(
            str(part.get("text", "")) if isinstance(part, Mapping) else str(part)
            for part in content
        )
    if content is not None and not isinstance(content, str):
        content = None
    return content, finish if isinstance(finish, str) else None


def _usage(data: Any) -> dict[str, int]:
    usage = data.get("usage") if isinstance(data, Mapping) else None
    if not isinstance(usage, Mapping):
        return {}
    out = {}
    for name in ("prompt_tokens", "completion_tokens"):
        value = usage.get(name)
        if isinstance(value, int | float) and value >= 0:
            out[name] = int(value)
    return out


def _server_message(response: httpx.Response, limit: int = 300) -> str:
    """The error message of a response body (JSON ``error.message`` or the text), shortened."""
    try:
        data = response.json()
    except ValueError:
        text = response.text
    else:
        error = data.get("error") if isinstance(data, Mapping) else None
        if isinstance(error, Mapping) and error.get("message"):
            text = str(error["message"])
        elif isinstance(error, str):
            text = error
        elif isinstance(data, Mapping) and data.get("message"):
            text = str(data["message"])
        else:
            text = response.text
    text = " ".join(text.split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _run_sync(factory: Callable[[], Coroutine[Any, Any, T]]) -> T:
    """Run a coroutine to completion from synchronous code, even inside a running event loop."""
    try:
        asyncio.get_running_loop()
    except RuntimeError:
        return asyncio.run(factory())
    # Called from async code (a notebook, an async app): run on a private loop in a thread.
    with concurrent.futures.ThreadPoolExecutor(max_workers=1) as pool:
        return pool.submit(lambda: asyncio.run(factory())).result()


# --------------------------------------------------------------------------------------------
# turning recorded or fresh answers into samples


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


@dataclass
class _Call:
    """One HTTP call: consecutive samples of one prompt request (several only with ``n``)."""

    messages: list[dict[str, str]]
    seed: int
    identities: list[RequestIdentity]


@dataclass
class _RoundState:
    """What one round has seen so far (for the decision that the endpoint is unavailable)."""

    answered: bool = False
    attempts: int = 0
    failures: Counter[str] = field(default_factory=Counter)
    last_error: str = ""


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
        self._transport_factory = transport_factory
        self._rng = random.Random(jitter_seed)
        self._cache = AnswerCache(config.cache_dir) if config.cache_dir is not None else None
        self._n_supported = config.n_per_request > 1
        url = httpx.URL(config.base_url)
        secrets = (config.api_key, url.password, url.username if url.password else None)
        self._secrets = [s for s in secrets if s and len(s) >= 4]

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
            answers.update(_run_sync(lambda: self._round(calls)))

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
    ) -> list[_Call]:
        per_call = self.config.n_per_request if self._n_supported else 1
        calls = []
        for position, group in pending.items():
            request = requests[position]
            for start in range(0, len(group), per_call):
                chunk = group[start : start + per_call]
                calls.append(
                    _Call(
                        messages=[dict(m) for m in request.messages],
                        seed=request.seed,
                        identities=chunk,
                    )
                )
        return calls

    def _body(self, call: _Call) -> dict[str, Any]:
        body: dict[str, Any] = dict(self.config.extra_body)
        body.update(
            model=self.config.model,
            messages=call.messages,
            temperature=self.config.temperature,
            max_tokens=self.config.max_tokens,
            stream=False,
        )
        if len(call.identities) > 1:
            body["n"] = len(call.identities)
        if self.config.send_seed:
            body["seed"] = derive_seed(call.seed, call.identities[0].sample)
        return body

    def _headers(self) -> dict[str, str]:
        headers = {"Accept": "application/json"}
        if self.config.api_key:
            headers["Authorization"] = f"Bearer {self.config.api_key}"
        return headers

    def _redact(self, text: str) -> str:
        for secret in self._secrets:
            text = text.replace(secret, "***")
        return text

    # -- one round ---------------------------------------------------------------------------

    async def _round(self, calls: list[_Call]) -> dict[str, CachedAnswer]:
        config = self.config
        timeout = httpx.Timeout(
            config.request_timeout, connect=min(config.connect_timeout, config.request_timeout)
        )
        limits = httpx.Limits(
            max_connections=config.concurrency, max_keepalive_connections=config.concurrency
        )
        state = _RoundState()
        results: dict[str, CachedAnswer] = {}
        async with httpx.AsyncClient(
            headers=self._headers(),
            auth=None if config.api_key else config.url_auth,
            timeout=timeout,
            limits=limits,
            transport=self._transport_factory() if self._transport_factory else None,
            trust_env=config.trust_env,
        ) as client:
            semaphore = asyncio.Semaphore(config.concurrency)
            tasks = {
                asyncio.create_task(self._call(client, semaphore, call, state, results)): call
                for call in calls
            }
            try:
                done, not_done = await asyncio.wait(
                    tasks, timeout=config.round_timeout, return_when=asyncio.FIRST_EXCEPTION
                )
                for task in done:
                    if task.exception() is not None:
                        raise task.exception()  # type: ignore[misc]
            finally:
                for task in tasks:
                    task.cancel()
                await asyncio.gather(*tasks, return_exceptions=True)

        for task in not_done:
            for identity in tasks[task].identities:
                if identity.key not in results:
                    self.stats.lost["round_timeout"] += 1
                    results[identity.key] = CachedAnswer(
                        status="failed", error=f"round timeout after {config.round_timeout:g} s"
                    )
        if not_done:
            logger.warning(
                "LLM round timeout after %g s: %d of %d calls unfinished; going on with the rest",
                config.round_timeout,
                len(not_done),
                len(calls),
            )

        if calls and not state.answered:
            raise LLMUnavailable(
                f"no answer from {config.public_chat_url} in this round: {len(calls)} calls, "
                f"{state.attempts} attempts (at most {config.max_retries} retries each, request "
                f"timeout {config.request_timeout:g} s, round timeout {config.round_timeout:g} s); "
                f"failures: {_counts(state.failures)}; "
                f"last error: {state.last_error or 'none (the round timed out)'}"
            )

        if self._cache is not None:
            for call in calls:
                for identity in call.identities:
                    answer = results.get(identity.key)
                    if answer is not None and answer.status == "failed":
                        self._store(identity, answer)
        return results

    async def _call(
        self,
        client: httpx.AsyncClient,
        semaphore: asyncio.Semaphore,
        call: _Call,
        state: _RoundState,
        results: dict[str, CachedAnswer],
    ) -> None:
        config = self.config
        url = config.chat_url
        body = self._body(call)
        self.stats.calls += 1
        kind = ""
        for attempt in range(config.max_retries + 1):
            retry_after: float | None = None
            if attempt:
                self.stats.retries += 1
            async with semaphore:
                self.stats.attempts += 1
                state.attempts += 1
                try:
                    response = await asyncio.wait_for(
                        client.post(url, json=body), timeout=config.request_timeout
                    )
                except (TimeoutError, httpx.TimeoutException) as exc:
                    kind = "connect" if isinstance(exc, httpx.ConnectTimeout) else "timeout"
                    error = f"{kind}: no answer within {config.request_timeout:g} s"
                except httpx.ConnectError as exc:
                    kind = "connect"
                    error = f"connection failed: {self._redact(str(exc)) or type(exc).__name__}"
                except httpx.TransportError as exc:
                    kind = "transport"
                    error = f"{type(exc).__name__}: {self._redact(str(exc))}"
                else:
                    status = response.status_code
                    if status == 200:
                        state.answered = True
                        await self._accept(client, semaphore, call, response, state, results)
                        return
                    kind = f"http_{status}"
                    error = (
                        f"HTTP {status} {response.reason_phrase}: "
                        f"{self._redact(_server_message(response))}"
                    )
                    if status not in RETRYABLE_STATUS and status < 500:
                        self.stats.failures[kind] += 1
                        state.failures[kind] += 1
                        raise LLMRequestError(self._refusal(status, response), status)
                    retry_after = parse_retry_after(response.headers.get("retry-after"))
            self.stats.failures[kind] += 1
            state.failures[kind] += 1
            state.last_error = error
            if attempt == config.max_retries:
                break
            if retry_after is not None:
                delay = min(retry_after, config.retry_after_cap)
                delay += self._rng.uniform(0.0, 0.1 * delay)
            else:
                delay = backoff_delay(attempt, config.backoff_base, config.backoff_cap, self._rng)
            logger.debug(
                "LLM call failed (%s); retry %d of %d in %.2f s",
                error,
                attempt + 1,
                config.max_retries,
                delay,
            )
            await asyncio.sleep(delay)

        attempts = config.max_retries + 1
        if kind == "connect" and not state.answered:
            raise LLMUnavailable(
                f"cannot reach the language model at {config.public_chat_url}: "
                f"{attempts} attempts failed to connect (backoff {config.backoff_base:g}-"
                f"{config.backoff_cap:g} s, connect timeout "
                f"{min(config.connect_timeout, config.request_timeout):g} s); "
                f"last error: {state.last_error}. Is the server running, and is the URL "
                "(host, port, /v1) right?"
            )
        logger.warning(
            "LLM call gave up after %d attempts (%d samples lost): %s",
            attempts,
            len(call.identities),
            state.last_error,
        )
        for identity in call.identities:
            self.stats.lost["retries_exhausted"] += 1
            results[identity.key] = CachedAnswer(
                status="failed", error=f"gave up after {attempts} attempts: {state.last_error}"
            )

    async def _accept(
        self,
        client: httpx.AsyncClient,
        semaphore: asyncio.Semaphore,
        call: _Call,
        response: httpx.Response,
        state: _RoundState,
        results: dict[str, CachedAnswer],
    ) -> None:
        """Record a 200 answer; ask again for samples a server without ``n`` left out."""
        try:
            data = response.json()
        except ValueError:
            data = None
            problem = (
                f"body is not JSON ({response.headers.get('content-type', 'no content type')})"
            )
        else:
            problem = ""
            if not isinstance(data, Mapping):
                problem = f"body is JSON {type(data).__name__}, not an object"
            elif not isinstance(data.get("choices"), list) or not data["choices"]:
                problem = "body has no choices"
                if data.get("error"):
                    problem += f" (error: {self._redact(_server_message(response))})"
        if problem:
            logger.warning("LLM answer dropped: %s", problem)
            for identity in call.identities:
                answer = CachedAnswer(status="bad_body", error=problem)
                results[identity.key] = answer
                self._store(identity, answer)
            return

        usage = _usage(data)
        self.stats.prompt_tokens += usage.get("prompt_tokens", 0)
        self.stats.completion_tokens += usage.get("completion_tokens", 0)
        choices = sorted(
            data["choices"],
            key=lambda c: c.get("index", 0) if isinstance(c, Mapping) else 0,
        )
        for i, identity in enumerate(call.identities[: len(choices)]):
            content, finish = _message_content(choices[i])
            answer = CachedAnswer(
                status="ok", content=content, finish_reason=finish, usage=usage if i == 0 else {}
            )
            results[identity.key] = answer
            self._store(identity, answer)

        missing = call.identities[len(choices) :]
        if missing:
            if self._n_supported:
                logger.warning(
                    "%s answered %d of %d choices asked with n: asking one sample per call "
                    "from now on (set n_per_request=1 for this server)",
                    self.config.public_chat_url,
                    len(choices),
                    len(call.identities),
                )
            self._n_supported = False
            for identity in missing:
                single = _Call(messages=call.messages, seed=call.seed, identities=[identity])
                await self._call(client, semaphore, single, state, results)

    def _store(self, identity: RequestIdentity, answer: CachedAnswer) -> None:
        if self._cache is None or self.config.replay:
            return
        try:
            self._cache.put(identity, answer)
        except OSError as exc:
            logger.warning("cannot write LLM cache entry in %s: %s", self.config.cache_dir, exc)
        else:
            self.stats.cache_writes += 1

    def _refusal(self, status: int, response: httpx.Response) -> str:
        config = self.config
        server = self._redact(_server_message(response))
        where = f"{config.public_chat_url} (model {config.model!r})"
        if status in (401, 403):
            if config.api_key:
                hint = (
                    f"the API key from {config.api_key_source or 'the configuration'} was refused; "
                    "check that it is valid for this endpoint"
                )
            else:
                hint = (
                    f"no API key was sent; set {ENV_API_KEY} (or {ENV_API_KEY_FALLBACK}), or name "
                    "the variable that holds it with --api-key-env VAR"
                )
            return f"{where} refused the request with HTTP {status}: {server}. {hint}."
        if status == 404:
            return (
                f"{where} answered HTTP 404: {server}. Check the base URL (it usually ends in "
                "/v1) and the model name (the server's /models lists them)."
            )
        return (
            f"{where} rejected the request with HTTP {status}: {server}. This is not retried; "
            "if it mentions 'seed' or 'n', set send_seed=False or n_per_request=1."
        )


def _counts(counter: Counter[str]) -> str:
    return ", ".join(f"{k} x{v}" for k, v in sorted(counter.items())) or "none"


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


# --------------------------------------------------------------------------------------------
# command line


def add_llm_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the language-model options to ``parser`` (as a group) and return it."""
    group = parser.add_argument_group(
        "language model",
        "Ask an OpenAI-compatible chat endpoint for skeletons (without --llm, --replay or "
        f"{ENV_BASE_URL}, the built-in offline proposer is used).",
    )
    group.add_argument(
        "--llm",
        metavar="URL",
        default=None,
        help=f"endpoint base URL, e.g. https://api.deepseek.com/v1 (default: ${ENV_BASE_URL})",
    )
    group.add_argument(
        "--model",
        metavar="NAME",
        default=None,
        help=f"model name, e.g. deepseek-chat (default: ${ENV_MODEL})",
    )
    group.add_argument(
        "--api-key-env",
        metavar="VAR",
        default=None,
        help=(
            "name of the environment variable holding the API key (the key itself never goes "
            f"on the command line; default: ${ENV_API_KEY}, then ${ENV_API_KEY_FALLBACK})"
        ),
    )
    group.add_argument(
        "--temperature",
        type=float,
        default=None,
        help=f"sampling temperature (default: {PAPER_TEMPERATURE}, the paper's)",
    )
    group.add_argument(
        "--llm-timeout",
        metavar="SECONDS",
        type=float,
        default=None,
        help=f"timeout of one request (default: {LLMConfig.request_timeout:g})",
    )
    group.add_argument(
        "--llm-concurrency",
        metavar="N",
        type=int,
        default=None,
        help=f"requests in flight at once (default: {LLMConfig.concurrency})",
    )
    group.add_argument(
        "--cache",
        metavar="DIR",
        default=None,
        help="record every request and answer in DIR and reuse recorded answers",
    )
    group.add_argument(
        "--replay",
        metavar="DIR",
        default=None,
        help="answer from the record in DIR only, without any endpoint",
    )
    return parser


def proposer_from_args(
    ns: argparse.Namespace, environ: Mapping[str, str] | None = None
) -> Proposer | None:
    """The proposer the language-model options ask for, or None for the offline proposer.

    None when neither ``--llm`` (nor ``$JAXDMD_LLM_BASE_URL``) nor ``--replay`` is given.

    Raises:
        LLMConfigError: inconsistent options (``--cache`` with ``--replay``, ``--cache``
            without an endpoint, a missing model name, an unset ``--api-key-env`` variable).
    """
    env = os.environ if environ is None else environ
    replay = getattr(ns, "replay", None)
    cache = getattr(ns, "cache", None)
    base_url = getattr(ns, "llm", None) or env.get(ENV_BASE_URL) or None
    model = getattr(ns, "model", None)
    temperature = getattr(ns, "temperature", None)
    if replay:
        if cache:
            raise LLMConfigError(
                "--cache DIR records a live run and --replay DIR replays one: give only one"
            )
        return ReplayProposer(
            replay, model=model, base_url=getattr(ns, "llm", None), temperature=temperature
        )
    if not base_url:
        if cache:
            raise LLMConfigError(
                f"--cache {cache} records language-model answers: give the endpoint with "
                f"--llm URL (or {ENV_BASE_URL}) too"
            )
        return None
    overrides: dict[str, Any] = {
        "base_url": base_url,
        "model": model,
        "temperature": temperature,
        "concurrency": getattr(ns, "llm_concurrency", None),
        "cache_dir": cache,
    }
    timeout = getattr(ns, "llm_timeout", None)
    if timeout is not None:
        overrides["request_timeout"] = timeout
        overrides["round_timeout"] = max(LLMConfig.round_timeout, 3.0 * timeout)
    key_var = getattr(ns, "api_key_env", None)
    if key_var:
        if not env.get(key_var):
            raise LLMConfigError(
                f"--api-key-env {key_var}: the environment variable {key_var} is not set or empty"
            )
        overrides["api_key"] = env[key_var]
        overrides["api_key_source"] = f"${key_var}"
    return LLMProposer(LLMConfig.from_env(env, **overrides))
