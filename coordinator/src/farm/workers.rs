//! The worker registry: identities the coordinator issued (kept in SQLite, so they survive a
//! restart) and what it has heard from each since it started. Names are labels only.

use std::collections::HashMap;

use protocol::{WorkerInfo, WorkerLease, WorkerState};

use crate::store::StoredWorker;

#[derive(Debug, Default)]
pub struct WorkerRecord {
    pub name: String,
    /// Heard from since this coordinator started (only those are listed).
    pub heard: bool,
    pub last_seen_ms: u64,
    pub address: Option<String>,
    pub tiles_done: u64,
    /// Its last lease lapsed without a heartbeat (cleared when it is heard from again).
    pub lapsed: bool,
}

#[derive(Debug, Default)]
pub struct Registry {
    records: HashMap<u64, WorkerRecord>,
}

impl Registry {
    pub fn load(stored: Vec<StoredWorker>) -> Registry {
        Registry {
            records: stored
                .into_iter()
                .map(|w| {
                    let record = WorkerRecord {
                        name: w.name,
                        ..WorkerRecord::default()
                    };
                    (w.id, record)
                })
                .collect(),
        }
    }

    pub fn len(&self) -> usize {
        self.records.len()
    }

    pub fn contains(&self, id: u64) -> bool {
        self.records.contains_key(&id)
    }

    pub fn insert(&mut self, id: u64, name: String, now: u64) {
        self.records.insert(
            id,
            WorkerRecord {
                name,
                heard: true,
                last_seen_ms: now,
                ..WorkerRecord::default()
            },
        );
    }

    pub fn remove(&mut self, id: u64) {
        self.records.remove(&id);
    }

    pub fn name(&self, id: u64) -> String {
        self.records
            .get(&id)
            .map_or_else(|| format!("worker {id}"), |r| r.name.clone())
    }

    /// Records that `id` was heard from.
    pub fn seen(&mut self, id: u64, now: u64) -> Option<&mut WorkerRecord> {
        let record = self.records.get_mut(&id)?;
        record.heard = true;
        record.last_seen_ms = now;
        record.lapsed = false;
        Some(record)
    }

    /// The id of the worker registered under `name` (tests, where names are unique).
    #[cfg(test)]
    pub fn id_of(&self, name: &str) -> Option<u64> {
        self.records
            .iter()
            .filter(|(_, r)| r.name == name)
            .map(|(id, _)| *id)
            .min()
    }

    pub fn get_mut(&mut self, id: u64) -> Option<&mut WorkerRecord> {
        self.records.get_mut(&id)
    }

    /// The worker to forget when the registry is full: the longest silent one that holds no
    /// lease.
    pub fn eviction_candidate(&self, holds_lease: impl Fn(u64) -> bool) -> Option<u64> {
        self.records
            .iter()
            .filter(|(id, _)| !holds_lease(**id))
            .min_by_key(|(id, r)| (r.last_seen_ms, **id))
            .map(|(id, _)| *id)
    }

    /// Every worker heard from since start-up, by name then id. A worker is lost when its
    /// lease lapsed, or when it has been silent longer than `silent_limit_ms`.
    pub fn list(
        &self,
        now: u64,
        silent_limit_ms: u64,
        lease_of: impl Fn(u64) -> Option<WorkerLease>,
    ) -> Vec<WorkerInfo> {
        let mut list: Vec<WorkerInfo> = self
            .records
            .iter()
            .filter(|(_, r)| r.heard)
            .map(|(&id, record)| {
                let lease = lease_of(id);
                let state = if lease.is_some() {
                    WorkerState::Rendering
                } else if record.lapsed || now.saturating_sub(record.last_seen_ms) > silent_limit_ms
                {
                    WorkerState::Lost
                } else {
                    WorkerState::Idle
                };
                WorkerInfo {
                    id,
                    name: record.name.clone(),
                    address: record.address.clone(),
                    state,
                    lease,
                    tiles_done: record.tiles_done,
                    last_seen_ms: record.last_seen_ms,
                }
            })
            .collect();
        list.sort_by(|a, b| a.name.cmp(&b.name).then(a.id.cmp(&b.id)));
        list
    }

    /// Workers heard from, and those heard from within `window_ms` of `now`.
    pub fn counts(&self, now: u64, window_ms: u64) -> (u64, u64) {
        let heard = self.records.values().filter(|r| r.heard);
        let seen = heard.clone().count() as u64;
        let active = heard
            .filter(|r| now.saturating_sub(r.last_seen_ms) < window_ms)
            .count() as u64;
        (seen, active)
    }
}
