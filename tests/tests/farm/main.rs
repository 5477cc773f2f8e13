//! The farm across processes: a real coordinator and real workers, compared with `tracer
//! render` byte for byte, through worker and coordinator crashes, bad submissions, ssh and
//! docker compose.

mod helpers;

mod api;
mod client_cli;
mod config;
mod dashboard;
mod dashboard_api;
mod deploy;
mod e2e;
mod faults;
mod hardening;
mod progressive;
mod webdriver;
