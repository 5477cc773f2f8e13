//! Where a ray is born. The pinhole camera of conventions §3 (vertical fov, aspect from the
//! image, +X right; with an aperture, a thin lens focused on a plane), and [`EyeRays`]: each
//! pixel sample's eye ray — its stratum jitter, shutter time, lens point and the random
//! streams it starts, all seeded by (seed, pixel, sample) alone.

use glam::{DQuat, DVec3};

use crate::geometry::Ray;
use crate::sampler::{concentric_disk, strata, Rng, SampleOrder, StrataOrder, Stream};
use crate::scene::{CameraDesc, Scene};
use crate::settings::{CameraOverride, RenderSettings};

#[derive(Clone, Copy, Debug)]
pub struct Camera {
    pub position: DVec3,
    forward: DVec3,
    up: DVec3,
    right: DVec3,
    tan_half_fov: f64,
    aspect: f64,
    /// Eye-ray hits are accepted only for t in [near, far] (unit directions).
    pub near: f64,
    pub far: f64,
    /// Lens radius; 0 is a pinhole.
    pub aperture: f64,
    /// Distance of the plane in focus, along the view direction.
    pub focus_distance: f64,
}

impl Camera {
    pub fn from_orientation(
        position: DVec3,
        orientation: DQuat,
        fov: f64,
        near: f64,
        far: f64,
        aspect: f64,
    ) -> Camera {
        let forward = orientation * DVec3::NEG_Z;
        let up = orientation * DVec3::Y;
        Camera {
            position,
            forward,
            up,
            right: forward.cross(up),
            tan_half_fov: (fov / 2.0).tan(),
            aspect,
            near,
            far,
            aperture: 0.0,
            focus_distance: 1.0,
        }
    }

    /// The same camera with a thin lens of radius `aperture` focused at `focus_distance`.
    pub fn with_lens(self, aperture: f64, focus_distance: f64) -> Camera {
        Camera {
            aperture,
            focus_distance,
            ..self
        }
    }

    /// The scene camera's fov and clip planes, placed by a look-at override.
    pub fn with_override(&self, o: &CameraOverride) -> Camera {
        let position = DVec3::from_array(o.position);
        let forward = (DVec3::from_array(o.look_at) - position).normalize();
        let right = forward.cross(DVec3::from_array(o.up)).normalize();
        Camera {
            position,
            forward,
            up: right.cross(forward),
            right,
            ..*self
        }
    }

    /// The eye ray through image point (x, y), in pixels from the **bottom-left** corner.
    #[inline]
    pub fn ray(&self, x: f64, y: f64, width: f64, height: f64) -> Ray {
        let i = 2.0 * x / width - 1.0;
        let j = 2.0 * y / height - 1.0;
        let dir = self.forward + self.tan_half_fov * (j * self.up + self.aspect * i * self.right);
        Ray::new(self.position, dir.normalize())
    }

    /// Inward normals of the four planes through the camera position that bound every
    /// pinhole eye ray through the image rectangle [x0, x1] × [y0, y1] (pixels from the
    /// bottom-left corner): a point p lies between them when n·(p − position) ≥ 0 for each.
    pub fn frustum(
        &self,
        x0: f64,
        y0: f64,
        x1: f64,
        y1: f64,
        width: f64,
        height: f64,
    ) -> [DVec3; 4] {
        let dir = |x: f64, y: f64| {
            let i = 2.0 * x / width - 1.0;
            let j = 2.0 * y / height - 1.0;
            self.forward + self.tan_half_fov * (j * self.up + self.aspect * i * self.right)
        };
        let corners = [dir(x0, y0), dir(x1, y0), dir(x1, y1), dir(x0, y1)];
        let centre = dir(0.5 * (x0 + x1), 0.5 * (y0 + y1));
        std::array::from_fn(|k| {
            let n = corners[k].cross(corners[(k + 1) % 4]);
            if n.dot(centre) < 0.0 {
                -n
            } else {
                n
            }
        })
    }

    /// The thin-lens eye ray through image point (x, y) from lens point `lens` (a point of
    /// the unit disk): it leaves the aperture there and passes through the point of the focal
    /// plane that the pinhole ray meets, so only that plane stays sharp.
    #[inline]
    pub fn lens_ray(&self, x: f64, y: f64, width: f64, height: f64, lens: (f64, f64)) -> Ray {
        let pinhole = self.ray(x, y, width, height);
        let focus = pinhole.at(self.focus_distance / pinhole.dir.dot(self.forward));
        let origin = self.position + self.aperture * (lens.0 * self.right + lens.1 * self.up);
        Ray::new(origin, (focus - origin).normalize())
    }
}

