"""Command line: ``sparsecomm train | imitate | eval | render | export | fit-code | reproduce |
paper-task | deploy`` (tyro).

Every flag is a documented config field: ``sparsecomm train --help`` lists them all. Two flags
of ``train`` and ``imitate`` choose the defaults the others start from: ``--preset NAME``
(``configs.PRESETS``) and ``--task NAME``, a registered task (``sparsecomm.envs.registry``)
whose config's defaults replace ``--config.env``'s (``--task NAME --help`` lists its fields).
``eval``, ``render``, ``export`` and ``deploy`` read the task from the run folder. The work is
done in :mod:`sparsecomm.experiment`, :mod:`sparsecomm.codestats`, :mod:`sparsecomm.deploy` and
the paper's pipelines (:mod:`sparsecomm.pipelines`: ``reproduce``, ``paper-task``); this module
only parses.
"""

from __future__ import annotations

import dataclasses
import sys
import typing
from pathlib import Path

from sparsecomm import learners
from sparsecomm.codestats import FitCode, fit_code
from sparsecomm.configs import PRESETS
from sparsecomm.deploy.args import Deploy
from sparsecomm.deploy.launcher import deploy
from sparsecomm.envs import registry
from sparsecomm.errors import RunError
from sparsecomm.experiment import (
    Eval,
    Export,
    Imitate,
    Render,
    Train,
    evaluate,
    export_team,
    render,
    train,
)
from sparsecomm.pipelines.paper_task import PaperTask, paper_task
from sparsecomm.pipelines.reproduce import Reproduce, reproduce
from sparsecomm.sharding import use_host_cores


def _take(flag: str, argv: list[str]) -> tuple[str | None, list[str]]:
    """Remove ``flag NAME`` (or ``flag=NAME``) from ``argv``; returns the name."""
    for i, arg in enumerate(argv):
        if arg == flag and i + 1 < len(argv):
            return argv[i + 1], argv[:i] + argv[i + 2 :]
        if arg.startswith(flag + "="):
            return arg.split("=", 1)[1], argv[:i] + argv[i + 1 :]
    return None, argv


COMMANDS = {
    learners.RL.command: (Train, train),
    learners.IMITATION.command: (Imitate, train),
    "eval": (Eval, evaluate),
    "render": (Render, render),
    "export": (Export, export_team),
    "fit-code": (FitCode, fit_code),
    "reproduce": (Reproduce, reproduce),
    "paper-task": (PaperTask, paper_task),
    "deploy": (Deploy, deploy),
}


def _refuse_empty_paths(argv: list[str]) -> None:
    """Refuse an empty value for a path flag of the command (``--out ''``, ``--run=``): the
    parser would read it as the current folder (``Path('')`` is ``.``)."""
    if not argv or argv[0] not in COMMANDS:
        return
    cls = COMMANDS[argv[0]][0]
    hints = typing.get_type_hints(cls)
    paths = {
        "--" + f.name.replace("_", "-"): f.name
        for f in dataclasses.fields(cls)
        if Path in (hints[f.name], *typing.get_args(hints[f.name]))
    }
    for i, arg in enumerate(argv[1:], 1):
        flag, eq, value = arg.partition("=")
        empty = value == "" if eq else i + 1 < len(argv) and argv[i + 1] == ""
        if flag in paths and empty:
            raise ValueError(f"{cls.__name__}.{paths[flag]} must be a path, got ''")


def parse(argv: list[str]):
    """The command's arguments, checked: every config's ``__post_init__`` has run."""
    import tyro

    preset, argv = _take("--preset", argv)
    task, argv = _take("--task", argv)
    _refuse_empty_paths(argv)
    command = argv[0] if argv else None
    if task is not None and command not in learners.COMMANDS:
        raise ValueError(
            "--task must follow 'sparsecomm train' or 'sparsecomm imitate' (the other commands "
            f"read the task from the run folder), got {command!r}"
        )
    if task is not None:  # checked before any work, naming the registered tasks
        task_config = registry.spec(task).config()
    if preset is not None:  # ``sparsecomm train|imitate --preset NAME [--config.* ...]``
        if preset in PRESETS and command in COMMANDS and command not in PRESETS[preset]:
            serves = " and ".join(f"'sparsecomm {c}'" for c in PRESETS[preset])
            raise ValueError(f"--preset {preset} serves only {serves}, not {command!r}")
        if preset not in PRESETS or command not in PRESETS[preset]:
            raise ValueError(
                f"--preset must be one of {sorted(PRESETS)} and follow 'sparsecomm train' or "
                f"'sparsecomm imitate', got {preset!r}" + (f" after {command!r}" if command else "")
            )
        cls = COMMANDS[command][0]
        out = Path("runs") / (preset if command == learners.RL.command else f"{command}_{preset}")
        config = PRESETS[preset][command]
        if task is not None:
            config = dataclasses.replace(config, env=task_config)
        default = cls(config=config, out=out)
        prog = f"sparsecomm {command} --preset {preset}" + (f" --task {task}" if task else "")
        return tyro.cli(cls, default=default, args=argv[1:], prog=prog)
    if task is not None:  # ``sparsecomm train|imitate --task NAME [--config.* ...]``
        cls = COMMANDS[command][0]
        default = cls(config=dataclasses.replace(cls().config, env=task_config))
        prog = f"sparsecomm {command} --task {task}"
        return tyro.cli(cls, default=default, args=argv[1:], prog=prog)
    commands = {name: cls for name, (cls, _) in COMMANDS.items()}
    return tyro.extras.subcommand_cli_from_dict(commands, args=argv)


def _fail(error: BaseException, code: int) -> SystemExit:
    print(f"sparsecomm: error: {error}", file=sys.stderr)
    return SystemExit(code)


def main(argv: list[str] | None = None) -> None:
    """Parse, check, run. A user error (a bad value, a refused checkpoint or resume, a program
    too large for the devices) prints one line and exits 2; a diverged run exits 3; anything
    else is a bug and keeps its traceback."""
    try:
        cmd = parse(list(sys.argv[1:] if argv is None else argv))
    except ValueError as e:  # raised by the configs' checks while parsing, before any work
        raise _fail(e, 2) from None
    handler = {cls: run for cls, run in COMMANDS.values()}[type(cmd)]
    try:
        handler(cmd)
    except RunError as e:
        raise _fail(e, e.exit_code) from None


def script() -> None:
    """The ``sparsecomm`` command (and ``python -m sparsecomm.cli``): one CPU device per usable
    core unless the user chose a count (:func:`sparsecomm.sharding.use_host_cores`), then
    :func:`main`. In-process callers of :func:`main` keep JAX's devices as they are."""
    use_host_cores()
    main()


if __name__ == "__main__":
    script()
