"""``python -m launcher rollout``: run grasp episodes with one gripper and one policy, print a summary.

Usage::

    python -m launcher rollout --scene single --objects train --gripper parallel_jaw-0 \\
        --policy heuristic --episodes 100 --seed 0 --cameras 1 --json out.json --png figs/
    python -m launcher rollout --policy checkpoint:runs/x/latest.pt --mode fix-config --gripper wsg_50 ...

Episode e runs on the scene seed ``SeedSequence([seed, e])`` (reproducible one by one). The
candidate openings are ``grippers.eval_openings``. ``--json`` writes
{"scene", "objects", "gripper", "policy", "episodes", "trials", "successes", "success_rate",
"median_trial_s"} (and "checkpoint", "mode" for a checkpoint policy); ``--png`` draws, for the first ``--png-trials`` trials, the heightmap with the
grasp (a line across the jaws at yaw theta, as long as the opening's finger aperture) and the outcome.
Bad input ends with one line on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from actors.grasp import TrialResult, run_episode
from actors.policies import Policy, make_policy
from actors.simulation import SCENE_KINDS, Simulation, SimulationError
from common.config import Config, load_config, set_flags
from common.files import finite_json
from common.gripper import check_scale, get_gripper


def episode_seed(seed: int, episode: int) -> int:
    """Scene seed of episode ``episode`` of a run with root ``seed``."""
    return int(np.random.SeedSequence([int(seed), int(episode)]).generate_state(1)[0])


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m launcher rollout", description="Run grasp episodes and summarise them.")
    ap.add_argument("--scene", choices=SCENE_KINDS, default=None, help="scene kind (default: sim.scene)")
    ap.add_argument("--objects", default=None, help="object set (default: sim.objects)")
    ap.add_argument("--gripper", required=True, help="gripper name or spec YAML")
    ap.add_argument("--scale", type=float, default=1.0, help="global gripper scale")
    ap.add_argument("--policy", default="heuristic", help="random | heuristic | checkpoint:PATH")
    ap.add_argument(
        "--mode", default=None, help="checkpoint policies only: fix-config | fix-gripper (default) | adagrasp"
    )
    ap.add_argument("--episodes", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cameras", type=int, default=None, help="1 (top-down) or 2-4 (ring); default sim.cameras")
    ap.add_argument("--config", default="default", help="config name (default, paper) or YAML path")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override, repeatable")
    ap.add_argument("--json", default=None, help="write the summary JSON here")
    ap.add_argument("--png", default=None, help="folder for pictures of the first trials")
    ap.add_argument("--png-trials", type=int, default=8, help="number of trials drawn with --png")
    ap.add_argument("--gui", action="store_true", help="open a PyBullet window")
    return ap


def _config(args) -> Config:
    cfg = load_config(args.config, list(args.set))
    set_flags(cfg, (("--scene", "sim.scene", args.scene), ("--objects", "sim.objects", args.objects),
                    ("--cameras", "sim.cameras", args.cameras)))
    return cfg


def _policy(args, cfg: Config, spec, openings: tuple[float, ...]) -> Policy:
    """The policy of ``--policy``; a checkpoint policy gets ``--mode`` and the gripper's encoding."""
    if not args.policy.startswith("checkpoint:"):
        if args.mode is not None:
            raise ValueError(f"--mode {args.mode}: only checkpoint policies take a mode, not {args.policy!r}")
        return make_policy(args.policy, cfg)
    from common.gripper_encoding import GripperEncoder, gripper_key

    encoding = GripperEncoder(cfg.gripper_grid).encode(spec, args.scale, openings)
    key = gripper_key(spec.name, args.scale, openings)
    return make_policy(args.policy, cfg, mode=args.mode or "fix-gripper", grippers=[(key, encoding)])


