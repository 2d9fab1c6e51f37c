//! Shared-memory batches served to the training thread one publisher at a
//! time.
//!
//! iceoryx2's subscriber returns the first connected publisher's sample
//! whenever that publisher has one. An actor blocked in `send` (the learner
//! is the bottleneck, so actors wait) refills its slot the moment a sample
//! is taken, so a second actor on shared memory was never heard: 8 s of
//! two actors stored none of the second's batches (issue 71). So once the
//! batches taken are all served, everything waiting is drained at once (a
//! blocked actor refills its slot once, then must step its environments
//! before it sends again: the drain empties every publisher's slots), and
//! the drained batches are served one publisher at a time.

use std::collections::{BTreeMap, HashSet, VecDeque};
use std::ops::Bound::{Excluded, Unbounded};

use lcrl_proto::shm::TransitionSubscriber;
use lcrl_proto::v1::TransitionBatch;

/// Batches waiting, by publisher ([`lcrl_proto::shm::publisher_stream`]),
/// and whose turn it is.
#[derive(Default)]
pub struct PublisherTurns {
    queues: BTreeMap<u64, VecDeque<TransitionBatch>>,
    /// The publisher served last; the next turn is the one after it.
    last: Option<u64>,
}

impl PublisherTurns {
    /// Once every batch taken has been served, takes what `subscriber`
    /// holds, at most `most` batches (a bound on the policy lag this adds:
    /// a round of every waiting actor's batches).
    pub fn fill(&mut self, subscriber: &TransitionSubscriber, most: usize) -> Result<(), String> {
        if self.queues.values().any(|queue| !queue.is_empty()) {
            return Ok(());
        }
        for _ in 0..most {
            let Some((batch, publisher)) = subscriber.receive()? else { break };
            self.queues.entry(publisher).or_default().push_back(batch);
        }
        Ok(())
    }

    /// The next publisher's oldest batch, in turn after the last served.
    pub fn next(&mut self) -> Option<(TransitionBatch, u64)> {
        let after = self.last.map_or(Unbounded, Excluded);
        let publisher = self.queues.range((after, Unbounded)).chain(self.queues.iter()).find(|(_, queue)| !queue.is_empty()).map(|(&p, _)| p)?;
        self.last = Some(publisher);
        let batch = self.queues.get_mut(&publisher)?.pop_front()?;
        Some((batch, publisher))
    }

    /// Forgets departed publishers whose batches have all been served.
    pub fn keep_live(&mut self, live: &HashSet<u64>) {
        self.queues.retain(|publisher, queue| live.contains(publisher) || !queue.is_empty());
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use lcrl_proto::shm::ShmPublisher;
    use lcrl_proto::v1::Transition;

    fn batch(run_id: &str, actor: &str, sequence: u64) -> TransitionBatch {
        let t = Transition { state: vec![0.0; 2], action: vec![0.0], next_state: vec![0.0; 2], ..Default::default() };
        TransitionBatch { run_id: run_id.into(), actor_id: actor.into(), sequence, transitions: vec![t], ..Default::default() }
    }

    /// The first publisher's full buffer no longer comes out before the
    /// second's one batch: the two are served in turn, each in its order,
    /// and nothing is lost.
    #[test]
    fn publishers_are_served_in_turn() {
        let run_id = format!("shm-turns-{}", std::process::id());
        let subscriber = TransitionSubscriber::open(&run_id, 4).expect("subscriber");
        let (busy, quiet) = (ShmPublisher::open(&run_id).expect("publisher"), ShmPublisher::open(&run_id).expect("publisher"));
        for sequence in 1..=4 {
            busy.send(&batch(&run_id, "busy", sequence)).expect("send");
        }
        quiet.send(&batch(&run_id, "quiet", 1)).expect("send");
        let mut turns = PublisherTurns::default();
        let mut served = Vec::new();
        loop {
            turns.fill(&subscriber, 16).expect("fill");
            let Some((batch, _)) = turns.next() else { break };
            served.push((batch.actor_id, batch.sequence));
        }
        let order: Vec<&str> = served.iter().map(|(actor, _)| actor.as_str()).collect();
        assert_eq!(order, ["busy", "quiet", "busy", "busy", "busy"]);
        let busy_sequences: Vec<u64> = served.iter().filter(|(actor, _)| actor == "busy").map(|(_, s)| *s).collect();
        assert_eq!(busy_sequences, vec![1, 2, 3, 4]);
    }

    /// A departed publisher's queue is kept until it is served, then
    /// forgotten.
    #[test]
    fn departed_publishers_are_forgotten_once_served() {
        let mut turns = PublisherTurns::default();
        turns.queues.entry(7).or_default().push_back(batch("r", "a", 1));
        turns.keep_live(&HashSet::new());
        assert_eq!(turns.next().map(|(b, p)| (b.sequence, p)), Some((1, 7)));
        turns.keep_live(&HashSet::new());
        assert!(turns.queues.is_empty());
    }
}
