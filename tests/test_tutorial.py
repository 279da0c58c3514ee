"""The tutorial (docs/tutorial.md) runs: its ```bash and ```python blocks, in order.

The default suite runs every block in a fresh folder, the training commands with a few updates
(``SMALL`` appended: a later flag wins) and the deployments parsed, not started; the slow set
runs the page exactly as written, as a user would, and checks what the page says the team does.
"""

import contextlib
import os
import re
import runpy
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from sparsecomm.cli import main, parse
from sparsecomm.jsonfile import read_json

REPO = Path(__file__).resolve().parent.parent
DOC = REPO / "docs" / "tutorial.md"
SMALL = {
    "train": ["--config.num-updates", "2", "--chunk", "1", "--config.num-envs", "8"],
    "eval": ["--episodes", "8"],
}
"""What the default suite appends to a command of the page, by command."""
SMALL["train"] += ["--eval-episodes", "8", "--no-gif", "--no-progress", "--no-tensorboard"]
SCRIPT_SMALL = ["--episodes", "4"]
"""What the default suite appends to a ``python scripts/...`` command of the page."""


def blocks() -> list[tuple[str, str]]:
    """The page's ```bash and ```python blocks, in order: ``(language, code)``."""
    found = re.findall(r"^```(bash|python)\n(.*?)^```", DOC.read_text(), flags=re.M | re.S)
    assert found, "docs/tutorial.md has no bash or python block"
    return found


def commands(code: str) -> list[list[str]]:
    """The commands of a bash block: lines joined at a trailing backslash, comments dropped."""
    lines = code.replace("\\\n", " ").splitlines()
    return [shlex.split(line, comments=True) for line in lines if shlex.split(line, comments=True)]


@contextlib.contextmanager
def _argv(argv: list[str]):
    previous = sys.argv
    sys.argv = argv
    try:
        yield
    finally:
        sys.argv = previous


def _run_small(argv: list[str]) -> None:
    """One command of the page, in this process, small: a training command with ``SMALL``, a
    deployment parsed only (its processes take a minute to start), a script with a few
    episodes."""
    if argv[0] == "sparsecomm":
        command = argv[1]
        if command == "deploy":
            parse(argv[1:])
        else:
            main(argv[1:] + SMALL.get(command, []))
    elif argv[0] == "python" and argv[1].startswith("scripts/"):
        with _argv([argv[1], *argv[2:], *SCRIPT_SMALL]):
            runpy.run_path(str(REPO / argv[1]), run_name="__main__")
    else:
        raise AssertionError(f"the tutorial runs a command the test does not know: {argv}")


def test_the_tutorial_names_what_it_runs():
    found = blocks()
    languages = [language for language, _ in found]
    assert "bash" in languages and "python" in languages
    run = [argv[:2] for language, code in found if language == "bash" for argv in commands(code)]
    assert ["sparsecomm", "train"] in run and ["sparsecomm", "deploy"] in run


def test_the_tutorial_runs_small(tmp_path, monkeypatch, fast_compile):
    monkeypatch.chdir(tmp_path)
    for language, code in blocks():
        if language == "bash":
            for argv in commands(code):
                _run_small(argv)
        else:
            exec(compile(code, str(DOC), "exec"), {"__name__": "tutorial"})
    assert (tmp_path / "runs" / "tutorial" / "curves.png").stat().st_size > 0


@pytest.mark.slow  # the page as written: two teams trained in full and two deployments
def test_the_tutorial_runs_as_written(tmp_path):
    (tmp_path / "scripts").symlink_to(REPO / "scripts")
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env['PATH']}"
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), *filter(None, [env.get("PYTHONPATH")])])
    for language, code in blocks():
        if language == "bash":
            run = ["bash", "-euo", "pipefail", "-c", code]
        else:
            run = [sys.executable, "-c", code]
        done = subprocess.run(run, cwd=tmp_path, env=env, capture_output=True, text=True)
        assert done.returncode == 0, code + done.stdout + done.stderr
    team = read_json(tmp_path / "runs" / "tutorial" / "results.json")["runs"][0]
    assert team["episode/success_rate"] > 0.95
    assert team["channel/speaking_fraction"] < 0.3
    budgets = read_json(tmp_path / "runs" / "budgets" / "results.json")["runs"]
    unlimited, sixteen = sorted(budgets, key=lambda r: -r["channel/wire_bits_per_step"])
    # without a budget most link-steps speak (87% measured); a budget of 16 cuts the wire 8x
    assert unlimited["channel/speaking_fraction"] > 0.5
    assert sixteen["channel/wire_bits_per_step"] < 0.2 * unlimited["channel/wire_bits_per_step"]
    assert sixteen["episode/success_rate"] > 0.9
    (deployed,) = read_json(tmp_path / "runs" / "tutorial" / "deploy" / "deploy.json")["runs"]
    assert deployed["simulation"]["identical_episodes"] == deployed["episodes"]
