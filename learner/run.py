"""``python -m launcher [train] --actors N ...``: the main job.

Builds the parts once (replay shards, learner, grasp actors) and decides where they live:
in this process (``--actors 0``: one in-process actor, for tests and debugging) or as Ray
actors (``--actors N``, N >= 1; a local Ray instance unless ``--address`` joins a cluster).

Run directory layout::

    RUN/config.yaml            resolved config
    RUN/replay/shard_XXX/      Zarr v3 groups, one writer each
    RUN/checkpoints/latest.pt  model, optimiser, step, epsilon, config, replay position
    RUN/progress.jsonl         one JSON line about every 5 s, and one at exit
    RUN/tb/                    TensorBoard logs
    RUN/summary.json           written at exit; earlier parts' kept (see with_earlier_parts)
    RUN/history.json           (step, mean loss) of every learner chunk; written when a Ray run
                               (--actors N >= 1) ends, after its final checkpoint; not by --actors 0
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import time
from pathlib import Path

import torch
import yaml

from common.checkpoint import SHIPPED_PREFIX, CheckpointError, initial_weights, network_difference, read_checkpoint
from common.config import Config, ConfigError, config_path, load_config, save_config, set_flags
from common.files import atomic_write_text, finite_json
from common.runtime import cluster_address
from replay.schema import ReplayError


def parse_args(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m launcher", description=__doc__.splitlines()[0])
    p.add_argument("--actors", type=int, default=2, help="grasp actors (0 = everything in this process)")
    p.add_argument("--shards", type=int, default=None, help="replay shards (default: replay.shards)")
    p.add_argument("--config", default=None, help="config name (default|paper|tiny) or YAML path (default: default)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config key")
    p.add_argument("--run-dir", default=None, help="run directory (default: runs/<time>)")
    p.add_argument("--resume", action="store_true", help="continue the run in --run-dir")
    p.add_argument("--max-trials", type=int, default=None, help="stop once the run has this many trials (a resumed run counts its earlier parts)")
    p.add_argument("--max-minutes", type=float, default=None, help="stop after this many minutes")
    p.add_argument("--address", default=None, help="Ray cluster address (e.g. auto); default: RAY_ADDRESS if set, else a local instance")
    p.add_argument("--quiet", action="store_true", help="no live progress line")
    return p.parse_args(argv)


def resolve(args: argparse.Namespace) -> tuple[Config, Path]:
    """Config (from the run dir when resuming, limits in cfg.run) and run directory (absolute:
    the learner and the shards may run in Ray workers in other working directories)."""
    if args.actors < 0:
        raise ConfigError(f"--actors: expected 0 (everything in this process) or more, got {args.actors}")
    if args.actors == 0 and args.address:
        raise ConfigError(f"--address {args.address}: --actors 0 runs everything in this process, without Ray; "
                          "give the cluster grasp actors")
    config_file = Path(args.run_dir or ".") / "config.yaml" if args.resume else config_path(args.config or "default")
    source = f"{config_file}{' with --set' if args.set else ''}"  # where the values came from, in errors
    if args.resume:
        if not args.run_dir:
            raise ConfigError("--resume: needs --run-dir of the run to continue")
        run_dir = Path(args.run_dir)
        if args.config is not None:
            raise ConfigError(
                f"--config {args.config}: a resumed run keeps {run_dir / 'config.yaml'}; change a key with --set"
            )
        if not (run_dir / "config.yaml").is_file():
            raise ConfigError(f"{run_dir / 'config.yaml'}: not found; nothing to resume")
        if not (run_dir / "config.yaml").read_text().strip():
            raise ConfigError(f"{run_dir / 'config.yaml'}: empty; a run's config.yaml holds the config it started with")
        cfg = load_config(run_dir / "config.yaml", overrides=args.set)
        # the seed_from the run's file records (read as written: --set may mend its other keys)
        stored = yaml.safe_load((run_dir / "config.yaml").read_text())
        recorded = ((stored.get("replay") if isinstance(stored, dict) else None) or {}).get("seed_from") or ""
        if cfg.replay.seed_from != recorded:
            origin = f"seeded from {recorded}" if recorded else "started empty"
            raise ConfigError(
                f"{run_dir / 'config.yaml'}: replay.seed_from: a resumed run keeps its replay ({origin}); "
                f"it cannot be seeded again"
            )
        started = ((stored.get("learner") if isinstance(stored, dict) else None) or {})
        for key in ("samples_per_insert", "min_replay"):
            if key in started and getattr(cfg.learner, key) != started[key]:
                raise ConfigError(
                    f"{run_dir / 'config.yaml'}: learner.{key}: {started[key]} in this run, "
                    f"{getattr(cfg.learner, key)} with --set; a resumed run keeps it (the learner's budget "
                    f"of samples counts every trial since the run began)"
                )
    else:
        cfg = load_config(args.config or "default", overrides=args.set)
        if not args.run_dir and not cfg.run.run_dir:
            raise ConfigError(f"{source}: run.run_dir: empty; name the folder new runs go in, or pass --run-dir")
        run_dir = Path(args.run_dir) if args.run_dir else Path(cfg.run.run_dir) / time.strftime("%Y%m%d-%H%M%S")
        if (run_dir / "config.yaml").exists():
            raise ConfigError(f"{run_dir}: already holds a run; pass --resume to continue it")
    set_flags(cfg, (  # range-checked before RUN/config.yaml is written
        ("--shards", "replay.shards", args.shards),
        ("--max-trials", "run.max_trials", args.max_trials),
        ("--max-minutes", "run.max_minutes", args.max_minutes),
    ))
    run_dir = run_dir.absolute()
    if run_dir.exists() and not run_dir.is_dir():
        raise ConfigError(f"{run_dir}: --run-dir: exists and is not a folder")
    if (run_dir / "replay" / "zarr.json").is_file() and (args.resume or not cfg.replay.seed_from):
        # Stored trials the config cannot take are refused here, before config.yaml is written
        # (a replay about to be seeded is checked by seed_replay, naming the seeding).
        from replay.shard import check_shards

        check_shards(run_dir / "replay", cfg)
    from learner.loop import check_resumable, checkpoint_path

    own = checkpoint_path(run_dir)
    if own.is_file():
        # A run with a checkpoint of its own continues from it: an unreadable one, one without the
        # learner's state, or one of another network than the config's, is refused here in one
        # line, before anything starts.
        ckpt = read_checkpoint(own)
        check_resumable(ckpt, own)
        differ = network_difference(cfg, ckpt.cfg)
        if differ:
            key, mine, stored = differ
            raise CheckpointError(f"{own}: {key} is {stored!r} there but {mine!r} in this run's config; "
                                  f"a resumed run keeps its network")
    elif cfg.learner.init_weights:
        # A run without a checkpoint of its own (new, or stopped before its first one) starts
        # from init_weights: check it here, before anything starts, and make a path absolute,
        # since Ray worker processes need not share the driver's working directory.
        if not cfg.learner.init_weights.startswith(SHIPPED_PREFIX):
            cfg.learner.init_weights = str(Path(cfg.learner.init_weights).resolve())
        initial_weights(cfg)
    check_names(cfg, source)
    if cluster_address(args.address) is None:  # the learner runs on this machine: its device must be here
        from learner.learner import resolve_device

        try:
            resolve_device(cfg.learner.device)
        except ValueError as e:
            raise ConfigError(f"{source}: {e}") from None
    new_dir = not run_dir.exists()
    run_dir.mkdir(parents=True, exist_ok=True)
    if cfg.replay.seed_from and not args.resume:
        from replay.seed import seed_replay

        def progress(done: int, total: int) -> None:
            print(f"seeding the replay: {done} of {total} trials done", flush=True)

        try:
            report = seed_replay(cfg.replay.seed_from, run_dir / "replay", cfg, progress=progress)
        except BaseException:
            if new_dir and not any(run_dir.iterdir()):
                run_dir.rmdir()  # a refused run leaves no run directory behind (its staging copy is gone)
            raise
        cfg.replay.seed_from = report["seeded_from"]
        if report["reused"]:
            print(f"replay already seeded with {report['trials']} trials of {report['seeded_from']} "
                  f"(a start that stopped before writing config.yaml); using it", flush=True)
        else:
            skipped = (f"; {report['skipped']} unreadable or evicted, skipped (first: {report['problems'][0]})"
                       if report["skipped"] else "")
            print(f"replay seeded with {report['trials']} of {report['available']} trials of "
                  f"{report['seeded_from']}{skipped}", flush=True)
    save_config(cfg, run_dir / "config.yaml")
    return cfg, run_dir


def check_names(cfg: Config, source: str) -> None:
    """What the config names beyond single values (the training grippers, the object set, a
    network its grids and widths can build) and the simulation's constraints between fields,
    checked before RUN/config.yaml is written: a ConfigError naming ``source`` and the key,
    instead of a failure in every actor."""
    from actors.grasp_actor import split_grippers
    from actors.objects import ObjectSetError, check_object_set
    from actors.simulation import check_sim_config
    from common.network import NetworkConfigError, build_model

    try:
        check_sim_config(cfg)
    except ConfigError as e:
        raise ConfigError(f"{source}: {e}") from None
    if cfg.learner.min_replay > cfg.replay.capacity:
        raise ConfigError(f"{source}: learner.min_replay: {cfg.learner.min_replay} trials before training, but the "
                          f"replay holds at most replay.capacity {cfg.replay.capacity}")
    try:
        split_grippers(cfg)
    except ValueError as e:  # GripperSpecError, or a selection of no gripper
        raise ConfigError(f"{source}: grippers.train_grippers: {e}") from None
    try:
        check_object_set(cfg.sim.objects)
    except ObjectSetError as e:
        raise ConfigError(f"{source}: sim.objects: {e}") from None
    try:
        with torch.random.fork_rng(devices=[]):
            build_model(cfg)
    except NetworkConfigError as e:
        raise ConfigError(f"{source}: {e}") from None


def cli(argv: list[str]) -> int:
    args = parse_args(argv)
    try:
        cfg, run_dir = resolve(args)
    except (ConfigError, CheckpointError, ReplayError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # a run directory that cannot be made or written: the file and the reason
        where = e.filename or args.run_dir or "the run directory"  # some OSErrors name no file
        print(f"error: {where}: {e.strerror or e}", file=sys.stderr)
        return 2
    from learner.loop import run_distributed, run_local

    print(f"run directory: {run_dir}", flush=True)
    stop = {"flag": False}

    def on_sigint(signum, frame):  # noqa: ARG001 - signal handler signature
        if stop["flag"]:
            raise KeyboardInterrupt
        stop["flag"] = True
        print("\nstopping: flushing replay and writing a checkpoint (Ctrl-C again to abort)", flush=True)

    previous = signal.signal(signal.SIGINT, on_sigint)
    try:
        if args.actors == 0:
            summary = run_local(cfg, run_dir, stop, quiet=args.quiet)
        else:
            summary = run_distributed(
                cfg, run_dir, stop, n_actors=args.actors, address=args.address, quiet=args.quiet
            )
    finally:
        signal.signal(signal.SIGINT, previous)
    summary_file = run_dir / "summary.json"
    summary = with_earlier_parts(summary_file, summary)
    summary = finite_json(summary)
    atomic_write_text(summary_file, json.dumps(summary, indent=2))
    print(json.dumps(summary), flush=True)
    if "error" in summary:  # actors whose episodes kept failing, or training diverged, ended the run
        ckpt = Path(summary["checkpoint"])
        kept = f"last checkpoint: {ckpt}" if ckpt.is_file() else "it wrote no checkpoint"
        print(f"error: {summary['error']}; the run stopped ({kept})", file=sys.stderr)
        return 2
    return 0


def with_earlier_parts(path: Path, summary: dict) -> dict:
    """``summary`` of the part of a run that just ended, with ``earlier_parts`` read from ``path``.

    A resumed run writes ``summary.json`` again. Its ``trials``, ``learner_steps``,
    ``learner_samples`` and ``weights_version`` count the whole run. Its ``episodes``,
    ``weights_published``, ``actor_restarts``, ``learner_restarts`` and ``actor_wait_s`` count
    this part only, so the earlier parts' summaries are carried over as ``earlier_parts``
    (oldest first).
    A part that was killed wrote no summary and has no entry. An unreadable file is
    renamed to ``summary.unreadable-<time>.json``, with a one-line warning, and never
    overwritten.
    """
    if not path.is_file():
        return summary
    try:
        earlier = json.loads(path.read_text())
        if not isinstance(earlier, dict):
            raise ValueError("not a JSON object")
    except ValueError as e:
        aside = path.with_name(f"summary.unreadable-{time.strftime('%Y%m%d-%H%M%S')}.json")
        path.rename(aside)
        print(f"warning: {path}: unreadable ({e}); kept as {aside.name}, not in earlier_parts", file=sys.stderr)
        return summary
    parts = earlier.pop("earlier_parts", [])
    return {**summary, "earlier_parts": [*parts, earlier]}
