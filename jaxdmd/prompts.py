"""Task contracts (DE and AE), in-context examples and the prompt requests sent to proposers."""

from __future__ import annotations

from collections.abc import Sequence
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
    def outputs(self) -> tuple[str, ...]:
        """Names of the skeleton's outputs: ``d_<state>`` (DE loop) or ``<variable>_`` (AE)."""
        return tuple(f"d_{t}" if self.loop == "DE" else f"{t}_" for t in self.targets)

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


# Descriptions of the channels jaxdmd's benchmark and a typical PMU export carry. A user's data
# with other names still works: the contract then shows the unit and role only.
DESCRIPTIONS: dict[str, str] = {
    "delta": "rotor angle",
    "omega": "rotor speed (1.0 = synchronous)",
    "e_qp": "q-axis transient EMF e'_q",
    "e_dp": "d-axis transient EMF e'_d",
    "e_dpp": "d-axis subtransient EMF e''_d",
    "i_d": "stator current, d axis",
    "i_q": "stator current, q axis",
    "P_e": "electromagnetic (air-gap) power",
    "Q_e": "reactive power at the terminal",
    "v_d": "terminal voltage, d axis",
    "v_q": "terminal voltage, q axis",
    "V": "terminal voltage magnitude",
    "theta": "terminal voltage angle",
    "P_m": "mechanical power from the prime mover",
    "v_f": "field voltage from the exciter",
}

REQUEST_FORMAT = (
    '{"variables": [{"name": "<variable name>", "role": "algebraic | input | boundary", '
    '"reason": "<why the equations need it>"}]}'
)


def describe(variable: Variable) -> str:
    text = variable.description or DESCRIPTIONS.get(variable.name, "")
    unit = f" [{variable.unit}]" if variable.unit else ""
    return f"- {variable.name}{unit}, {variable.role}" + (f": {text}" if text else "")


def header(contract: Contract, name: str | None = None) -> str:
    """The target function header, e.g. ``def equation(delta, omega, p):``."""
    return f"def {name or contract.function_name}({', '.join([*contract.arguments, 'p'])}):"


def _task(contract: Contract) -> str:
    targets = ", ".join(contract.targets)
    if contract.loop == "DE":
        return (
            f"Find the differential equations of a {contract.system}: one expression for the "
            f"time derivative of each state, in this order: {targets}."
        )
    return (
        f"Find the algebraic equations of a {contract.system}: one explicit expression for "
        f"each algebraic variable, in this order: {targets}, as functions of the states, "
        "inputs and boundary variables."
    )


def render_contract(contract: Contract) -> str:
    """The task contract (role, completion rules, variables, parameters, request format)."""
    library = (
        "\n".join(describe(v) for v in contract.library)
        if contract.library
        else "(empty: only the states are available so far)"
    )
    outputs = ", ".join(contract.outputs if contract.loop == "DE" else contract.targets)
    return "\n".join(
        [
            "# Role",
            "You are an expert in power-system dynamics who writes dynamic models as Python code.",
            "",
            "# Task",
            _task(contract),
            "",
            "# Completion rules",
            f"- Complete the function `{contract.function_name}` at the end; return {outputs}.",
            "- Write trainable parameters as p[0], p[1], ...: their values are fitted to data.",
            "- Use only the function's arguments, arithmetic, and jnp math functions "
            "(jnp.sin, jnp.cos, jnp.exp, jnp.log, jnp.sqrt, jnp.tanh, jnp.abs, jnp.where, "
            "jnp.clip, jnp.maximum, jnp.minimum).",
            "- No imports, loops, attribute access or other function calls.",
            "- Prefer short, physically meaningful equations.",
            "",
            "# States",
            "\n".join(describe(v) for v in contract.states),
            "",
            "# Variable library",
            library,
            "",
            "# Requesting variables",
            "If the equations need a measured quantity that is not an argument (an algebraic "
            "variable or an input), request it after the function in a JSON block:",
            REQUEST_FORMAT,
        ]
    )


def render_examples(contract: Contract, examples: Sequence[Example]) -> str:
    blocks = []
    for i, ex in enumerate(examples):
        losses = ", ".join(
            f"{t}: {loss:.3g}" for t, loss in zip(contract.targets, ex.losses, strict=False)
        )
        source = _rename(ex.source, f"{contract.function_name}_v{i}")
        blocks.append(
            f"# Version {i}: score {ex.score:.4g} (normalised error per equation: {losses})\n"
            f"{source.rstrip()}"
        )
    return "\n\n".join(blocks)


def _rename(source: str, name: str) -> str:
    head, sep, rest = source.partition("(")
    return f"def {name}{sep}{rest}" if head.startswith("def ") else source


def render(
    contract: Contract,
    examples: Sequence[Example],
    *,
    n_samples: int = 4,
    island: int = 0,
    seed: int = 0,
) -> PromptRequest:
    """A prompt request: examples ordered worst to best, and exactly the messages a model reads."""
    ordered = tuple(sorted(examples, key=lambda e: e.score))
    head = header(contract)
    user = "\n".join(
        [
            render_contract(contract),
            "",
            "# Previous versions, worst to best",
            render_examples(contract, ordered) if ordered else "(none yet)",
            "",
            f"# Write an improved version of the equations (higher score is better):\n{head}",
        ]
    )
    system = (
        "You write concise, correct Python functions that model power-system dynamics. "
        "Answer with one Python function in a ```python block, optionally followed by a "
        "```json block of variable requests."
    )
    messages = ({"role": "system", "content": system}, {"role": "user", "content": user})
    return PromptRequest(
        contract=contract,
        examples=ordered,
        header=head,
        messages=messages,
        n_samples=n_samples,
        island=island,
        seed=seed,
    )


def parse_variable_requests(requests: Sequence[object]) -> tuple[str, ...]:
    """Variable names from JSON requests, in order, without repeats.

    Accepts the documented format and the near misses models write: a list of names, objects
    with ``name``, or the list under ``new_variables``/``variables``/``request_variables``.
    """
    names: list[str] = []

    def visit(item: object) -> None:
        if isinstance(item, str):
            if item.isidentifier() and item not in names:
                names.append(item)
        elif isinstance(item, dict):
            for key in ("variables", "new_variables", "request_variables", "requests"):
                if key in item:
                    visit(item[key])
            if "name" in item:
                visit(item["name"])
        elif isinstance(item, list | tuple):
            for sub in item:
                visit(sub)

    visit(list(requests))
    return tuple(names)
