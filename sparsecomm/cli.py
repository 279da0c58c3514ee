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
import functools
import sys
from pathlib import Path

from sparsecomm.cmdline import check_device_counts, refuse_empty_paths


def _take(flag: str, argv: list[str]) -> tuple[str | None, list[str]]:
    """Remove ``flag NAME`` (or ``flag=NAME``) from ``argv``; returns the name."""
    for i, arg in enumerate(argv):
        if arg == flag and i + 1 < len(argv):
            return argv[i + 1], argv[:i] + argv[i + 2 :]
        if arg.startswith(flag + "="):
            return arg.split("=", 1)[1], argv[:i] + argv[i + 1 :]
    return None, argv


@functools.cache
def commands() -> dict:
    """Every command's arguments class and function, by name. Imported when a command is
    parsed, not with this module: :func:`script` checks the environment before JAX starts."""
    from sparsecomm import learners
    from sparsecomm.codestats import FitCode, fit_code
    from sparsecomm.deploy.args import Deploy
    from sparsecomm.deploy.launcher import deploy
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

    return {
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


def parse(argv: list[str]):
    """The command's arguments, checked: every config's ``__post_init__`` has run."""
    import tyro

    from sparsecomm import learners
    from sparsecomm.configs import PRESETS
    from sparsecomm.envs import registry

    known = commands()
    preset, argv = _take("--preset", argv)
    task, argv = _take("--task", argv)
    command = argv[0] if argv else None
    if command in known:
        refuse_empty_paths(known[command][0], argv[1:])
    if task is not None and command not in learners.COMMANDS:
        raise ValueError(
            "--task must follow 'sparsecomm train' or 'sparsecomm imitate' (the other commands "
            f"read the task from the run folder), got {command!r}"
        )
    if task is not None:  # checked before any work, naming the registered tasks
        task_config = registry.spec(task).config()
    if preset is not None:  # ``sparsecomm train|imitate --preset NAME [--config.* ...]``
        if preset in PRESETS and command in known and command not in PRESETS[preset]:
            serves = " and ".join(f"'sparsecomm {c}'" for c in PRESETS[preset])
            raise ValueError(f"--preset {preset} serves only {serves}, not {command!r}")
        if preset not in PRESETS or command not in PRESETS[preset]:
            raise ValueError(
                f"--preset must be one of {sorted(PRESETS)} and follow 'sparsecomm train' or "
                f"'sparsecomm imitate', got {preset!r}" + (f" after {command!r}" if command else "")
            )
        cls = known[command][0]
        out = Path("runs") / (preset if command == learners.RL.command else f"{command}_{preset}")
        config = PRESETS[preset][command]
        if task is not None:
            config = dataclasses.replace(config, env=task_config)
        default = cls(config=config, out=out)
        prog = f"sparsecomm {command} --preset {preset}" + (f" --task {task}" if task else "")
        return tyro.cli(cls, default=default, args=argv[1:], prog=prog)
    if task is not None:  # ``sparsecomm train|imitate --task NAME [--config.* ...]``
        cls = known[command][0]
        default = cls(config=dataclasses.replace(cls().config, env=task_config))
        prog = f"sparsecomm {command} --task {task}"
        return tyro.cli(cls, default=default, args=argv[1:], prog=prog)
    if command in known:  # errors then name the command's fields, not tyro's inner ones
        return tyro.cli(known[command][0], args=argv[1:], prog=f"sparsecomm {command}")
    classes = {name: cls for name, (cls, _) in known.items()}
    return tyro.extras.subcommand_cli_from_dict(classes, args=argv, prog="sparsecomm")


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
    from sparsecomm.errors import RunError

    handler = {cls: run for cls, run in commands().values()}[type(cmd)]
    try:
        handler(cmd)
    except RunError as e:
        raise _fail(e, e.exit_code) from None


def script() -> None:
    """The ``sparsecomm`` command (and ``python -m sparsecomm.cli``): one CPU device per usable
    core unless the user chose a count (:func:`sparsecomm.sharding.use_host_cores`), then
    :func:`main`. In-process callers of :func:`main` keep JAX's devices as they are."""
    try:  # before JAX reads them: its own errors would be tracebacks, XLA's a fatal error
        check_device_counts()
    except ValueError as e:
        raise _fail(e, 2) from None
    from sparsecomm.sharding import use_host_cores

    use_host_cores()
    main()


if __name__ == "__main__":
    script()
