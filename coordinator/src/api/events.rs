//! `GET /events`: a server-sent event stream of what changes in the farm, for the dashboard.
//! Change notifications carry only ids; the current state is looked up when an event is
//! written, and a burst of notifications about one job or tile becomes one event.

use std::collections::HashSet;
use std::convert::Infallible;
use std::sync::Arc;
use std::time::Duration;

use axum::response::sse::{Event, KeepAlive, Sse};
use futures_util::Stream;
use protocol::{EVENT_JOB, EVENT_RESYNC, EVENT_TILE, EVENT_WORKERS};
use tokio::sync::broadcast::error::{RecvError, TryRecvError};
use tokio::sync::broadcast::Receiver;

use super::AppState;
use crate::farm::{Farm, FarmEvent};

/// How often the worker list goes out whole (it also does after tile changes): worker states
/// also change with time alone (a silent worker becomes lost), which no notification marks.
const WORKERS_EVERY: Duration = Duration::from_secs(2);

struct Reader {
    farm: Arc<Farm>,
    events: Receiver<FarmEvent>,
    ticker: tokio::time::Interval,
    /// Events ready to be written, oldest first.
    ready: std::collections::VecDeque<Event>,
    done: bool,
}

fn json_event(name: &str, value: &impl serde::Serialize) -> Event {
    let data = serde_json::to_string(value).unwrap_or_else(|_| "null".into());
    Event::default().event(name).data(data)
}

impl Reader {
    fn workers(&self) -> Event {
        json_event(EVENT_WORKERS, &self.farm.workers())
    }

    /// Turns `first` and every notification already waiting into events, each job and tile
    /// once, in the order first seen.
    fn collect(&mut self, first: FarmEvent) {
        let mut batch = vec![first];
        loop {
            match self.events.try_recv() {
                Ok(e) => batch.push(e),
                Err(TryRecvError::Lagged(_)) => {
                    self.ready.push_back(json_event(EVENT_RESYNC, &()));
                }
                Err(TryRecvError::Empty | TryRecvError::Closed) => break,
            }
        }
        // Tiles changing hands change their workers' states too.
        let workers_changed = batch.iter().any(|e| matches!(e, FarmEvent::Tile(..)));
        let mut seen = HashSet::new();
        for e in batch {
            if !seen.insert(e.clone()) {
                continue;
            }
            let event = match e {
                FarmEvent::Job(id) => self.farm.job(id).ok().map(|j| json_event(EVENT_JOB, &j)),
                FarmEvent::Tile(id, t) => self
                    .farm
                    .tile(id, t)
                    .ok()
                    .map(|t| json_event(EVENT_TILE, &t)),
                FarmEvent::Stopping => {
                    self.done = true;
                    None
                }
            };
            self.ready.extend(event);
        }
        if workers_changed {
            let workers = self.workers();
            self.ready.push_back(workers);
        }
    }

    async fn next(mut self) -> Option<(Result<Event, Infallible>, Self)> {
        loop {
            if let Some(event) = self.ready.pop_front() {
                return Some((Ok(event), self));
            }
            if self.done || self.farm.is_stopping() {
                return None;
            }
            tokio::select! {
                received = self.events.recv() => match received {
                    Ok(e) => self.collect(e),
                    Err(RecvError::Lagged(_)) => {
                        self.ready.push_back(json_event(EVENT_RESYNC, &()));
                    }
                    Err(RecvError::Closed) => self.done = true,
                },
                _ = self.ticker.tick() => {
                    let workers = self.workers();
                    self.ready.push_back(workers);
                }
            }
        }
    }
}

pub async fn stream(
    axum::extract::State(app): AppState,
) -> Sse<impl Stream<Item = Result<Event, Infallible>>> {
    let farm = app.farm.clone();
    let reader = Reader {
        events: farm.subscribe(),
        ticker: tokio::time::interval(WORKERS_EVERY),
        farm,
        ready: Default::default(),
        done: false,
    };
    // The first tick is immediate: a new reader gets the worker list at once.
    Sse::new(futures_util::stream::unfold(reader, Reader::next)).keep_alive(KeepAlive::default())
}
