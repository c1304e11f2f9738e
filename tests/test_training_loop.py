"""The loop every trainer runs (mapless/train/loop.py), driven by a trainer that only counts: the
budget, the checkpoint schedule, a graceful stop and the summary, without model or scenes."""

from __future__ import annotations

from mapless.train.config import TrainConfig
from mapless.train.loop import TrainingLoop


class CountingTrainer(TrainingLoop):
    """Three episodes of ten frames per update; records the checkpoints instead of writing them."""

    label = "counting"

    def __init__(self, config: TrainConfig, stop_after_episodes: int | None = None):
        super().__init__(config, run_dir=None)
        self.stop_after_episodes = stop_after_episodes
        self.saved: list[tuple[int, bool, bool]] = []  # (episodes, final, snapshot)

    def _setup(self, resume: dict | None) -> None:
        self.model = self.optimizer = None

    def _train_step(self, stop_requested: bool) -> bool:
        # As if Ctrl-C came during the update that starts at stop_after_episodes.
        stop = stop_requested or self.counters["episodes"] == self.stop_after_episodes
        return self._count(3, 30, stop)

    def _checkpoint(self, final: bool = False, snapshot: bool = True) -> None:
        self.saved.append((self.counters["episodes"], final, snapshot))


def _config(**fields) -> TrainConfig:
    return TrainConfig(checkpoint_every=6, log_every=6, progress=False, **fields)


def test_the_loop_checkpoints_on_schedule_until_the_budget_and_then_writes_the_final_model() -> None:
    trainer = CountingTrainer(_config(episodes=20))
    summary = trainer.run()
    # Updates end at 3, 6, ..., 21; snapshots where one crossed a multiple of 6, none at the budget.
    assert trainer.saved == [(6, False, True), (12, False, True), (18, False, True), (21, True, True)]
    assert (summary["episodes"], summary["frames"], summary["updates"]) == (21, 210, 7)
    assert not summary["stopped_early"]


def test_a_frame_budget_ends_the_run_too() -> None:
    trainer = CountingTrainer(_config(frames=95))
    assert trainer.run()["frames"] == 120 and trainer.saved[-1] == (12, True, True)


def test_a_graceful_stop_keeps_the_snapshot_its_update_was_due_and_writes_no_final_model() -> None:
    trainer = CountingTrainer(_config(episodes=100), stop_after_episodes=9)  # its update ends at 12
    summary = trainer.run()
    assert trainer.saved == [(6, False, True), (12, False, True)]
    assert summary["stopped_early"] and summary["episodes"] == 12


def test_a_graceful_stop_between_snapshots_writes_only_the_resumable_checkpoint() -> None:
    trainer = CountingTrainer(_config(episodes=100), stop_after_episodes=6)  # its update ends at 9
    trainer.run()
    assert trainer.saved == [(6, False, True), (9, False, False)]
