"""Learning curve of a run as a PNG: ``python -m learner.curve RUN --out curve.png [--greedy A.json ...] [--held-out R.json ...]``.

Panels, all against trials collected:

- training success: the rolling success rate of the last 200 trials the actors ran (their
  epsilon-greedy policy, so it mixes exploration and the learned policy) with epsilon;
- loss: the learner's mean training loss per chunk of steps;
- greedy success (with ``--greedy``): rollout summaries written by ``python -m launcher rollout
  --policy checkpoint:RUN/checkpoints/step-NNNNNNN.pt --json A.json``; each point sits at the
  trials the checkpoint had seen (its ``replay.inserted``), with a 95% Wilson interval;
- held-out rate (with ``--held-out``): results written by ``python -m launcher evaluate
  --checkpoint CKPT --json A.json`` for the run's checkpoints (or for models exported from it),
  one line per table row and cell (policy, scene, objects x grippers, scene seed), each point at
  the trials its checkpoint had seen, with the 95% interval over scene resamples of
  ``evaluate compare``. A checkpoint path that does not exist from here (the evaluation ran in
  another directory) is looked up by its file name in RUN/checkpoints.

Reads RUN/progress.jsonl (one line every few seconds) and the checkpoints the summaries name.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

PROGRESS_KEYS = ("trials", "success_rate", "epsilon", "loss")
"""Keys of a RUN/progress.jsonl record the curve plots."""


def wilson(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95% Wilson score interval of a success rate."""
    if n == 0:
        return 0.0, 1.0
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return centre - half, centre + half


def read_progress(run: Path) -> list[dict]:
    """The lines of RUN/progress.jsonl, in order."""
    path = run / "progress.jsonl"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: not found (is {run} a run directory?)")
    lines = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            record = json.loads(line)
        except ValueError as e:  # a killed run can leave a torn last line
            raise ValueError(f"{path}: line {n}: not valid JSON ({e.msg})") from None
        missing = [k for k in PROGRESS_KEYS if not isinstance(record, dict) or k not in record]
        if missing:
            raise ValueError(f"{path}: line {n}: {missing[0]}: missing (not a progress record)")
        # a value not yet known (the loss before the first step) is null, or NaN in older files
        lines.append({**record, **{k: math.nan for k in PROGRESS_KEYS if record[k] is None}})
    return lines


def read_greedy(paths: list[str], run: Path | None = None) -> list[dict]:
    """Rollout summaries of checkpoint policies with the trials and steps their checkpoints had
    seen (a checkpoint path missing from here is looked up in RUN/checkpoints when ``run`` is given)."""
    points = []
    for p in paths:
        try:
            summary = json.loads(Path(p).read_text())
        except ValueError as e:
            raise ValueError(f"{p}: not valid JSON ({' '.join(str(e).split())})") from None
        if not isinstance(summary, dict) or "checkpoint" not in summary:
            raise ValueError(f"{p}: checkpoint: missing (not a rollout of a checkpoint policy)")
        for key, kind in (("success_rate", (int, float)), ("successes", int), ("trials", int), ("mode", str)):
            if isinstance(summary.get(key), bool) or not isinstance(summary.get(key), kind):
                raise ValueError(f"{p}: {key}: missing or not a {'number' if key == 'success_rate' else kind.__name__} "
                                 "(a rollout --json summary of a checkpoint policy)")
        inserted, step = _trials_seen(str(summary["checkpoint"]), run, p)
        points.append({**summary, "inserted": inserted, "step": step})
    return sorted(points, key=lambda d: d["inserted"])


def _trials_seen(checkpoint: str, run: Path | None, where: str) -> tuple[int, int]:
    """(replay.inserted, step) of ``checkpoint`` (a path or ``model:NAME``); a path missing from
    here is taken from RUN/checkpoints by its file name (``run`` given)."""
    from common.checkpoint import SHIPPED_PREFIX, read_checkpoint

    if run is not None and not checkpoint.startswith(SHIPPED_PREFIX) and not Path(checkpoint).is_file():
        local = run / "checkpoints" / Path(checkpoint).name
        if not local.is_file():
            raise ValueError(f"{where}: checkpoint: {checkpoint} not found, nor {local}")
        checkpoint = str(local)
    ckpt = read_checkpoint(checkpoint)
    inserted = (ckpt.extra.get("replay") or {}).get("inserted")
    if inserted is None:
        raise ValueError(f"{checkpoint}: replay.inserted: missing (not a learner checkpoint)")
    return int(inserted), ckpt.step


