//! Episode returns and lengths checked against every reward the learner
//! stored for them, not only the batch's (issue 71). An actor's episode may
//! span several of its batches: each batch's part ends in a cut
//! (mid-episode) and the next part begins, in a later batch of the same
//! actor, at the state the cut's step led to. The learner keeps every
//! actor's unfinished parts, keyed by that state (bit for bit, as PPO joins
//! its streams, ppo/mod.rs), and so knows an episode's stored steps across its
//! batches.
//!
//! An episode's return and length in the record (metrics.csv, the
//! training curve, `final_return`, the budget's count) are those of the
//! steps the learner received for it, never what a peer claims beyond them
//! (issue 82: one step claiming 10⁶ steps and a return of 9.9e11 was
//! taken). A claim is kept only where it is exactly those steps, its
//! return their sum to rounding (the actor sums the environment's f64
//! rewards, which travel as f32); any other claim is rewritten to the
//! received steps' sum and count. "Received" means the steps passed the
//! door's checks: trained on, or discarded as stale by an on-policy
//! learner (PPO) but still this episode's steps.
//!
//! What this costs an honest record: an episode that began before what the
//! learner received (before this learner process started, in a batch
//! refused or lost, or a part evicted) is recorded as its received part.
//! The wire does not say where an environment's episode began, so the
//! learner cannot tell such a part from a whole episode.

use std::collections::HashMap;

use lcrl_proto::v1::{EpisodeSummary, TransitionBatch};

/// Unfinished parts kept per actor (one per environment it steps; an
/// actor with more loses its oldest, whose episode is then checked on its
/// later batches alone, as by the door).
pub const OPEN_PER_ACTOR: usize = 256;

/// Every actor's unfinished episode parts.
#[derive(Debug, Default)]
pub struct OpenEpisodes {
    by_actor: HashMap<String, Vec<Open>>,
}

#[derive(Debug)]
struct Open {
    /// The state the part's last step led to, as f32 bits.
    next_state: Vec<u32>,
    part: Stored,
}

/// The stored steps of (a part of) an episode: what its claim is checked
/// against, here and at the door (ingest.rs, `returns_agree`).
#[derive(Debug, Default, Clone, Copy)]
pub struct Stored {
    pub sum: f64,
    sum_abs: f64,
    pub steps: u32,
}

impl Stored {
    pub fn add(&mut self, reward: f32) {
        self.sum += f64::from(reward);
        self.sum_abs += f64::from(reward.abs());
        self.steps = self.steps.saturating_add(1);
    }

    /// Whether a claim is exactly these steps: their number, and their
    /// sum to rounding (rewards travel as f32, returns are f64 sums of
    /// the f64 rewards).
    pub fn is_exactly(&self, claimed_return: f64, claimed_length: u32) -> bool {
        claimed_length == self.steps && (claimed_return - self.sum).abs() <= 1e-5 * (self.sum_abs + 1.0)
    }

    /// Whether a claimed return and length can be those of an episode
    /// holding these steps and others not in view: at least their number,
    /// and a return within [`lcrl_sim::REWARD_LIMIT`] per step claimed
    /// beyond them of their sum (the door's check of one batch).
    pub fn admits(&self, claimed_return: f64, claimed_length: u32) -> bool {
        let tolerance = 1e-5 * (self.sum_abs + 1.0);
        let unseen = f64::from(claimed_length.saturating_sub(self.steps));
        claimed_length >= self.steps && (claimed_return - self.sum).abs() <= unseen * lcrl_sim::REWARD_LIMIT + tolerance
    }
}

fn bits(state: &[f32]) -> Vec<u32> {
    state.iter().map(|v| v.to_bits()).collect()
}

impl OpenEpisodes {
    /// The summaries of a `batch` that passed the door (one per end, in
    /// order, as the door checked), each claim that is not exactly its
    /// received steps rewritten to them; the batch's unfinished parts are
    /// kept for the actor's next batches. Returns the summaries and how
    /// many claims were rewritten.
    pub fn settle(&mut self, batch: &TransitionBatch) -> (Vec<EpisodeSummary>, u64) {
        let mut summaries = batch.episodes.clone();
        let mut rewritten = 0;
        let open = self.by_actor.entry(batch.actor_id.clone()).or_default();
        let mut ends = summaries.iter_mut();
        let mut part: Option<Stored> = None;
        for t in &batch.transitions {
            let p = part.get_or_insert_with(|| {
                let key = bits(&t.state);
                open.iter().position(|o| o.next_state == key).map_or_else(Stored::default, |k| open.remove(k).part)
            });
            p.add(t.reward);
            if t.terminated || t.truncated {
                let Some(p) = part.take() else { continue };
                let Some(claim) = ends.next() else { break };
                if !p.is_exactly(claim.episode_return, claim.length) {
                    (claim.episode_return, claim.length) = (p.sum, p.steps);
                    claim.return_terms = None; // a claimed split of a return not taken
                    rewritten += 1;
                }
            } else if t.cut {
                if let Some(p) = part.take() {
                    keep(open, Open { next_state: bits(&t.next_state), part: p });
                }
            }
        }
        // A last part with neither an end nor a cut goes on in a later
        // batch all the same.
        if let (Some(p), Some(last)) = (part, batch.transitions.last()) {
            keep(open, Open { next_state: bits(&last.next_state), part: p });
        }
        if open.is_empty() {
            self.by_actor.remove(&batch.actor_id);
        }
        (summaries, rewritten)
    }

