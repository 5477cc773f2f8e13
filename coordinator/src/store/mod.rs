//! Persistence: every SQL statement lives in [`db`], every blob file in [`files`]. The farm's
//! state machine writes through to both before it answers a request.

pub mod db;
pub mod files;

pub use db::{Db, Durable, JobRow, LoadedJob, StoredJob, StoredLease, StoredWorker, UnloadableJob};
pub use files::Files;

#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("database: {0}")]
    Db(#[from] rusqlite::Error),
    #[error("{context}: {source}")]
    Io {
        context: String,
        source: std::io::Error,
    },
    #[error("corrupt data: {0}")]
    Corrupt(String),
    /// A change whose batch could not be committed.
    #[error("{0}")]
    Lost(String),
}

impl From<tracer_core::film::ImageError> for StoreError {
    /// A stored tile that does not make the image it belongs to.
    fn from(e: tracer_core::film::ImageError) -> Self {
        StoreError::Corrupt(e.to_string())
    }
}

impl StoreError {
    pub fn io(context: impl Into<String>, source: std::io::Error) -> Self {
        StoreError::Io {
            context: context.into(),
            source,
        }
    }
}
