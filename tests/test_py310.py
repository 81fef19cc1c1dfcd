"""Python 3.10 (NVIDIA JetPack 6) stays supported: what neither ruff nor mypy catches.

mypy runs at ``python_version = 3.10`` (pyproject.toml), which finds standard-library names that
3.10 lacks (``datetime.UTC``, ``asyncio.timeout``, ``Task.cancelling``). Two differences it does
not see are checked here on the source:

- on 3.10, ``asyncio.TimeoutError`` (raised by ``asyncio.wait_for`` and ``async_timeout``) is not
  the builtin ``TimeoutError``: a handler around such a wait must name both, or the timeout
  escapes (the service's tick loops would have died on their first idle tick);
- ``tomllib`` is 3.11+: it is imported only behind a version check, with ``tomli`` below it.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SOURCES = sorted(p for d in ("companion", "sim", "tests") for p in (REPO / d).rglob("*.py"))
WAITS = {"wait_for", "timeout", "_timeout"}


def _calls_in(nodes: list[ast.stmt]) -> Iterator[str]:
    """Names of the functions called in ``nodes``, not descending into nested definitions."""
    stack: list[ast.AST] = list(nodes)
    while stack:
        node = stack.pop()
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda, ast.ClassDef)):
            continue
        if isinstance(node, ast.Call):
            f = node.func
            yield f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""
        stack.extend(ast.iter_child_nodes(node))


def _caught(handler: ast.ExceptHandler) -> list[str]:
    types = handler.type.elts if isinstance(handler.type, ast.Tuple) else [handler.type] if handler.type else []
    return [ast.unparse(t) for t in types]


def timeout_handlers_missing_asyncio(tree: ast.AST) -> list[int]:
    """Lines of ``except TimeoutError`` handlers around an asyncio wait that miss asyncio.TimeoutError."""
    bad = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Try) and WAITS & set(_calls_in(node.body)):
            for h in node.handlers:
                caught = _caught(h)
                if "TimeoutError" in caught and "asyncio.TimeoutError" not in caught:
                    bad.append(h.lineno)
    return bad


def _sources_saying(word: str) -> Iterator[tuple[Path, ast.AST]]:
    """Each source whose text holds ``word``, parsed: a file without it can hold neither such a
    handler (``TimeoutError``) nor such an import (``tomllib``), so the others need no parse."""
    for path in SOURCES:
        text = path.read_text()
        if word in text:
            yield path, ast.parse(text)


def test_asyncio_timeouts_are_caught_on_python_3_10() -> None:
    bad = {str(p.relative_to(REPO)): lines for p, tree in _sources_saying("TimeoutError")
           if (lines := timeout_handlers_missing_asyncio(tree))}
    assert not bad, (f"{bad}: these lines catch TimeoutError around asyncio.wait_for/timeout; on 3.10 that "
                     "misses asyncio.TimeoutError: catch (TimeoutError, asyncio.TimeoutError)")


def test_tomllib_is_imported_behind_a_version_check() -> None:
    for path, tree in _sources_saying("tomllib"):
        guarded = {id(n) for node in ast.walk(tree) if isinstance(node, ast.If) and "version_info" in ast.unparse(node.test)
                   for n in ast.walk(node)}
        for node in ast.walk(tree):
            if isinstance(node, ast.Import) and any(a.name == "tomllib" for a in node.names):
                assert id(node) in guarded, f"{path.name}:{node.lineno} imports tomllib without a 3.10 fallback"


def test_the_checker_finds_an_unguarded_handler() -> None:
    src = ("async def f(e):\n"
           "    try:\n        await asyncio.wait_for(e.wait(), 1)\n    except TimeoutError:\n        pass\n"
           "    try:\n        await asyncio.wait_for(e.wait(), 1)\n    except (TimeoutError, asyncio.TimeoutError):\n        pass\n"
           "    try:\n        sock.recv(1)\n    except TimeoutError:\n        pass\n")
    assert timeout_handlers_missing_asyncio(ast.parse(src)) == [4]
