"""On-disk record of language-model requests and answers, for caching and exact replay.

Every sample a language model is asked for is one *entry*: one JSON file, written atomically
(temporary file + ``os.replace``), named by the hash of the exact request that produced it.
The hash covers everything that determines the answer::

    base_url (without credentials or query), model, messages, temperature, max_tokens,
    the request's seed, the sample index (and any extra body fields)

so that a run recorded with ``--cache DIR`` can be replayed with ``--replay DIR`` and no
endpoint, giving the same samples. The API key, the ``Authorization`` header and any other
request header are never part of an entry.

An entry holds one of three kinds of answer:

``ok``
    The model answered (content, finish reason, token usage). Answers later dropped as
    unusable (no code, truncated, empty) are stored too, so that replay drops them again.
``bad_body``
    The endpoint answered 200 with a body that is not a chat completion. Replay drops it again;
    a live run asks again (the body was most likely a proxy's error page).
``failed``
    The sample was lost (retries exhausted, round timeout). Replay drops it with the recorded
    reason; a live run asks again.

Layout: ``DIR/<first two hex digits>/<sha256>.json``.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import tempfile
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import httpx

logger = logging.getLogger(__name__)

FORMAT = "jaxdmd-llm-cache/1"

AnswerStatus = Literal["ok", "bad_body", "failed"]


def public_url(url: str) -> str:
    """``url`` without user info (``user:password@``), query and fragment, and no trailing slash.

    This is the form of an endpoint URL that may be stored, logged or shown in an error.
    """
    try:
        parsed = httpx.URL(url)
    except (httpx.InvalidURL, TypeError, ValueError):
        return "<invalid URL>"
    if not parsed.host:
        return "<invalid URL>"
    port = f":{parsed.port}" if parsed.port is not None else ""
    path = parsed.path.rstrip("/")
    return f"{parsed.scheme}://{parsed.host}{port}{path}"


def _canonical(value: Any) -> bytes:
    return json.dumps(value, sort_keys=True, ensure_ascii=False, separators=(",", ":")).encode()


@dataclass(frozen=True)
class RequestIdentity:
    """Everything that determines one sample's answer; its hash names the cache entry.

    ``seed`` is the prompt request's seed and ``sample`` the index of the sample within that
    request (0 .. n_samples-1); the seed actually sent to the endpoint is derived from both.
    """

    base_url: str
    model: str
    messages: tuple[tuple[tuple[str, str], ...], ...]
    temperature: float
    max_tokens: int
    seed: int
    sample: int
    extra: tuple[tuple[str, str], ...] = ()

    @classmethod
    def build(
        cls,
        *,
        base_url: str,
        model: str,
        messages: Sequence[Mapping[str, str]],
        temperature: float,
        max_tokens: int,
        seed: int,
        sample: int,
        extra: Mapping[str, Any] | None = None,
    ) -> RequestIdentity:
        """An identity from plain values; ``base_url`` is stripped of credentials here."""
        frozen_messages = tuple(
            tuple(sorted((str(k), str(v)) for k, v in m.items())) for m in messages
        )
        frozen_extra = tuple(
            sorted((str(k), _canonical(v).decode()) for k, v in (extra or {}).items())
        )
        return cls(
            base_url=public_url(base_url),
            model=model,
            messages=frozen_messages,
            temperature=float(temperature),
            max_tokens=int(max_tokens),
            seed=int(seed),
            sample=int(sample),
            extra=frozen_extra,
        )

    def messages_as_dicts(self) -> list[dict[str, str]]:
        """The chat messages as a list of dicts, in order."""
        return [dict(m) for m in self.messages]

    def as_dict(self) -> dict[str, Any]:
        """A JSON-ready description (stored in the entry; contains no credentials)."""
        return {
            "base_url": self.base_url,
            "model": self.model,
            "messages": self.messages_as_dicts(),
            "temperature": self.temperature,
            "max_tokens": self.max_tokens,
            "seed": self.seed,
            "sample": self.sample,
            "extra": {k: json.loads(v) for k, v in self.extra},
        }

    @property
    def key(self) -> str:
        """SHA-256 of the exact request: the entry's file name."""
        return hashlib.sha256(_canonical({"format": FORMAT, **self.as_dict()})).hexdigest()

    @property
    def prompt_key(self) -> str:
        """SHA-256 of (messages, seed, sample) only: finds an entry when the endpoint is unknown."""
        return prompt_key(self.messages_as_dicts(), self.seed, self.sample)

    @property
    def endpoint(self) -> Endpoint:
        """The endpoint settings this sample was asked with."""
        return Endpoint.of(self.as_dict())

    def describe(self) -> str:
        """A one-line human description, for error messages."""
        last_user = next(
            (
                dict(m).get("content", "")
                for m in reversed(self.messages)
                if dict(m).get("role") == "user"
            ),
            "",
        )
        first_line = last_user.strip().splitlines()[0] if last_user.strip() else ""
        if len(first_line) > 60:
            first_line = first_line[:57] + "..."
        return (
            f"sample {self.sample} of the request with seed {self.seed} "
            f"(model {self.model!r} at {self.base_url}, temperature {self.temperature}, "
            f"max_tokens {self.max_tokens}, {len(self.messages)} messages, "
            f"user message starting {first_line!r}, key {self.key[:12]})"
        )


