"""A worker taking its slot over mid-run rebuilds the slot exactly (docs/DESIGN-DECISIONS.md,
"Faults keep the order"): it asks the learner for the slot's current episode
(services/roles/episodes.py), resets the env with that episode's seed, steps the recorded
actions checking every observation bit for bit, and puts the slot's random streams where the
plan says they stand (mam_core.slot). The slot then continues as if nothing had happened.

Where that cannot be done (the env replays differently, the episode has left the replay) the
worker goes on in lock-step from a freshly seeded episode and every batch it sends says why the
slot is no longer the seed's: the learner records it as the end of exactness.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

from mam_core.algorithm1 import Algorithm1
from mam_core.policy import EnvSpec
from mam_core.slot import SlotStreams, replay_episode
from services.messaging import bus, keys
from services.messaging.codec import LearnerStats, MessageError, SlotEpisode
from services.roles.kept import KeptBatches
from services.roles.simulator import GuardedSimulator
from services.roles.worker_state import LearnerWatch, SlotState

log = logging.getLogger("mam.worker")

ASK_TIMEOUT_S = 5.0
RESYNC_S = 2.0  # waiting this long while a restarted learner needs another iteration of this slot: go there


def ask_episode(session: Any, run: str, slot: int, spec: EnvSpec, done: bus.Latest, rejects: bus.RejectLog,
                stopping: Callable[[], bool]) -> SlotEpisode | None:
    """The learner's answer for `slot` (asked until one comes; None: `stopping`, or the run is
    `done`). Every answer is read: when they disagree (a process that is not the run's learner
    answers too, or a stale learner), none is taken and the question is asked again."""
    key = keys.episode(run, slot)
    while not stopping() and not bus.run_is_done(done, run, rejects):
        payloads = bus.ask_all(session, key, ASK_TIMEOUT_S)
        if not payloads:
            log.info("no answer from the learner on %s yet; asking again", key)
            continue
        episode = agreed_episode(payloads, slot, spec.obs_dim, spec.act_dim, rejects)
        if episode is not None:
            return episode
        time.sleep(0.5)
    return None


def agreed_episode(payloads: list[bytes], slot: int, obs_dim: int, act_dim: int,
                   rejects: bus.RejectLog) -> SlotEpisode | None:
    """The episode every valid answer for `slot` gives, or None (none valid, or they disagree:
    counted as rejected, reason `disagreeing_answers`, and logged once)."""
    episodes = []
    for payload in payloads:
        try:
            episode = SlotEpisode.from_bytes(payload, obs_dim, act_dim)
        except MessageError as e:
            rejects.reject("learner", e)
            continue
        if episode.slot == slot:
            episodes.append(episode)
    distinct = {(e.start, e.next, e.why, e.obs.tobytes(), e.action.tobytes(), e.next_obs.tobytes()) for e in episodes}
    if len(distinct) > 1:
        rejects.reject("learner", MessageError("disagreeing_answers", f"{len(distinct)} different episodes of slot "
                                               f"{slot} answered: not this run's learner alone; asking again"))
        return None
    return episodes[0] if episodes else None


def out_of_step(learner: LearnerWatch, slot: int, index: int, waiting_since: float, pending_rows: int,
                flushed_at: float, kept: KeptBatches) -> bool:
    """Slot `slot` waits at iteration `index`, and a learner restarted since its position was set
    still needs another iteration of it well after this worker's resends (and not one its `kept`
    batches hold: a learner still catching up on a long resend): the slot is rebuilt there (`rebuild`)."""
    st = learner.stats  # (rows still pending here, after a pause: no resync)
    if st is None or slot >= len(st.slots_next) or st.slots_next[slot] == index or pending_rows or \
            st.incarnation == learner.synced_with:
        return False
    since = max(waiting_since, flushed_at, learner.seen_at)  # stats must be newer than all three
    if not (time.monotonic() - since > RESYNC_S and learner.stats_at - since > RESYNC_S / 2):
        return False
    # The catch-up of a long checkpoint interval's resend takes the learner longer than RESYNC_S; one
    # batch lost in flight goes again (Worker.resend_lost). Stepping again would end exactness for nothing.
    need = st.slots_next[slot]
    return not (need < index and kept.holds(need))


def follow_owner(learner: LearnerWatch, st: LearnerStats, slot: int, worker: str, incarnation: str) -> None:
    """Fencing: the learner's stats name each slot's owner. Once they named this incarnation, another
    owner means a worker took the slot over while this one was away (paused, cut off): this one is
    stale, its rows are refused, and it leaves (`lost_to`) instead of waiting forever."""
    owner = st.owners[slot] if slot < len(st.owners) else ""
    if owner == f"{worker}/{incarnation}":
        learner.owned = True
    elif owner and learner.owned and not learner.lost_to:
        learner.lost_to = owner
        log.warning("slot %d was taken over by %s while this worker (incarnation %s) was away (paused or cut off): "
                    "the learner takes that one's rows now; this worker leaves the slot and exits", slot, owner,
                    incarnation)


def rebuild(sim: GuardedSimulator, episode: SlotEpisode, plan: Algorithm1, seed: int, slot: int,
            inexact: str) -> SlotState:
    """Slot `slot` where the learner needs it next (`episode.next`), its env `sim` stepped there:
    the episode replayed, or a fresh one when that cannot be done exactly (the state then says why;
    `inexact`: why it was not the seed's already)."""
    streams = SlotStreams.for_slot(seed, slot)
    why = episode.why
    if not why:
        try:
            replayed = replay_episode(sim.env, streams, episode.start, episode.next, episode.obs, episode.action,
                                      episode.next_obs)
            why = replayed.mismatch and f"{sim.cfg.env_id} replayed slot {slot}'s episode differently: " \
                                        f"{replayed.mismatch} (the env is not deterministic)"
        except Exception as e:  # the simulator failed on the recorded actions: the same outcome as a mismatch
            why = f"{sim.cfg.env_id} failed replaying slot {slot}'s episode: {type(e).__name__}: {e}"
    if why:
        log.warning("slot %d cannot be rebuilt exactly: %s; it goes on from a fresh episode at iteration %d",
                    slot, why, episode.next)
        state = SlotState(streams, sim.reset_env(seed=streams.episode_seed(episode.next)), inexact=why[:1000])
    else:
        state = SlotState(streams, replayed.obs, replayed.episode_return, replayed.fresh, inexact)
        log.info("slot %d rebuilt at iteration %d: its episode from iteration %d replayed (%d steps, every "
                 "observation equal)", slot, episode.next, episode.start, len(episode.action))
    random_steps, policy_steps = plan.slot_steps(slot, episode.next)
    streams.fast_forward(sim.env, random_steps, policy_steps)
    return state
