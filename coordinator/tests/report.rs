//! `coordinator report` end to end on a small render: the embedded farm at two worker counts
//! plus the in-process baseline, the three files written, and the error falling as the sample
//! count rises on every curve.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::process::{Command, Output};

/// `coordinator report` on the course's cornell_box, the options left to the caller.
fn cornell_box_report() -> Command {
    let scene = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/scenes/course/cornell_box.scene");
    let mut command = Command::new(env!("CARGO_BIN_EXE_coordinator"));
    command.arg("report").arg(scene);
    command
}

/// A fresh output folder per test and process, so parallel test runs do not collide.
fn report_dir(name: &str) -> PathBuf {
    std::env::temp_dir().join(format!("tessera-{name}-{}", std::process::id()))
}

fn assert_succeeded(output: &Output) {
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
}

#[test]
fn a_small_farm_report_runs_and_error_falls_with_samples() {
    let out = report_dir("farm-report");
    let output = cornell_box_report()
        .args([
            "--width",
            "64",
            "--height",
            "48",
            "--reference-spp",
            "64",
            "--spp",
            "1,4,16",
            "--workers",
            "1,2",
            "--threads",
            "2",
            "--tile-size",
            "16",
        ])
        .arg("-o")
        .arg(&out)
        .output()
        .unwrap();
    assert_succeeded(&output);
    for file in ["report.csv", "report.md", "error_vs_time.png"] {
        assert!(out.join(file).is_file(), "{file} is missing");
    }
    let csv = std::fs::read_to_string(out.join("report.csv")).unwrap();
    let mut lines = csv.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    // Counted from the right: the label comes first and may be quoted (with commas inside).
    let rmse_from_right = header.len() - 1 - header.iter().position(|&c| c == "rmse").unwrap();
    let mut curves: BTreeMap<String, Vec<f64>> = BTreeMap::new();
    for line in lines {
        let fields: Vec<&str> = line.rsplitn(header.len(), ',').collect();
        curves
            .entry(fields[header.len() - 1].trim_matches('"').to_string())
            .or_default()
            .push(fields[rmse_from_right].parse().unwrap());
    }
    let names: Vec<&String> = curves.keys().collect();
    assert_eq!(
        names,
        ["farm: 1 worker", "farm: 2 workers", "in-process: 2 threads"],
        "{csv}"
    );
    for (config, rmse) in &curves {
        assert!(
            rmse[0] > rmse[1] && rmse[1] > rmse[2],
            "{config}: error does not fall: {rmse:?}"
        );
    }
    // The farm renders the same pixels as the tracer: the same errors on every curve.
    assert_eq!(curves["farm: 1 worker"], curves["in-process: 2 threads"]);
    assert_eq!(curves["farm: 2 workers"], curves["in-process: 2 threads"]);
    std::fs::remove_dir_all(&out).unwrap();
}

#[test]
fn a_report_rejects_impossible_worker_counts() {
    let output = Command::new(env!("CARGO_BIN_EXE_coordinator"))
        .args(["report", "missing.scene", "--workers", "0"])
        .output()
        .unwrap();
    assert!(!output.status.success());
    assert!(String::from_utf8_lossy(&output.stderr).contains("--workers 0"));
}

#[test]
fn repeated_adaptive_runs_are_listed_paired_and_summarised_by_their_median() {
    let out = report_dir("paired-report");
    let output = cornell_box_report()
        .args(["--width", "64", "--height", "48", "--reference-spp", "64"])
        .args(["--spp", "4,16", "--workers", "1", "--threads", "2"])
        .args(["--no-baseline", "--adaptive", "0.01", "--repeats", "3"])
        .arg("-o")
        .arg(&out)
        .output()
        .unwrap();
    assert_succeeded(&output);
    // Every run: 2 budgets × 3 repeats × (uniform, adaptive), uniform first in each pair.
    let runs = std::fs::read_to_string(out.join("runs.csv")).unwrap();
    let lines: Vec<&str> = runs.lines().skip(1).collect();
    assert_eq!(lines.len(), 12, "{runs}");
    for pair in lines.chunks(2) {
        assert!(
            pair[0].contains(",false,") && pair[1].contains(",true,"),
            "{runs}"
        );
    }
    // One median row per configuration and budget.
    let csv = std::fs::read_to_string(out.join("report.csv")).unwrap();
    assert_eq!(csv.lines().count(), 1 + 4, "{csv}");
    let md = std::fs::read_to_string(out.join("report.md")).unwrap();
    assert!(md.contains("pair by pair"), "{md}");
    assert!(md.contains("| 1 | 16 | 3 |"), "{md}");
    std::fs::remove_dir_all(&out).unwrap();
}
