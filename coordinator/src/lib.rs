//! Tessera's farm coordinator: splits each job's frame into tiles, leases them to pull
//! workers over HTTP, persists everything, and assembles the final PNG.
//!
//! - [`farm`]: the state machine that owns every job, tile and lease transition.
//! - [`store`]: SQLite (jobs, finished tiles, failures, leases) and files (content-addressed
//!   blobs, tile pixels, images) under the data dir.
//! - [`api`]: the HTTP routes (`docs/api.md`), authentication and error mapping.
//! - [`server`]: serving the API and reaping lapsed leases.
//! - [`config`], [`clock`], [`metrics`]: tunables and limits, injected time, Prometheus text.
//! - [`embedded`]: an in-process farm (coordinator + local workers) on loopback.
//! - [`cli`]: the `serve`, `render` (embedded farm), `report` and `submit` commands.
//!
//! The wire types and the client live in the `protocol` crate (re-exported as [`protocol`]);
//! the worker crate is named only by [`embedded`] and [`cli`], which run in-process workers.

pub mod api;
pub mod cli;
pub mod clock;
pub mod config;
pub mod embedded;
pub mod farm;
pub mod metrics;
pub mod server;
pub mod store;

pub use protocol;
