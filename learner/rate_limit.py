"""Samples-per-insert rate limiting, so a run learns alike on 2 cores or 200.

The learner may draw ``samples_per_insert`` trials for every trial inserted into the replay,
once the replay holds ``min_replay`` trials. The paper's schedule is 32 batches of 8 per 8
new trials, i.e. 32 samples per insert. Call loop::

    limiter = SamplesPerInsert(spi=32, min_replay=32, batch_size=8)
    steps = limiter.allowed_steps(inserted=replay_total, sampled=learner_samples)
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SamplesPerInsert:
    """Allowance of learner steps given how many trials were inserted and sampled so far."""

    spi: float
    """Trials sampled per trial inserted."""
    min_replay: int
    """Inserted trials before any step is allowed."""
    batch_size: int
    """Trials per learner step."""

    def allowed_steps(self, inserted: int, sampled: int) -> int:
        """Whole learner steps that may run now (>= 0)."""
        if inserted < self.min_replay:
            return 0
        budget = self.spi * (inserted - self.min_replay + 1) - sampled
        return max(0, int(budget // self.batch_size))
