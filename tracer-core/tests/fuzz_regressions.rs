//! Every input that ever crashed a fuzz target (`fuzz/`, run with `scripts/fuzz`), replayed by
//! the target's own code on the stable toolchain. Inputs live in `fuzz-regressions/TARGET/`,
//! each named after what it found.

#[path = "../../fuzz/src/harness.rs"]
mod harness;

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::PathBuf;

#[test]
fn every_saved_fuzz_input_replays_cleanly() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fuzz-regressions");
    let mut replayed = 0;
    let mut failures = Vec::new();
    for target in ["scene_xml", "obj", "obj_render"] {
        // A target that never crashed has no folder (git keeps no empty ones).
        let Ok(entries) = std::fs::read_dir(root.join(target)) else {
            continue;
        };
        let mut inputs: Vec<PathBuf> = entries
            .map(|entry| entry.unwrap().path())
            .filter(|path| path.is_file())
            .collect();
        inputs.sort();
        for input in inputs {
            let data = std::fs::read(&input).unwrap();
            if catch_unwind(AssertUnwindSafe(|| harness::run(target, &data))).is_err() {
                failures.push(input.display().to_string());
            }
            replayed += 1;
        }
    }
    assert!(replayed > 0, "no saved inputs under {}", root.display());
    assert!(
        failures.is_empty(),
        "these inputs crash again: {failures:#?}"
    );
}