def draw_trial(path: Path, sim: Simulation, result: TrialResult, aperture: float, title: str) -> None:
    """Save a PNG of the trial's heightmap (x right, y up) with the grasp drawn across the jaws
    (green: success, red: failure) and the obstacle cells outlined in red."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    grid = sim.grid
    hm = result.observation.heightmap
    fig, ax = plt.subplots(figsize=(4.2, 4.2), dpi=100)
    im = ax.imshow(hm.T, origin="lower", cmap="viridis", extent=(*grid.x_range, *grid.y_range), vmin=0.0)
    fig.colorbar(im, ax=ax, fraction=0.046, label="height (m)")
    obstacle = result.observation.obstacle.max(axis=2) > 0.5
    if obstacle.any():
        xs = np.linspace(grid.x_range[0], grid.x_range[1], hm.shape[0])
        ys = np.linspace(grid.y_range[0], grid.y_range[1], hm.shape[1])
        ax.contour(xs, ys, obstacle.T.astype(float), levels=[0.5], colors="red", linewidths=1.0)
    x, y, _ = result.outcome.grasp_position
    d = np.array([np.cos(result.outcome.yaw), np.sin(result.outcome.yaw)]) * aperture / 2
    colour = "lime" if result.outcome.success else "red"
    ax.plot([x - d[0], x + d[0]], [y - d[1], y + d[1]], color=colour, lw=2.5)
    ax.plot([x - d[0], x + d[0]], [y - d[1], y + d[1]], "o", color=colour, ms=4)
    ax.set_title(title, fontsize=8)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def draw_scores(png_dir: Path, stem: str, policy: Policy, result: TrialResult, cfg: Config,
                openings: tuple[float, ...], title: str) -> list[Path]:
    """For a learned policy, save STEM_scores.png (the paper's score-map figure for the chosen
    gripper: three rotations per opening, best rotation framed, max score per map) and
    STEM_grasp.png (the chosen grasp with the gripper footprint over the heightmap); returns the
    paths (none for scripted policies)."""
    from common.policy import LearnedPolicy, valid_cells
    from common.viz import grasp_image, save_png, score_maps_image

    if not isinstance(policy, LearnedPolicy) or policy.last_probs is None or policy.last_choice is None:
        return []
    obs, choice = result.observation, policy.last_choice
    _, _, _, s, g = choice.action
    shown = openings if policy.last_probs.shape[1] == len(openings) else (openings[s],)
    mask = valid_cells(obs, cfg, policy.region)
    maps = score_maps_image(policy.last_probs[g], obs.heightmap, cfg, shown, mask=mask, title=title)
    grasp = grasp_image(obs.heightmap, cfg, choice, policy.grippers[g][1][s], title=title)
    return [save_png(maps, png_dir / f"{stem}_scores.png"), save_png(grasp, png_dir / f"{stem}_grasp.png")]


def run(args) -> dict:
    """Run the episodes of ``args`` (parsed CLI) and return the summary dict."""
    cfg = _config(args)
    if args.episodes < 1:
        raise ValueError(f"--episodes: expected at least 1, got {args.episodes}")
    check_scale(args.scale, "--scale")
    spec = get_gripper(args.gripper)
    openings = tuple(float(o) for o in cfg.grippers.eval_openings)
    policy = _policy(args, cfg, spec, openings)
    png_dir = Path(args.png) if args.png else None
    if png_dir is not None and png_dir.exists() and not png_dir.is_dir():
        raise ValueError(f"--png {png_dir}: exists and is not a folder")
    from actors.evaluate import check_output_path  # imported here: actors.evaluate builds on this module

    weights = [args.policy[len("checkpoint:"):]] if args.policy.startswith("checkpoint:") else []
    check_output_path("--json", args.json, weights)  # written after the last episode: refused before the first
    if png_dir is not None:
        png_dir.mkdir(parents=True, exist_ok=True)
    trials, successes, times = 0, 0, []
    with Simulation(cfg, seed=args.seed, gui=args.gui) as sim:
        gripper = sim.load_gripper(spec, args.scale)
        apertures = []
        for o in openings:
            gripper.reset(sim.park_pose(), o)
            apertures.append(gripper.finger_aperture())
        sim.park_gripper()
        for e in range(args.episodes):
            seed = episode_seed(args.seed, e)
            for result in run_episode(sim, gripper, policy, openings, cfg.sim.scene, cfg.sim.objects, seed=seed):
                trials += 1
                successes += int(result.outcome.success)
                times.append(result.trial_s)
                if png_dir is not None and trials <= args.png_trials:
                    i, j, k, s = result.action
                    title = (
                        f"ep {e} step {result.step}: {result.outcome.failure or 'success'}  "
                        f"cell ({i},{j}) k={k} opening={openings[s]:.3f}\n"
                        f"{policy.name}, score {result.score:.2f}, {len(result.object_ids)} objects (obstacles outlined red)"
                    )
                    draw_trial(png_dir / f"trial_{trials - 1:03d}.png", sim, result, apertures[s], title)
                    draw_scores(png_dir, f"trial_{trials - 1:03d}", policy, result, cfg, openings, title)
    return {
        "scene": cfg.sim.scene,
        "objects": cfg.sim.objects,
        "gripper": spec.name,
        "policy": policy.name,
        "episodes": int(args.episodes),
        "trials": trials,
        "successes": successes,
        "success_rate": successes / trials,
        "median_trial_s": float(np.median(times)),
        **({"checkpoint": args.policy[len("checkpoint:"):], "mode": args.mode or "fix-gripper"}
           if args.policy.startswith("checkpoint:") else {}),
    }


def cli(argv: list[str]) -> int:
    args = _parser().parse_args(argv)
    t0 = time.perf_counter()
    try:
        summary = run(args)
    except (ValueError, SimulationError) as e:
        print(f"rollout: error: {e}", file=sys.stderr)
        return 2
    print(
        f"rollout: {summary['scene']} scene, objects {summary['objects']}, gripper {summary['gripper']}, "
        f"policy {summary['policy']}: {summary['successes']}/{summary['trials']} grasps succeeded "
        f"({summary['success_rate']:.3f}) over {summary['episodes']} episodes; median trial "
        f"{summary['median_trial_s']:.3f} s; total {time.perf_counter() - t0:.1f} s"
    )
    if args.json:
        out = Path(args.json)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(finite_json(summary), indent=1) + "\n")
    return 0
