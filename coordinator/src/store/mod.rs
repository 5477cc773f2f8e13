//! Persistence: every SQL statement lives in [`db`], every blob file in [`files`]. The farm's
//! state machine writes through to both before it answers a request.

pub mod db;
pub mod files;

pub use db::{Db, JobRow, LoadedJob, StoredJob, StoredLease, StoredWorker, UnloadableJob};
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
}

impl StoreError {
    pub fn io(context: impl Into<String>, source: std::io::Error) -> Self {
        StoreError::Io {
            context: context.into(),
            source,
        }
    }
}
