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
        stderr(&out).contains("the output must be a .png, .exr or .pfm file"),
        "{}",
        stderr(&out)
    );
    assert!(!dir.path().join("x.jpg").exists());
}

/// The float outputs hold the linear pixels the PNG quantises: the EXR read back with the
/// `exr` crate, quantised, gives the PNG's bytes, and the PFM holds the same floats.
#[test]
fn exr_and_pfm_outputs_hold_the_linear_pixels_of_the_png() {
    use exr::prelude::{ReadChannels, ReadLayers};
    use tracer_core::film::quantize;
    let dir = tempfile::tempdir().unwrap();
    let scene = common::course("spheres.scene");
    for name in ["x.png", "x.exr", "x.pfm"] {
        let out = tracer(
            &[
                "render",
                scene.to_str().unwrap(),
                "-o",
                name,
                "--width",
                "16",
                "--height",
                "12",
                "--spp",
                "2",
                "-q",
            ],
            dir.path(),
        );
        assert!(out.status.success(), "{name}: {}", stderr(&out));
    }
    let read = |name: &str| std::fs::read(dir.path().join(name)).unwrap();
    let png = tracer_core::Image::from_png_bytes(&read("x.png")).unwrap();
    let exr = exr::prelude::read()
        .no_deep_data()
        .largest_resolution_level()
        .rgb_channels(
            |size, _| vec![0f32; 3 * size.area()],
            |pixels: &mut Vec<f32>, pos, (r, g, b): (f32, f32, f32)| {
                let i = 3 * (pos.y() * 16 + pos.x());
                pixels[i..i + 3].copy_from_slice(&[r, g, b]);
            },
        )
        .first_valid_layer()
        .all_attributes()
        .from_buffered(std::io::Cursor::new(read("x.exr")))
        .unwrap();
    let size = exr.layer_data.size;
    assert_eq!((size.width(), size.height()), (16, 12));
    let linear = exr.layer_data.channel_data.pixels;
    let quantised: Vec<u8> = linear.iter().map(|&v| quantize(v)).collect();
    assert_eq!(quantised, png.to_rgb8());
    assert!(
        linear.iter().any(|&v| v != quantize(v) as f32 / 255.0),
        "the EXR holds more than 8-bit values"
    );
    let pfm = read("x.pfm");
    let header = b"PF\n16 12\n-1.0\n";
    assert_eq!(&pfm[..header.len()], header);
    let rows: Vec<&[u8]> = pfm[header.len()..].chunks_exact(16 * 3 * 4).collect();
    let top_first: Vec<f32> = rows
        .iter()
        .rev()
        .flat_map(|row| row.chunks_exact(4))
        .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
        .collect();
    assert_eq!(top_first, linear);
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
