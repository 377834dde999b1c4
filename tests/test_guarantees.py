"""docs/guarantees.md names the tests that hold each promise: every test it names exists."""

import re

from service import ROOT

TESTS = ROOT / "tests"


def _citations() -> list[str]:
    """The italic test lists closing each bullet of the Guarantees, one string each."""
    page = (ROOT / "docs" / "guarantees.md").read_text()
    section = page[page.index("# Guarantees") :]
    section = section[: section.index("\n## ", 1)]  # the limits that follow name test files only
    return re.findall(r"\*(test_[^*]+)\*", " ".join(section.split()))


def test_every_test_the_guarantees_name_exists():
    cited = _citations()
    assert len(cited) > 20, "the Guarantees' citations were not found"
    missing = []
    for citation in cited:
        for group in citation.split(";"):
            files = re.findall(r"test_\w+\.py", group)
            assert files, f"no test file in {group!r}"
            for name in files:
                if not (TESTS / name).exists():
                    missing.append(name)
            if ":" in group:  # "test_x.py: test_a, test_b, TestC (...)": names in that one file
                (file,) = files
                source = (TESTS / file).read_text()
                names = re.findall(r"\b(?:test_\w+|Test[A-Z]\w*)\b(?!\.py)", group.split(":", 1)[1])
                for name in names:
                    if not re.search(
                        rf"^\s*(?:(?:async )?def {name}\b|class {name}\b|{name} =)", source, re.M
                    ):
                        missing.append(f"{file}::{name}")
    assert not missing, f"the Guarantees name tests that do not exist: {missing}"


def test_every_mutant_of_the_promise_check_applies_to_the_code_and_names_a_promise():
    """``benchmarks.promises`` breaks each promise by replacing text that must occur once in
    its file: code that moved on would leave a mutant that breaks nothing, and a check that
    cannot fail."""
    from benchmarks.promises import MUTANTS

    page = (ROOT / "docs" / "guarantees.md").read_text()
    promises = re.findall(r"^- \*\*([^*]+)\*\*", page, re.M)
    for mutant in MUTANTS:
        assert (ROOT / mutant.path).read_text().count(mutant.old) == 1, (
            f"{mutant.what}: its text is not in {mutant.path} once"
        )
        assert any(p.startswith(mutant.promise) for p in promises), (
            f"{mutant.promise!r} is no promise of the Guarantees"
        )
