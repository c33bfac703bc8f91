"""``python -m replay``: look into a replay without writing to it.

PATH is a replay root (the folder holding shard_000, shard_001, ...) or one shard group.
Trials are numbered by position among PATH's visible trials in commit order: 0 is the oldest,
-1 the newest (``inspect`` prints the range).

Usage::

    python -m replay inspect runs/x/replay [--json summary.json]
    python -m replay show runs/x/replay --trial 17 --out trial17.png
    python -m replay export runs/x/replay --trials 0:100 --out first100.npz

Every error is one line on stderr (exit code 2); the replay is opened read-only, so a live
writer may keep appending meanwhile.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import warnings
from collections import defaultdict
from pathlib import Path

import numpy as np

from common.files import finite_json
from replay.schema import ReplayError, ReplayInputError
from replay.shard import ReplayShard, StoredTrial, disk_usage, find_shards

RATE_BINS = 12
"""Bins of the insert-rate histogram over the replay's time span."""


def open_readers(path: str | Path) -> list[ReplayShard]:
    """Read-only shards under PATH (a root or one shard)."""
    paths = find_shards(path)
    if not paths:
        raise ReplayError(f"{path}: no shard groups found under this replay root")
    return [ReplayShard(p, read_only=True) for p in paths]


def trial_table(readers: list[ReplayShard]) -> dict[str, np.ndarray]:
    """Every visible readable trial of ``readers`` in commit order: shard (n,), trial_id (n,),
    seeded (n,) bool (copied in by replay.seed_from), insert_time (n,) s, label (n,) bool,
    score (n,), meta (n,) JSON text."""
    shard, ids = [], []
    for k, r in enumerate(readers):
        v = r.visible_ids()
        shard.append(np.full(len(v), k, np.int64))
        ids.append(v)
    shard_a = np.concatenate(shard)
    ids_a = np.concatenate(ids)
    cols = {name: [] for name in ("insert_time", "label", "score", "meta")}
    for k, r in enumerate(readers):
        m = shard_a == k
        for name in cols:
            cols[name].append(r.column(name, ids_a[m]))
    seeded = np.array([r.seeded_trials for r in readers], np.int64)
    out = {"shard": shard_a, "trial_id": ids_a, "seeded": ids_a < seeded[shard_a]}
    out.update({name: np.concatenate(v) for name, v in cols.items()})
    out["label"] = out["label"] == 1
    order = np.lexsort((out["trial_id"], out["shard"], out["insert_time"]))
    return {k: v[order] for k, v in out.items()}


def _natural(value) -> tuple:
    """Sort key: numbers inside a name compare as numbers (version 2 before 10); seeded last."""
    text = str(value)
    return text.endswith("(seeded)"), [int(p) if p.isdigit() else p for p in re.split(r"(\d+)", text)]


def _rates(groups: dict[str, list[bool]]) -> dict[str, dict]:
    return {
        str(k): {"trials": len(v), "success_rate": float(np.mean(v)) if v else None}
        for k, v in sorted(groups.items(), key=lambda kv: _natural(kv[0]))
    }


