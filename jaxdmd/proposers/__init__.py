"""Proposers turn prompt requests into skeleton texts: the offline search and LLMs over HTTP."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

from jaxdmd.prompts import PromptRequest


@dataclass(frozen=True)
class Sample:
    """One answer of a proposer: raw text (untrusted) and the island whose prompt produced it."""

    text: str
    island: int
    origin: str = ""


class Proposer(Protocol):
    """Anything that answers prompt requests with samples.

    A proposer is the only part of a search loop that may talk to the world (HTTP, disk).
    Given the same requests (which carry their own seeds) a deterministic proposer gives the
    same samples.
    """

    def propose(self, requests: Sequence[PromptRequest]) -> list[Sample]: ...
