//! Change notifications for `GET /events`: readers look the current state up, so a burst of
//! changes to one job costs one message.

use tokio::sync::broadcast;

#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub enum FarmEvent {
    Job(u64),
    Tile(u64, u32),
    /// The farm is stopping: event streams end so the server can.
    Stopping,
}

/// How many events a slow reader may fall behind before it is told to resynchronise.
const EVENT_BACKLOG: usize = 4096;

pub struct Events(broadcast::Sender<FarmEvent>);

impl Default for Events {
    fn default() -> Events {
        Events(broadcast::channel(EVENT_BACKLOG).0)
    }
}

impl Events {
    pub fn subscribe(&self) -> broadcast::Receiver<FarmEvent> {
        self.0.subscribe()
    }

    pub fn send(&self, event: FarmEvent) {
        // An error only means nobody is listening.
        let _ = self.0.send(event);
    }

    /// A tile changed, and with it its job's progress.
    pub fn tile(&self, job_id: u64, tile: u32) {
        self.send(FarmEvent::Tile(job_id, tile));
        self.send(FarmEvent::Job(job_id));
    }
}
