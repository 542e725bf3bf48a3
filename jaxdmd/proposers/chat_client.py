"""The OpenAI-compatible HTTP client: one round of chat-completions calls, and what comes back.

:class:`ChatClient` sends planned calls (:class:`Call`: the messages of one prompt request and
the samples it asks for) to ``POST {base_url}/chat/completions`` with at most
``config.concurrency`` in flight, and returns one :class:`~jaxdmd.proposers.cache.CachedAnswer`
per sample. Here and only here are the requests, the retries and the rate limits:

* every HTTP attempt has a timeout (``request_timeout``), every round a deadline
  (``round_timeout``); a round that runs out of time goes on with the answers it got;
* 429, 408, 5xx, connection errors and timeouts are retried with exponential backoff and
  jitter, honouring ``Retry-After`` (seconds or HTTP-date, capped at ``retry_after_cap``);
* an endpoint that answers nothing in a round raises one
  :class:`~jaxdmd.proposers.llm_config.LLMUnavailable`, never a hang; other 4xx answers fail
  fast with :class:`~jaxdmd.proposers.llm_config.LLMRequestError`;
* a 200 answer is parsed (choices, message content, finish reason, token usage); a body that is
  not a chat completion becomes a ``bad_body`` answer; a server that ignores ``n`` is asked
  again one sample per call.

Which samples to ask for, the cache and the turning of answers into samples are the proposer's
(:mod:`.llm`). Secrets (the API key, a password in the URL) are redacted from every message.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import email.utils
import hashlib
import logging
import random
from collections import Counter
from collections.abc import Callable, Coroutine, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any, TypeVar

import httpx

from jaxdmd.proposers.cache import CachedAnswer, RequestIdentity
from jaxdmd.proposers.llm_config import (
    ENV_API_KEY,
    ENV_API_KEY_FALLBACK,
    LLMConfig,
    LLMRequestError,
    LLMStats,
    LLMUnavailable,
)

logger = logging.getLogger(__name__)

RETRYABLE_STATUS = frozenset({408, 409, 425, 429, 500, 502, 503, 504, 520, 522, 524, 529})
"""HTTP statuses that are retried; any other 5xx is retried too, any other 4xx fails fast."""

T = TypeVar("T")


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
# one round


@dataclass
class Call:
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


class ChatClient:
    """Runs rounds of chat-completions calls against one endpoint; keeps what it learns.

    Args:
        config: endpoint and behaviour settings.
        stats: where calls, attempts, retries, failures, lost samples and tokens are counted
            (the proposer's :class:`~jaxdmd.proposers.llm_config.LLMStats`).
        store: called with every answer worth recording (each 200 answer and bad body as it
            arrives, each failure at the end of the round); the proposer's cache.
        transport_factory: makes the httpx async transport of each round instead of the network
            (e.g. ``lambda: httpx.MockTransport(handler)``); a client closes its transport
            after each round, hence a factory.
        jitter_seed: seed of the backoff jitter (the jitter needs no reproducibility).

    :attr:`n_supported` starts true when ``config.n_per_request > 1`` and turns false for good
    once the server answers fewer choices than asked with ``n``.
    """

    def __init__(
        self,
        config: LLMConfig,
        stats: LLMStats,
        *,
        store: Callable[[RequestIdentity, CachedAnswer], None] | None = None,
        transport_factory: Callable[[], httpx.AsyncBaseTransport] | None = None,
        jitter_seed: int | None = None,
    ) -> None:
        self.config = config
        self.stats = stats
        self.n_supported = config.n_per_request > 1
        self._store = store if store is not None else lambda identity, answer: None
        self._transport_factory = transport_factory
        self._rng = random.Random(jitter_seed)
        url = httpx.URL(config.base_url)
        secrets = (config.api_key, url.password, url.username if url.password else None)
        self._secrets = [s for s in secrets if s and len(s) >= 4]

    def __repr__(self) -> str:
        return f"ChatClient({self.config!r})"

    def run(self, calls: list[Call]) -> dict[str, CachedAnswer]:
        """One round: every call's samples answered (or failed), by identity key.

        Synchronous: runs its own event loop (on a private thread inside a running loop).

        Raises:
            LLMUnavailable: no call of the round got an answer.
            LLMRequestError: the endpoint refused a request (bad key, unknown model, ...).
        """
        return _run_sync(lambda: self._round(calls))

    # -- the request -------------------------------------------------------------------------

    def _body(self, call: Call) -> dict[str, Any]:
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

    async def _round(self, calls: list[Call]) -> dict[str, CachedAnswer]:
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
        call: Call,
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
        call: Call,
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
            if self.n_supported:
                logger.warning(
                    "%s answered %d of %d choices asked with n: asking one sample per call "
                    "from now on (set n_per_request=1 for this server)",
                    self.config.public_chat_url,
                    len(choices),
                    len(call.identities),
                )
            self.n_supported = False
            for identity in missing:
                single = Call(messages=call.messages, seed=call.seed, identities=[identity])
                await self._call(client, semaphore, single, state, results)

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
