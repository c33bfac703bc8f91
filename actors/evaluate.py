"""``python -m launcher evaluate``: the paper's evaluation protocol (Table I) for one cell, and the table.

Usage::

    python -m launcher evaluate --checkpoint runs/x/checkpoints/latest.pt --scene multi --objects test \\
        --grippers test --policy fix-gripper --cameras 1 --episodes 100 --actors 2 --seed 0 \\
        --json results/multi-te-te-fix-gripper.json --md results/multi-te-te-fix-gripper.md
    python -m launcher evaluate --scene single --objects test --grippers wsg_50,panda_hand \\
        --policy heuristic --episodes 100 --json results/single-te-te-heuristic.json
    python -m launcher evaluate table results/*.json --md results/table1.md
    python -m launcher evaluate compare results/a.json results/b.json   # paired, same scenes
    python -m launcher evaluate runs --a r1.json --a r2.json --b s1.json --b s2.json   # across training runs
    python -m launcher evaluate holm cmp1.json cmp2.json cmp3.json   # Holm's correction over comparisons

Protocol (docs/EVALUATION.md has the whole text):

- Episode e uses the scene seed ``actors.rollout.episode_seed(S, e)`` =
  ``SeedSequence([S, e]).generate_state(1)[0]`` for root seed S (``--seed``), whatever the policy,
  gripper, scene kind, object set or number of actors; its policy generator is
  ``numpy.random.default_rng([S, e, 1, crc32(gripper name)])`` for a per-gripper policy and
  ``numpy.random.default_rng([S, e, 1])`` for ``adagrasp`` (:func:`policy_seed`), so every
  gripper draws its own random openings, actions and blobs. Every (gripper, episode) runs in a fresh
  :class:`actors.simulation.Simulation`, so its outcome does not depend on what ran before it
  in the same process: results are identical for any ``--actors``.
- One attempt = one grasp; it succeeds when exactly one target ends above ``sim.lift_height``
  and no obstacle does (``actors.grasp.execute_grasp``). An episode ends when no target is left
  or after ``sim.multi_max_attempts`` (multi) / ``sim.obstacle_max_attempts`` (obstacle) / 1
  (single) attempts. Success rate = successes / attempts.
- Policies: ``scene-only`` and ``init-only`` need a checkpoint of that variant and, like
  ``fix-config``, take a random opening per attempt (the paper tests all three with
  ``--random_open_scale``); ``fix-config``, ``fix-gripper`` (best opening) and
  ``adagrasp`` (best gripper of ``--grippers`` and best opening, per attempt; the chosen gripper
  is loaded into the simulation) need an ``adagrasp`` checkpoint; ``random`` and ``heuristic``
  need none. Candidate openings: ``grippers.eval_openings``. The evaluation config (``--config``,
  ``--set``) fixes the simulation for every policy; a checkpoint brings its network and weights,
  and its grids and rotations must match that config.
- ``--calibration RESULT.json`` (``adagrasp`` only): before comparing grippers, each gripper's
  scores are mapped through a logit shift fitted to its trials in RESULT.json, a ``fix-gripper``
  evaluation of the same checkpoint on other scenes (``common.calibration``); the result records
  the shifts, its rows read ``adagrasp (calibrated)``, and each attempt's ``score`` is the
  calibrated one.
- Every gripper of ``--grippers`` runs the same N episodes (except ``adagrasp``, which runs N
  episodes and picks among them); the headline rate is the mean of the per-gripper rates
  (``adagrasp``: its successes / attempts).

Call loop (the parts are built once; :func:`run_units` decides where they run)::

    plan = plan_from_argv(argv)                  # config, grippers, encodings, weights; validated
    results = run_units(plan, plan.units(), actors=K)   # EvalWorker here (K=1) or on K Ray actors
    summary = summarise(plan, results, argv, "test")    # per gripper, average, every episode
    markdown = table_markdown([("out.json", summary)])  # the paper's Table I layout

Bad input ends with one line on stderr and exit status 2; nothing is written then.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import sys
import time
import zlib
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from actors.grasp import FAILURE_MODES, execute_grasp, max_attempts
from actors.objects import ObjectSetError, object_names
from actors.policies import make_policy
from actors.rollout import episode_seed
from actors.simulation import SCENE_KINDS, Simulation, SimulationError
from common.calibration import Calibration, calibration_from_result, file_sha256
from common.checkpoint import CheckpointError, inference_config, read_checkpoint, resolve_checkpoint
from common.config import Config, from_dict, load_config, set_flags, to_dict
from common.files import finite_json
from common.gripper import SPLITS as GRIPPER_SPLITS
from common.gripper import GripperSpec, check_scale, get_gripper, list_grippers
from common.gripper_encoding import GripperEncoder, gripper_key
from common.network import build_model
from common.policy import LearnedPolicy
from common.runtime import ray_init

FORMAT = "adagrasp-scale-evaluation/1"
"""Value of the ``format`` key of every result JSON."""
LEARNED = {
    "scene-only": ("scene-only", "fix-config"),
    "init-only": ("init-only", "fix-config"),
    "fix-config": ("adagrasp", "fix-config"),
    "fix-gripper": ("adagrasp", "fix-gripper"),
    "adagrasp": ("adagrasp", "adagrasp"),
}
"""Learned evaluation policy -> (the checkpoint's required ``model.variant``, LearnedPolicy mode)."""
SCRIPTED = ("random", "heuristic")
"""Reference policies that need no checkpoint."""
POLICIES = (*LEARNED, *SCRIPTED)
"""Every ``--policy``, in the row order of the paper's table (reference rows last)."""
CALIBRATED = "adagrasp (calibrated)"
"""Table row of ``adagrasp`` results run with ``--calibration`` (after the ``adagrasp`` row)."""
OPENING_RULES = {"fix-config": "random", "fix-gripper": "best", "adagrasp": "best"}
"""LearnedPolicy mode -> how a learned policy's result chose its opening (its ``opening_rule``)."""
EARLIER_OPENING_RULES = {"scene-only": "first", "init-only": "best"}
"""The opening rule of ``scene-only`` / ``init-only`` results written before ``opening_rule`` was
recorded: they ran in fix-gripper mode, where scene-only's equal scores take the first candidate."""
EARLIER_ROWS = tuple(f"{p} ({rule} opening)" for p, rule in EARLIER_OPENING_RULES.items())
"""Table rows of those results: not the paper's protocol, so never averaged with its rows."""
ROWS = (*LEARNED, CALIBRATED, *EARLIER_ROWS, *SCRIPTED)
"""Row labels of the table, in order."""
POLICY_STREAM = 1
"""Third entropy word of the policy generator (:func:`policy_seed`)."""
CELL_ORDER = ("O_tr/G_tr", "O_tr/G_te", "O_te/G_tr", "O_te/G_te")
"""Object x gripper cells of the paper's table, in its column order."""


class EvaluationError(ValueError):
    """Bad evaluation input (policy, checkpoint, grippers, result file); one line naming the field."""


def policy_seed(seed: int, episode: int, gripper: str | None = None) -> list[int]:
    """Entropy of the policy generator of episode ``episode`` run by ``gripper`` (None: the
    ``adagrasp`` policy, which chooses among all grippers).

    The same for every policy, so rows of a table that draw alike draw the same numbers; one
    stream per gripper name (its CRC-32, independent of the order of ``--grippers``), so the
    random draws of ``fix-config``, ``random`` and ``heuristic`` are independent across the
    grippers of a cell: with a stream shared by all grippers, a cell of 32 grippers x 4 episodes
    would try only the openings of 4 episodes' draws.
    """
    words = [int(seed), int(episode), POLICY_STREAM]
    return words if gripper is None else [*words, zlib.crc32(gripper.encode())]


# --------------------------------------------------------------------------------------
# Plan: everything the workers need, validated in the driver
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Unit:
    """One episode to run: index into the result list, episode number, gripper index (None: adagrasp)."""

    index: int
    episode: int
    gripper: int | None


@dataclass
class EvalPlan:
    """One evaluation cell: config, policy, grippers, weights; sent as is to every worker."""

    cfg: Config
    """Evaluation config (sim, grids, ``grippers.eval_openings``, ``sim.cameras``)."""
    policy: str
    """One of :data:`POLICIES`."""
    scene: str
    """Scene kind."""
    objects: str
    """Object set name."""
    gripper_ids: list[str]
    """How each gripper is found (``get_gripper`` argument: name or spec path)."""
    gripper_names: list[str]
    """Registered name of each gripper (``GripperSpec.name``)."""
    scale: float
    """Global gripper scale."""
    openings: tuple[float, ...]
    """Candidate initial openings in [0, 1]."""
    episodes: int
    """Episodes per gripper (adagrasp: in all)."""
    seed: int
    """Root seed S of the scene and policy seeds."""
    model_cfg: Config | None = None
    """Config the checkpoint's network was built from (learned policies)."""
    model_state: dict | None = None
    """Network state dict, CPU tensors (learned policies)."""
    model_version: int = -1
    """Weights version of the checkpoint."""
    model_sha256: str | None = None
    """:func:`common.checkpoint.model_sha256` of the checkpoint (learned policies): which network
    and weights were evaluated, whatever the file was called."""
    encodings: list[np.ndarray] | None = None
    """Per gripper (S, 2, gX, gY, gZ) float32 encodings at ``scale`` and ``openings`` (learned policies)."""
    device: str = "cpu"
    """Torch device of the network in every worker: cpu | cuda."""
    calibration: Calibration | None = None
    """Per-gripper score calibration of the ``adagrasp`` policy (``--calibration``), or None."""

    def units(self) -> list[Unit]:
        """Every episode of the cell: gripper-major for per-gripper policies, episode order for adagrasp."""
        if self.policy == "adagrasp":
            return [Unit(e, e, None) for e in range(self.episodes)]
        return [
            Unit(g * self.episodes + e, e, g) for g in range(len(self.gripper_ids)) for e in range(self.episodes)
        ]


def resolve_grippers(selection: str) -> list[tuple[str, GripperSpec]]:
    """``train`` | ``test`` | ``NAME,NAME,...`` -> [(identifier, spec)]; raises one line on unknown names."""
    if selection in GRIPPER_SPLITS:
        specs = list_grippers(split=selection)
        found = [(s.name, s) for s in specs]
    else:
        names = [n.strip() for n in selection.split(",")]
        if not all(names):
            raise EvaluationError(f"--grippers {selection!r}: empty gripper name in the list")
        found = [(n, get_gripper(n)) for n in names]
    if not found:
        raise EvaluationError(f"--grippers {selection!r}: selects no gripper")
    seen: dict[str, str] = {}
    for ident, spec in found:
        if spec.name in seen:
            raise EvaluationError(
                f"--grippers {selection!r}: gripper {spec.name} given twice ({seen[spec.name]}, {ident})"
            )
        seen[spec.name] = ident
    return found


def _config(args) -> Config:
    cfg = load_config(args.config, list(args.set))
    set_flags(cfg, (("--scene", "sim.scene", args.scene), ("--objects", "sim.objects", args.objects),
                    ("--cameras", "sim.cameras", args.cameras)))
    return cfg


def make_plan(args) -> EvalPlan:
    """Validate ``args`` (parsed CLI) and gather what the workers need; raises one-line errors."""
    if args.episodes < 1:
        raise EvaluationError(f"--episodes: expected at least 1, got {args.episodes}")
    if args.actors < 1:
        raise EvaluationError(f"--actors: expected at least 1, got {args.actors}")
    check_scale(args.scale, "--scale")
    cfg = _config(args)
    if not object_names(args.objects):
        raise ObjectSetError(f"--objects {args.objects}: the object set is empty")
    grippers = resolve_grippers(args.grippers)
    openings = tuple(float(o) for o in cfg.grippers.eval_openings)
    plan = EvalPlan(
        cfg=cfg,
        policy=args.policy,
        scene=args.scene,
        objects=args.objects,
        gripper_ids=[ident for ident, _ in grippers],
        gripper_names=[spec.name for _, spec in grippers],
        scale=float(args.scale),
        openings=openings,
        episodes=int(args.episodes),
        seed=int(args.seed),
        device=args.device,
    )
    if args.calibration is not None and args.policy != "adagrasp":
        raise EvaluationError(
            f"--calibration: only --policy adagrasp compares grippers; {args.policy} would choose the same grasps"
        )
    if args.policy in SCRIPTED:
        if args.checkpoint is not None:
            raise EvaluationError(f"--checkpoint: the {args.policy} policy takes no checkpoint")
        return plan
    if args.checkpoint is None:
        raise EvaluationError(f"--checkpoint: the {args.policy} policy needs a checkpoint")
    if args.device == "cuda" and not torch.cuda.is_available():
        raise EvaluationError("--device cuda: torch sees no CUDA device on this machine")
    variant, mode = LEARNED[args.policy]
    ckpt = read_checkpoint(args.checkpoint)
    if ckpt.variant != variant:
        hint = ckpt.variant if ckpt.variant != "adagrasp" else "fix-config, fix-gripper or adagrasp"
        raise EvaluationError(
            f"{args.checkpoint}: model.variant: --policy {args.policy} needs a checkpoint of variant {variant}, "
            f"this one is {ckpt.variant} (use --policy {hint})"
        )
    LearnedPolicy.from_checkpoint(args.checkpoint, cfg, mode=mode)  # grid and rotation checks, one line
    plan.model_sha256 = ckpt.model_sha256()
    if args.calibration is not None:
        plan.calibration = _calibration(args, plan, ckpt.version)
    encoder = GripperEncoder(cfg.gripper_grid)
    plan.encodings = [encoder.encode(spec, plan.scale, openings) for _, spec in grippers]
    plan.model_cfg = inference_config(ckpt.cfg)
    plan.model_state = ckpt.model_state
    plan.model_version = ckpt.version
    return plan


def _same_checkpoint_file(path: str, fitted_on, fitted_version, checkpoint: str, version: int) -> None:
    """A calibration without ``checkpoint_sha256``: it must name the file of ``checkpoint`` (the
    same path, or the same ``model:NAME``) at weights ``version``; one-line errors otherwise."""
    try:
        same = isinstance(fitted_on, str) and (
            resolve_checkpoint(fitted_on).resolve() == resolve_checkpoint(checkpoint).resolve()
        )
    except CheckpointError as e:
        raise EvaluationError(f"{path}: checkpoint: {e}") from None
    if not same:
        raise EvaluationError(f"{path}: checkpoint: fitted with {fitted_on!r}, this evaluation uses {checkpoint!r}")
    if fitted_version != version:
        raise EvaluationError(
            f"{path}: checkpoint_version: fitted with weights v{fitted_version}, the checkpoint holds v{version}"
        )


CALIBRATION_FREE = ("sim.scene", "sim.objects")
"""Config keys in which a calibration's evaluation may differ from the evaluation it serves."""


def _flat(tree: dict, prefix: str = "") -> dict:
    out = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            out.update(_flat(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def _calibration(args, plan: EvalPlan, version: int) -> Calibration:
    """The calibration of ``--calibration``, checked against this evaluation: the same network and
    weights, openings, scale and config (but scene kind and object set; read as a checkpoint's
    is, so a key added to the config since it was written takes its default), every gripper, no
    shared scene seed (in any scene kind); one-line errors naming the file and the key.

    The network and weights agree by ``checkpoint_sha256`` when the calibration records it,
    whatever either file is called (a run's checkpoint and the model exported from it); a
    calibration written before that digest was recorded must name the same checkpoint file and
    weights version."""
    path = args.calibration
    data = read_result(path)
    fitted_on = data.get("checkpoint")
    digest = data.get("checkpoint_sha256")
    if digest is not None:
        if digest != plan.model_sha256:
            raise EvaluationError(
                f"{path}: checkpoint_sha256: fitted with network and weights {str(digest)[:12]}... "
                f"({fitted_on!r}), {args.checkpoint!r} holds {plan.model_sha256[:12]}..."
            )
    else:
        _same_checkpoint_file(path, fitted_on, data.get("checkpoint_version"), args.checkpoint, version)
    openings = data.get("openings")
    if not isinstance(openings, list) or openings != list(plan.openings):
        raise EvaluationError(f"{path}: openings: fitted with {openings}, this evaluation uses {list(plan.openings)}")
    if data.get("scale") != plan.scale:
        raise EvaluationError(f"{path}: scale: fitted with {data.get('scale')!r}, this evaluation uses {plan.scale}")
    if not isinstance(data.get("config"), dict):
        raise EvaluationError(f"{path}: config: missing (the resolved config of the calibration's evaluation)")
    theirs = _flat(to_dict(from_dict(data["config"], source=f"{path}: config")))
    mine = _flat(to_dict(plan.cfg))
    for key in sorted(mine):
        if key not in CALIBRATION_FREE and theirs[key] != mine[key]:
            raise EvaluationError(
                f"{path}: config.{key}: fitted with {theirs[key]!r}, this evaluation uses {mine[key]!r}"
            )
    # Scene kinds aside: a scene seed drops nearly the same objects in every kind (a single-object
    # scene's object is the first of the pile of the same seed), so shared seeds leak whatever the kind.
    if data.get("objects") == plan.objects:
        evaluated = {episode_seed(plan.seed, e) for e in range(plan.episodes)}
        fitted = {record["scene_seed"] for record in data["episode_results"]}  # checked by read_result
        if fitted & evaluated:
            raise EvaluationError(
                f"{path}: scene_seeds: the calibration trials share {len(fitted & evaluated)} scenes with this "
                "evaluation (fit it on other objects or another --seed)"
            )
    cal = calibration_from_result(str(path), data)
    cal.shifts(plan.gripper_names)  # every evaluated gripper has trials
    return replace(cal, sha256=file_sha256(path))


# --------------------------------------------------------------------------------------
# Worker: runs units; the same class in this process and in Ray actors
# --------------------------------------------------------------------------------------


class EvalWorker:
    """Runs evaluation episodes of one plan; one model copy, grippers and policies built on demand."""

    def __init__(self, plan: EvalPlan, torch_threads: int | None = None) -> None:
        """``torch_threads``: set torch's intra-op threads (Ray actors; the driver sets its own)."""
        if torch_threads is not None:
            torch.set_num_threads(int(torch_threads))
        self.plan = plan
        self._specs: dict[int, GripperSpec] = {}
        self._policies: dict[int | None, object] = {}
        self.model = None
        if plan.model_state is not None:
            self.model = build_model(plan.model_cfg)
            self.model.set_weights(plan.model_state, plan.model_version)
            self.model.to(plan.device).eval()

    def spec(self, g: int) -> GripperSpec:
        """Spec of gripper ``g`` of the plan."""
        if g not in self._specs:
            self._specs[g] = get_gripper(self.plan.gripper_ids[g])
        return self._specs[g]

    def policy(self, g: int | None):
        """The policy of gripper ``g`` (None: the adagrasp policy over every gripper)."""
        if g not in self._policies:
            plan = self.plan
            if plan.policy in SCRIPTED:
                self._policies[g] = make_policy(plan.policy, plan.cfg)
            else:
                indices = range(len(plan.gripper_ids)) if g is None else [g]
                grippers = [
                    (gripper_key(plan.gripper_names[n], plan.scale, plan.openings), plan.encodings[n]) for n in indices
                ]
                mode = LEARNED[plan.policy][1]
                shifts = None
                if plan.calibration is not None:
                    shifts = plan.calibration.shifts([plan.gripper_names[n] for n in indices])
                self._policies[g] = LearnedPolicy(
                    self.model, plan.cfg, grippers, mode=mode, epsilon=0.0, score_shifts=shifts
                )
        return self._policies[g]

    def run(self, unit: Unit) -> dict:
        """Run one episode in a fresh simulation; returns its JSON-ready record."""
        t0 = time.perf_counter()
        plan = self.plan
        seed = episode_seed(plan.seed, unit.episode)
        name = None if unit.gripper is None else plan.gripper_names[unit.gripper]
        rng = np.random.default_rng(policy_seed(plan.seed, unit.episode, name))
        policy = self.policy(unit.gripper)
        attempts = []
        with Simulation(plan.cfg, seed=seed) as sim:
            sim.reset_scene(plan.scene, plan.objects, seed=seed)
            scene_objects = [[o.name, o.role] for o in sim.objects.values()]
            limit = max_attempts(sim, plan.scene)
            for step in range(limit):
                if step > 0:
                    sim.settle()
                obs = sim.observe()
                action, score = policy.act(obs, plan.openings, rng)
                chosen = unit.gripper if unit.gripper is not None else policy.last_choice.action[4]
                gripper = sim.load_gripper(self.spec(chosen), plan.scale)
                outcome = execute_grasp(sim, gripper, action, plan.openings, obs.heightmap)
                attempts.append(
                    {
                        "step": step,
                        "gripper": plan.gripper_names[chosen],
                        "executed": gripper.spec.name,
                        "action": [int(a) for a in action],
                        "opening": outcome.opening,
                        "score": float(score),
                        "success": bool(outcome.success),
                        "failure": outcome.failure,
                        "stopped_at_contact": bool(outcome.stopped_at_contact),
                        "lifted_targets": len(outcome.lifted_targets),
                        "lifted_obstacles": len(outcome.lifted_obstacles),
                    }
                )
                if not sim.targets:
                    break
            targets_left = len(sim.targets)
        return {
            "index": unit.index,
            "episode": unit.episode,
            "gripper": None if unit.gripper is None else plan.gripper_names[unit.gripper],
            "scene_seed": seed,
            "objects": scene_objects,
            "max_attempts": limit,
            "attempts": len(attempts),
            "successes": sum(a["success"] for a in attempts),
            "targets_left": targets_left,
            "trials": attempts,
            "wall_s": time.perf_counter() - t0,
        }


# --------------------------------------------------------------------------------------
# Where the units run
# --------------------------------------------------------------------------------------


def _progress(done: int, total: int, quiet: bool) -> None:
    if not quiet and (done == total or done % max(1, total // 10) == 0):
        print(f"evaluate: {done}/{total} episodes", file=sys.stderr, flush=True)


def _run_local(plan: EvalPlan, units: list[Unit], quiet: bool) -> list[dict]:
    before = torch.get_num_threads()
    try:
        worker = EvalWorker(plan, torch_threads=plan.cfg.actor.torch_threads)
        out = []
        for n, unit in enumerate(units):
            out.append(worker.run(unit))
            _progress(n + 1, len(units), quiet)
        return out
    finally:
        torch.set_num_threads(before)


def _run_ray(plan: EvalPlan, units: list[Unit], actors: int, address: str | None, quiet: bool) -> list[dict]:
    import ray
    from ray.exceptions import RayTaskError

    started = not ray.is_initialized()
    if started:
        ray_init(address, num_cpus=max(os.cpu_count() or 1, actors))
    workers = []
    try:
        gpus = 1.0 / actors if plan.device == "cuda" and plan.model_state is not None else 0
        remote = ray.remote(num_cpus=1, num_gpus=gpus)(EvalWorker)
        plan_ref = ray.put(plan)
        workers = [remote.remote(plan_ref, plan.cfg.actor.torch_threads) for _ in range(actors)]
        todo = list(reversed(units))
        pending: dict = {}
        out: list[dict] = []
        for w in workers:
            if todo:
                pending[w.run.remote(todo.pop())] = w
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            w = pending.pop(ready[0])
            try:
                out.append(ray.get(ready[0]))
            except RayTaskError as e:
                cause = getattr(e, "cause", None)
                if isinstance(cause, (ValueError, SimulationError)):
                    raise cause from None
                raise
            _progress(len(out), len(units), quiet)
            if todo:
                pending[w.run.remote(todo.pop())] = w
        return out
    finally:
        for w in workers:
            ray.kill(w)
        if started:
            ray.shutdown()


def run_units(plan: EvalPlan, units: list[Unit], actors: int = 1, address: str | None = None,
              quiet: bool = True) -> list[dict]:
    """Run ``units`` in this process (``actors`` = 1) or on ``actors`` Ray actors (one torch thread
    each); episode records sorted by unit index (the same for any ``actors``)."""
    actors = max(1, min(int(actors), len(units)))
    if actors == 1 and not address:
        out = _run_local(plan, units, quiet)
    else:
        out = _run_ray(plan, units, actors, address, quiet)
    return sorted(out, key=lambda r: r["index"])


# --------------------------------------------------------------------------------------
# Summary, JSON and Markdown
# --------------------------------------------------------------------------------------


def _rate(successes: int, attempts: int) -> float | None:
    return successes / attempts if attempts else None


def objects_label(objects: str) -> str:
    """Column label of an object set: ``O_tr`` (train), ``O_te`` (test), else ``O_<name>``."""
    return {"train": "O_tr", "test": "O_te"}.get(objects, f"O_{objects}")


def grippers_label(selection: str, names: list[str]) -> str:
    """Column label of a gripper selection: ``G_tr`` (train), ``G_te`` (test), else ``G_<name>+<name>``
    from the grippers' registered ``names``."""
    if selection in ("train", "test"):
        return {"train": "G_tr", "test": "G_te"}[selection]
    return "G_" + "+".join(names)


def summarise(plan: EvalPlan, results: list[dict], argv: list[str], grippers: str, extra: dict | None = None) -> dict:
    """The result JSON of one cell: per gripper, the average, every episode and attempt.

    ``grippers``: the ``--grippers`` selection; ``extra``: more keys (checkpoint, actors, wall time).
    """
    per: dict[str, dict] = {}
    for name in plan.gripper_names:
        per[name] = {"episodes": 0, "attempts": 0, "successes": 0, "failures": dict.fromkeys(FAILURE_MODES, 0)}
    for r in results:
        for name in {t["gripper"] for t in r["trials"]} | ({r["gripper"]} if r["gripper"] is not None else set()):
            per[name]["episodes"] += 1
        for t in r["trials"]:
            per[t["gripper"]]["attempts"] += 1
            per[t["gripper"]]["successes"] += int(t["success"])
            if not t["success"]:
                per[t["gripper"]]["failures"][t["failure"]] += 1
    for v in per.values():
        v["rate"] = _rate(v["successes"], v["attempts"])
    attempts = sum(r["attempts"] for r in results)
    successes = sum(r["successes"] for r in results)
    pooled = _rate(successes, attempts)
    if plan.policy == "adagrasp":
        rate = pooled
        for v in per.values():
            v["chosen_fraction"] = v["attempts"] / attempts if attempts else None
    else:
        rate = float(np.mean([v["rate"] for v in per.values()]))
    return {
        "format": FORMAT,
        "command": "python -m launcher evaluate " + shlex.join(argv),
        "policy": plan.policy,
        "scene": plan.scene,
        "objects": plan.objects,
        "objects_label": objects_label(plan.objects),
        "grippers": grippers,
        "grippers_label": grippers_label(grippers, plan.gripper_names),
        "gripper_names": plan.gripper_names,
        "cameras": plan.cfg.sim.cameras,
        "episodes": plan.episodes,
        "seed": plan.seed,
        "scene_seeds": [episode_seed(plan.seed, e) for e in range(plan.episodes)],
        "openings": list(plan.openings),
        "scale": plan.scale,
        "max_attempts": results[0]["max_attempts"],
        "rate": rate,
        "average": {
            "rate": rate,
            "rate_definition": "successes / attempts" if plan.policy == "adagrasp" else "mean of per-gripper rates",
            "attempts": attempts,
            "successes": successes,
            "pooled_rate": pooled,
        },
        "per_gripper": per,
        "episode_results": results,
        **(extra or {}),
        "config": to_dict(plan.cfg),
    }


def policy_opening_rule(policy: str) -> str | None:
    """How ``policy`` chooses its opening now (its LearnedPolicy mode's :data:`OPENING_RULES`);
    None for the scripted policies."""
    return OPENING_RULES[LEARNED[policy][1]] if policy in LEARNED else None


def opening_rule(summary: dict) -> str | None:
    """How a learned policy's result chose its opening: ``random`` (one drawn per attempt),
    ``best`` or ``first`` (:data:`EARLIER_OPENING_RULES`); None for the scripted policies."""
    policy = summary["policy"]
    if policy not in LEARNED:
        return None
    return summary.get("opening_rule") or EARLIER_OPENING_RULES.get(policy) or policy_opening_rule(policy)


def row_label(summary: dict) -> str:
    """Table row of a result: its policy, :data:`CALIBRATED` for a calibrated ``adagrasp`` run, or
    one of :data:`EARLIER_ROWS` for a scene-only / init-only result that did not draw its opening."""
    policy = summary["policy"]
    if policy == "adagrasp" and summary.get("calibration"):
        return CALIBRATED
    rule = opening_rule(summary)
    if policy in EARLIER_OPENING_RULES and rule != policy_opening_rule(policy):
        return f"{policy} ({rule} opening)"
    return policy


def _cell(summary: dict) -> str:
    return f"{summary['objects_label']}/{summary['grippers_label']}"


def _seeds(summary: dict) -> tuple[int, ...]:
    """The scene seeds of a result: its ``--seed``, or each pooled file's (:func:`actors.compare.pool_result`)."""
    seed = summary["seed"]
    return tuple(seed) if isinstance(seed, list) else (seed,)


def _column_key(summary: dict, with_cameras: bool, with_seeds: bool) -> tuple:
    cell = _cell(summary)
    order = CELL_ORDER.index(cell) if cell in CELL_ORDER else len(CELL_ORDER)
    cams = summary["cameras"] if with_cameras else None
    seeds = _seeds(summary) if with_seeds else None
    return (SCENE_KINDS.index(summary["scene"]), order, cell, cams, seeds)


def _column_title(key: tuple) -> str:
    scene, _, cell, cams, seeds = key
    qualifiers = [f"{cams} cam{'s' if cams > 1 else ''}"] if cams is not None else []
    if seeds is not None:
        qualifiers += [f"seed{'s' if len(seeds) > 1 else ''} {', '.join(map(str, seeds))}"]
    return f"{SCENE_KINDS[scene]} {cell}" + (f" ({', '.join(qualifiers)})" if qualifiers else "")


def _fmt(rate: float | None) -> str:
    return "n/a" if rate is None else f"{rate:.3f}"


def _mean_rate(cell: list[tuple[str, dict]]) -> float | None:
    """The rate of a table cell: its result's, or the mean over its training runs (n/a if one has none)."""
    rates = [s["rate"] for _, s in cell]
    return None if any(r is None for r in rates) else sum(rates) / len(rates)


def _add_run(cell: list[tuple[str, dict]], path: str, s: dict, title: str, runs: bool) -> None:
    """Add a result to a table cell that already holds ``cell``: with ``runs``, another training run
    of the row (:func:`actors.compare_runs.check_table_run`), else a clash. One line naming the file
    and key."""
    from actors.compare_runs import check_table_run  # imported here: actors.compare_runs builds on this module

    if not runs:
        raise EvaluationError(f"{path}: policy {row_label(s)}, {title}: the same cell is already in {cell[0][0]} "
                              "(--runs averages training runs of one row)")
    check_table_run(path, s, title, cell)
    cell.append((path, s))


def table_markdown(results: list[tuple[str, dict]], runs: bool = False) -> str:
    """Markdown of the paper's Table I layout: rows = policies, columns = scene kind x O x G (x
    cameras when the results mix camera counts, x scene seeds when they mix seeds or pool several),
    then the sources and, for one result of one file, its grippers. With ``runs``, results of one
    row and cell from different models are training runs of that row: the cell is the mean of
    their rates, and a table of the runs follows."""
    with_cameras = len({s["cameras"] for _, s in results}) > 1
    seed_sets = {_seeds(s) for _, s in results}
    with_seeds = len(seed_sets) > 1 or any(len(seeds) > 1 for seeds in seed_sets)
    cells: dict[tuple[str, tuple], list[tuple[str, dict]]] = {}
    for path, s in results:
        key = (row_label(s), _column_key(s, with_cameras, with_seeds))
        if key in cells:
            _add_run(cells[key], path, s, _column_title(key[1]), runs)
        else:
            cells[key] = [(path, s)]
    columns = sorted({k for _, k in cells})
    rows = [p for p in ROWS if any(pol == p for pol, _ in cells)]
    lines = ["| policy | " + " | ".join(_column_title(c) for c in columns) + " |"]
    lines.append("|---|" + "---:|" * len(columns))
    for p in rows:
        vals = [_fmt(_mean_rate(cells[(p, c)])) if (p, c) in cells else "–" for c in columns]
        lines.append(f"| {p} | " + " | ".join(vals) + " |")
    odd = []
    for c in columns:
        scenes = {p: len({seed for _, s in cells[(p, c)] for seed in s["scene_seeds"]})
                  for p in rows if (p, c) in cells}
        counts = list(scenes.values())
        usual = max(counts, key=counts.count)
        if len(set(counts)) > 1:
            other = ", ".join(f"{p} {n}" for p, n in scenes.items() if n != usual)
            odd.append(f"{_column_title(c)}: {other} (the other rows {usual})")
    if odd:
        lines += ["", "Rows on another number of scenes than the rest of their column (`evaluate compare` pairs "
                  "two rows on the scenes both ran): " + "; ".join(odd) + "."]
    several = {k: v for k, v in cells.items() if len(v) > 1}
    if several:
        lines += ["", "Cells of several training runs: the mean of the runs' rates (each run's rate over its scenes).",
                  "", "| policy | column | runs | rate of each run | mean |", "|---|---|---:|---|---:|"]
        for (p, c), cell in sorted(several.items(), key=lambda kv: (ROWS.index(kv[0][0]), kv[0][1])):
            each = " / ".join(_fmt(s["rate"]) for _, s in cell)
            lines.append(f"| {p} | {_column_title(c)} | {len(cell)} | {each} | {_fmt(_mean_rate(cell))} |")
    lines += [
        "",
        "Success rate = successes / attempts (one attempt = one grasp; success = exactly one target lifted "
        "and no obstacle); per-gripper policies: mean of the per-gripper rates; adagrasp: over all attempts.",
        "",
        "| source | policy | scene | objects | grippers | cameras | episodes | attempts | successes | seed "
        "| checkpoint |",
        "|---|---|---|---|---|---:|---:|---:|---:|---:|---|",
    ]
    for path, s in results:
        lines.append(
            f"| {path} | {row_label(s)} | {s['scene']} | {s['objects']} | {s['grippers']} | {s['cameras']} | "
            f"{s['episodes']} | {s['average']['attempts']} | {s['average']['successes']} | "
            f"{', '.join(map(str, _seeds(s)))} | {s.get('checkpoint') or '–'} |"
        )
    if len(results) == 1 and "pooled_from" not in results[0][1]:
        s = results[0][1]
        head = "chosen attempts" if s["policy"] == "adagrasp" else "attempts"
        lines += [
            "",
            f"| gripper | {head} | successes | rate | " + " | ".join(FAILURE_MODES) + " |",
            "|---|---:|---:|---:|" + "---:|" * len(FAILURE_MODES),
        ]
        for name, v in s["per_gripper"].items():
            failures = v.get("failures")  # result files written before failure modes were recorded lack it
            counts = [str(failures[m]) if failures else "–" for m in FAILURE_MODES]
            lines.append(f"| {name} | {v['attempts']} | {v['successes']} | {_fmt(v['rate'])} | " + " | ".join(counts) + " |")
    return "\n".join(lines) + "\n"


_REQUIRED = ("format", "policy", "scene", "objects", "objects_label", "grippers_label", "grippers", "cameras", "rate",
             "episodes", "seed", "scene_seeds", "average", "per_gripper", "episode_results")

_TYPES = {
    "rate": ((int, float), "a number"), "episodes": (int, "an integer"), "cameras": (int, "an integer"),
    "average": (dict, "an object"), "per_gripper": (dict, "an object"), "scene_seeds": (list, "a list"),
    "episode_results": (list, "a list"),
}
"""Keys of a result whose value a reader computes with: the JSON type each must have, in words."""


def read_json(path: str | Path):
    """The parsed JSON of the file ``path``; one line naming the file when it is missing or not JSON."""
    path = Path(path)
    if not path.is_file():
        raise EvaluationError(f"{path}: file not found")
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise EvaluationError(f"{path}: not valid JSON ({' '.join(str(e).split())})") from None


def read_result(path: str | Path) -> dict:
    """A result JSON written by ``evaluate --json``; raises one line naming the file and the key."""
    data = read_json(path)
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        got = data.get("format") if isinstance(data, dict) else type(data).__name__
        raise EvaluationError(f"{path}: format: expected {FORMAT!r}, got {got!r}")
    for key in _REQUIRED:
        if key not in data:
            raise EvaluationError(f"{path}: {key}: missing")
    for key, (types, words) in _TYPES.items():
        if isinstance(data[key], bool) or not isinstance(data[key], types):
            raise EvaluationError(f"{path}: {key}: expected {words}, got {data[key]!r:.60}")
    if data["policy"] not in POLICIES:
        raise EvaluationError(f"{path}: policy: expected one of {list(POLICIES)}, got {data['policy']!r}")
    if data["scene"] not in SCENE_KINDS:
        raise EvaluationError(f"{path}: scene: expected one of {list(SCENE_KINDS)}, got {data['scene']!r}")
    for key in ("objects", "grippers"):
        if not isinstance(data[key], str):
            raise EvaluationError(f"{path}: {key}: expected the selection as text, got {data[key]!r:.60}")
    if not isinstance(data.get("checkpoint_sha256"), (str, type(None))):
        raise EvaluationError(f"{path}: checkpoint_sha256: expected a hex digest, got {data['checkpoint_sha256']!r:.60}")
    if row_label(data) not in ROWS:
        raise EvaluationError(f"{path}: opening_rule: {data.get('opening_rule')!r} is not a rule {data['policy']} "
                              f"results are written with")
    if not math.isfinite(data["rate"]):
        raise EvaluationError(f"{path}: rate: expected a finite number, got {data['rate']!r}")
    counted = [("average", data["average"])] + [(f"per_gripper.{k}", v) for k, v in data["per_gripper"].items()]
    for where, entry in counted:
        for key in ("attempts", "successes"):
            value = entry.get(key) if isinstance(entry, dict) else None
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise EvaluationError(f"{path}: {where}.{key}: expected a count, got {value!r:.60}")
        rate = entry.get("rate")
        if isinstance(rate, bool) or not isinstance(rate, (int, float, type(None))) or "rate" not in entry:
            raise EvaluationError(f"{path}: {where}.rate: expected a number or null, got {rate!r:.60}")
    for n, e in enumerate(data["episode_results"]):
        if not isinstance(e, dict):
            raise EvaluationError(f"{path}: episode_results[{n}]: expected an object, got {e!r:.60}")
        if isinstance(e.get("scene_seed"), bool) or not isinstance(e.get("scene_seed"), int):
            raise EvaluationError(f"{path}: episode_results[{n}]: scene_seed: missing or not an integer")
        if "objects" not in e:
            raise EvaluationError(f"{path}: episode_results[{n}]: objects: missing")
    return data


def _write_atomic(path: str | Path, text: str) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_json(path: str | Path, record) -> None:
    """``record`` as the project's JSON files are written (indent 1, a final newline), atomically."""
    _write_atomic(path, json.dumps(finite_json(record), indent=1) + "\n")


def check_output_path(flag: str, path: str | None, inputs=()) -> None:
    """Raise one line when ``path`` (an output of ``flag``) cannot be written, or is one of the
    command's ``inputs`` (paths; each may be a comma-separated list), before any work is done."""
    if path is None:
        return
    target = Path(path)
    if target.is_dir():
        raise EvaluationError(f"{flag} {path}: is a directory")
    read = {Path(p.strip()).resolve() for group in inputs if group for p in str(group).split(",") if p.strip()}
    if target.resolve() in read:
        raise EvaluationError(f"{flag} {path}: is one of this command's input files; it would be overwritten")
    folder = next((p for p in [target.parent, *target.parent.parents] if p.exists()), Path("."))
    if not folder.is_dir() or not os.access(folder, os.W_OK | os.X_OK):
        raise EvaluationError(f"{flag} {path}: {folder} is not a writable directory")


# --------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------


def plan_from_argv(argv: list[str]) -> EvalPlan:
    """The validated :class:`EvalPlan` of an ``evaluate`` command line (nothing runs yet)."""
    return make_plan(_parser().parse_args(argv))


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="python -m launcher evaluate",
        description="Evaluate one policy on one (scene, objects, grippers) cell with the paper's protocol; "
        "'evaluate table RESULT.json ... --md OUT' merges results into the paper's Table I; "
        "'evaluate compare A.json B.json' compares two results on the scenes they share; "
        "'evaluate runs --a RUN --a RUN --b RUN --b RUN' compares two rows across training runs.",
    )
    ap.add_argument("--checkpoint", default=None, help="model checkpoint (learned policies only)")
    ap.add_argument("--scene", choices=SCENE_KINDS, required=True)
    ap.add_argument("--objects", required=True, help="object set: train | test | ycb | household | ...")
    ap.add_argument("--grippers", required=True, help="train | test | NAME,NAME,... (names or spec YAML paths)")
    ap.add_argument("--policy", choices=POLICIES, required=True)
    ap.add_argument("--cameras", type=int, default=None,
                    help="cameras fused into the TSDF, 1-4 (default: the config's sim.cameras)")
    ap.add_argument("--episodes", type=int, required=True, help="episodes per gripper (adagrasp: in all)")
    ap.add_argument("--actors", type=int, default=1, help="Ray actors (1 = this process, no Ray)")
    ap.add_argument("--address", default=None, help="Ray cluster address (default: RAY_ADDRESS if set, else a local Ray)")
    ap.add_argument("--device", choices=("cpu", "cuda"), default="cpu",
                    help="torch device of the network (learned policies; Ray actors share one GPU)")
    ap.add_argument("--seed", type=int, default=0, help="root seed of the scene and policy seeds")
    ap.add_argument("--scale", type=float, default=1.0, help="global gripper scale")
    ap.add_argument("--config", default="default", help="evaluation config: default | paper | YAML path")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override, repeatable")
    ap.add_argument("--calibration", default=None, metavar="RESULT.json",
                    help="adagrasp: calibrate each gripper's scores with its trials in this fix-gripper result")
    ap.add_argument("--json", default=None, help="write every number here")
    ap.add_argument("--md", default=None, help="write the Markdown table here")
    ap.add_argument("--quiet", action="store_true", help="no progress lines")
    return ap


def _table_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="python -m launcher evaluate table", description="Merge evaluation results into the paper's Table I."
    )
    ap.add_argument("results", nargs="+",
                    help="result JSON files written by evaluate --json; A.json,B.json,... is one model's results "
                         "at other scene seeds, read as one result over all their scenes")
    ap.add_argument("--runs", action="store_true",
                    help="results of one row and cell from different models are training runs of that row: "
                         "the cell shows the mean of their rates (they must share their scenes)")
    ap.add_argument("--md", default=None, help="write the Markdown here (default: print it)")
    return ap


def evaluate(argv: list[str]) -> dict:
    """Parse ``argv``, run the evaluation, write --json / --md; returns the summary."""
    args = _parser().parse_args(argv)
    check_output_path("--json", args.json, [args.checkpoint, args.calibration])
    check_output_path("--md", args.md, [args.checkpoint, args.calibration, args.json])
    t0 = time.perf_counter()
    plan = make_plan(args)
    results = run_units(plan, plan.units(), actors=args.actors, address=args.address, quiet=args.quiet)
    extra = {
        "checkpoint": args.checkpoint,
        "checkpoint_variant": plan.model_cfg.model.variant if plan.model_cfg is not None else None,
        "checkpoint_version": plan.model_version if plan.model_cfg is not None else None,
        "checkpoint_sha256": plan.model_sha256,
        "opening_rule": policy_opening_rule(args.policy),
        "calibration": plan.calibration.to_dict() if plan.calibration is not None else None,
        "actors": args.actors,
        "wall_s": time.perf_counter() - t0,
    }
    summary = summarise(plan, results, argv, args.grippers, extra)
    if args.json:
        write_json(args.json, summary)
    if args.md:
        _write_atomic(args.md, table_markdown([(args.json or "(this run)", summary)]))
    return summary


def scene_object_notes(results: list[tuple[str, dict]]) -> list[str]:
    """One ``note:`` line per result and scene seed whose objects differ from the objects most
    results hold at that seed (same scene kind and object set): the table keeps such a scene, while
    ``evaluate compare`` and ``evaluate runs`` refuse it (or leave it out)."""
    held: dict[tuple, dict[str, list[str]]] = {}
    for path, s in results:
        for e in s["episode_results"]:
            objects = json.dumps(e["objects"])
            paths = held.setdefault((s["scene"], s["objects"], e["scene_seed"]), {}).setdefault(objects, [])
            if path not in paths:
                paths.append(path)
    notes = []
    for (scene, objects, seed), by_objects in held.items():
        usual = max(by_objects, key=lambda k: len(by_objects[k]))
        for other, paths in by_objects.items():
            if other != usual:
                notes += [f"note: {p}: scene_seed {seed} ({scene}, {objects}): other objects than in "
                          f"{by_objects[usual][0]}; the table keeps the scene, evaluate compare and evaluate runs "
                          "refuse it (runs --drop-mismatched-scenes leaves it out)" for p in paths]
    return notes


def table(argv: list[str]) -> str:
    """``evaluate table``: merge result files; writes the Markdown to --md or prints it; returns it.
    Scenes of other objects at one seed (:func:`scene_object_notes`) are named on stderr."""
    args = _table_parser().parse_args(argv)
    check_output_path("--md", args.md, args.results)
    from actors.compare_runs import pool_result  # imported here: actors.compare_runs builds on this module

    results = []
    for arg in args.results:
        paths = arg.split(",")
        if any(not p for p in paths):
            raise EvaluationError(f"{arg}: expected RESULT.json or RESULT.json,RESULT.json,... "
                                  "(one model's scene seeds)")
        results.append((" + ".join(paths), pool_result(paths) if len(paths) > 1 else read_result(arg)))
    markdown = table_markdown(results, runs=args.runs)
    for note in scene_object_notes(results):
        print(note, file=sys.stderr)
    if args.md:
        _write_atomic(args.md, markdown)
    else:
        print(markdown, end="")
    return markdown


EVALUATE_COMMANDS = ("table", "compare", "runs", "holm")
"""``evaluate`` subcommands; without one, ``evaluate`` runs an evaluation."""


def cli(argv: list[str]) -> int:
    if argv and not argv[0].startswith("-") and argv[0] not in EVALUATE_COMMANDS:
        print(f"evaluate: error: {argv[0]!r}: not a command (one of {', '.join(EVALUATE_COMMANDS)}; an evaluation "
              "starts with its flags)", file=sys.stderr)
        return 2
    try:
        if argv and argv[0] == "table":
            table(argv[1:])
            return 0
        if argv and argv[0] == "compare":
            from actors.compare import compare_cli  # imported here: actors.compare builds on this module

            compare_cli(argv[1:])
            return 0
        if argv and argv[0] == "runs":
            from actors.compare_runs import runs_cli  # imported here: actors.compare_runs builds on this module

            runs_cli(argv[1:])
            return 0
        if argv and argv[0] == "holm":
            from actors.holm import holm_cli  # imported here: actors.holm builds on this module

            holm_cli(argv[1:])
            return 0
        summary = evaluate(argv)
    except (ValueError, SimulationError) as e:
        print(f"evaluate: error: {e}", file=sys.stderr)
        return 2
    per = ", ".join(
        f"{n} {v['successes']}/{v['attempts']}" for n, v in summary["per_gripper"].items() if v["attempts"]
    )
    print(
        f"evaluate: {row_label(summary)} on {summary['scene']} {summary['objects_label']}/{summary['grippers_label']} "
        f"({summary['cameras']} camera(s), {summary['episodes']} episodes, seed {summary['seed']}): "
        f"rate {_fmt(summary['rate'])} ({summary['average']['rate_definition']}; "
        f"{summary['average']['successes']}/{summary['average']['attempts']} grasps); "
        f"{per}; {summary['wall_s']:.1f} s"
    )
    return 0
