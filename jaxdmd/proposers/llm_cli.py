"""Command-line options of the language-model proposer, and the proposer they ask for.

:func:`add_llm_arguments` adds the options (``--llm``, ``--llm-model`` (its old spelling
``--model`` still works, hidden from the help: ``--model`` names the machine model in
``simulate`` and ``diagnose``), ``--api-key-env``, ``--temperature``, ``--llm-timeout``,
``--llm-concurrency``, ``--cache``, ``--replay``) to a parser; :func:`proposer_from_args`
turns the parsed options (and the environment) into an
:class:`~jaxdmd.proposers.llm.LLMProposer`, a :class:`~jaxdmd.proposers.llm.ReplayProposer` or
None (the offline proposer). Both are also importable from :mod:`jaxdmd.proposers.llm`.
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from jaxdmd.proposers.llm_config import (
    ENV_API_KEY,
    ENV_API_KEY_FALLBACK,
    ENV_BASE_URL,
    ENV_MODEL,
    PAPER_TEMPERATURE,
    LLMConfig,
    LLMConfigError,
)

if TYPE_CHECKING:
    from jaxdmd.proposers import Proposer


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
        "--llm-model",
        metavar="NAME",
        default=None,
        help=f"language model name, e.g. deepseek-chat (default: ${ENV_MODEL})",
    )
    # the old spelling, kept working but hidden: --model names the machine model elsewhere
    group.add_argument("--model", dest="llm_model", default=None, help=argparse.SUPPRESS)
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
    # imported here: jaxdmd.proposers.llm re-exports this module's functions
    from jaxdmd.proposers.llm import LLMProposer, ReplayProposer

    env = os.environ if environ is None else environ
    replay = getattr(ns, "replay", None)
    cache = getattr(ns, "cache", None)
    base_url = getattr(ns, "llm", None) or env.get(ENV_BASE_URL) or None
    model = (
        getattr(ns, "llm_model", None) if hasattr(ns, "llm_model") else getattr(ns, "model", None)
    )
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
