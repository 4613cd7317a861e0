"""Docs and code comments state what is true now; the history is in git.

A doc (README.md, docs/**/*.md) or a comment or docstring of the product packages fails here
when it cites an issue number ("issue 13"), a work session ("session 7", "pre-session-7"), a
commit hash, or, in a doc's running text, an ISO date. Where the date rule stops: fenced blocks
(```) of a doc are command lines and example output, and a program's output may carry a
timestamp (a file's `created` field) that is data, not history, so dates are allowed there; JSON
result files under docs/ are data and are not read. Issue numbers, sessions and commit hashes
are refused everywhere, fences included: no command or output needs them.

Also: every file kept under docs/ is referenced by a doc, and every relative link of a doc points
to a file that exists (results and figures no doc cites, or citations of files never committed,
are what a lab notebook leaves behind).
"""

from __future__ import annotations

import ast
import io
import re
import tokenize
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("dpmhw", "drivers", "calibration", "server", "firmware_mocks")

ISSUE = re.compile(r"\bissues? ?#?\d+", re.IGNORECASE)
# a work session by number; "a session of 30 s" or "session 5 s" is a duration, not history
SESSION = re.compile(r"\bsessions?[- ]\d+\b(?!\s*(?:s|ms|min|minutes?|seconds?|fps|Hz)\b)", re.IGNORECASE)
# 7-40 lowercase hex digits with at least one letter and one digit: an abbreviated or full commit
COMMIT = re.compile(r"(?<![\w.-])(?=[0-9a-f]*[a-f])(?=[0-9a-f]*\d)[0-9a-f]{7,40}(?![\w-])")
ISO_DATE = re.compile(r"\b(?:19|20)\d\d-[01]\d-[0-3]\d\b")
FENCE = re.compile(r"^\s*(```|~~~)")
LINK = re.compile(r"\]\(([^)\s]+)\)")


def _docs() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def _history(text: str, *, dates: bool) -> list[str]:
    found = [m.group(0) for rx in (ISSUE, SESSION, COMMIT) for m in rx.finditer(text)]
    if dates:
        found += [m.group(0) for m in ISO_DATE.finditer(text)]
    return found


def _doc_findings(path: Path) -> list[str]:
    out, fenced = [], False
    for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if FENCE.match(line):
            fenced = not fenced
            continue
        for hit in _history(line, dates=not fenced):
            out.append(f"{path.relative_to(ROOT)}:{n}: {hit!r} in {line.strip()[:100]!r}")
    return out


def _comments_and_docstrings(path: Path):
    """(line, text) of every comment and every module, class and function docstring."""
    source = path.read_text(encoding="utf-8")
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.COMMENT:
            yield tok.start[0], tok.string
    tree = ast.parse(source)
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) \
                    and isinstance(body[0].value.value, str):
                yield body[0].lineno, body[0].value.value


@pytest.mark.parametrize("path", _docs(), ids=lambda p: str(p.relative_to(ROOT)))
def test_a_doc_tells_no_history(path):
    findings = _doc_findings(path)
    assert not findings, "history in a doc (it belongs in git):\n" + "\n".join(findings)


def test_comments_and_docstrings_tell_no_history():
    findings = []
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            for line, text in _comments_and_docstrings(path):
                for hit in _history(text, dates=True):
                    findings.append(f"{path.relative_to(ROOT)}:{line}: {hit!r}")
    assert not findings, "history in a comment or docstring (it belongs in git):\n" + "\n".join(findings)


def test_every_file_under_docs_is_cited_and_every_link_resolves():
    docs = _docs()
    text = {p: p.read_text(encoding="utf-8") for p in docs}
    broken = []
    for p, t in text.items():
        for target in LINK.findall(t):
            if re.match(r"^[a-z]+:|^#", target):
                continue
            if not (p.parent / target.split("#")[0]).exists():
                broken.append(f"{p.relative_to(ROOT)}: {target}")
    assert not broken, "links to files that do not exist:\n" + "\n".join(broken)
    everything = "\n".join(text.values())
    uncited = [str(f.relative_to(ROOT)) for f in sorted((ROOT / "docs").rglob("*"))
               if f.is_file() and f.suffix != ".md" and f.name not in everything]
    assert not uncited, "files under docs/ that no doc cites:\n" + "\n".join(uncited)


@pytest.mark.parametrize("text, hits", [
    ("measured in session 7 (issue 13), commit 4051c13, on 2026-11-30", 4),
    ("the pre-session-7 frame_ms; issues 11/12", 2),
    ("a session of 30 s; `session start`; session 5 s; DLPC900 0x1A2A; 1e-6; serial A100", 0),
    ("sha 0123456789abcdef0123456789abcdef01234567", 1),
])
def test_the_rules_catch_history_and_pass_the_present(text, hits):
    assert len(_history(text, dates=True)) == hits


def test_the_lab_example_config_passes_the_offline_check():
    """docs/lab.toml is what docs/lab.md tells an operator to start from: without devices it fails
    only for want of the calibration file the doc says how to make, and passes without it."""
    import json

    from typer.testing import CliRunner

    from dpmhw.cli import _register, app

    _register()
    lab, runner = str(ROOT / "docs" / "lab.toml"), CliRunner()
    r = runner.invoke(app, ["session", "config", "--offline", "-c", lab])
    assert r.exit_code == 2 and "scene.calibration: cannot load" in r.output and "calib_tracker.json" in r.output
    r = runner.invoke(app, ["session", "config", "--offline", "-c", lab, "--set", 'scene.calibration=""'])
    assert r.exit_code == 0, r.output
    data = json.loads(r.stdout)
    assert data["sink"]["display"] == 1 and data["bindings"] == [{"rigid_body": 1, "object": "bunny"}]
    assert data["tracker"]["kind"] == "natnet" and data["projector"]["kind"] == "dlpc900"