    /// Forgets an actor (its id left the learner's table).
    pub fn forget(&mut self, actor_id: &str) {
        self.by_actor.remove(actor_id);
    }
}

fn keep(open: &mut Vec<Open>, part: Open) {
    if open.len() >= OPEN_PER_ACTOR {
        open.remove(0);
    }
    open.push(part);
}

#[cfg(test)]
mod tests {
    use super::*;
    use lcrl_proto::v1::Transition;

    fn step(state: f32, reward: f32, end: bool, cut: bool) -> Transition {
        Transition { state: vec![state], next_state: vec![state + 1.0], action: vec![0.0], reward, terminated: end, cut, ..Default::default() }
    }

    fn batch(actor: &str, transitions: Vec<Transition>, claims: &[(f64, u32)]) -> TransitionBatch {
        let episodes = claims.iter().map(|&(episode_return, length)| EpisodeSummary { episode_return, length, ..Default::default() }).collect();
        TransitionBatch { actor_id: actor.into(), transitions, episodes, ..Default::default() }
    }

    /// Two environments' episodes cut across two batches are checked
    /// against all their received steps: an honest claim is kept as it is,
    /// any other (a return or a length those steps do not give) rewritten
    /// to them, also where the episode's start was not received; another
    /// actor's parts are its own.
    #[test]
    fn returns_are_checked_against_every_batch_that_holds_them() {
        let mut open = OpenEpisodes::default();
        // Env A: states 0, 1 (cut); env B: 10 (cut).
        let first = batch("a", vec![step(0.0, -1.0, false, false), step(1.0, -1.0, false, true), step(10.0, -0.5, false, true)], &[]);
        assert_eq!(open.settle(&first), (vec![], 0));
        // B goes on from 11 and ends; A goes on from 2 and ends claiming a
        // return of 1e5 over the 3 steps the learner stored.
        let second = batch("a", vec![step(11.0, -0.5, true, false), step(2.0, -1.0, true, false)], &[(-1.0, 2), (1e5, 3)]);
        let (summaries, rewritten) = open.settle(&second);
        assert_eq!(rewritten, 1);
        assert_eq!((summaries[0].episode_return, summaries[0].length), (-1.0, 2), "an honest claim is kept");
        assert_eq!((summaries[1].episode_return, summaries[1].length), (-3.0, 3), "the stored rewards, not the claim");
        // The door alone would have taken this claim (1 step in the batch,
        // 2 claimed beyond it); the stored part says otherwise.
        open.settle(&batch("a", vec![step(20.0, -1.0, false, true)], &[]));
        let (summaries, rewritten) = open.settle(&batch("a", vec![step(21.0, -1.0, true, false)], &[(-1.0, 1)]));
        assert_eq!((rewritten, summaries[0].episode_return, summaries[0].length), (1, -2.0, 2), "fewer steps than stored");
        // An episode whose beginning was not received (state 50 follows no
        // kept part; another actor's part at 2 is not this one's) is
        // recorded as the steps that were: the claim of 20 is not taken.
        open.settle(&batch("b", vec![step(1.0, -1.0, false, true)], &[]));
        let (summaries, rewritten) = open.settle(&batch("a", vec![step(50.0, -2.0, false, false), step(51.0, -2.0, true, false)], &[(-40.0, 20)]));
        assert_eq!((rewritten, summaries[0].episode_return, summaries[0].length), (1, -4.0, 2));
        // Issue 82: one step claiming 10⁶ steps and a return of 9.9e11
        // (within 10⁶ per unseen step, so the door lets it in) is one step
        // with its own reward in the record.
        let (summaries, rewritten) = open.settle(&batch("a", vec![step(60.0, 5.0, true, false)], &[(9.9e11, 1_000_000)]));
        assert_eq!((rewritten, summaries[0].episode_return, summaries[0].length), (1, 5.0, 1));
        let (summaries, _) = open.settle(&batch("b", vec![step(2.0, -1.0, true, false)], &[(-2.0, 2)]));
        assert_eq!((summaries[0].episode_return, summaries[0].length), (-2.0, 2));
        assert!(open.by_actor.is_empty(), "every part was finished");
    }

    /// The oldest part is the one an actor with too many loses.
    #[test]
    fn the_oldest_part_is_evicted() {
        let mut open = OpenEpisodes::default();
        let parts: Vec<Transition> = (0..=OPEN_PER_ACTOR).map(|k| step(10.0 * k as f32, -1.0, false, true)).collect();
        // Continue part 1 first (it moves to the end of the list), then
        // add the one too many.
        open.settle(&batch("a", parts[..OPEN_PER_ACTOR].to_vec(), &[]));
        open.settle(&batch("a", vec![step(11.0, -1.0, false, true)], &[]));
        open.settle(&batch("a", vec![parts[OPEN_PER_ACTOR].clone()], &[]));
        let kept = &open.by_actor["a"];
        assert_eq!(kept.len(), OPEN_PER_ACTOR);
        assert!(!kept.iter().any(|o| o.next_state == bits(&[1.0])), "part 0, the oldest, is gone");
        assert!(kept.iter().any(|o| o.next_state == bits(&[12.0])), "part 1, continued since, stays");
    }
}
