"""Command-line entry point: ``python -m launcher [SUBCOMMAND] ...``.

With no subcommand it trains (``python -m launcher --actors 2``). The launcher only chooses
where the parts run; each subcommand's body lives with its part and takes ``argv``:

- ``train`` (default) -> learner.run.cli
- ``rollout``         -> actors.rollout.cli
- ``grippers``        -> actors.gripper_cli.cli
- ``evaluate``        -> actors.evaluate.cli
"""

from __future__ import annotations

import importlib
import sys

from common.runtime import apply_process_env

SUBCOMMANDS = {
    "train": "learner.run",
    "rollout": "actors.rollout",
    "grippers": "actors.gripper_cli",
    "evaluate": "actors.evaluate",
}


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] in ("-h", "--help") and len(argv) == 1:
        print(__doc__)
        return 0
    if argv and not argv[0].startswith("-") and argv[0] not in SUBCOMMANDS:
        print(f"launcher: error: {argv[0]!r}: not a command (one of {', '.join(SUBCOMMANDS)}; none = train)",
              file=sys.stderr)
        return 2
    name = argv[0] if argv and argv[0] in SUBCOMMANDS else "train"
    rest = argv[1:] if argv and argv[0] in SUBCOMMANDS else argv
    apply_process_env()
    module = importlib.import_module(SUBCOMMANDS[name])
    return int(module.cli(rest) or 0)


if __name__ == "__main__":
    sys.exit(main())
