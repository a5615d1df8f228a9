"""Comments, docstrings and the public contract say why for today's reader: no issue numbers in them.

An issue number sends the reader to a tracker for what the text should say itself, and goes stale as the
code moves on. Every comment and every string literal (docstrings, and the descriptions that become the
OpenAPI text) of ``core/`` and ``service/`` is read, and so is the generated ``openapi/openapi.json``.
"""

from __future__ import annotations

import ast
import io
import re
import tokenize
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
ISSUE = re.compile(r"\bissues? ?#?\d+", re.IGNORECASE)


def prose(source: str):
    """``(line, text)`` of every comment and every string literal of a module's ``source``."""
    for token in tokenize.generate_tokens(io.StringIO(source).readline):
        if token.type == tokenize.COMMENT:
            yield token.start[0], token.string
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            yield node.lineno, node.value


def issue_mentions(path: Path) -> list[str]:
    return [f"{path.relative_to(REPO)}:{line}: {ISSUE.search(text).group(0)}"
            for line, text in prose(path.read_text()) if ISSUE.search(text)]


def test_the_check_sees_comments_docstrings_and_strings():
    source = '"""Done in issue 9."""\nx = 1  # see issue 14\nhelp = "Until Issue #6, none"\nok = "an issue with it"\n'
    assert sorted(line for line, text in prose(source) if ISSUE.search(text)) == [1, 2, 3]


@pytest.mark.parametrize("package", ["core", "service"])
def test_no_issue_number_in_comments_or_docstrings(package):
    found = [hit for path in sorted((REPO / package).rglob("*.py")) for hit in issue_mentions(path)]
    assert found == []


def test_no_issue_number_in_the_public_contract():
    assert ISSUE.findall((REPO / "openapi" / "openapi.json").read_text()) == []
