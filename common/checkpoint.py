"""Model checkpoints: weights, variant, resolved config, counters, optional optimiser state.

One file written by ``torch.save`` (atomically: a temporary file, then a rename), readable with
``torch.load(path, weights_only=True)``. Keys:

- ``format``: ``adagrasp-scale-checkpoint/1``
- ``model``: the network's state dict (CPU tensors)
- ``variant``: ``model.variant`` of the config (checked against it on load)
- ``config``: the resolved config, :func:`common.config.to_dict`
- ``step``, ``version``: learner steps and weights version; ``epsilon``: exploration at save time or None
- ``optimizer``: optimiser state dict or None; anything else the writer adds is kept as is

Call loop::

    save_checkpoint(run_dir / "checkpoints/latest.pt", model, cfg, step=1200, version=60, epsilon=0.5)
    model, ckpt = load_checkpoint(path)             # eval mode, weights_version = ckpt.version
    model.train(); optimizer.load_state_dict(ckpt.optimizer)
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import torch

from common.config import Config, ConfigError, from_dict, to_dict
from common.network import AdaGraspNet, NetworkConfigError, build_model

FORMAT = "adagrasp-scale-checkpoint/1"
"""Value of the ``format`` key of every checkpoint this module writes and reads."""
_KNOWN = ("format", "model", "variant", "config", "step", "version", "epsilon", "optimizer")


class CheckpointError(ValueError):
    """A checkpoint file is missing, corrupt or inconsistent; the message names the file and the key."""


@dataclass
class Checkpoint:
    """The contents of a checkpoint file."""

    cfg: Config
    """The resolved config the model was built from."""
    model_state: dict
    """Network state dict (CPU tensors)."""
    variant: str
    """Model variant: adagrasp | init-only | scene-only."""
    step: int
    """Learner steps taken when it was written."""
    version: int
    """Weights version (the kernel-cache key of the loaded model)."""
    epsilon: float | None
    """Exploration epsilon when it was written, if recorded."""
    optimizer: dict | None
    """Optimiser state dict, if saved."""
    extra: dict = field(default_factory=dict)
    """Every other key of the file (e.g. the learner's own state)."""

    def model_sha256(self) -> str:
        """:func:`model_sha256` of this checkpoint's network: the same for every file that holds
        these weights for this network (a run's checkpoint and the model exported from it)."""
        return model_sha256(self.cfg, self.model_state)


def save_checkpoint(
    path: str | Path,
    model: AdaGraspNet,
    cfg: Config,
    *,
    step: int = 0,
    version: int = 0,
    epsilon: float | None = None,
    optimizer: torch.optim.Optimizer | dict | None = None,
    extra: dict | None = None,
) -> Path:
    """Write a checkpoint of ``model`` (built from ``cfg``) to ``path`` atomically; returns the path."""
    if model.variant != cfg.model.variant:
        raise CheckpointError(f"{path}: variant: the model is {model.variant!r} but the config says {cfg.model.variant!r}")
    extra = dict(extra or {})
    clash = sorted(set(extra) & set(_KNOWN))
    if clash:
        raise CheckpointError(f"{path}: extra: keys {clash} are reserved")
    if isinstance(optimizer, torch.optim.Optimizer):
        optimizer = optimizer.state_dict()
    state = {
        "format": FORMAT,
        "model": {k: v.detach().to("cpu", copy=True) for k, v in model.state_dict().items()},
        "variant": model.variant,
        "config": to_dict(cfg),
        "step": int(step),
        "version": int(version),
        "epsilon": None if epsilon is None else float(epsilon),
        "optimizer": optimizer,
        **extra,
    }
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    torch.save(state, tmp)
    os.replace(tmp, path)
    return path


SHIPPED_PREFIX = "model:"
"""``model:NAME`` names a checkpoint shipped with the project: assets/models/NAME/checkpoint.pt."""


def shipped_models_dir() -> Path:
    """assets/models of the installed package (trained checkpoints shipped with the project)."""
    return Path(__file__).resolve().parents[1] / "assets" / "models"


def resolve_checkpoint(path: str | Path) -> Path:
    """The file of ``path``, or of a shipped model when ``path`` is ``model:NAME``."""
    text = str(path)
    if not text.startswith(SHIPPED_PREFIX):
        return Path(path)
    name = text[len(SHIPPED_PREFIX):]
    shipped = shipped_models_dir()
    out = shipped / name / "checkpoint.pt"
    if not name or "/" in name or not out.is_file():
        known = sorted(p.parent.name for p in shipped.glob("*/checkpoint.pt"))
        raise CheckpointError(f"{text}: no shipped model of that name (known: {', '.join(known) or 'none'})")
    return out


def checkpoint_origin_file(path: str | Path) -> str:
    """Where ``path`` (a file or ``model:NAME``) is, for a run's provenance record: a shipped model
    as its place inside the package (the same on every machine), any other file as an absolute path."""
    out = resolve_checkpoint(path).resolve()
    if str(path).startswith(SHIPPED_PREFIX):
        return _package_place(out)
    return str(out)


def _package_place(path: Path) -> str:
    """``path`` (inside assets/models) relative to the package root, e.g. assets/models/NAME/checkpoint.pt."""
    return path.relative_to(shipped_models_dir().parents[1]).as_posix()


def portable_init_source(record: dict | None) -> dict | None:
    """A fine-tuning provenance record (``init_weights``, ``file``, ``step``, ``version``) whose
    shipped source (``model:NAME``) is named by its place in the package. Records written before
    that rule, and carried on by ``--resume``, hold the writing machine's absolute path; the name
    alone fixes the place, whether or not the model is still shipped. Other records are returned
    unchanged; None stays None."""
    if not record or not str(record.get("init_weights", "")).startswith(SHIPPED_PREFIX):
        return record
    name = str(record["init_weights"])[len(SHIPPED_PREFIX):]
    return {**record, "file": _package_place(shipped_models_dir() / name / "checkpoint.pt")}


def read_checkpoint(path: str | Path) -> Checkpoint:
    """Read and check a checkpoint file (or ``model:NAME``, a shipped one) without building the model."""
    path = resolve_checkpoint(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint file not found")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises pickle, zip and runtime errors for damaged files
        reason = " ".join(str(e).split())[:200]
        raise CheckpointError(f"{path}: not a readable checkpoint ({type(e).__name__}: {reason})") from None
    if not isinstance(state, dict):
        raise CheckpointError(f"{path}: format: expected a dict, got {type(state).__name__}")
    if state.get("format") != FORMAT:
        raise CheckpointError(f"{path}: format: expected {FORMAT!r}, got {state.get('format')!r}")
    for key in ("model", "variant", "config", "step", "version"):
        if key not in state:
            raise CheckpointError(f"{path}: {key}: missing")
    if not isinstance(state["model"], dict):
        raise CheckpointError(f"{path}: model: expected a state dict")
    try:
        cfg = from_dict(state["config"], source=f"{path}: config")
    except ConfigError as e:
        raise CheckpointError(str(e)) from None
    if state["variant"] != cfg.model.variant:
        raise CheckpointError(
            f"{path}: variant: {state['variant']!r} does not match config model.variant {cfg.model.variant!r}"
        )
    return Checkpoint(
        cfg=cfg,
        model_state=state["model"],
        variant=state["variant"],
        step=int(state["step"]),
        version=int(state["version"]),
        epsilon=state.get("epsilon"),
        optimizer=state.get("optimizer"),
        extra={k: v for k, v in state.items() if k not in _KNOWN},
    )


def inference_config(cfg: Config, scene_chunk: int = 0, decoder_chunk: int = 0) -> Config:
    """``cfg`` with the inference batching ``model.scene_chunk`` / ``model.decoder_chunk`` replaced
    (0 = chosen for the device the model runs on).

    The batching bounds memory and does not change results, so a checkpoint's own values, chosen
    for the machine it was trained on, are not the ones to run it with elsewhere.
    """
    if scene_chunk < 0 or decoder_chunk < 0:
        raise ValueError(
            f"inference_config: scene_chunk and decoder_chunk must be >= 0, got {scene_chunk}, {decoder_chunk}"
        )
    batching = dataclasses.replace(cfg.model, scene_chunk=int(scene_chunk), decoder_chunk=int(decoder_chunk))
    return dataclasses.replace(cfg, model=batching)


def load_checkpoint(
    path: str | Path, device: str | torch.device = "cpu", scene_chunk: int = 0, decoder_chunk: int = 0
) -> tuple[AdaGraspNet, Checkpoint]:
    """The model of a checkpoint, built from its config with its weights, in eval mode on ``device``.

    The model runs with ``scene_chunk`` / ``decoder_chunk`` (:func:`inference_config`); ``ckpt.cfg``
    is the checkpoint's config as saved.
    """
    ckpt = read_checkpoint(path)
    try:
        model = build_model(inference_config(ckpt.cfg, scene_chunk, decoder_chunk))
    except NetworkConfigError as e:
        raise CheckpointError(f"{path}: config: {e}") from None
    try:
        model.set_weights(ckpt.model_state, ckpt.version)
    except RuntimeError as e:
        first = " ".join(str(e).split())[:200]
        raise CheckpointError(f"{path}: model: weights do not fit the {ckpt.variant} network ({first})") from None
    return model.to(device).eval(), ckpt


NETWORK_KEYS = (
    "model.variant",
    "model.rotate",
    "model.channels",
    "model.feature_cell",
    "model.scene_widths",
    "model.gripper_widths",
    "model.decoder_width",
    "scene_grid",
    "gripper_grid",
)
"""Config keys that fix what a network's weights mean; they must agree to start from a checkpoint."""


def network_values(cfg: Config) -> dict:
    """The value of each of :data:`NETWORK_KEYS` in ``cfg``, by key, in that order."""
    tree = to_dict(cfg)
    out = {}
    for key in NETWORK_KEYS:
        value = tree
        for part in key.split("."):
            value = value[part]
        out[key] = value
    return out


def network_difference(mine: Config, theirs: Config) -> tuple[str, object, object] | None:
    """The first of :data:`NETWORK_KEYS` whose value differs between two configs, as (key, value
    in ``mine``, value in ``theirs``); None when the two build the same network."""
    a_all, b_all = network_values(mine), network_values(theirs)
    for key in NETWORK_KEYS:
        if a_all[key] != b_all[key]:
            return key, a_all[key], b_all[key]
    return None


def model_sha256(cfg: Config, model_state: dict) -> str:
    """SHA-256 (hex) of what fixes a network's output: the values of :data:`NETWORK_KEYS` in
    ``cfg`` and every tensor of ``model_state`` (name, dtype, shape and bytes, in name order).

    Files that differ only in counters, optimiser state, paths or other config keys give the same
    digest; any changed weight, dtype or network key gives another.
    """
    digest = hashlib.sha256(json.dumps(network_values(cfg), sort_keys=True).encode())
    for name in sorted(model_state):
        tensor = model_state[name]
        if not isinstance(tensor, torch.Tensor):
            raise CheckpointError(f"model.{name}: expected a tensor, got {type(tensor).__name__}")
        data = tensor.detach().to("cpu").contiguous().reshape(-1)
        digest.update(f"{name}|{data.dtype}|{tuple(tensor.shape)}|".encode())
        digest.update(data.view(torch.uint8).numpy().tobytes())
    return digest.hexdigest()


def initial_weights(cfg: Config) -> Checkpoint | None:
    """The checkpoint ``cfg.learner.init_weights`` names (a path or ``model:NAME``), its weights
    checked against ``cfg``'s network; None when it is "".

    Raises :class:`CheckpointError` naming the file and the first of :data:`NETWORK_KEYS` that
    differs, or the weights that do not fit.
    """
    source = cfg.learner.init_weights
    if not source:
        return None
    try:
        ckpt = read_checkpoint(source)
    except CheckpointError as e:
        raise CheckpointError(f"learner.init_weights: {e}") from None
    path = resolve_checkpoint(source)
    differ = network_difference(cfg, ckpt.cfg)
    if differ:
        key, a, b = differ
        raise CheckpointError(f"{path}: learner.init_weights: {key} is {b!r} there but {a!r} in this run")
    try:
        with torch.random.fork_rng(devices=[]):  # the trial build leaves torch's global (CPU) generator as it was
            build_model(cfg).load_state_dict(ckpt.model_state)
    except RuntimeError as e:
        first = " ".join(str(e).split())[:200]
        raise CheckpointError(f"{path}: learner.init_weights: weights do not fit this run's network ({first})") from None
    return ckpt
