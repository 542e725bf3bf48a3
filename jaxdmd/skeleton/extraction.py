"""Extraction: a model's answer -> the skeleton's source and its variable requests."""

from __future__ import annotations

import ast
import json
import re
import textwrap
from typing import Any

from jaxdmd.skeleton.core import MAX_ANSWER_CHARS, MAX_SOURCE_CHARS, SkeletonError, _parse

__all__ = ["extract"]

_FENCE = re.compile(r"[ \t]*(`{3,}|~{3,})[ \t]*([\w+.-]*)")
_DEF = re.compile(r"([ \t]*)(?:async[ \t]+)?def[ \t]+([A-Za-z_]\w*)[ \t]*\(")
_MAX_JSON_TRIES = 20


def extract(text: str, function_name: str | None = None) -> tuple[str, tuple[dict, ...]]:
    """Find the skeleton's source and the variable requests in a model's answer.

    Code is taken from the markdown code fences that contain a ``def`` (or from the whole text if
    none does). The function is the last one named ``function_name`` if that is given, otherwise
    the last function that parses and whose last parameter is ``p`` (otherwise the last one, so
    that ``check`` can say what is wrong). Its lines are detabbed and dedented. Requests are the
    last ``json`` fence (or bare JSON object/list that ends the text) that parses: a list of
    dicts, or an object with a ``"variables"`` list; malformed JSON is ignored.
    Raises ``SkeletonError`` if no function is found.
    """
    if not isinstance(text, str):
        raise SkeletonError(f"the answer must be text, not {type(text).__name__}")
    if len(text) > MAX_ANSWER_CHARS:
        raise SkeletonError(
            f"the answer is {len(text)} characters long; at most {MAX_ANSWER_CHARS} are read"
        )
    lines = text.splitlines()
    code_blocks, json_texts, outside, last_fence = _split_fences(lines)

    regions = [block for block in code_blocks if any(_DEF.match(line) for line in block)]
    if not regions:
        regions = [outside]
    candidates = [c for region in regions for c in _functions(region)]
    if not candidates:
        raise SkeletonError("the answer contains no Python function (def name(..., p): ...)")
    if function_name is not None:
        named = [c for c in candidates if c[0] == function_name]
        if not named:
            found = ", ".join(sorted({c[0] for c in candidates}))
            raise SkeletonError(
                f"the answer has no function named {function_name!r} (found {found})"
            )
        source = named[-1][1]
    else:
        complete = [src for _, src in candidates if _ends_with_p(src)]
        source = complete[-1] if complete else candidates[-1][1]

    requests: tuple[dict, ...] = ()
    for blob in reversed(json_texts):
        requests = _requests(blob)
        if requests:
            break
    if not requests:
        requests = _trailing_json(lines, last_fence)
    return source, requests


def _split_fences(lines: list[str]) -> tuple[list[list[str]], list[str], list[str], int]:
    """Code fences, JSON texts, the lines outside fences (fences blanked), the last fence line."""
    code_blocks: list[list[str]] = []
    json_texts: list[str] = []
    outside: list[str] = []
    block: list[str] | None = None
    language = ""
    last_fence = -1
    for index, line in enumerate(lines):
        match = _FENCE.match(line)
        if match:
            last_fence = index
            outside.append("")
            opening = block is None or bool(match.group(2))  # ```lang also ends an open fence
            if block is not None:
                _file_block(block, language, code_blocks, json_texts)
                block = None
            if opening:
                block, language = [], match.group(2).lower()
            continue
        if block is None:
            outside.append(line)
        else:
            block.append(line)
            outside.append("")
    if block is not None:  # an unclosed fence: the answer was cut off
        _file_block(block, language, code_blocks, json_texts)
    return code_blocks, json_texts, outside, last_fence


def _file_block(block: list[str], language: str, code: list[list[str]], data: list[str]) -> None:
    content = "\n".join(block).strip()
    if language == "json" or (language in ("", "javascript", "js") and content[:1] in "{["):
        data.append(content)
    else:
        code.append(block)


def _functions(lines: list[str]) -> list[tuple[str, str]]:
    """The top-level ``def`` blocks of a region: (name, dedented source)."""
    found = []
    index = floor = 0
    while index < len(lines):
        match = _DEF.match(lines[index])
        if match is None:
            index += 1
            continue
        indent = _width(match.group(1))
        depth = _bracket_delta(lines[index])
        end = index + 1
        while end < len(lines):
            line = lines[end]
            if line.strip():
                leading = line[: len(line) - len(line.lstrip())]
                if depth <= 0 and _width(leading) <= indent:
                    break
                depth += _bracket_delta(line)
            end += 1
        start = index  # decorators belong to the function, so that check() rejects them
        while start > floor and lines[start - 1].lstrip().startswith("@"):
            start -= 1
        block = [_detab(line) for line in lines[start:end]]
        found.append((match.group(2), textwrap.dedent("\n".join(block)).strip("\n") + "\n"))
        index = floor = end
    return found


def _width(whitespace: str) -> int:
    return len(whitespace.replace("\u00a0", " ").expandtabs(4))


def _detab(line: str) -> str:
    stripped = line.lstrip(" \t\u00a0")
    leading = line[: len(line) - len(stripped)]
    return " " * _width(leading) + stripped.rstrip()


def _bracket_delta(line: str) -> int:
    code = line.split("#", 1)[0]
    return sum(code.count(c) for c in "([{") - sum(code.count(c) for c in ")]}")


def _ends_with_p(source: str) -> bool:
    if len(source) > MAX_SOURCE_CHARS:
        return False
    try:
        tree = _parse(source)
    except Exception:  # SyntaxError, RecursionError, MemoryError, ValueError: not complete
        return False
    if len(tree.body) != 1 or not isinstance(tree.body[0], ast.FunctionDef):
        return False
    args = tree.body[0].args.args
    return bool(args) and args[-1].arg == "p"


def _trailing_json(lines: list[str], last_fence: int) -> tuple[dict, ...]:
    """A bare JSON object or list that ends the answer (after the last fence and ``def``)."""
    start = last_fence + 1
    for index in range(len(lines) - 1, start - 1, -1):
        if _DEF.match(lines[index]):
            start = index + 1
            break
    starts = [i for i in range(start, len(lines)) if lines[i].lstrip()[:1] in ("{", "[")]
    for index in starts[:_MAX_JSON_TRIES]:
        requests = _requests("\n".join(lines[index:]).strip())
        if requests:
            return requests
    return ()


def _requests(blob: str) -> tuple[dict, ...]:
    """Parse variable requests; anything malformed gives ``()``."""
    if not blob or len(blob) > 50_000:
        return ()
    try:
        obj = json.loads(blob)
    except (ValueError, RecursionError):
        return ()
    items: Any = []
    if isinstance(obj, list):
        items = obj
    elif isinstance(obj, dict):
        for key in ("variables", "requests"):
            if isinstance(obj.get(key), list):
                items = obj[key]
                break
        else:
            items = [obj] if "name" in obj else []
    out = []
    for item in items:
        if isinstance(item, dict):
            out.append(dict(item))
        elif isinstance(item, str):
            out.append({"name": item})
    return tuple(out)
