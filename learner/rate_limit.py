"""Samples-per-insert rate limiting, so a run learns alike on 2 cores or 200.

The learner may draw ``samples_per_insert`` trials for every trial inserted into the replay,
once the replay holds ``min_replay`` trials. The paper's schedule is 32 batches of 8 per 8
new trials, i.e. 32 samples per insert. The limit holds on both sides: the learner waits for
trials, and actors wait (start no new episode) while the trials inserted run more than
``insert_lead`` ahead of what the learner has sampled, so a slow learner is not starved by
fast actors (on a laptop they share the cores), but never while the learner cannot take a step.
Call loop::

    limiter = SamplesPerInsert(spi=32, min_replay=32, batch_size=8, insert_lead=32)
    steps = limiter.allowed_steps(inserted=replay_total, sampled=learner_samples)
    if limiter.may_insert(inserted=replay_total, sampled=learner_samples): ...start an episode
"""

from __future__ import annotations

from dataclasses import dataclass

from common.config import LearnerConfig


@dataclass(frozen=True)
class SamplesPerInsert:
    """Allowance of learner steps given how many trials were inserted and sampled so far."""

    spi: float
    """Trials sampled per trial inserted."""
    min_replay: int
    """Inserted trials before any step is allowed."""
    batch_size: int
    """Trials per learner step."""
    insert_lead: float = 0.0
    """Trials the inserts may run ahead of the learner's schedule before actors wait; 0 = never wait."""

    def allowed_steps(self, inserted: int, sampled: int) -> int:
        """Whole learner steps that may run now (>= 0)."""
        if inserted < self.min_replay:
            return 0
        budget = self.spi * (inserted - self.min_replay + 1) - sampled
        return max(0, int(budget // self.batch_size))

    @classmethod
    def from_config(cls, learner: LearnerConfig) -> "SamplesPerInsert":
        """The limiter of a run's ``learner`` config section."""
        return cls(spi=learner.samples_per_insert, min_replay=learner.min_replay,
                   batch_size=learner.batch_size, insert_lead=learner.insert_lead)

    def lead(self, inserted: int, sampled: int) -> float:
        """Trials inserted beyond what the learner's samples so far account for (< 0 before min_replay)."""
        return inserted - self.min_replay - sampled / self.spi

    def may_insert(self, inserted: int, sampled: int) -> bool:
        """Whether actors may start another episode now: while the inserts lead by less than
        ``insert_lead``, and always while the learner cannot take a step (were they to wait then,
        when ``spi * (insert_lead + 1) < batch_size``, neither side would move again)."""
        return (self.insert_lead <= 0 or self.spi <= 0 or self.lead(inserted, sampled) < self.insert_lead
                or self.allowed_steps(inserted, sampled) == 0)
