"""A grasp actor stores, for every attempt, the trial that ran: its observation, action, score,
label and the opening it executed."""

from __future__ import annotations

import pytest

import actors.grasp_actor as grasp_actor
from common.config import load_config


class _Recorder:
    """A replay client that keeps the trials it is given."""

    def __init__(self) -> None:
        self.trials = []

    def insert(self, trial) -> None:
        self.trials.append(trial)

    def flush(self) -> None:
        pass


def test_stored_trial_is_the_attempt_that_ran(monkeypatch, tmp_path):
    monkeypatch.setenv("ADAGRASP_CACHE", str(tmp_path / "cache"))
    cfg = load_config("tiny", overrides=["sim.scene=multi", "sim.multi_max_attempts=2"])
    ran = []
    real = grasp_actor.run_episode

    def spy(*args, **kwargs):
        for result in real(*args, **kwargs):
            ran.append(result)
            yield result

    monkeypatch.setattr(grasp_actor, "run_episode", spy)
    replay = _Recorder()
    actor = grasp_actor.GraspActor(cfg, actor_id=0, seed=0, replay=replay)
    try:
        actor.run_episodes(1, epsilon=1.0)
    finally:
        actor.close()
    assert len(replay.trials) == len(ran) >= 1
    for trial, result in zip(replay.trials, ran):
        assert trial.label == result.outcome.success and trial.action == result.action
        assert trial.score == result.score and trial.meta.step == result.step
        assert trial.observation is result.observation, "the observation the action was chosen on"
        assert result.outcome.opening == trial.meta.openings[trial.action[3]]
    # encodings of a random scale and random openings are never read again: none is written
    assert not list((tmp_path / "cache").rglob("*.npy"))
    # nor is a URDF at the episode's scale (with or without the arm): only the processed ones stay
    assert {f.name for f in (tmp_path / "cache" / "grippers").rglob("*.urdf")} == {"gripper.urdf"}


def test_an_actor_whose_grippers_cannot_be_chosen_opens_no_physics_client(monkeypatch):
    """A train_grippers selection that fails raises before the actor's Simulation (a PyBullet
    client that nothing would close) is made."""
    made = []
    monkeypatch.setattr(grasp_actor, "Simulation", lambda *args, **kwargs: made.append(args))
    cfg = load_config("tiny")
    cfg.grippers.train_grippers = "no_such_gripper"
    with pytest.raises(ValueError, match="no_such_gripper"):
        grasp_actor.GraspActor(cfg, actor_id=0, seed=0, replay=_Recorder())
    assert made == []