/// One pixel sample's start: its eye ray, the range of hits it accepts, and its streams.
#[derive(Clone, Debug)]
pub struct EyeSample {
    pub ray: Ray,
    pub near: f64,
    pub far: f64,
    /// The sample's main stream, after the jitter's draws: shading continues on it.
    pub rng: Rng,
    /// The glossy-lobe stream, when some material of the scene is glossy.
    pub gloss: Option<Rng>,
}

/// The eye rays of one frame of a render.
#[derive(Clone, Debug)]
pub struct EyeRays<'a> {
    desc: &'a CameraDesc,
    /// The world point the scene is built around; cameras are placed relative to it.
    origin: DVec3,
    camera: Camera,
    width: u32,
    height: u32,
    spp: u32,
    seed: u64,
    strata: (u32, u32),
    /// The progressive order of those strata, made when first asked for.
    progressive: std::sync::OnceLock<StrataOrder>,
    /// Time of the shutter's opening for this frame, and how long it stays open.
    time_open: f64,
    shutter_length: f64,
    /// Whether samples draw a time (something moves while the shutter is open).
    sample_time: bool,
    /// Whether the camera itself moves while the shutter is open.
    camera_moves: bool,
    /// Whether samples seed the glossy-lobe stream.
    glossy: bool,
}

impl<'a> EyeRays<'a> {
    /// The eye rays of frame `settings.frame` of `scene` (a frame the scene has).
    pub fn new(scene: &'a Scene, settings: &RenderSettings) -> Self {
        let desc = &scene.description.camera;
        let time_open = settings.frame as f64 + desc.shutter[0];
        let shutter_length = desc.shutter[1] - desc.shutter[0];
        let moving = shutter_length > 0.0 && scene.description.has_motion();
        let origin = scene.origin();
        let mut camera = camera_at(desc, origin, settings.width, settings.height, time_open);
        if let Some(o) = &settings.camera {
            // Look-at points are world points: only the position moves with the frame.
            camera = camera.with_override(o);
            camera.position -= origin;
        }
        Self {
            desc,
            origin,
            camera,
            width: settings.width,
            height: settings.height,
            spp: settings.spp,
            seed: settings.seed,
            strata: strata(settings.spp),
            progressive: std::sync::OnceLock::new(),
            time_open,
            shutter_length,
            sample_time: moving,
            camera_moves: moving && settings.camera.is_none() && !desc.motion.is_static(),
            glossy: scene.has_gloss,
        }
    }

    /// The camera at the shutter's opening (overridden where the settings say so).
    pub fn camera(&self) -> &Camera {
        &self.camera
    }

    /// Where every eye ray of pixel (x, y) starts, and the inward normals of four planes
    /// through that point that enclose them all (see [`Camera::frustum`]); None where the
    /// pixel's rays do not share an origin (a thin lens, a moving camera). The pixel is
    /// widened by a twentieth of a pixel each way, far beyond the rounding of the rays'
    /// directions, so that no ray strays outside.
    pub fn pixel_frustum(&self, x: u32, y: u32) -> Option<(DVec3, [DVec3; 4])> {
        self.span_frustum(x..x + 1, y)
    }

    /// [`EyeRays::pixel_frustum`] of the pixels `xs` of row `y` together: one frustum holding
    /// each of theirs.
    pub fn span_frustum(&self, xs: std::ops::Range<u32>, y: u32) -> Option<(DVec3, [DVec3; 4])> {
        if self.camera_moves || self.camera.aperture > 0.0 {
            return None;
        }
        const MARGIN: f64 = 0.05;
        let (x0, x1, y) = (xs.start as f64, xs.end as f64, y as f64);
        let planes = self.camera.frustum(
            x0 - MARGIN,
            y - MARGIN,
            x1 + MARGIN,
            y + 1.0 + MARGIN,
            self.width as f64,
            self.height as f64,
        );
        Some((self.camera.position, planes))
    }

    /// The strata of pixel (x, y)'s samples `samples` under `order` into `out` (`out[i]` is
    /// sample `samples.start + i`'s stratum); left empty for the grid order, where sample k
    /// takes stratum k.
    pub fn strata_order(
        &self,
        order: SampleOrder,
        x: u32,
        y: u32,
        samples: std::ops::Range<u32>,
        out: &mut Vec<u32>,
    ) {
        match order {
            SampleOrder::Grid => out.clear(),
            SampleOrder::Progressive => self
                .progressive
                .get_or_init(|| StrataOrder::new(self.strata))
                .fill(self.seed, x, y, samples.start, samples.end, out),
        }
    }

