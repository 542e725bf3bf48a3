"""The language-model proposer's shared types: its settings, its errors and its counters.

:class:`LLMConfig` says which OpenAI-compatible chat-completions endpoint to ask and how (from
arguments or the ``JAXDMD_LLM_*`` environment variables); :class:`LLMStats` is what a proposer
counts over its rounds; the ``LLM*`` exceptions are everything the proposers raise. The HTTP
client (:mod:`.chat_client`), the proposers (:mod:`.llm`) and the command-line options
(:mod:`.llm_cli`) all use them; everything here is also importable from
:mod:`jaxdmd.proposers.llm`. The API key is never shown: not in any ``repr`` nor in a message.
"""

from __future__ import annotations

import os
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import Any

import httpx

from jaxdmd.proposers.cache import public_url

ENV_BASE_URL = "JAXDMD_LLM_BASE_URL"
ENV_MODEL = "JAXDMD_LLM_MODEL"
ENV_API_KEY = "JAXDMD_LLM_API_KEY"
ENV_API_KEY_FALLBACK = "OPENAI_API_KEY"

PAPER_TEMPERATURE = 1.2
"""The sampling temperature tau of the M-Agent in the paper."""


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