def summarize(path: str | Path) -> dict:
    """Everything ``inspect`` reports, as a JSON-ready dict. Every visible trial's chunks are read
    first, so unreadable ones are counted and listed, not summarised."""
    readers = open_readers(path)
    for r in readers:
        r.verify()
    table = trial_table(readers)
    metas = [json.loads(str(m)) for m in table["meta"]]
    labels = table["label"].tolist()
    by = {key: defaultdict(list) for key in ("gripper", "scene", "object_set", "policy_version")}
    for meta, lab, seeded in zip(metas, labels, table["seeded"]):
        for key in by:
            value = meta[key]
            if seeded and key == "policy_version":  # another run's versions; this run's count from 0 again
                value = f"{value} (seeded)"
            by[key][value].append(lab)
    times = table["insert_time"][~table["seeded"]]  # the copies all arrive at once: not an insert rate
    rate: dict = {"bins": [], "span_s": 0.0}
    if len(times) >= 2 and times[-1] > times[0]:
        span = float(times[-1] - times[0])
        counts, edges = np.histogram(times, bins=RATE_BINS)
        width = float(edges[1] - edges[0])
        rate = {
            "span_s": span,
            "mean_per_min": 60.0 * (len(times) - 1) / span,
            "bins": [
                {"start_s": float(edges[i] - edges[0]), "end_s": float(edges[i + 1] - edges[0]),
                 "trials": int(counts[i]), "per_min": 60.0 * counts[i] / width}
                for i in range(len(counts))
            ],
        }
    shards = []
    total_bytes = total_alloc = 0
    for r in readers:
        st = r.stats()
        apparent, allocated = disk_usage(r.path)
        total_bytes += apparent
        total_alloc += allocated
        shards.append({
            "path": str(r.path),
            "capacity": st["capacity"],
            "visible": st["visible"],
            "first": st["first"],
            "end": st["end"],
            "seeded": st["seeded"],
            "lost": st["lost"],
            "corrupt": st["corrupt"],
            "gripper_table_rows_used": st["table_rows_used"],
            "bytes_on_disk": apparent,
            "problems": st["problems"],
        })
    n = len(labels)
    info = readers[0].info()
    return {
        "path": str(path),
        "schema_version": info["schema_version"],
        "scene_shape": info["scene_shape"],
        "gripper_shape": info["gripper_shape"],
        "tsdf_levels": info["tsdf_levels"],
        "max_abs_error": info["max_abs_error"],
        "shards": shards,
        "capacity": int(sum(s["capacity"] for s in shards)),
        "trials": n,
        "trial_range": [0, n - 1] if n else None,
        "seeded_trials": int(table["seeded"].sum()),
        "success_rate": float(np.mean(labels)) if n else None,
        "by_gripper": _rates(by["gripper"]),
        "by_scene": _rates(by["scene"]),
        "by_object_set": _rates(by["object_set"]),
        "by_policy_version": _rates(by["policy_version"]),
        "insert_rate": rate,
        "bytes_on_disk": total_bytes,
        "bytes_allocated": total_alloc,
        "bytes_per_trial": total_bytes / n if n else None,
    }


def format_summary(s: dict) -> str:
    """Human-readable text of :func:`summarize`."""

    def pct(v):
        return "-" if v is None else f"{100 * v:.1f}%"

    lines = [
        f"replay {s['path']}  (schema version {s['schema_version']}, {len(s['shards'])} shard(s))",
        f"trials            {s['trials']} of capacity {s['capacity']}"
        + (f"  (numbered 0..{s['trial_range'][1]}, oldest first)" if s["trials"] else ""),
        f"success rate      {pct(s['success_rate'])}",
    ]
    if s["seeded_trials"]:
        lines.append(f"seeded            {s['seeded_trials']} of them copied from another replay before the run "
                     f"(replay.seed_from); left out of the insert rate")
    lines += [
        f"scene grid        {s['scene_shape']}, gripper grid {s['gripper_shape']}, TSDF levels {s['tsdf_levels']}",
        f"bytes on disk     {s['bytes_on_disk']:,}"
        + (f"  ({s['bytes_per_trial'] / 1024:.1f} KiB per trial)" if s["bytes_per_trial"] else ""),
    ]
    for title, key in (("gripper", "by_gripper"), ("scene kind", "by_scene"), ("object set", "by_object_set"),
                       ("policy version", "by_policy_version")):
        lines.append(f"by {title}:")
        for name, v in s[key].items():
            lines.append(f"  {name:<28} {v['trials']:>7} trials  success {pct(v['success_rate'])}")
    rate = s["insert_rate"]
    if rate["bins"]:
        lines.append(f"insert rate       {rate['mean_per_min']:.1f} trials/min over {rate['span_s']:.0f} s")
        for b in rate["bins"]:
            lines.append(
                f"  {b['start_s']:>10.1f} - {b['end_s']:<10.1f} s {b['trials']:>7} trials {b['per_min']:9.1f}/min"
            )
    for sh in s["shards"]:
        lines.append(
            f"shard {sh['path']}: {sh['visible']} visible (trials {sh['first']}..{sh['end'] - 1}), "
            f"{sh['lost'] + sh['corrupt']} unreadable, {sh['bytes_on_disk']:,} bytes"
            + (f", seeded with trials 0..{sh['seeded'] - 1} (replay.seed_from)" if sh["seeded"] else "")
        )
        lines.extend(f"  problem: {p}" for p in sh["problems"])
    return "\n".join(lines)


def _select(table: dict[str, np.ndarray], positions: np.ndarray) -> list[tuple[int, int]]:
    return [(int(table["shard"][p]), int(table["trial_id"][p])) for p in positions]


def resolve_trial(path: str | Path, n: int) -> tuple[ReplayShard, StoredTrial, int]:
    """The shard, the decoded trial and the position (>= 0) of trial ``n`` (negative: from the newest)."""
    readers = open_readers(path)
    table = trial_table(readers)
    count = len(table["trial_id"])
    if not -count <= n < count:
        raise ReplayError(f"{path}: --trial {n}: out of range (replay holds {count} trials)")
    (k, t), = _select(table, np.array([n % count]))
    return readers[k], readers[k].get_trial(t), n % count