    /// Sample `sample` of pixel (x, y), y counted from the image's **bottom** row, in the grid
    /// order.
    #[inline]
    pub fn sample(&self, x: u32, y: u32, sample: u32) -> EyeSample {
        self.sample_in(x, y, sample, sample)
    }

    /// Sample `sample` of pixel (x, y), jittered within stratum `stratum` (see
    /// [`EyeRays::strata_order`]). Its random numbers depend on the sample index alone.
    /// Always inlined (the eye ray is a large share of a simple scene's sample), its rare
    /// paths (a moving camera, a lens) kept out of line.
    #[inline(always)]
    pub fn sample_in(&self, x: u32, y: u32, sample: u32, stratum: u32) -> EyeSample {
        let seed = self.seed;
        let mut rng = Rng::for_sample(seed, x, y, sample);
        // One sample goes through the pixel centre; more are jittered within strata.
        let (jx, jy) = if self.spp == 1 {
            (0.5, 0.5)
        } else {
            jitter(self.strata, stratum, &mut rng)
        };
        // Effects draw from their own streams, so the numbers above stay the course's.
        let time = if self.sample_time {
            let mut r = Rng::for_stream(seed, x, y, sample, Stream::Time);
            self.time_open + self.shutter_length * r.next_f64()
        } else {
            self.time_open
        };
        let moved;
        let camera = if self.camera_moves {
            moved = camera_at(self.desc, self.origin, self.width, self.height, time);
            &moved
        } else {
            &self.camera
        };
        let (w, h) = (self.width as f64, self.height as f64);
        let (px, py) = (x as f64 + jx, y as f64 + jy);
        let ray = if camera.aperture > 0.0 {
            lens_ray(camera, seed, (x, y, sample), (px, py), (w, h))
        } else {
            camera.ray(px, py, w, h)
        }
        .at_time(time);
        EyeSample {
            ray,
            near: camera.near,
            far: camera.far,
            rng,
            gloss: self
                .glossy
                .then(|| Rng::for_stream(seed, x, y, sample, Stream::Gloss)),
        }
    }
}

impl EyeRays<'_> {
    /// [`EyeRays::sample_in`] for several samples of pixel (x, y), each a (sample, stratum)
    /// pair, appended to `out`: the same samples, bit for bit. For a still pinhole camera
    /// the rays are set up lane by lane over arrays, so that the compiler issues a step's
    /// divisions and square roots for several samples at once: one by one, the divider was
    /// the eye rays' bottleneck (seven divisions and a square root each).
    #[inline(always)]
    pub fn samples_in(&self, x: u32, y: u32, picks: &[(u32, u32)], out: &mut Vec<EyeSample>) {
        if self.spp == 1 || self.sample_time || self.camera_moves || self.camera.aperture > 0.0 {
            out.extend(
                picks
                    .iter()
                    .map(|&(s, stratum)| self.sample_in(x, y, s, stratum)),
            );
            return;
        }
        const LANES: usize = 8;
        let c = &self.camera;
        let (w, h) = (self.width as f64, self.height as f64);
        for chunk in picks.chunks(LANES) {
            let mut rngs = [const { Rng::from_state(0) }; LANES];
            let (mut px, mut py) = ([0.0; LANES], [0.0; LANES]);
            for (k, &(sample, stratum)) in chunk.iter().enumerate() {
                let mut rng = Rng::for_sample(self.seed, x, y, sample);
                let (jx, jy) = jitter(self.strata, stratum, &mut rng);
                px[k] = x as f64 + jx;
                py[k] = y as f64 + jy;
                rngs[k] = rng;
            }
            // `Camera::ray` and `Ray::new` written out per lane, in glam's order of
            // operations (so the same roundings).
            let mut dir = [[0.0; LANES]; 3];
            let mut inv = [[0.0; LANES]; 3];
            for k in 0..LANES {
                let i = 2.0 * px[k] / w - 1.0;
                let j = 2.0 * py[k] / h - 1.0;
                let a = c.aspect * i;
                let d: [f64; 3] = std::array::from_fn(|e| {
                    c.forward[e] + c.tan_half_fov * (j * c.up[e] + a * c.right[e])
                });
                let recip = 1.0 / (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                for e in 0..3 {
                    let unit = d[e] * recip;
                    dir[e][k] = unit;
                    inv[e][k] = if unit.abs() < 1e-300 {
                        1e300f64.copysign(unit)
                    } else {
                        1.0 / unit
                    };
                }
            }
            for (k, rng) in rngs.into_iter().take(chunk.len()).enumerate() {
                let sample = chunk[k].0;
                out.push(EyeSample {
                    ray: Ray::with_inverse(
                        c.position,
                        DVec3::new(dir[0][k], dir[1][k], dir[2][k]),
                        DVec3::new(inv[0][k], inv[1][k], inv[2][k]),
                    )
                    .at_time(self.time_open),
                    near: c.near,
                    far: c.far,
                    rng,
                    gloss: self
                        .glossy
                        .then(|| Rng::for_stream(self.seed, x, y, sample, Stream::Gloss)),
                });
            }
        }
    }
}