def read_held_out(paths: list[str], run: Path) -> dict[str, list[dict]]:
    """Evaluation results of the run's checkpoints, as lines of points: label -> points sorted by
    the trials their checkpoints had seen; each point has ``inserted``, ``step``, ``rate``,
    ``low`` and ``high`` (the 95% interval over scene resamples) and ``path``."""
    from actors.compare import rate_interval
    from actors.evaluate import read_result, row_label

    lines: dict[str, list[dict]] = {}
    for p in paths:
        result = read_result(p)
        if not result.get("checkpoint"):
            raise ValueError(f"{p}: checkpoint: missing (not an evaluation of a learned policy)")
        inserted, step = _trials_seen(str(result["checkpoint"]), run, p)
        rate, low, high = rate_interval(p, result)
        label = (f"{row_label(result)}, {result['scene']} {result['objects_label']}/{result['grippers_label']}, "
                 f"seed {result['seed']}")
        lines.setdefault(label, []).append(
            {"inserted": inserted, "step": step, "rate": rate, "low": low, "high": high, "path": p})
    for points in lines.values():
        points.sort(key=lambda d: d["inserted"])
    return lines


def plot(run: Path, out: Path, greedy: list[dict], title: str | None = None,
         held_out: dict[str, list[dict]] | None = None) -> Path:
    """Draw the panels to ``out`` (PNG); returns the path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lines = read_progress(run)
    trials = [d["trials"] for d in lines]
    panels = 2 + bool(greedy) + bool(held_out)
    fig, axes = plt.subplots(1, panels, figsize=(4.4 * panels, 3.6), dpi=100)
    ax = axes[0]
    ax.plot(trials, [d["success_rate"] for d in lines], color="tab:blue", label="training success (last 200)")
    ax.plot(trials, [d["epsilon"] for d in lines], color="tab:gray", ls="--", label="epsilon")
    ax.set_xlabel("trials collected")
    ax.set_ylim(0, 1)
    ax.legend(fontsize=8, loc="lower right")
    ax = axes[1]
    ax.plot(trials, [d["loss"] for d in lines], color="tab:red")
    ax.set_xlabel("trials collected")
    ax.set_ylabel("training loss")
    if greedy:
        ax = axes[2]
        xs = [g["inserted"] for g in greedy]
        rates = [g["success_rate"] for g in greedy]
        lo_hi = [wilson(g["successes"], g["trials"]) for g in greedy]
        ax.errorbar(xs, rates, yerr=[[r - lo for r, (lo, _) in zip(rates, lo_hi)], [hi - r for r, (_, hi) in zip(rates, lo_hi)]],
                    marker="o", color="tab:green", capsize=3)
        for g in greedy:
            ax.annotate(f"{g['success_rate']:.2f} (n={g['trials']})", (g["inserted"], g["success_rate"]),
                        textcoords="offset points", xytext=(4, 6), fontsize=7)
        ax.set_xlabel("trials collected")
        ax.set_ylabel(f"greedy success ({greedy[-1]['mode']}), 95% CI")
        ax.set_ylim(0, 1)
    if held_out:
        ax = axes[-1]
        for label, points in held_out.items():
            xs = [d["inserted"] for d in points]
            rates = [d["rate"] for d in points]
            ax.errorbar(xs, rates, yerr=[[r - d["low"] for r, d in zip(rates, points)],
                                         [d["high"] - r for r, d in zip(rates, points)]],
                        marker="o", capsize=3, label=label)
            for x, r in zip(xs, rates):
                ax.annotate(f"{r:.2f}", (x, r), textcoords="offset points", xytext=(4, 6), fontsize=7)
        ax.set_xlabel("trials collected")
        ax.set_ylabel("held-out rate, 95% CI over scenes")
        ax.set_xlim(axes[0].get_xlim())
        ax.set_ylim(0, 1)
        ax.legend(fontsize=7, loc="lower right")
    fig.suptitle(title or f"{run}", fontsize=9)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m learner.curve", description=__doc__.splitlines()[0])
    ap.add_argument("run", help="run directory")
    ap.add_argument("--out", required=True, help="PNG to write")
    ap.add_argument("--greedy", nargs="*", default=[], help="rollout --json summaries of the run's checkpoints")
    ap.add_argument("--held-out", nargs="*", default=[],
                    help="evaluate --json results of the run's checkpoints or of models exported from it")
    ap.add_argument("--title", default=None)
    args = ap.parse_args(argv)
    run = Path(args.run)
    try:
        path = plot(run, Path(args.out), read_greedy(args.greedy, run), args.title, read_held_out(args.held_out, run))
    except (OSError, ValueError, KeyError) as e:
        print(f"curve: error: {e}", file=sys.stderr)
        return 2
    print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
