//! Group commit: the hot transitions (grant, complete, fail, hand back, expiry) are stored in
//! an open SQLite batch, and the batch is committed by the first request that waits for it
//! ([`Farm::durable`]). That request first yields to the async runtime, so every request
//! already runnable adds its change to the batch and waits for the same commit: one commit
//! for many requests under load, one yield of latency when idle. A request is answered only
//! once the commit holding its change succeeded: what a worker was told is on disk, exactly as
//! with a commit per request. Rarer transitions (submit, cancel, retry, register, done) commit
//! on the spot ([`Farm::flush`]). Changes no request waits for (expired leases) are committed
//! with the next batch, or when the farm is dropped.
//!
//! A failed commit loses its whole batch: its requests are answered with an error, and the
//! farm's memory is then ahead of the database in ways a restart repairs (a tile counted done
//! renders again, a lease is forgotten).

use std::sync::atomic::{AtomicBool, Ordering};

use tokio::sync::watch;

use super::{Farm, FarmError, Result};
use crate::store::{Durable, StoreError};

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Committed {
    /// Every transition up to this number is durable, except the lost ones.
    pub upto: u64,
    /// The latest batch whose commit failed (first, last).
    pub lost: Option<(u64, u64)>,
}

impl Committed {
    fn covers(&self, seq: u64) -> Option<Durable> {
        match self.lost {
            Some((first, last)) if (first..=last).contains(&seq) => Some(Durable::Lost),
            _ if seq <= self.upto => Some(Durable::Yes),
            _ => None,
        }
    }
}

pub struct Commits {
    /// A request is about to commit the open batch; the others wait for its result.
    leading: AtomicBool,
    status: watch::Sender<Committed>,
}

impl Default for Commits {
    fn default() -> Self {
        Commits {
            leading: AtomicBool::new(false),
            status: watch::Sender::new(Committed::default()),
        }
    }
}

impl Commits {
    pub fn publish(&self, committed: Committed) {
        self.status.send_replace(committed);
    }
}

/// The leading request's turn. Dropped unfinished (the request was cancelled while it
/// yielded), it commits anyway, so the requests waiting on it are answered.
struct Lead<'a> {
    farm: &'a Farm,
    done: bool,
}

impl Lead<'_> {
    fn commit(mut self) {
        self.finish();
    }

    fn finish(&mut self) {
        self.done = true;
        let committed = self.farm.commit_batch();
        // Released before publishing: a request woken by this commit but not covered by it
        // can lead the next one.
        self.farm.commits.leading.store(false, Ordering::Release);
        self.farm.commits.publish(committed);
    }
}

impl Drop for Lead<'_> {
    fn drop(&mut self) {
        if !self.done {
            self.finish();
        }
    }
}

impl Farm {
    /// Commits the open batch now; returns what is durable.
    fn commit_batch(&self) -> Committed {
        let mut state = self.lock();
        let result = state.db.commit();
        let (upto, lost) = state.db.committed();
        drop(state);
        if let Err(e) = result {
            tracing::error!("a batch of farm changes could not be committed: {e}");
        }
        Committed { upto, lost }
    }

    /// Commits the open batch at once (the rare transitions answer only after it).
    pub(super) fn flush(&self) -> Result<()> {
        let mut state = self.lock();
        let result = state.db.commit();
        let (upto, lost) = state.db.committed();
        drop(state);
        self.commits.publish(Committed { upto, lost });
        Ok(result?)
    }

    /// The number of the latest transition stored (a request that changed the farm waits for
    /// it, or a later one, to be durable).
    pub fn written(&self) -> u64 {
        self.lock().db.written()
    }

    /// Waits until transition `seq` is committed, committing it (with every change made
    /// meanwhile) unless another request is about to; an error if its batch was lost.
    pub async fn durable(&self, seq: u64) -> Result<()> {
        let mut status = self.commits.status.subscribe();
        loop {
            let covered = status.borrow_and_update().covers(seq);
            match covered {
                Some(Durable::Yes) => return Ok(()),
                Some(Durable::Lost) => {
                    return Err(FarmError::Store(StoreError::Lost(format!(
                        "change {seq} was lost: its batch could not be committed"
                    ))))
                }
                None => {}
            }
            let lead = self
                .commits
                .leading
                .compare_exchange(false, true, Ordering::AcqRel, Ordering::Acquire)
                .is_ok();
            if lead {
                let lead = Lead {
                    farm: self,
                    done: false,
                };
                // Requests already runnable make their changes before this commit.
                tokio::task::yield_now().await;
                lead.commit();
            } else if status.changed().await.is_err() {
                // The farm is going away; its last batch is committed on drop.
                return Ok(());
            }
        }
    }
}
