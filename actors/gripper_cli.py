"""``python -m launcher grippers ...``: list, check and generate grippers.

Usage::

    python -m launcher grippers list [--json] [--split train|test] [--family 2-finger|3-finger|multi]
    python -m launcher grippers check NAME_OR_SPEC [--out DIR] [--json OUT] [--config default]
    python -m launcher grippers generate --count 1000 [--start 0] [--json OUT] [--no-physics] [--pool-yaml OUT]

``check`` loads the gripper, moves it through openings 0..1 in PyBullet and reports the finger
aperture at each (it must grow monotonically), checks that coupled joints follow their drivers in
free air (and reports how far from it they are while holding the lift-test objects), checks the
kinematics at scales 0.8 and 1.2, renders the open and closed encodings to PNG
(marching-cubes iso-surface and a slice), runs lift tests on a box and a cylinder, and prints
pass/fail with reasons. Exit code 0 = pass, 1 = fail, 2 = the spec itself is broken (one line
naming the file and the field).

``generate`` builds ``count`` procedural grippers (families in turn, seeds from ``start``), runs
the same check on each (without the PNGs) and reports the pass rate and every rejection reason;
``--pool-yaml`` writes the seeds that passed in the form of catalog.yaml's ``pool`` section.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from common.files import atomic_write_text, finite_json

CHECK_OPENINGS = 11
"""Openings visited from 0 to 1 by the check."""
CHECK_SCALES = (0.8, 1.2)
"""Global scales whose kinematics the check verifies besides 1.0."""
LIFT_OFFSETS = ((0.0, 0.0), (0.005, 0.005), (-0.005, 0.003))
"""Object placements (m from the TCP axis) of the lift tests; physics makes single trials noisy."""
LIFT_MIN_SUCCESSES = 2
"""A lift test passes when at least this many placements are lifted."""
LIFT_SIZE_FRACTION = 0.7
"""Lift-test objects are this fraction of the open aperture wide (clipped to 2.5-5 cm)."""
SETTLE_STEPS = 120
"""Simulation steps allowed for the joints to reach each opening (0.5 s at 240 Hz)."""


@dataclass
class CheckReport:
    """Result of checking one gripper."""

    name: str
    family: str
    split: str
    passed: bool = False
    reasons: list[str] = field(default_factory=list)
    apertures_fk: list[float] = field(default_factory=list)
    """Aperture (m) from forward kinematics at each checked opening."""
    apertures_sim: list[float] = field(default_factory=list)
    """Aperture (m) measured in PyBullet after driving to each checked opening."""
    coupling_error: float = 0.0
    """Largest |q_coupled - Coupling.value(q_driver, scale)| seen in PyBullet in free air (m or rad)."""
    coupling_error_held: float = 0.0
    """The same, the largest when closing on a lift-test object ended: how far the load bends the
    linkage away from its kinematics (reported, not a pass criterion)."""
    lift: dict = field(default_factory=dict)
    """Lift test per object: {"box": {...}, "cylinder": {...}}."""
    images: list[str] = field(default_factory=list)
    seconds: float = 0.0


def _summary(spec) -> dict:
    from common.gripper import GripperModel

    model = GripperModel(spec)
    return {
        "name": spec.name,
        "family": spec.family,
        "split": spec.split,
        "drive_joints": len(spec.drive_joints),
        "coupled_joints": len(spec.couplings),
        "aperture_min_m": round(model.aperture(0.0), 4),
        "aperture_max_m": round(model.aperture(1.0), 4),
        "tcp_estimated": spec.tcp_estimated,
        "description": spec.description,
    }


def _sim_sweep(spec, scale: float, report: CheckReport) -> None:
    """Drive through the openings in PyBullet; record apertures and coupling errors."""
    import pybullet as p

    from actors.bullet_gripper import BulletGripper
    from common.geometry import Transform

    client = p.connect(p.DIRECT)
    try:
        p.setGravity(0, 0, -9.81, physicsClientId=client)
        g = BulletGripper(client, spec, scale)
        g.reset(Transform.from_yaw(0.0, (0.0, 0.0, 1.0)), 0.0)
        err = 0.0
        for o in np.linspace(0.0, 1.0, CHECK_OPENINGS):
            g.set_opening_target(float(o))
            for _ in range(SETTLE_STEPS):
                g.step()
                p.stepSimulation(physicsClientId=client)
            err = max(err, g.coupling_error())
            report.apertures_sim.append(round(g.finger_aperture(), 5))
        report.coupling_error = float(err)
        g.remove()
    finally:
        p.disconnect(physicsClientId=client)


def _monotonic(ap: list[float], scale: float) -> str:
    from common.gripper import CLOSED_APERTURE

    floor = CLOSED_APERTURE * scale
    for i in range(1, len(ap)):
        if max(ap[i], floor) < max(ap[i - 1], floor) - 2e-3 * scale:
            return f"aperture in simulation falls from {ap[i - 1]:.4f} to {ap[i]:.4f} m between openings {i - 1} and {i}"
    return ""


def _render(spec, out: Path, grid) -> list[str]:
    """PNG of the open and closed encodings: iso-surfaces (marching cubes) and an x-z slice."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection
    from skimage.measure import marching_cubes

    from common.gripper_encoding import GripperEncoder

    enc = GripperEncoder(grid, disk=False).encode(spec, 1.0, (1.0,))[0]
    fig = plt.figure(figsize=(12, 6))
    for col, (title, vol) in enumerate((("open (opening 1)", enc[0]), ("closed (opening 0)", enc[1]))):
        ax = fig.add_subplot(2, 2, col + 1, projection="3d")
        if vol.min() < 0 < vol.max():
            verts, faces, _, _ = marching_cubes(vol, 0.0, spacing=(grid.voxel_size,) * 3)
            ax.add_collection3d(Poly3DCollection(verts[faces], alpha=0.8, facecolor="0.6", edgecolor="0.3", linewidth=0.1))
        ext = np.array(grid.shape) * grid.voxel_size
        ax.set_xlim(0, ext[0]), ax.set_ylim(0, ext[1]), ax.set_zlim(0, ext[2])
        ax.set_box_aspect(ext)
        ax.set_title(f"{spec.name}: {title}")
        ax2 = fig.add_subplot(2, 2, col + 3)
        im = ax2.imshow(vol[:, vol.shape[1] // 2, :].T, origin="lower", cmap="RdBu", vmin=-1, vmax=1)
        ax2.set_title("TSDF slice y = 0 (x right, z up)")
        fig.colorbar(im, ax=ax2, fraction=0.03)
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{spec.name}_encoding.png"
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return [str(path)]


def check_gripper(spec, out: Path | None = None, grid=None, physics: bool = True) -> CheckReport:
    """Run every check on ``spec``; ``out`` gets the PNGs (none if None)."""
    from common.gripper import GripperSpecError, check_kinematics

    t0 = time.perf_counter()
    r = CheckReport(spec.name, spec.family, spec.split)
    try:
        r.apertures_fk = [round(a, 5) for a in check_kinematics(spec, 1.0, CHECK_OPENINGS)]
        for s in CHECK_SCALES:
            check_kinematics(spec, s, CHECK_OPENINGS)
    except GripperSpecError as e:
        r.reasons.append(str(e))
    if physics and not r.reasons:
        try:
            _physics_checks(spec, r)
        except GripperSpecError as e:  # PyBullet cannot load or drive the processed URDF
            r.reasons.append(str(e))
    if out is not None and not r.reasons:
        r.images = _render(spec, out, grid)
    r.passed = not r.reasons
    r.seconds = round(time.perf_counter() - t0, 3)
    return r


def _physics_checks(spec, r: CheckReport) -> None:
    """The simulated aperture sweep and lift tests of :func:`check_gripper`; reasons go into ``r``."""
    from actors.bullet_gripper import lift_test

    _sim_sweep(spec, 1.0, r)
    bad = _monotonic(r.apertures_sim, 1.0)
    if bad:
        r.reasons.append(bad)
    if r.apertures_sim[-1] - r.apertures_sim[0] < 0.005:
        r.reasons.append(f"opening does not move the fingers in simulation (aperture {r.apertures_sim[0]:.4f} -> {r.apertures_sim[-1]:.4f} m)")
    if r.coupling_error > 0.02:
        r.reasons.append(f"couplings do not follow their drivers (error {r.coupling_error:.4f})")
    size = float(np.clip(LIFT_SIZE_FRACTION * r.apertures_fk[-1], 0.025, 0.05))
    for shape in ("box", "cylinder"):
        results = [lift_test(spec, 1.0, shape, size, offset=off) for off in LIFT_OFFSETS]
        wins = sum(x.success for x in results)
        ok = wins >= LIFT_MIN_SUCCESSES
        r.lift[shape] = {"size_m": round(size, 4), "success": ok, "successes": wins, "trials": len(results),
                         "rise_m": [round(x.object_rise, 4) for x in results],
                         "coupling_error_held": [round(x.coupling_error_held, 4) for x in results]}
        r.coupling_error_held = max(r.coupling_error_held, *(x.coupling_error_held for x in results))
        if not ok:
            r.reasons.append(f"lift test: {shape} lifted in {wins} of {len(results)} placements "
                             f"({'; '.join(x.reason for x in results if x.reason)})")


def _cmd_list(args) -> int:
    from common.gripper import list_grippers

    rows = [_summary(s) for s in list_grippers(split=args.split, family=args.family)]
    if args.json:
        print(json.dumps(finite_json(rows), indent=1))
        return 0
    print(f"{'name':22s} {'family':9s} {'split':5s} {'drive':>5s} {'coupled':>7s} {'aperture (m)':>15s}  description")
    for r in rows:
        ap = f"{r['aperture_min_m']:.3f}-{r['aperture_max_m']:.3f}"
        print(f"{r['name']:22s} {r['family']:9s} {r['split']:5s} {r['drive_joints']:5d} {r['coupled_joints']:7d} "
              f"{ap:>15s}  {r['description'][:70]}")
    return 0


def _cmd_check(args) -> int:
    from common.config import ConfigError, load_config
    from common.gripper import GripperSpecError, get_gripper

    try:
        spec = get_gripper(args.gripper)
        grid = load_config(args.config).gripper_grid
    except (GripperSpecError, ConfigError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    r = check_gripper(spec, Path(args.out) if args.out else None, grid)
    print(f"{spec.name}: {'PASS' if r.passed else 'FAIL'} ({r.seconds:.1f} s)")
    print("  aperture (FK, m):  " + " ".join(f"{a:.3f}" for a in r.apertures_fk))
    if r.apertures_sim:
        print("  aperture (sim, m): " + " ".join(f"{a:.3f}" for a in r.apertures_sim))
        print(f"  coupling error: {r.coupling_error:.5f} in free air, {r.coupling_error_held:.5f} holding the lift-test objects")
    for shape, res in r.lift.items():
        print(f"  lift {shape} ({res['size_m'] * 100:.1f} cm): {'ok' if res['success'] else 'FAILED'} "
              f"({res['successes']} of {res['trials']} placements lifted)")
    for img in r.images:
        print(f"  image: {img}")
    for reason in r.reasons:
        print(f"  reason: {reason}")
    if args.json:
        atomic_write_text(Path(args.json), json.dumps(finite_json(asdict(r)), indent=1))
    return 0 if r.passed else 1


def _cmd_generate(args) -> int:
    from common.gripper import GripperSpecError
    from common.gripper_procedural import FAMILY_NAMES, generate

    t0 = time.perf_counter()
    results = []
    for i in range(args.start, args.start + args.count):
        family, seed = FAMILY_NAMES[i % len(FAMILY_NAMES)], i // len(FAMILY_NAMES)
        name = f"{family}-{seed}"
        try:
            spec = generate(family, seed).spec
        except GripperSpecError as e:
            results.append({"name": name, "family": family, "passed": False, "reasons": [str(e)]})
            continue
        r = check_gripper(spec, physics=not args.no_physics)
        results.append({"name": name, "family": family, "passed": r.passed, "reasons": r.reasons})
        if not args.quiet and not r.passed:
            print(f"rejected {name}: {'; '.join(r.reasons)}", file=sys.stderr)
    per_family = {
        f: {"generated": sum(r["family"] == f for r in results), "passed": sum(r["family"] == f and r["passed"] for r in results)}
        for f in FAMILY_NAMES
    }
    passed = sum(r["passed"] for r in results)
    summary = {
        "generated": len(results),
        "passed": passed,
        "pass_rate": round(passed / max(len(results), 1), 4),
        "physics": not args.no_physics,
        "per_family": per_family,
        "seconds": round(time.perf_counter() - t0, 1),
    }
    print(json.dumps(finite_json(summary)))
    if args.json:
        atomic_write_text(Path(args.json), json.dumps(finite_json({"summary": summary, "grippers": results}), indent=1))
    if args.pool_yaml:
        atomic_write_text(Path(args.pool_yaml), _pool_yaml(results))
    return 0


def _pool_yaml(results: list[dict]) -> str:
    """The passed grippers of a ``generate`` run as catalog.yaml's ``pool`` section, seeds sorted."""
    import yaml

    from common.gripper_procedural import FAMILY_NAMES

    seeds: dict[str, list[int]] = {f: [] for f in FAMILY_NAMES}
    for r in results:
        if r["passed"]:
            seeds[r["family"]].append(int(r["name"].rsplit("-", 1)[1]))
    pool = {f: sorted(v) for f, v in seeds.items() if v}
    return yaml.safe_dump({"pool": pool}, default_flow_style=None, width=100, sort_keys=False)


def cli(argv: list[str]) -> int:
    """Entry point of ``python -m launcher grippers``."""
    ap = argparse.ArgumentParser(prog="python -m launcher grippers", description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    p_list = sub.add_parser("list", help="every registered gripper and the procedural catalogue")
    p_list.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p_list.add_argument("--split", choices=("train", "test"))
    p_list.add_argument("--family", choices=("2-finger", "3-finger", "multi"))
    p_check = sub.add_parser("check", help="load, sweep openings, couplings, encodings, lift tests")
    p_check.add_argument("gripper", help="registered name, <family>-<seed>, or a spec YAML path")
    p_check.add_argument("--out", help="folder for the encoding PNGs")
    p_check.add_argument("--json", help="write the report as JSON here")
    p_check.add_argument("--config", default="default", help="config giving the gripper grid (default, paper or a path)")
    p_gen = sub.add_parser("generate", help="generate and check many procedural grippers; report the pass rate")
    p_gen.add_argument("--count", type=int, default=100)
    p_gen.add_argument("--start", type=int, default=0)
    p_gen.add_argument("--json", help="write the summary and every result here")
    p_gen.add_argument("--no-physics", action="store_true", help="kinematic checks only")
    p_gen.add_argument("--quiet", action="store_true", help="do not print rejections")
    p_gen.add_argument("--pool-yaml", help="write the passed seeds here as catalog.yaml's pool section")
    args = ap.parse_args(argv)
    if args.cmd in ("check", "generate"):
        from actors.evaluate import EvaluationError, check_output_path

        try:  # outputs are written after the whole run: refuse one that cannot be written first
            if args.cmd == "generate" and args.count < 1:
                raise EvaluationError(f"--count {args.count}: expected >= 1")
            if args.cmd == "generate" and args.start < 0:
                raise EvaluationError(f"--start {args.start}: expected >= 0")
            check_output_path("--json", args.json)
            check_output_path("--pool-yaml", getattr(args, "pool_yaml", None))
        except EvaluationError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
    return {"list": _cmd_list, "check": _cmd_check, "generate": _cmd_generate}[args.cmd](args)
