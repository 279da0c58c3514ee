"""The package's words state rules, figures, units, defaults and where they come from (a docs
page, the paper, a test), never the story of how the code was made: no work sessions, issue
numbers or tuning versions in docstrings, comments or help texts (tyro's ``--help`` is built
from the field docstrings, so checking the source checks the help too)."""

import re
from pathlib import Path

import sparsecomm

PACKAGE = Path(sparsecomm.__file__).resolve().parent

MAKING = re.compile(
    "|".join(
        [
            # a work session (the word with its number, or "in another session"); a POSIX
            # process session is fine, and ``start_new_session`` has no word boundary before it
            r"(?<!posix )(?<!process )\bsessions?\b",
            r"\bissues?\s+#?\d",  # the word "issue" or "issues" and a number, "#" or not
            r"\bissue's\b",
            r"\bthe issue\b",
            r"\bcontroller v\d",
            # a tuning version ("v6", "v2's"), not a version string ("jax v0.4.30")
            r"(?<![\w.])v\d+\b(?![.\d])",
            r"\btuning versions?\b",
            r"\btuning rounds?\b",
            r"\brounds?\s+\d+\b(?![.\d])",  # "round 5", not "round 0.5 up"
        ]
    ),
    re.IGNORECASE,
)
"""A line that speaks of how the package was made."""


def speaks_of_making(line: str) -> bool:
    """Whether ``line`` names a work session, an issue, or a tuning version or round."""
    return MAKING.search(line) is not None


def test_package_does_not_speak_of_its_making():
    found = [
        f"{path.relative_to(PACKAGE.parent)}:{number}: {line.strip()}"
        for path in sorted(PACKAGE.rglob("*.py"))
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
        if speaks_of_making(line)
    ]
    assert not found, (
        "state the rule, the figure, the unit, the default and its source (e.g. a docs page), "
        "not the story:\n" + "\n".join(found)
    )


def test_the_check_flags_the_story_and_passes_the_rest():
    for story in [
        # numbers interpolated, so that this file's own text names no session or issue
        f"chosen in session {27} (issue {32})",
        f"(docs/paper-task.md, sessions {22} and 24)",
        "and earlier sessions of a resumed sweep included",
        "a part run in another session, whose run folder is gone",
        f"(issue {17}, docs/channel.md)",
        f"Issue {14}'s target: budget 16",
        f"first written (issues {31}, 34)",
        "ours: 0 (the issue's fault test: 0.01)",
        "(docs/budget.md, controller v6)",
        "    v5).",  # the second line of "(docs/budget.md, controller\n    v5)"
        "the settings of v2's curves",
        "(docs/tuning.md, round 5)",
        "(docs/tuning.md, rounds 1-4)",
    ]:
        assert speaks_of_making(story), story
    for fine in [
        "proc = subprocess.Popen(cmd, start_new_session=True)",
        "each in its own POSIX session, so a Ctrl-C reaches the launcher alone",
        "(docs/paper-task.md, links that fall silent, RL)",
        "the fault test of tests/test_deploy.py: 0.01",
        "requires jax v0.4.30 or later",
        "round 0.5 up to 1",
        "an 11-byte header and an 8-byte HMAC-SHA-256",
        "Hamming(7,4), hamming74, a 2-core VM",
        "the decoder issues no warning",
    ]:
        assert not speaks_of_making(fine), fine
