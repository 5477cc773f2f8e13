//! `tracer report` end to end on a small render: the three files appear and the error falls
//! as the sample count rises.

use std::path::PathBuf;
use std::process::Command;

#[test]
fn a_small_report_runs_and_error_falls_with_samples() {
    let scene = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/scenes/course/cornell_box.scene");
    let out = std::env::temp_dir().join(format!("tessera-report-{}", std::process::id()));
    let status = Command::new(env!("CARGO_BIN_EXE_tracer"))
        .arg("report")
        .arg(&scene)
        .args([
            "--width",
            "80",
            "--height",
            "60",
            "--reference-spp",
            "64",
            "--spp",
            "1,4,16",
        ])
        .arg("-o")
        .arg(&out)
        .status()
        .unwrap();
    assert!(status.success());
    for file in ["report.csv", "report.md", "error_vs_time.png"] {
        assert!(out.join(file).is_file(), "{file} is missing");
    }
    let csv = std::fs::read_to_string(out.join("report.csv")).unwrap();
    let rmse: Vec<f64> = csv
        .lines()
        .skip(1)
        .map(|l| l.split(',').nth(3).unwrap().parse().unwrap())
        .collect();
    assert_eq!(rmse.len(), 3);
    assert!(
        rmse[0] > rmse[1] && rmse[1] > rmse[2],
        "error does not fall: {rmse:?}"
    );
    assert!(std::fs::read_to_string(out.join("report.md"))
        .unwrap()
        .contains("Fitted slope"));
    std::fs::remove_dir_all(&out).unwrap();
}
