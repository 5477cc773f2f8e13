//! What Tessera's command lines share: the render flags (declared once, flattened into
//! `tracer render` and the coordinator's `render` and `submit`), the output flags, loading a
//! scene file, and how a failure is printed and what it exits with.

use std::error::Error;
use std::path::{Path, PathBuf};

use clap::Args;

use crate::film::ImageFormat;
use crate::scene::{FsAssets, Scene, SceneDescription, SceneError};
use crate::settings::{parse_vec3, CameraOverride, CausticsSettings, FrameRange, RenderSettings};
use crate::texture::TextureFilter;

/// Exit codes (documented in the README).
pub mod exit {
    /// Bad flags or settings: nothing was rendered.
    pub const USAGE: u8 = 2;
    /// The scene cannot be read or loaded.
    pub const SCENE: u8 = 3;
    /// Rendering, the farm or writing the output failed.
    pub const FAILURE: u8 = 4;
}

/// Render settings as command-line flags.
#[derive(Args, Clone, Debug, PartialEq)]
#[group(id = "render_flags")]
pub struct RenderArgs {
    /// Image width in pixels.
    #[arg(long, default_value_t = 800)]
    pub width: u32,
    /// Image height in pixels.
    #[arg(long, default_value_t = 600)]
    pub height: u32,
    /// Samples per pixel (stratified); 1 traces through pixel centres.
    #[arg(long, default_value_t = 4)]
    pub spp: u32,
    /// Ray levels, the eye ray included (the course's 5 allows 4 bounces).
    #[arg(long, default_value_t = 5)]
    pub depth: u32,
    /// Random seed.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Camera position x,y,z (with --look-at), replacing the scene's camera.
    #[arg(long, value_parser = parse_vec3, allow_hyphen_values = true, requires = "look_at")]
    pub camera_pos: Option<[f64; 3]>,
    /// Point the camera looks at, x,y,z.
    #[arg(long, value_parser = parse_vec3, allow_hyphen_values = true, requires = "camera_pos")]
    pub look_at: Option<[f64; 3]>,
    /// Camera up vector x,y,z (with --camera-pos) [default: 0,1,0].
    #[arg(long, value_parser = parse_vec3, allow_hyphen_values = true, requires = "camera_pos")]
    pub up: Option<[f64; 3]>,
    /// Bilinear texture filtering instead of nearest texel.
    #[arg(long)]
    pub bilinear: bool,
    /// Caustics by photon mapping, even if the scene has no <caustics> element.
    #[arg(long, conflicts_with = "no_caustics")]
    pub caustics: bool,
    /// No caustics, even if the scene asks for them.
    #[arg(long)]
    pub no_caustics: bool,
    /// Caustic photons to emit (turns caustics on; overrides the scene's count).
    #[arg(long, conflicts_with = "no_caustics")]
    pub photons: Option<u32>,
    /// Caustic gather radius in scene units (turns caustics on; overrides the scene's).
    #[arg(long, conflicts_with = "no_caustics", allow_negative_numbers = true)]
    pub photon_radius: Option<f64>,
    /// Render this frame of an animated scene (0-based) [default: 0].
    #[arg(long, conflicts_with = "frames")]
    pub frame: Option<u32>,
    /// Render frames A through B inclusive (A..B), each to the output name with the frame
    /// number inserted: out.png → out_0003.png.
    #[arg(long)]
    pub frames: Option<FrameRange>,
}

impl RenderArgs {
    /// The settings the flags ask for (frame `--frame`, or 0 when rendering `--frames`).
    pub fn to_settings(&self) -> RenderSettings {
        RenderSettings {
            width: self.width,
            height: self.height,
            spp: self.spp,
            max_depth: self.depth,
            seed: self.seed,
            camera: self
                .camera_pos
                .zip(self.look_at)
                .map(|(position, look_at)| CameraOverride {
                    position,
                    look_at,
                    up: self.up.unwrap_or([0.0, 1.0, 0.0]),
                }),
            texture_filter: if self.bilinear {
                TextureFilter::Bilinear
            } else {
                TextureFilter::Nearest
            },
            frame: self.frame.unwrap_or(0),
            caustics: CausticsSettings::from_flags(
                self.caustics,
                self.no_caustics,
                self.photons,
                self.photon_radius,
            ),
        }
    }
}

/// Where the image goes, and whether progress is shown.
#[derive(Args, Clone, Debug, PartialEq)]
#[group(id = "output_flags")]
pub struct OutputArgs {
    /// Output image: .png (8-bit, the course's quantisation), .exr or .pfm (linear f32)
    /// [default: the scene's name with .png, in the current folder].
    #[arg(short, long)]
    pub output: Option<PathBuf>,
    /// No progress bar.
    #[arg(short, long)]
    pub quiet: bool,
}