@dataclass(frozen=True)
class Endpoint:
    """The endpoint settings of a request: what, besides the prompt, shapes an answer."""

    base_url: str
    model: str
    temperature: float
    max_tokens: int
    extra: str = "{}"

    @classmethod
    def of(cls, request: Mapping[str, Any]) -> Endpoint:
        """The settings of a stored request description (:meth:`RequestIdentity.as_dict`)."""
        return cls(
            base_url=str(request.get("base_url", "")),
            model=str(request.get("model", "")),
            temperature=float(request.get("temperature", 0.0)),
            max_tokens=int(request.get("max_tokens", 0)),
            extra=_canonical(request.get("extra") or {}).decode(),
        )

    def __str__(self) -> str:
        extra = "" if self.extra == "{}" else f", extra {self.extra}"
        return (
            f"model {self.model!r} at {self.base_url} (temperature {self.temperature}, "
            f"max_tokens {self.max_tokens}{extra})"
        )


def prompt_key(messages: Sequence[Mapping[str, str]], seed: int, sample: int) -> str:
    """SHA-256 of the messages, the request seed and the sample index."""
    frozen = [sorted((str(k), str(v)) for k, v in m.items()) for m in messages]
    return hashlib.sha256(
        _canonical({"format": FORMAT, "messages": frozen, "seed": int(seed), "sample": int(sample)})
    ).hexdigest()


