"""Command line: ``sparsecomm train | imitate | eval | render | export | reproduce`` (tyro).

Every flag is a documented config field: ``sparsecomm train --help`` lists them all. The work is
done in :mod:`sparsecomm.experiment` and :mod:`sparsecomm.reproduce`; this module only parses.
"""

from __future__ import annotations

import sys
from pathlib import Path

from sparsecomm.configs import PRESETS
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


def _take_preset(argv: list[str]) -> tuple[str | None, list[str]]:
    """Remove ``--preset NAME`` (or ``--preset=NAME``) from ``argv``; returns the name."""
    for i, arg in enumerate(argv):
        if arg == "--preset" and i + 1 < len(argv):
            return argv[i + 1], argv[:i] + argv[i + 2 :]
        if arg.startswith("--preset="):
            return arg.split("=", 1)[1], argv[:i] + argv[i + 1 :]
    return None, argv


def main(argv: list[str] | None = None) -> None:
    import tyro

    from sparsecomm.reproduce import Reproduce, reproduce

    preset, argv = _take_preset(list(sys.argv[1:] if argv is None else argv))
    if preset is not None:  # ``sparsecomm train --preset NAME [--config.* ...]``
        if preset not in PRESETS or not argv or argv[0] != "train":
            raise SystemExit(
                f"--preset must be one of {sorted(PRESETS)} and follow 'sparsecomm train', "
                f"got {preset!r}"
            )
        default = Train(config=PRESETS[preset], out=Path("runs") / preset)
        train(
            tyro.cli(
                Train, default=default, args=argv[1:], prog=f"sparsecomm train --preset {preset}"
            )
        )
        return

    commands = {
        "train": Train,
        "imitate": Imitate,
        "eval": Eval,
        "render": Render,
        "export": Export,
    }
    cmd = tyro.extras.subcommand_cli_from_dict({**commands, "reproduce": Reproduce}, args=argv)
    handler = {
        Train: train,
        Imitate: train,
        Eval: evaluate,
        Render: render,
        Export: export_team,
        Reproduce: reproduce,
    }
    handler[type(cmd)](cmd)


if __name__ == "__main__":
    main()