def render_trial(path: str | Path, n: int, out: str | Path) -> Path:
    """PNG of trial ``n``: heightmap with the grasp and gripper footprint, TSDF slices, label, score."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    reader, trial, position = resolve_trial(path, n)
    info = reader.info()
    grid = info["scene_grid"]
    ggrid = info["gripper_grid"]
    vs, gvs = float(grid["voxel_size"]), float(ggrid["voxel_size"])
    i, j, k, s = trial.action
    theta = 2 * np.pi * k / int(info["rotations"])
    hm = trial.observation.heightmap
    # footprint: gripper voxels inside the open hand (channel 0 < 0), projected along z, in the TCP frame
    occ = (trial.gripper_encoding[0] < 0).any(axis=2)
    gx, gy = occ.shape
    px, py = np.nonzero(occ)
    fx = (px + 0.5) * gvs - 0.5 * gx * gvs
    fy = (py + 0.5) * gvs - 0.5 * gy * gvs
    c, sn = np.cos(theta), np.sin(theta)
    wx = c * fx - sn * fy
    wy = sn * fx + c * fy
    cell_x = i + wx / vs
    cell_y = j + wy / vs
    z_lo = float(grid["z_range"][0])
    grasp_z = max(float(hm[i, j]) - float(info.get("grasp_depth_m", 0.0)), z_lo)
    zi = int(np.clip((grasp_z - z_lo) / vs, 0, trial.observation.tsdf.shape[2] - 1))

    fig = Figure(figsize=(16, 5.5), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 3, 1)
    im = ax.imshow(hm.T, origin="lower", cmap="viridis")
    fig.colorbar(im, ax=ax, label="height (m)")
    obstacle = trial.observation.obstacle.max(axis=2) > 0.5
    if obstacle.any():
        ax.contour(obstacle.T.astype(float), levels=[0.5], colors="orange", linewidths=1.5)
        ax.plot([], [], color="orange", label="obstacles")
    ax.scatter(cell_x, cell_y, s=2, c="white", alpha=0.5, label="gripper footprint (open)")
    ax.plot([i], [j], "r+", ms=14, mew=2, label="grasp centre")
    ax.plot([i, i + 8 * c], [j, j + 8 * sn], "r-", lw=2)
    ax.set_xlim(0, hm.shape[0] - 1)
    ax.set_ylim(0, hm.shape[1] - 1)
    ax.set_xlabel("i (x cell)")
    ax.set_ylabel("j (y cell)")
    ax.legend(loc="upper right", fontsize=7)
    ax.set_title(f"heightmap; grasp i={i} j={j} k={k} s={s}", fontsize=10)
    ax = fig.add_subplot(1, 3, 2)
    im = ax.imshow(trial.observation.tsdf[:, :, zi].T, origin="lower", cmap="RdBu", vmin=-1, vmax=1)
    fig.colorbar(im, ax=ax, label="TSDF / truncation")
    ax.plot([i], [j], "k+", ms=12, mew=2)
    ax.set_title(f"TSDF at z index {zi} (grasp height {grasp_z * 1000:.0f} mm)", fontsize=10)
    ax = fig.add_subplot(1, 3, 3)
    im = ax.imshow(trial.observation.tsdf[:, j, :].T, origin="lower", cmap="RdBu", vmin=-1, vmax=1, aspect="auto")
    fig.colorbar(im, ax=ax, label="TSDF / truncation")
    ax.axvline(i, color="k", lw=1)
    ax.set_xlabel("i (x cell)")
    ax.set_ylabel("z index")
    ax.set_title(f"TSDF x-z slice at j={j}", fontsize=10)
    m = trial.meta
    fig.suptitle(
        f"trial {position} ({reader.path.name} #{trial.trial_id}): label {'SUCCESS' if trial.label else 'failure'}, "
        f"score {trial.score:.3f} | {m.scene} / {m.object_set} | gripper {m.gripper} x{m.gripper_scale:.2f} "
        f"opening {m.openings[s]:.2f} | policy v{m.policy_version}"
    )
    out = Path(out)
    fig.savefig(out)
    return out


def parse_range(text: str, count: int) -> range:
    """Python-style ``A:B`` (either side optional, negatives from the end) over ``count`` trials."""
    if ":" not in text:
        raise ReplayError(f"--trials {text}: expected A:B")
    a, b = text.split(":", 1)
    try:
        sl = slice(int(a) if a else None, int(b) if b else None)
    except ValueError:
        raise ReplayError(f"--trials {text}: A and B must be integers") from None
    return range(*sl.indices(count))


def export_trials(path: str | Path, trials: str, out: str | Path) -> dict:
    """Decoded trials A:B as plain arrays in one .npz; returns {name: shape}. A trial that cannot
    be read (a damaged chunk, or evicted by a live writer since the replay was opened) is left
    out with one warning; ``position`` lists the trials exported."""
    readers = open_readers(path)
    table = trial_table(readers)
    positions = np.asarray(parse_range(trials, len(table["trial_id"])), np.int64)
    if not len(positions):
        raise ReplayError(f"{path}: --trials {trials}: selects no trial (replay holds {len(table['trial_id'])})")
    got, kept, metas = [], [], []
    for position, (k, t) in zip(positions.tolist(), _select(table, positions)):
        try:
            got.append(readers[k].get_trial(t))
        except ReplayError as e:
            warnings.warn(f"trial {position} left out: {str(e).splitlines()[0]}", stacklevel=2)
            continue
        kept.append(position)
        metas.append(str(readers[k].column("meta", [t])[0]))
    if not got:
        raise ReplayError(f"{path}: --trials {trials}: none of the {len(positions)} selected trials can be read")
    positions = np.asarray(kept, np.int64)
    arrays = {
        "position": positions,
        "shard": table["shard"][positions],
        "trial_id": np.array([t.trial_id for t in got], np.int64),
        "insert_time": np.array([t.insert_time for t in got], np.float64),
        "tsdf": np.stack([t.observation.tsdf for t in got]),
        "obstacle": np.stack([t.observation.obstacle for t in got]),
        "heightmap": np.stack([t.observation.heightmap for t in got]),
        "valid": np.stack([t.observation.valid for t in got]),
        "gripper_encoding": np.stack([t.gripper_encoding for t in got]),
        "gripper_key": np.array([t.gripper_key for t in got]),
        "action": np.array([t.action for t in got], np.int64),
        "label": np.array([t.label for t in got], bool),
        "score": np.array([t.score for t in got], np.float64),
        "meta_json": np.array(metas),
    }
    out = Path(out)
    np.savez_compressed(out, **arrays)
    return {k: v.shape for k, v in arrays.items()}


def cli(argv: list[str]) -> int:
    """Entry point of ``python -m replay``."""
    parser = argparse.ArgumentParser(prog="python -m replay", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("inspect", help="trials, success rates, insert rate, bytes, schema")
    p.add_argument("path")
    p.add_argument("--json", dest="json_out", help="also write the summary as JSON to this file")
    p = sub.add_parser("show", help="PNG of one trial")
    p.add_argument("path")
    p.add_argument("--trial", type=int, required=True, help="position, 0 = oldest, -1 = newest")
    p.add_argument("--out", required=True)
    p = sub.add_parser("export", help="decoded trials A:B as an .npz of plain arrays")
    p.add_argument("path")
    p.add_argument("--trials", required=True, help="A:B, Python slice over positions")
    p.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    with warnings.catch_warnings():
        warnings.showwarning = _one_line_warning  # restored on exit
        return _run(args)


def _one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Warnings of the replay (a corrupt chunk skipped, say) as one line on stderr, without the
    source line Python's default format adds."""
    print(f"warning: {message}", file=sys.stderr if file is None else file)


def _run(args: argparse.Namespace) -> int:
    try:
        if args.command == "inspect":
            summary = summarize(args.path)
            print(format_summary(summary))
            if args.json_out:
                Path(args.json_out).write_text(json.dumps(finite_json(summary), indent=2))
        elif args.command == "show":
            if Path(args.out).suffix.lower() != ".png":
                raise ReplayInputError(f"--out {args.out}: expected a .png file")
            print(render_trial(args.path, args.trial, args.out))
        else:
            if Path(args.out).suffix != ".npz":
                raise ReplayInputError(f"--out {args.out}: expected a .npz file (numpy.savez would add the suffix)")
            shapes = export_trials(args.path, args.trials, args.out)
            print(f"{args.out}: " + ", ".join(f"{k} {tuple(v)}" for k, v in shapes.items()))
    except (ReplayError, OSError) as e:
        print(f"error: {str(e).splitlines()[0] if str(e) else type(e).__name__}", file=sys.stderr)
        return 2
    return 0


__all__ = ["cli", "summarize", "format_summary", "render_trial", "export_trials", "trial_table"]
