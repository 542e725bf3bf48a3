"""Task contracts (DE and AE), in-context examples and the prompt requests sent to proposers."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

Role = Literal["state", "algebraic", "input", "boundary"]
Loop = Literal["DE", "AE"]


@dataclass(frozen=True)
class Variable:
    """A named quantity a skeleton may use: its identifier in code, role, unit and meaning."""

    name: str
    role: Role
    unit: str = "pu"
    description: str = ""


@dataclass(frozen=True)
class Contract:
    """What one loop asks for: targets, the variables a skeleton may use, and the header."""

    loop: Loop
    targets: tuple[str, ...]  # DE: the states (d/dt of each); AE: the algebraic variables
    states: tuple[Variable, ...]  # always arguments of the skeleton
    library: tuple[Variable, ...] = ()  # the variable library (grows by extension)
    function_name: str = "equation"
    system: str = "synchronous generator"

    @property
    def arguments(self) -> tuple[str, ...]:
        """Argument names of the target function, in order, before the parameter vector `p`."""
        return tuple(v.name for v in self.states) + tuple(v.name for v in self.library)


@dataclass(frozen=True)
class Example:
    """An evaluated skeleton shown to the proposer: code, score, per-equation NMSE, parameters."""

    source: str
    score: float
    losses: tuple[float, ...]
    params: tuple[float, ...]


@dataclass(frozen=True)
class PromptRequest:
    """One prompt: the structured request and the exact chat messages a model reads."""

    contract: Contract
    examples: tuple[Example, ...]  # ordered worst to best
    header: str  # the target function header, e.g. "def equation(delta, omega, p):"
    messages: tuple[dict[str, str], ...] = field(default=())
    n_samples: int = 4
    island: int = 0
    seed: int = 0
