"""Average the weights of a run's checkpoints: ``python -m learner.average CKPT CKPT ... --out FILE``.

A uniform average of several checkpoints taken along one run (stochastic weight averaging done
after the fact; Izmailov et al., UAI 2018). A run with a constant learning rate and no
``learner.ema_decay`` moves between grasp modes from one snapshot to the next (docs/RESULTS.md),
so one snapshot's held-out rate depends on where the run stopped; the average of the snapshots
of a stretch of training does not.

- Every floating-point tensor of the model state is averaged, the batch-norm running
  statistics included (as the learner's moving average does); integer tensors (batch-norm step
  counts) are taken from the last checkpoint.
- The written checkpoint carries the last checkpoint's config, variant, step, weights version
  and replay position (so a learning curve places it where the stretch ends), and
  ``averaged_from``: the file name, step and trials seen of each averaged checkpoint, in the
  order given. It has no optimiser state and no learner state, so a run cannot resume from it;
  ``python -m learner.export RUN NAME --checkpoint FILE`` ships it.
- The checkpoints must build the same network (:data:`common.checkpoint.NETWORK_KEYS`) and hold
  the same tensors; otherwise one line names the file and the key, and nothing is written.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from common.checkpoint import (
    CheckpointError,
    load_checkpoint,
    network_difference,
    read_checkpoint,
    resolve_checkpoint,
    save_checkpoint,
)

KEPT_EXTRA = ("replay", "init_weights")
"""Keys of the last checkpoint's extra state that the average keeps (where the run was, not how to resume it)."""


def average_checkpoints(paths: list[str | Path], out: str | Path, force: bool = False) -> Path:
    """Write the uniform average of the checkpoints ``paths`` (at least two) to ``out``; returns it.
    An existing ``out`` is replaced only with ``force``, and never when it is one of ``paths``."""
    files = [resolve_checkpoint(p).resolve() for p in paths]  # model:NAME and ./a.pt name their files
    if Path(out).resolve() in files:
        raise ValueError(f"--out {out}: is one of the checkpoints averaged; it would be overwritten")
    if Path(out).exists() and not force:
        raise ValueError(f"--out {out}: exists (use --force to replace it)")
    if len(paths) < 2:
        raise ValueError(f"checkpoints: {len(paths)} given, at least two are needed to average")
    if len(set(files)) != len(paths):
        twice = next(str(p) for p, f in zip(paths, files) if files.count(f) > 1)
        raise ValueError(f"checkpoints: {twice}: the file is named twice (it would weigh double)")
    model, first = load_checkpoint(paths[0])  # the network the average is loaded into
    sums = {k: v.double() if v.is_floating_point() else v for k, v in first.model_state.items()}
    origin = [first]
    for path in paths[1:]:
        ckpt = read_checkpoint(path)
        differ = network_difference(first.cfg, ckpt.cfg)
        if differ:
            key, a, b = differ
            raise CheckpointError(f"{path}: config: {key} is {b!r} there but {a!r} in {paths[0]}")
        if set(ckpt.model_state) != set(sums):
            odd = sorted(set(ckpt.model_state) ^ set(sums))[0]
            raise CheckpointError(f"{path}: model: tensor {odd} is not in both it and {paths[0]}")
        for k, v in ckpt.model_state.items():
            if v.shape != sums[k].shape or v.is_floating_point() != sums[k].is_floating_point():
                raise CheckpointError(f"{path}: model: {k} is {tuple(v.shape)} {v.dtype}, "
                                      f"{tuple(sums[k].shape)} in {paths[0]}")
            sums[k] = sums[k] + v.double() if v.is_floating_point() else v
        origin.append(ckpt)
    last = origin[-1]
    dtypes = {k: v.dtype for k, v in last.model_state.items()}
    model.set_weights({k: (v / len(paths)).to(dtypes[k]) if v.is_floating_point() else v for k, v in sums.items()},
                      last.version)
    extra = {k: last.extra[k] for k in KEPT_EXTRA if k in last.extra}
    extra["averaged_from"] = [
        {"file": Path(str(p)).name, "step": c.step, "inserted": (c.extra.get("replay") or {}).get("inserted")}
        for p, c in zip(paths, origin)
    ]
    return save_checkpoint(out, model, last.cfg, step=last.step, version=last.version, epsilon=last.epsilon,
                           optimizer=None, extra=extra)


def cli(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m learner.average", description=__doc__.splitlines()[0])
    ap.add_argument("checkpoints", nargs="+", help="checkpoint files (or model:NAME), oldest first")
    ap.add_argument("--out", required=True, help="checkpoint file to write")
    ap.add_argument("--force", action="store_true", help="replace an existing --out file")
    args = ap.parse_args(argv)
    try:
        out = average_checkpoints(args.checkpoints, args.out, force=args.force)
    except (ValueError, OSError) as e:
        print(f"average: error: {e}", file=sys.stderr)
        return 2
    print(out)
    return 0


if __name__ == "__main__":
    sys.exit(cli())
