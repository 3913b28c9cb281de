"""Where each slot's current episode began, and the answer to a worker taking a slot over.

A replacement worker rebuilds its slot exactly (mam_core.slot.replay_episode): it needs the
slot's current episode, from its first step to the learner's next iteration of the slot. The
learner knows it: the workers flag each episode's first row (`TransitionBatch.episode_starts`),
so `SlotEpisodes` keeps, per slot, the iteration its current episode began; the rows since are
in the replay (iteration t's row of slot s: `Algorithm1.row_of`, read with `Replay.rows_at`) or
still staged. The learner answers `mam/<run>/episode/w<i>` queries from its loop.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable

import numpy as np

from mam_core.algorithm1 import Algorithm1
from mam_core.replay import Replay
from services.messaging import keys
from services.messaging.codec import SlotEpisode, TransitionBatch
from services.roles.lockstep import SlotStage

log = logging.getLogger("mam.learner")


class SlotEpisodes:
    def __init__(self, plan: Algorithm1, inserted_through: int = 0) -> None:
        self.plan = plan
        self.start = [1] * plan.slots  # per slot: the iteration of its current episode's first step
        self.inserted_through = inserted_through  # the last iteration whose rows are in the replay

    def inserted(self, index: int, slots: tuple[int, ...], sources: list[tuple[TransitionBatch, int]]) -> None:
        """Iteration `index`'s rows went in, from `sources` (batch, rows of it used so far) in slot order."""
        for s, (batch, used) in zip(slots, sources):
            if used - 1 in batch.episode_starts:
                self.start[s] = index
        self.inserted_through = index

    def to_json(self) -> str:
        return json.dumps({"start": self.start, "through": self.inserted_through})

    def restore(self, text: str) -> None:
        data = json.loads(text)
        start = [int(v) for v in data["start"]]
        if len(start) == len(self.start):
            self.start, self.inserted_through = start, int(data["through"])

    def reply(self, key: str, stage: SlotStage | None, buffer: Replay, sender: str,
              next_seq: Callable[[], int]) -> bytes | None:
        """A worker taking slot w<i> over asks (on `key`) for the slot's current episode: the
        answer, encoded from `sender` with the next sequence number; None: no answer."""
        try:
            slot = int(keys.parse_last(key)[1:])
        except ValueError:
            return None
        if stage is None or not 0 <= slot < self.plan.slots:
            return None
        log.info("slot %d's current episode to its new worker (it continues at iteration %d)", slot, stage.end[slot])
        return self.answer(slot, stage, buffer).to_bytes(sender, next_seq())

    def answer(self, slot: int, stage: SlotStage, buffer: Replay) -> SlotEpisode:
        """Slot `slot`'s current episode up to the stage's next iteration of it."""
        obs_dim, act_dim = buffer.obs_dim, buffer.act_dim
        nxt = stage.end[slot]
        start = self.start[slot]
        rows = [self.plan.row_of(t, slot) for t in range(start, min(self.inserted_through, nxt - 1) + 1)]
        if rows and not buffer.holds(rows[0]):
            return SlotEpisode(slot, start, nxt, np.zeros((0, obs_dim)), np.zeros((0, act_dim)),
                               np.zeros((0, obs_dim)), f"its episode from iteration {start} has left the replay")
        held = buffer.rows_at(rows)
        obs, action, next_obs = [held["obs"]], [held["action"]], [held["next_obs"]]
        for staged in stage.queues[slot]:  # rows not yet inserted (with B > 0, or waiting for other slots)
            b = staged.batch
            for r in range(staged.used, b.rows):
                if r in b.episode_starts:  # a later episode began: the earlier rows are not needed
                    start, obs, action, next_obs = staged.first + r - staged.used, [], [], []
                obs.append(b.obs[r:r + 1])
                action.append(b.action[r:r + 1])
                next_obs.append(b.next_obs[r:r + 1])
        return SlotEpisode(slot, start, nxt, _rows(obs, obs_dim), _rows(action, act_dim), _rows(next_obs, obs_dim))


def _rows(parts: list[np.ndarray], dim: int) -> np.ndarray:
    return np.concatenate(parts).reshape(-1, dim) if parts else np.zeros((0, dim), np.float32)