/// An output the command lines cannot write.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum OutputError {
    #[error("cannot write {0}: the output must be a .png, .exr or .pfm file")]
    Unsupported(PathBuf),
}

impl OutputArgs {
    /// The output for `scene`: `-o` as given, or the scene's name with `.png`; refused
    /// unless its extension names a format [`check_output`] accepts.
    pub fn path_for(&self, scene: &Path) -> Result<PathBuf, OutputError> {
        let path = self.output.clone().unwrap_or_else(|| default_output(scene));
        check_output(&path)?;
        Ok(path)
    }
}

/// The scene's file name with `.png`, in the current folder.
pub fn default_output(scene: &Path) -> PathBuf {
    let stem = scene
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "render".into());
    PathBuf::from(format!("{stem}.png"))
}

/// The format an output name's extension (in any case) asks for: `.png`, `.exr` or `.pfm`.
/// Anything else is refused rather than written as PNG: a `.jpg` full of PNG bytes would
/// only mislead.
pub fn check_output(path: &Path) -> Result<ImageFormat, OutputError> {
    ImageFormat::from_path(path).ok_or_else(|| OutputError::Unsupported(path.to_path_buf()))
}

/// A scene file that cannot be loaded.
#[derive(Debug, thiserror::Error)]
pub enum LoadError {
    #[error("cannot read {path}")]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error(transparent)]
    Scene(#[from] SceneError),
}

/// Reads and loads a scene file with the assets it references (see [`Scene::load`]); a file
/// that cannot be read is reported as such, with no line and column.
pub fn load_scene(path: &Path) -> Result<Scene, LoadError> {
    let text = std::fs::read_to_string(path).map_err(|source| LoadError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    let file = path.display().to_string();
    let description = SceneDescription::parse(&text, &file)?;
    Ok(Scene::build(
        &description,
        &file,
        &FsAssets::for_scene(path),
    )?)
}

/// `error`'s message followed by each of its causes: `a: b: c`.
pub fn error_chain(error: &dyn Error) -> String {
    let mut out = error.to_string();
    let mut source = error.source();
    while let Some(cause) = source {
        out.push_str(": ");
        out.push_str(&cause.to_string());
        source = cause.source();
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        render: RenderArgs,
        #[command(flatten)]
        output: OutputArgs,
    }

    #[test]
    fn defaults_are_the_default_settings() {
        let cli = Cli::try_parse_from(["t"]).unwrap();
        assert_eq!(cli.render.to_settings(), RenderSettings::default());
        assert_eq!(
            cli.output.path_for(Path::new("a/b/stacks.scene")).unwrap(),
            Path::new("stacks.png")
        );
        assert!(!cli.output.quiet);
    }

    #[test]
    fn negative_coordinates_parse_and_camera_flags_go_together() {
        let cli = Cli::try_parse_from([
            "t",
            "--camera-pos",
            "-10,4,10",
            "--look-at",
            "-1,-2,-3",
            "--up",
            "0,-1,0",
        ])
        .unwrap();
        let camera = cli.render.to_settings().camera.unwrap();
        assert_eq!(camera.position, [-10.0, 4.0, 10.0]);
        assert_eq!(camera.look_at, [-1.0, -2.0, -3.0]);
        assert_eq!(camera.up, [0.0, -1.0, 0.0]);
        assert!(Cli::try_parse_from(["t", "--look-at", "0,0,0"]).is_err());
        assert!(Cli::try_parse_from(["t", "--up", "0,0,1"]).is_err());
        let radius = Cli::try_parse_from(["t", "--photon-radius", "-1"]).unwrap();
        assert!(radius.render.to_settings().validate().is_err());
    }

    #[test]
    fn only_supported_outputs_are_accepted() {
        assert_eq!(check_output(Path::new("x.png")), Ok(ImageFormat::Png));
        assert_eq!(check_output(Path::new("X.PNG")), Ok(ImageFormat::Png));
        assert_eq!(check_output(Path::new("out.exr")), Ok(ImageFormat::Exr));
        assert_eq!(check_output(Path::new("out.Pfm")), Ok(ImageFormat::Pfm));
        let err = check_output(Path::new("x.jpg")).unwrap_err();
        assert!(err.to_string().contains(".png, .exr or .pfm"), "{err}");
        assert!(check_output(Path::new("x")).is_err());
        assert!(check_output(Path::new("x.exr.gz")).is_err());
    }

    #[test]
    fn a_missing_scene_file_says_so_without_a_position() {
        let err = load_scene(Path::new("nosuch.scene")).unwrap_err();
        assert!(matches!(err, LoadError::Read { .. }));
        let message = error_chain(&err);
        assert!(
            message.starts_with("cannot read nosuch.scene: "),
            "{message}"
        );
        assert!(!message.contains(":0:0"), "{message}");
    }
}
