//! The `tracer` binary's flags, messages and exit codes (2 usage, 3 scene, 4 render or I/O).

mod common;

use std::path::Path;
use std::process::{Command, Output};

fn tracer(args: &[&str], dir: &Path) -> Output {
    Command::new(env!("CARGO_BIN_EXE_tracer"))
        .args(args)
        .current_dir(dir)
        .output()
        .expect("the tracer binary runs")
}

fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

#[test]
fn a_missing_scene_file_is_a_scene_error_without_a_position() {
    let dir = tempfile::tempdir().unwrap();
    let out = tracer(&["render", "nosuch.scene", "-o", "x.png"], dir.path());
    assert_eq!(out.status.code(), Some(3), "{}", stderr(&out));
    assert_eq!(
        stderr(&out).trim(),
        "error: cannot read nosuch.scene: No such file or directory (os error 2)"
    );
}

#[test]
fn a_broken_scene_is_a_scene_error_at_its_position() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("broken.scene"),
        "<scene>\n  <camera>\n</scene>\n",
    )
    .unwrap();
    let out = tracer(&["render", "broken.scene", "-o", "x.png"], dir.path());
    assert_eq!(out.status.code(), Some(3), "{}", stderr(&out));
    assert!(
        stderr(&out).starts_with("error: broken.scene:"),
        "{}",
        stderr(&out)
    );
}

#[test]
fn an_unsupported_output_format_is_refused_before_rendering() {
    let dir = tempfile::tempdir().unwrap();
    // The scene does not exist: the output is refused first, so nothing is read.
    let out = tracer(&["render", "nosuch.scene", "-o", "x.jpg"], dir.path());
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    assert!(
        stderr(&out).contains("only PNG output is supported"),
        "{}",
        stderr(&out)
    );
    assert!(!dir.path().join("x.jpg").exists());
}

#[test]
fn bad_flags_and_settings_are_usage_errors() {
    let dir = tempfile::tempdir().unwrap();
    let scene = common::course("spheres.scene");
    let scene = scene.to_str().unwrap();
    let out = tracer(&["render", scene, "--spp", "0"], dir.path());
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    assert!(
        stderr(&out).contains("spp must be at least 1"),
        "{}",
        stderr(&out)
    );
    let out = tracer(&["render", scene, "--look-at", "0,0,0"], dir.path());
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    let out = tracer(&["render", scene, "--depth", "0", "-q"], dir.path());
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
}

#[test]
fn an_unwritable_output_is_an_io_failure() {
    let dir = tempfile::tempdir().unwrap();
    let scene = common::course("spheres.scene");
    let out = tracer(
        &[
            "render",
            scene.to_str().unwrap(),
            "-o",
            "no/such/dir/x.png",
            "--width",
            "8",
            "--height",
            "6",
            "--spp",
            "1",
        ],
        dir.path(),
    );
    assert_eq!(out.status.code(), Some(4), "{}", stderr(&out));
    assert!(
        stderr(&out).contains("cannot write no/such/dir/x.png: No such file"),
        "{}",
        stderr(&out)
    );
}

#[test]
fn negative_camera_coordinates_render_to_the_default_output_name() {
    let dir = tempfile::tempdir().unwrap();
    let scene = common::course("spheres.scene");
    let out = tracer(
        &[
            "render",
            scene.to_str().unwrap(),
            "--camera-pos",
            "-10,4,10",
            "--look-at",
            "0,1,0",
            "--width",
            "8",
            "--height",
            "6",
            "--spp",
            "1",
            "-q",
        ],
        dir.path(),
    );
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(dir.path().join("spheres.png").is_file());
}
