//! The `worker` binary's refusals: bad input stops it at once with exit code 2 and a message
//! that says what to fix, before it contacts anything.
//!
//! Also why this file exists in worker/ rather than tests/: cargo builds a package's binaries
//! for its integration tests, so `cargo test --workspace` builds `target/<profile>/worker`,
//! which the farm tests in tests/ start as a process.

use std::process::{Command, Output};

fn worker(args: &[&str]) -> Output {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_worker"));
    // The caller's TESSERA_* variables must not fill in flags.
    for (key, _) in std::env::vars_os() {
        if key.to_string_lossy().starts_with("TESSERA_") {
            cmd.env_remove(key);
        }
    }
    cmd.args(args).output().expect("running the worker binary")
}

#[test]
fn a_coordinator_url_without_a_scheme_is_refused() {
    let out = worker(&["--coordinator", "10.0.0.5:7878"]);
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("must start with http:// or https://"), "{err}");
}

#[test]
fn an_unknown_key_in_the_config_file_names_the_key_and_the_file() {
    let file = std::env::temp_dir().join(format!("tessera-worker-cli-{}.toml", std::process::id()));
    std::fs::write(&file, "[worker]\ncoordinatr = \"http://127.0.0.1:7878\"\n").unwrap();
    let out = worker(&["--config", file.to_str().unwrap()]);
    std::fs::remove_file(&file).unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("unknown key `coordinatr` in [worker]"),
        "{err}"
    );
    assert!(err.contains(&file.display().to_string()), "{err}");
}