/// A point of stratum `stratum` of a pixel's grid of `cols` × `rows` strata, drawn from `rng`, in
/// [0, 1)²: (column + u) / columns, (row + v) / rows. Where the grid's sides are powers
/// of two (4 × 4 for 16 spp), the divisions are multiplications by the exact
/// reciprocals, which give the same bits, and the stratum's column and row are masks and
/// shifts: the two divisions were on each eye ray's chain of latencies.
#[inline(always)]
fn jitter((cols, rows): (u32, u32), stratum: u32, rng: &mut Rng) -> (f64, f64) {
    if cols.is_power_of_two() && rows.is_power_of_two() {
        let (cx, cy) = (stratum & (cols - 1), stratum >> cols.trailing_zeros());
        let (u, v) = (rng.next_f64(), rng.next_f64());
        (
            (cx as f64 + u) * (1.0 / cols as f64),
            (cy as f64 + v) * (1.0 / rows as f64),
        )
    } else {
        let (cx, cy) = (stratum % cols, stratum / cols);
        (
            (cx as f64 + rng.next_f64()) / cols as f64,
            (cy as f64 + rng.next_f64()) / rows as f64,
        )
    }
}

/// A thin-lens eye ray through image point (px, py) of a `w`×`h` image, its lens point drawn
/// from the lens stream of pixel (x, y)'s sample `sample`.
#[cold]
#[inline(never)]
fn lens_ray(
    camera: &Camera,
    seed: u64,
    (x, y, sample): (u32, u32, u32),
    (px, py): (f64, f64),
    (w, h): (f64, f64),
) -> Ray {
    let mut r = Rng::for_stream(seed, x, y, sample, Stream::Lens);
    let lens = concentric_disk(r.next_f64(), r.next_f64());
    camera.lens_ray(px, py, w, h, lens)
}

