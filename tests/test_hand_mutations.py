"""tools/hand-mutations stays runnable: every whole-behaviour removal of the safety code
(docs/testing.md, "Safety mutations, checked by hand") still applies to the code, names test
files that exist, and has its row in docs/testing.md.

An outside fresh-machine audit found 7 of the 72 no longer applying (the code had moved: the
SIGTERM handler, the preflight exit 2, "a breach stops the motors first", ...): the tool said
NOT APPLIED, but only when someone ran it, and nothing in the suite did. Now the suite does
(the edits' texts only: running the mutations takes ~40 min, tools/hand-mutations)."""

from __future__ import annotations

import importlib.util
import re
import sys
from importlib.machinery import SourceFileLoader
from types import ModuleType

import pytest

from tests.conftest import ROOT

TOOL = ROOT / "tools" / "hand-mutations"


def _tool() -> ModuleType:
    loader = SourceFileLoader("hand_mutations", str(TOOL))
    spec = importlib.util.spec_from_loader("hand_mutations", loader)
    assert spec is not None
    module = importlib.util.module_from_spec(spec)
    loader.exec_module(module)
    return module


def test_every_hand_mutation_applies_to_the_code_as_it_is() -> None:
    """Each edit's text occurs exactly once in its file (the working tree's: the code these
    tests test). One that does not: find where the behaviour lives now and update its row in
    tools/hand-mutations, then run it (tools/hand-mutations ID) and see it killed."""
    tool = _tool()
    stale = tool.not_applying(lambda path: (ROOT / path).read_text(encoding="utf-8"))
    assert not stale, "\n".join(
        f"{mid}: {n} matches in {path} of {old!r}" for mid, path, n, old in stale
    )


def test_every_hand_mutation_runs_tests_that_exist() -> None:
    tool = _tool()
    missing = {t for m in tool.MUTATIONS for t in m.tests if not (ROOT / t).is_file()}
    assert not missing
    ids = [m.id for m in tool.MUTATIONS]
    assert len(ids) == len(set(ids))


def test_the_testing_doc_has_a_row_per_hand_mutation() -> None:
    tool = _tool()
    doc = (ROOT / "docs" / "testing.md").read_text(encoding="utf-8")
    rows = re.findall(r"^\| [^|]+ \| [^|]+ \| `([a-z0-9-]+)`:", doc, re.M)
    assert sorted(rows) == sorted(m.id for m in tool.MUTATIONS)
    behaviours = len({m.behaviour for m in tool.MUTATIONS})
    assert f"{len(tool.MUTATIONS)} mutations of {behaviours} behaviours" in " ".join(doc.split())


def test_check_exits_1_naming_a_mutation_that_no_longer_applies(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """--check (against HEAD) fails, naming the mutation, when an edit's text is gone: here
    one text changed in the tool's list (HEAD itself is the first test's business)."""
    tool = _tool()
    moved = [
        m._replace(subs=[(path, old + "  # moved", new) for path, old, new in m.subs])
        if m.id == "con-origin"
        else m
        for m in tool.MUTATIONS
    ]
    monkeypatch.setattr(tool, "MUTATIONS", moved)
    monkeypatch.setattr(sys, "argv", ["tools/hand-mutations", "--check"])
    assert tool.main() == 1
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("con-origin: 0 matches in x6wd/app/console/server.py of ")
    assert out[-1] == f"{len(moved) - 1} of {len(moved)} apply to HEAD"
