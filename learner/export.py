"""Ship a run's checkpoint as a named model: ``python -m learner.export RUN NAME [--checkpoint FILE]``.

Writes ``DEST/NAME/`` (``--dest``, default the package's ``assets/models``):

- ``checkpoint.pt``: the weights, variant, resolved config, step, weights version, epsilon and the
  learner's own keys (replay position), without what only resuming needs: the optimiser state
  (twice the weights) and, for a run with ``learner.ema_decay`` > 0, the trained weights behind
  the shipped average (``--trained-weights`` ships those instead of the average, recorded as
  ``exported_weights: trained``, to compare the two);
- ``config.yaml``: the resolved config;
- ``progress.jsonl``, ``summary.json``, ``history.json``: the run's training log, copied when
  present.

The model then loads by name everywhere a checkpoint path is taken: ``model:NAME``
(``GraspPlanner.from_checkpoint("model:NAME")``, ``evaluate --checkpoint model:NAME``,
``rollout --policy checkpoint:model:NAME``). An existing folder is only replaced with ``--force``.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

from common.checkpoint import (
    CheckpointError,
    load_checkpoint,
    portable_init_source,
    save_checkpoint,
    shipped_models_dir,
)
from common.config import save_config

RUN_LOGS = ("progress.jsonl", "summary.json", "history.json")
"""Files of a run directory copied next to an exported checkpoint."""


def export_model(run: str | Path, name: str, checkpoint: str | Path | None = None,
                 dest: str | Path | None = None, force: bool = False, trained_weights: bool = False) -> Path:
    """Export ``checkpoint`` (default RUN/checkpoints/latest.pt) as DEST/NAME; returns the folder.
    ``trained_weights``: ship the trained weights a weight-averaging run keeps beside its average
    (CheckpointError when the file has none)."""
    run = Path(run)
    if not name or "/" in name or name.startswith("."):
        raise ValueError(f"name: {name!r} is not a folder name")
    source = Path(checkpoint) if checkpoint else run / "checkpoints" / "latest.pt"
    out = Path(dest) if dest else shipped_models_dir()
    out = out / name
    if out.exists() and not force:
        raise ValueError(f"{out}: exists (use --force to replace it)")
    if out.exists() and (out.resolve() == run.resolve() or out.resolve() in run.resolve().parents):
        raise ValueError(f"{out}: is the run directory or holds it; --force would delete the run it exports")
    model, ckpt = load_checkpoint(source)
    learner_state = ckpt.extra.get("learner")
    if trained_weights:
        trained = learner_state.get("trained_model") if isinstance(learner_state, dict) else None
        if trained is None:
            raise CheckpointError(f"{source}: learner.trained_model: not present (the run kept no weight "
                                  "average, so its model is the trained weights)")
        model.load_state_dict(trained)
    tmp = out.with_name(out.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    extra = dict(ckpt.extra)
    if isinstance(extra.get("learner"), dict):
        extra["learner"] = {k: v for k, v in extra["learner"].items() if k != "trained_model"}
    if "init_weights" in extra:
        extra["init_weights"] = portable_init_source(extra["init_weights"])
    if trained_weights:
        extra["exported_weights"] = "trained"
    save_checkpoint(tmp / "checkpoint.pt", model, ckpt.cfg, step=ckpt.step, version=ckpt.version,
                    epsilon=ckpt.epsilon, optimizer=None, extra=extra)
    save_config(ckpt.cfg, tmp / "config.yaml")
    for log in RUN_LOGS:
        if (run / log).is_file():
            shutil.copy2(run / log, tmp / log)
    if out.exists():
        shutil.rmtree(out)
    tmp.rename(out)
    return out


def cli(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m learner.export", description=__doc__.splitlines()[0])
    ap.add_argument("run", help="run directory")
    ap.add_argument("name", help="model name (folder name; loads as model:NAME)")
    ap.add_argument("--checkpoint", default=None, help="checkpoint file (default RUN/checkpoints/latest.pt)")
    ap.add_argument("--dest", default=None, help="parent folder (default: the package's assets/models)")
    ap.add_argument("--force", action="store_true", help="replace an existing folder of that name")
    ap.add_argument("--trained-weights", action="store_true",
                    help="ship the trained weights behind a learner.ema_decay run's average, not the average")
    args = ap.parse_args(argv)
    try:
        out = export_model(args.run, args.name, args.checkpoint, args.dest, args.force, args.trained_weights)
    except (ValueError, CheckpointError, OSError) as e:
        print(f"export: error: {e}", file=sys.stderr)
        return 2
    print(out)
    return 0


if __name__ == "__main__":
    sys.exit(cli())
