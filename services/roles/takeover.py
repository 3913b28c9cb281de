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
from typing import TYPE_CHECKING

from mam_core.slot import SlotStreams, replay_episode
from services.messaging import bus, keys
from services.messaging.codec import LearnerStats, MessageError, SlotEpisode

if TYPE_CHECKING:
    from services.roles.worker import Worker

log = logging.getLogger("mam.worker")

ASK_TIMEOUT_S = 5.0
RESYNC_S = 2.0  # waiting this long while a restarted learner needs another iteration of this slot: go there


def ask_episode(w: Worker) -> SlotEpisode | None:
    """The learner's answer for this worker's slot (asked until one comes; None: stopping, or
    the run is over). Every answer is read: when they disagree (a process that is not the
    run's learner answers too, or a stale learner), none is taken and the question is asked again."""
    key = keys.episode(w.cfg.run, w.slot)
    while not w.stop_requested and not bus.run_is_done(w.done, w.cfg.run, w.rejects):
        payloads = bus.ask_all(w.session, key, ASK_TIMEOUT_S)
        if not payloads:
            log.info("no answer from the learner on %s yet; asking again", key)
            continue
        episode = agreed_episode(payloads, w.slot, w.spec.obs_dim, w.spec.act_dim, w.rejects)
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


def out_of_step(w: Worker, index: int, waiting_since: float) -> bool:
    """The slot waits, and a learner restarted since its position was set still needs another
    iteration of it well after this worker's resends (and not one its kept batches hold: a learner
    still catching up on a long resend): the slot is rebuilt there (`take_over`)."""
    st = w.stats  # (rows still pending here, after a pause: no resync)
    if st is None or w.slot >= len(st.slots_next) or st.slots_next[w.slot] == index or w.p_n or \
            st.incarnation == w.synced_with:
        return False
    since = max(waiting_since, w.flushed_at, w.learner_seen_at)  # stats must be newer than all three
    if not (time.monotonic() - since > RESYNC_S and w.stats_at - since > RESYNC_S / 2):
        return False
    # The catch-up of a long checkpoint interval's resend takes the learner longer than RESYNC_S; one
    # batch lost in flight goes again (Worker.resend_lost). Stepping again would end exactness for nothing.
    need = st.slots_next[w.slot]
    return not (need < index and w.kept.holds(need))


def follow_owner(w: Worker, st: LearnerStats) -> None:
    """Fencing: the learner's stats name each slot's owner. Once they named this incarnation, another
    owner means a worker took the slot over while this one was away (paused, cut off): this one is
    stale, its rows are refused, and it leaves (`lost_to`) instead of waiting forever."""
    owner = st.owners[w.slot] if w.slot < len(st.owners) else ""
    if owner == f"{w.id}/{w.incarnation}":
        w.owned = True
    elif owner and w.owned and not w.lost_to:
        w.lost_to = owner
        log.warning("slot %d was taken over by %s while this worker (incarnation %s) was away (paused or cut off): "
                    "the learner takes that one's rows now; this worker leaves the slot and exits", w.slot, owner,
                    w.incarnation)


def take_over(w: Worker, index: int) -> int:
    """Rebuild slot `w.slot` where the learner needs it next; that iteration."""
    episode = ask_episode(w)
    if episode is None:
        return index
    w.streams = SlotStreams.for_slot(w.algo.seed, w.slot)
    why = episode.why
    if not why:
        try:
            replayed = replay_episode(w.env, w.streams, episode.start, episode.next, episode.obs, episode.action,
                                      episode.next_obs)
            why = replayed.mismatch and f"{w.cfg.env_id} replayed slot {w.slot}'s episode differently: " \
                                        f"{replayed.mismatch} (the env is not deterministic)"
        except Exception as e:  # the simulator failed on the recorded actions: the same outcome as a mismatch
            why = f"{w.cfg.env_id} failed replaying slot {w.slot}'s episode: {type(e).__name__}: {e}"
    if why:
        log.warning("slot %d cannot be rebuilt exactly: %s; it goes on from a fresh episode at iteration %d",
                    w.slot, why, episode.next)
        w.inexact = why[:1000]
        w.obs, w.episode_return, w.first_row = w.reset_env(seed=w.streams.episode_seed(episode.next)), 0.0, True
    else:
        w.obs, w.episode_return, w.first_row = replayed.obs, replayed.episode_return, replayed.fresh
        log.info("slot %d rebuilt at iteration %d: its episode from iteration %d replayed (%d steps, every "
                 "observation equal)", w.slot, episode.next, episode.start, len(episode.action))
    random_steps, policy_steps = w.plan.slot_steps(w.slot, episode.next)
    w.streams.fast_forward(w.env, random_steps, policy_steps)
    return episode.next