@dataclass(frozen=True)
class CachedAnswer:
    """A recorded answer for one sample.

    ``usage`` is the token usage of the HTTP call that produced it (attributed to the first
    sample of a call that asked for several samples with ``n``; empty for the others).
    """

    status: AnswerStatus
    content: str | None = None
    finish_reason: str | None = None
    usage: Mapping[str, int] = field(default_factory=dict)
    error: str = ""

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {
            "status": self.status,
            "content": self.content,
            "finish_reason": self.finish_reason,
            "usage": dict(self.usage),
            "error": self.error,
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> CachedAnswer:
        """Inverse of :meth:`as_dict`; raises ``ValueError`` on a malformed record."""
        status = data.get("status")
        if status not in ("ok", "bad_body", "failed"):
            raise ValueError(f"unknown answer status {status!r}")
        content = data.get("content")
        if content is not None and not isinstance(content, str):
            raise ValueError("answer content is not a string")
        usage = data.get("usage") or {}
        if not isinstance(usage, Mapping):
            raise ValueError("answer usage is not an object")
        return cls(
            status=status,
            content=content,
            finish_reason=data.get("finish_reason"),
            usage={str(k): int(v) for k, v in usage.items() if isinstance(v, int | float)},
            error=str(data.get("error") or ""),
        )


@dataclass(frozen=True)
class CacheEntry:
    """One stored entry: the request (without credentials) and its answer."""

    key: str
    prompt_key: str
    request: Mapping[str, Any]
    answer: CachedAnswer

    @property
    def model(self) -> str:
        """The model that answered."""
        return str(self.request.get("model", ""))

    @property
    def endpoint(self) -> Endpoint:
        """The endpoint settings the answer was asked with."""
        return Endpoint.of(self.request)


class AnswerCache:
    """A directory of cache entries, one JSON file per sample, written atomically.

    Safe for several processes writing the same directory: a writer never leaves a partial
    file behind, and two writers of the same key leave one of the two complete entries.
    """

    def __init__(self, directory: str | os.PathLike[str]) -> None:
        self.directory = Path(directory)

    def __repr__(self) -> str:
        return f"AnswerCache({str(self.directory)!r})"

    def path(self, key: str) -> Path:
        """File of the entry with ``key``."""
        return self.directory / key[:2] / f"{key}.json"

    def get(self, identity: RequestIdentity) -> CachedAnswer | None:
        """The recorded answer for ``identity``, or None (missing or unreadable entry)."""
        entry = self._read(self.path(identity.key))
        return None if entry is None else entry.answer

    def put(self, identity: RequestIdentity, answer: CachedAnswer) -> Path:
        """Store ``answer`` for ``identity`` (replacing any earlier entry); return the file."""
        key = identity.key
        record = {
            "format": FORMAT,
            "key": key,
            "prompt_key": identity.prompt_key,
            "request": identity.as_dict(),
            "answer": answer.as_dict(),
        }
        target = self.path(key)
        target.parent.mkdir(parents=True, exist_ok=True)
        data = json.dumps(record, ensure_ascii=False, indent=1, sort_keys=True).encode()
        fd, tmp = tempfile.mkstemp(prefix=f".{key[:12]}.", suffix=".tmp", dir=target.parent)
        try:
            with os.fdopen(fd, "wb") as handle:
                handle.write(data)
                handle.flush()
                os.fsync(handle.fileno())
            os.replace(tmp, target)
        except BaseException:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
            raise
        return target

    def entries(self) -> Iterator[CacheEntry]:
        """All readable entries (unreadable files are skipped with a warning)."""
        if not self.directory.is_dir():
            return
        for file in sorted(self.directory.glob("??/*.json")):
            entry = self._read(file)
            if entry is not None:
                yield entry

    def __len__(self) -> int:
        return sum(1 for _ in self.directory.glob("??/*.json")) if self.directory.is_dir() else 0

    def index_by_prompt(self) -> dict[str, list[CacheEntry]]:
        """Entries grouped by :attr:`RequestIdentity.prompt_key` (messages, seed, sample)."""
        index: dict[str, list[CacheEntry]] = {}
        for entry in self.entries():
            index.setdefault(entry.prompt_key, []).append(entry)
        return index

    @staticmethod
    def _read(file: Path) -> CacheEntry | None:
        try:
            raw = file.read_bytes()
        except FileNotFoundError:
            return None
        except OSError as exc:
            logger.warning("cannot read cache entry %s: %s", file, exc)
            return None
        try:
            record = json.loads(raw)
            if record.get("format") != FORMAT:
                raise ValueError(f"format {record.get('format')!r}, expected {FORMAT!r}")
            return CacheEntry(
                key=str(record["key"]),
                prompt_key=str(record["prompt_key"]),
                request=record["request"],
                answer=CachedAnswer.from_dict(record["answer"]),
            )
        except (ValueError, KeyError, TypeError, AttributeError) as exc:
            logger.warning("skipping unreadable cache entry %s: %s", file, exc)
            return None