/// The scene's camera at `time`, before any override, for a `width`×`height` image, placed
/// relative to the world point `origin`.
#[cold]
#[inline(never)]
fn camera_at(desc: &CameraDesc, origin: DVec3, width: u32, height: u32, time: f64) -> Camera {
    let (position, orientation) = desc.at(time);
    Camera::from_orientation(
        position - origin,
        orientation,
        desc.fov,
        desc.near_clip.max(0.0),
        desc.far_clip,
        width as f64 / height as f64,
    )
    .with_lens(desc.aperture, desc.focus_at(time))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn jitter_in_grids_of_powers_of_two_gives_the_divisions_bits() {
        for grid in [(1, 1), (2, 1), (2, 2), (4, 2), (4, 4), (8, 8), (16, 8)] {
            let (cols, rows) = grid;
            for stratum in 0..cols * rows {
                for sample in 0..50 {
                    let mut rng = Rng::for_sample(7, 3, 5, sample);
                    let mut reference = rng.clone();
                    let (jx, jy) = jitter(grid, stratum, &mut rng);
                    let (cx, cy) = (stratum % cols, stratum / cols);
                    let ex = (cx as f64 + reference.next_f64()) / cols as f64;
                    let ey = (cy as f64 + reference.next_f64()) / rows as f64;
                    assert_eq!((jx.to_bits(), jy.to_bits()), (ex.to_bits(), ey.to_bits()));
                    assert_eq!(rng.next_u64(), reference.next_u64());
                }
            }
        }
    }

    #[test]
    fn centre_ray_looks_down_minus_z_and_corners_follow_fov() {
        let cam = Camera::from_orientation(DVec3::ZERO, DQuat::IDENTITY, 1.0, 0.1, 10.0, 2.0);
        let centre = cam.ray(50.0, 25.0, 100.0, 50.0);
        assert!((centre.dir - DVec3::NEG_Z).length() < 1e-15);
        // Top edge centre: vertical half-angle = fov/2.
        let top = cam.ray(50.0, 50.0, 100.0, 50.0);
        assert!((top.dir.y.atan2(-top.dir.z) - 0.5).abs() < 1e-12);
        // Right edge: horizontal half-extent is aspect·tan(fov/2), toward +X.
        let right = cam.ray(100.0, 25.0, 100.0, 50.0);
        assert!((right.dir.x / -right.dir.z - 2.0 * 0.5f64.tan()).abs() < 1e-12);
    }

    #[test]
    fn lens_rays_meet_on_the_focal_plane() {
        let cam = Camera::from_orientation(DVec3::ZERO, DQuat::IDENTITY, 1.0, 0.1, 10.0, 1.0)
            .with_lens(0.5, 4.0);
        let pinhole = cam.ray(30.0, 70.0, 100.0, 100.0);
        let focus = pinhole.at(4.0 / -pinhole.dir.z);
        assert!((focus.z + 4.0).abs() < 1e-12);
        for lens in [(1.0, 0.0), (-0.3, 0.7), (0.0, -1.0)] {
            let r = cam.lens_ray(30.0, 70.0, 100.0, 100.0, lens);
            assert!(
                (r.origin.length() - 0.5 * (lens.0 * lens.0 + lens.1 * lens.1).sqrt()).abs()
                    < 1e-12
            );
            let t = (focus - r.origin).length();
            assert!((r.at(t) - focus).length() < 1e-12);
        }
    }

    #[test]
    fn override_looks_at_its_target() {
        let cam = Camera::from_orientation(DVec3::ZERO, DQuat::IDENTITY, 0.8, 0.1, 10.0, 1.0);
        let moved = cam.with_override(&CameraOverride {
            position: [5.0, 5.0, 5.0],
            look_at: [0.0, 0.0, 0.0],
            up: [0.0, 1.0, 0.0],
        });
        let ray = moved.ray(0.5, 0.5, 1.0, 1.0);
        assert!((ray.dir + DVec3::ONE.normalize()).length() < 1e-12);
        assert_eq!(moved.near, 0.1);
    }

    #[test]
    fn a_batch_of_eye_samples_is_each_sample_bit_for_bit() {
        // Still pinhole cameras (the lane path; glossy.scene seeds the glossy stream too), a
        // thin lens and motion blur (the one-by-one path), at sample counts with square,
        // oblong and single strata, in the grid order and a progressive one.
        let root = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR"));
        for scene in [
            "../../shared/scenes/course/stacks.scene",
            "../scenes/glossy.scene",
            "../scenes/dof.scene",
            "../scenes/motion_blur.scene",
        ] {
            let scene = Scene::load(&root.join(scene)).unwrap_or_else(|e| panic!("{e}"));
            for spp in [1, 8, 16, 37] {
                let settings = RenderSettings {
                    width: 13,
                    height: 7,
                    spp,
                    seed: 77,
                    ..RenderSettings::default()
                };
                let eye = EyeRays::new(&scene, &settings);
                let mut order = Vec::new();
                for (x, y) in [(0, 0), (12, 6), (5, 3)] {
                    for sample_order in [SampleOrder::Grid, SampleOrder::Progressive] {
                        eye.strata_order(sample_order, x, y, 3..spp, &mut order);
                        let picks: Vec<(u32, u32)> = (3..spp)
                            .map(|s| {
                                (
                                    s,
                                    if order.is_empty() {
                                        s
                                    } else {
                                        order[(s - 3) as usize]
                                    },
                                )
                            })
                            .collect();
                        let mut batch = Vec::new();
                        eye.samples_in(x, y, &picks, &mut batch);
                        assert_eq!(batch.len(), picks.len());
                        for (b, &(s, stratum)) in batch.iter_mut().zip(&picks) {
                            let mut one = eye.sample_in(x, y, s, stratum);
                            let bits = |r: &Ray| {
                                [r.origin, r.dir, r.inv_dir].map(|v| v.to_array().map(f64::to_bits))
                            };
                            assert_eq!(bits(&b.ray), bits(&one.ray), "pixel ({x}, {y}) sample {s}");
                            assert_eq!(b.ray.time.to_bits(), one.ray.time.to_bits());
                            assert_eq!((b.near, b.far), (one.near, one.far));
                            assert_eq!(b.rng.next_u64(), one.rng.next_u64());
                            assert_eq!(
                                b.gloss.as_mut().map(Rng::next_u64),
                                one.gloss.as_mut().map(Rng::next_u64)
                            );
                        }
                    }
                }
            }
        }
    }
}
