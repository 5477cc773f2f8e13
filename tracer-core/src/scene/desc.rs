//! The scene as the XML file describes it: plain values with their file positions, names
//! resolved to indices, no assets read. Follows conventions.md §1 and §2.

use glam::{DQuat, DVec2, DVec3};

use super::xml::{parse_document, Element, Pos};
use super::SceneError;
// The keyed transforms are geometry (the world intersects movers with them); the loader
// fills them in.
pub use crate::geometry::{Keyframe, Motion, TransformDesc};

#[derive(Clone, Debug, PartialEq)]
pub struct CameraDesc {
    /// Vertical field of view in radians.
    pub fov: f64,
    pub near_clip: f64,
    pub far_clip: f64,
    pub position: DVec3,
    pub orientation: DQuat,
    /// Thin-lens radius; 0 is the course's pinhole.
    pub aperture: f64,
    /// Distance along the view direction of the plane in focus (used when aperture > 0).
    pub focus_distance: f64,
    /// A focus pull: (time in frames, focus distance) keys after time 0, where
    /// `focus_distance` is the key; interpolated linearly, held after the last.
    pub focus_keys: Vec<(f64, f64)>,
    /// Shutter interval in frames after the frame's start; open == close is an instant.
    pub shutter: [f64; 2],
    /// Keyed camera path; its scale is unused.
    pub motion: Motion,
}

impl CameraDesc {
    /// The focus distance at `time` (in frames).
    pub fn focus_at(&self, time: f64) -> f64 {
        let mut previous = (0.0, self.focus_distance);
        for &(t, focus) in &self.focus_keys {
            if time < t {
                let s = ((time - previous.0) / (t - previous.0)).clamp(0.0, 1.0);
                return previous.1 + s * (focus - previous.1);
            }
            previous = (t, focus);
        }
        previous.1
    }

    /// Position and orientation at `time` (in frames).
    pub fn at(&self, time: f64) -> (DVec3, DQuat) {
        let base = TransformDesc {
            position: self.position,
            orientation: self.orientation,
            scale: DVec3::ONE,
        };
        let t = self.motion.at(&base, time);
        (t.position, t.orientation)
    }
}

#[derive(Clone, Debug, PartialEq)]
pub struct LightDesc {
    pub position: DVec3,
    pub color: DVec3,
    /// Constant, linear and quadratic terms of 1/(a_c + a_l·d + a_q·d²).
    pub attenuation: [f64; 3],
    /// Radius of a spherical area light; 0 is a point light.
    pub radius: f64,
}

#[derive(Clone, Debug, PartialEq)]
pub struct MaterialDesc {
    pub name: String,
    pub texture: Option<String>,
    /// 0 means opaque; anything else is a dielectric with that index.
    pub refractive_index: f64,
    pub ambient: DVec3,
    pub diffuse: DVec3,
    pub specular: DVec3,
    /// Spread of mirror reflections (0 is a perfect mirror).
    pub glossiness: f64,
    /// Beer's-law absorption coefficients per unit distance inside a dielectric.
    pub absorption: DVec3,
    pub pos: Pos,
}

#[derive(Clone, Debug, PartialEq)]
pub struct MeshDesc {
    pub name: String,
    pub filename: Option<String>,
    pub pos: Pos,
}

/// A latitude–longitude background image seen by rays that leave the scene.
#[derive(Clone, Debug, PartialEq)]
pub struct EnvironmentDesc {
    pub file: String,
    /// Multiplies the image's colours.
    pub intensity: f64,
    /// Turn about +Y, in radians.
    pub rotation: f64,
    pub pos: Pos,
}

#[derive(Clone, Debug, PartialEq)]
pub struct VertexDesc {
    pub position: DVec3,
    /// Unit length (normalised at load).
    pub normal: DVec3,
    pub tex_coord: DVec2,
    pub material: usize,
}

#[derive(Clone, Debug, PartialEq)]
pub struct SphereDesc {
    pub transform: TransformDesc,
    pub motion: Motion,
    pub radius: f64,
    pub material: usize,
}

#[derive(Clone, Debug, PartialEq)]
pub struct TriangleDesc {
    pub transform: TransformDesc,
    pub motion: Motion,
    pub vertices: [VertexDesc; 3],
}

#[derive(Clone, Debug, PartialEq)]
pub struct ModelDesc {
    pub transform: TransformDesc,
    pub motion: Motion,
    pub mesh: usize,
    pub material: usize,
}

/// `<caustics photons="…" radius="…"/>`: caustic photon mapping on, with optional overrides
/// of the photon count and gather radius (defaults in `photon.rs`).
#[derive(Clone, Debug, PartialEq)]
pub struct CausticsDesc {
    pub photons: Option<u32>,
    pub radius: Option<f64>,
    pub pos: Pos,
}

/// A parsed, validated scene file. Building a renderable scene from it reads only the assets
/// that [`SceneDescription::referenced_assets`] lists.
#[derive(Clone, Debug, PartialEq)]
pub struct SceneDescription {
    pub file: String,
    pub camera: CameraDesc,
    pub background: DVec3,
    /// Index of the medium the camera sits in.
    pub refractive_index: f64,
    pub ambient: DVec3,
    pub lights: Vec<LightDesc>,
    pub materials: Vec<MaterialDesc>,
    pub meshes: Vec<MeshDesc>,
    pub spheres: Vec<SphereDesc>,
    pub triangles: Vec<TriangleDesc>,
    pub models: Vec<ModelDesc>,
    /// Replaces `background` for rays that leave the scene.
    pub environment: Option<EnvironmentDesc>,
    /// Frames the scene describes (frame k is time k).
    pub frames: u32,
    /// Present when the scene asks for caustics.
    pub caustics: Option<CausticsDesc>,
}

impl SceneDescription {
    /// Parses scene XML; `file` names it in error messages.
    pub fn parse(text: &str, file: &str) -> Result<Self, SceneError> {
        let root = parse_document(text, file)?;
        Parser { file }.scene(&root)
    }

    /// Whether any geometry uses material `index`.
    pub fn material_used(&self, index: usize) -> bool {
        self.spheres.iter().any(|s| s.material == index)
            || self.models.iter().any(|m| m.material == index)
            || self
                .triangles
                .iter()
                .any(|t| t.vertices.iter().any(|v| v.material == index))
    }

    /// Whether anything in the scene moves (the camera included).
    pub fn has_motion(&self) -> bool {
        !self.camera.motion.is_static()
            || self.spheres.iter().any(|s| !s.motion.is_static())
            || self.triangles.iter().any(|t| !t.motion.is_static())
            || self.models.iter().any(|m| !m.motion.is_static())
    }

    /// Whether any model instances mesh `index`.
    pub fn mesh_used(&self, index: usize) -> bool {
        self.models.iter().any(|m| m.mesh == index)
    }

    /// The asset paths, exactly as written, that rendering this scene reads: textures of
    /// materials some geometry uses and meshes some model uses. Deduplicated, in file order.
    pub fn referenced_assets(&self) -> Vec<String> {
        let textures = self
            .materials
            .iter()
            .enumerate()
            .filter(|(i, _)| self.material_used(*i))
            .filter_map(|(_, m)| m.texture.clone());
        let meshes = self
            .meshes
            .iter()
            .enumerate()
            .filter(|(i, _)| self.mesh_used(*i))
            .filter_map(|(_, m)| m.filename.clone());
        let environment = self.environment.iter().map(|e| e.file.clone());
        let mut out: Vec<String> = Vec::new();
        for path in textures.chain(meshes).chain(environment) {
            if !out.contains(&path) {
                out.push(path);
            }
        }
        out
    }
}

struct Parser<'f> {
    file: &'f str,
}

impl Parser<'_> {
    fn error(&self, at: &Element, message: impl Into<String>) -> SceneError {
        SceneError::new(self.file, at.pos.line, at.pos.column, message)
    }

    /// At most one child called `tag`; a second one is fatal even for optional fields (§1.1).
    fn single<'e>(
        &self,
        parent: &'e Element,
        tag: &'e str,
    ) -> Result<Option<&'e Element>, SceneError> {
        let mut found = parent.children_named(tag);
        let first = found.next();
        if let (Some(first), Some(second)) = (first, found.next()) {
            return Err(self.error(
                first,
                format!(
                    "in <{}>, <{tag}> appears more than once (again at line {}, column {})",
                    parent.name, second.pos.line, second.pos.column
                ),
            ));
        }
        Ok(first)
    }

    fn required<'e>(&self, parent: &'e Element, tag: &'e str) -> Result<&'e Element, SceneError> {
        self.single(parent, tag)?.ok_or_else(|| {
            self.error(
                parent,
                format!("in <{}>, required element <{tag}> is missing", parent.name),
            )
        })
    }

    fn attr<'e>(&self, el: &'e Element, name: &str) -> Result<&'e str, SceneError> {
        el.attr(name).ok_or_else(|| {
            self.error(
                el,
                format!("in <{}>, required attribute '{name}' is missing", el.name),
            )
        })
    }

    fn number(&self, el: &Element, name: &str) -> Result<f64, SceneError> {
        let text = self.attr(el, name)?;
        match parse_c_double(text) {
            Some(v) if v.is_finite() => Ok(v),
            Some(_) => Err(self.error(
                el,
                format!(
                    "in <{}>, attribute '{name}' = \"{text}\" is not a finite number",
                    el.name
                ),
            )),
            None => Err(self.error(
                el,
                format!(
                    "in <{}>, error parsing attribute '{name}' = \"{text}\" as a number",
                    el.name
                ),
            )),
        }
    }

    fn scalar(&self, el: &Element) -> Result<f64, SceneError> {
        self.number(el, "v")
    }

    fn vec3(&self, el: &Element) -> Result<DVec3, SceneError> {
        Ok(DVec3::new(
            self.number(el, "x")?,
            self.number(el, "y")?,
            self.number(el, "z")?,
        ))
    }

    fn color(&self, el: &Element) -> Result<DVec3, SceneError> {
        Ok(DVec3::new(
            self.number(el, "r")?,
            self.number(el, "g")?,
            self.number(el, "b")?,
        ))
    }

    fn optional_scalar(
        &self,
        parent: &Element,
        tag: &str,
        default: f64,
    ) -> Result<f64, SceneError> {
        self.single(parent, tag)?
            .map_or(Ok(default), |el| self.scalar(el))
    }

    fn optional_color(
        &self,
        parent: &Element,
        tag: &str,
        default: DVec3,
    ) -> Result<DVec3, SceneError> {
        self.single(parent, tag)?
            .map_or(Ok(default), |el| self.color(el))
    }

    /// `a x y z`: angle in radians about an axis that need not be unit length (§2.1).
    fn orientation(&self, el: &Element) -> Result<DQuat, SceneError> {
        let angle = self.number(el, "a")?;
        let axis = self.vec3(el)?;
        let length = axis.length();
        if length == 0.0 || !length.is_finite() {
            return Err(self.error(
                el,
                format!("in <{}>, the rotation axis must not be zero", el.name),
            ));
        }
        Ok(DQuat::from_axis_angle(axis / length, angle).normalize())
    }

    fn transform(&self, el: &Element) -> Result<TransformDesc, SceneError> {
        let position = self.vec3(self.required(el, "position")?)?;
        let orientation = match self.single(el, "orientation")? {
            Some(o) => self.orientation(o)?,
            None => DQuat::IDENTITY,
        };
        let scale = self.scale(el, DVec3::ONE)?;
        Ok(TransformDesc {
            position,
            orientation,
            scale,
        })
    }

    fn non_negative(&self, el: &Element, value: f64, what: &str) -> Result<f64, SceneError> {
        if value < 0.0 {
            return Err(self.error(
                el,
                format!("in <{}>, {what} must not be negative, not {value}", el.name),
            ));
        }
        Ok(value)
    }

    /// The motion of `el`: its own `<keyframe>`, `<velocity>` and `<spin>` children, or those
    /// of the root `<motion>` its `motion` attribute names. Keys start from `base`.
    fn motion(
        &self,
        el: &Element,
        base: &TransformDesc,
        named: &[(&str, usize)],
        definitions: &[&Element],
    ) -> Result<Motion, SceneError> {
        let inline = ["keyframe", "velocity", "spin"]
            .iter()
            .any(|tag| el.children_named(tag).next().is_some());
        let source = if el.attr("motion").is_some() {
            let index = self.lookup(el, "motion", "motion", named)?;
            if inline {
                return Err(self.error(
                    el,
                    format!(
                        "in <{}>, give either a 'motion' attribute or keyframe/velocity/spin children, not both",
                        el.name
                    ),
                ));
            }
            definitions[index]
        } else {
            el
        };
        let mut keys: Vec<Keyframe> = Vec::new();
        let mut previous = *base;
        let mut previous_time = 0.0;
        for key in source.children_named("keyframe") {
            let time = self.number(key, "time")?;
            if time <= previous_time {
                return Err(self.error(
                    key,
                    format!(
                        "in <keyframe>, time {time} must come after the previous key's time {previous_time} (the element's own transform is the key at time 0)"
                    ),
                ));
            }
            let position = match self.single(key, "position")? {
                Some(p) => self.vec3(p)?,
                None => previous.position,
            };
            let orientation = match self.single(key, "orientation")? {
                Some(o) => self.orientation(o)?,
                None => previous.orientation,
            };
            let scale = self.scale(key, previous.scale)?;
            previous = TransformDesc {
                position,
                orientation,
                scale,
            };
            previous_time = time;
            keys.push(Keyframe {
                time,
                transform: previous,
            });
        }
        let velocity = match self.single(source, "velocity")? {
            Some(v) => self.vec3(v)?,
            None => DVec3::ZERO,
        };
        let spin = match self.single(source, "spin")? {
            Some(sp) => {
                let rate = self.number(sp, "a")?;
                let axis = self.vec3(sp)?;
                if axis == DVec3::ZERO {
                    return Err(self.error(sp, "in <spin>, the rotation axis must not be zero"));
                }
                (rate != 0.0).then(|| (axis.normalize(), rate))
            }
            None => None,
        };
        Ok(Motion {
            keys,
            velocity,
            spin,
        })
    }

    /// An optional `<scale>` child, rejecting zero components.
    fn scale(&self, el: &Element, default: DVec3) -> Result<DVec3, SceneError> {
        let scale = match self.single(el, "scale")? {
            Some(s) => {
                let scale = self.vec3(s)?;
                if scale.x == 0.0 || scale.y == 0.0 || scale.z == 0.0 {
                    return Err(self.error(
                        s,
                        format!(
                            "in <{}>, a zero scale component flattens the object and cannot be inverted",
                            s.name
                        ),
                    ));
                }
                scale
            }
            None => default,
        };
        Ok(scale)
    }

    fn lookup(
        &self,
        el: &Element,
        attr: &str,
        what: &str,
        names: &[(&str, usize)],
    ) -> Result<usize, SceneError> {
        let name = self.attr(el, attr)?;
        names
            .iter()
            .find(|(n, _)| *n == name)
            .map(|(_, i)| *i)
            .ok_or_else(|| {
                self.error(
                    el,
                    format!(
                        "in <{}>, attribute '{attr}' names {what} \"{name}\", which is not defined",
                        el.name
                    ),
                )
            })
    }

    fn check_unique(
        &self,
        el: &Element,
        what: &str,
        name: &str,
        seen: &[(&str, usize)],
    ) -> Result<(), SceneError> {
        if seen.iter().any(|(n, _)| *n == name) {
            return Err(self.error(el, format!("{what} \"{name}\" is defined twice")));
        }
        Ok(())
    }

    fn scene(&self, root: &Element) -> Result<SceneDescription, SceneError> {
        // Named motions (an extension) may be used by the camera and any geometry.
        let mut motion_names: Vec<(&str, usize)> = Vec::new();
        let mut motion_defs: Vec<&Element> = Vec::new();
        for el in root.children_named("motion") {
            let name = self.attr(el, "name")?;
            self.check_unique(el, "motion", name, &motion_names)?;
            motion_names.push((name, motion_defs.len()));
            motion_defs.push(el);
        }
        let motions = (&motion_names[..], &motion_defs[..]);
        // The passes run in the order of §1.1, whatever the document order.
        let camera = self.camera(self.required(root, "camera")?, motions)?;
        let background = self.color(self.required(root, "background_color")?)?;
        let refractive_index = self.scalar(self.required(root, "refractive_index")?)?;
        let ambient = self.optional_color(root, "ambient_light", DVec3::ZERO)?;
        let environment = self
            .single(root, "environment_map")?
            .map(|el| self.environment(el))
            .transpose()?;
        let frames = match self.single(root, "animation")? {
            Some(el) => {
                let frames = self.number(el, "frames")?;
                if frames.fract() != 0.0 || !(1.0..=1e6).contains(&frames) {
                    return Err(self.error(
                        el,
                        format!("in <animation>, frames must be a whole number from 1 to 1000000, not {frames}"),
                    ));
                }
                frames as u32
            }
            None => 1,
        };
        let lights = root
            .children_named("point_light")
            .map(|el| self.light(el))
            .collect::<Result<Vec<_>, _>>()?;

        let mut materials = Vec::new();
        let mut material_names: Vec<(&str, usize)> = Vec::new();
        for el in root.children_named("material") {
            let material = self.material(el)?;
            let name = self.attr(el, "name")?;
            self.check_unique(el, "material", name, &material_names)?;
            material_names.push((name, materials.len()));
            materials.push(material);
        }

        let mut meshes = Vec::new();
        let mut mesh_names: Vec<(&str, usize)> = Vec::new();
        for el in root.children_named("mesh") {
            let name = self.attr(el, "name")?;
            self.check_unique(el, "mesh", name, &mesh_names)?;
            mesh_names.push((name, meshes.len()));
            meshes.push(MeshDesc {
                name: name.to_string(),
                filename: el
                    .attr("filename")
                    .filter(|f| !f.is_empty())
                    .map(str::to_string),
                pos: el.pos,
            });
        }

        let mut vertices = Vec::new();
        let mut vertex_names: Vec<(&str, usize)> = Vec::new();
        for el in root.children_named("vertex") {
            let position = self.vec3(self.required(el, "position")?)?;
            let normal_el = self.required(el, "normal")?;
            let normal = self.vec3(normal_el)?;
            if normal == DVec3::ZERO {
                return Err(self.error(normal_el, "in <normal>, the normal must not be zero"));
            }
            let tex = self.required(el, "tex_coord")?;
            let tex_coord = DVec2::new(self.number(tex, "u")?, self.number(tex, "v")?);
            let material = self.lookup(el, "material", "material", &material_names)?;
            let name = self.attr(el, "name")?;
            self.check_unique(el, "vertex", name, &vertex_names)?;
            vertex_names.push((name, vertices.len()));
            vertices.push(VertexDesc {
                position,
                normal: normal.normalize(),
                tex_coord,
                material,
            });
        }

        let mut spheres = Vec::new();
        for el in root.children_named("sphere") {
            let transform = self.transform(el)?;
            let motion = self.motion(el, &transform, motions.0, motions.1)?;
            let radius_el = self.required(el, "radius")?;
            let radius = self.scalar(radius_el)?;
            if radius <= 0.0 {
                return Err(
                    self.error(radius_el, "in <radius>, a sphere's radius must be positive")
                );
            }
            let material = self.lookup(el, "material", "material", &material_names)?;
            spheres.push(SphereDesc {
                transform,
                motion,
                radius,
                material,
            });
        }

        let mut triangles = Vec::new();
        for el in root.children_named("triangle") {
            let transform = self.transform(el)?;
            let motion = self.motion(el, &transform, motions.0, motions.1)?;
            let refs: Vec<&Element> = el.children_named("vertex").collect();
            if refs.len() > 3 {
                return Err(self.error(
                    refs[3],
                    "in <triangle>, too many vertices (a triangle has 3)",
                ));
            }
            if refs.len() < 3 {
                return Err(self.error(
                    el,
                    format!("in <triangle>, too few vertices: {} of 3", refs.len()),
                ));
            }
            let corner = |i: usize| -> Result<VertexDesc, SceneError> {
                let index = self.lookup(refs[i], "name", "vertex", &vertex_names)?;
                Ok(vertices[index].clone())
            };
            let vertices = [corner(0)?, corner(1)?, corner(2)?];
            triangles.push(TriangleDesc {
                transform,
                motion,
                vertices,
            });
        }

        let mut models = Vec::new();
        for el in root.children_named("model") {
            let transform = self.transform(el)?;
            let motion = self.motion(el, &transform, motions.0, motions.1)?;
            let mesh = self.lookup(el, "mesh", "mesh", &mesh_names)?;
            let material = self.lookup(el, "material", "material", &material_names)?;
            models.push(ModelDesc {
                transform,
                motion,
                mesh,
                material,
            });
        }

        Ok(SceneDescription {
            file: self.file.to_string(),
            camera,
            background,
            refractive_index,
            ambient,
            lights,
            materials,
            meshes,
            spheres,
            triangles,
            models,
            environment,
            frames,
            caustics: self
                .single(root, "caustics")?
                .map(|el| self.caustics(el))
                .transpose()?,
        })
    }

    fn caustics(&self, el: &Element) -> Result<CausticsDesc, SceneError> {
        let photons = match el.attr("photons") {
            None => None,
            Some(text) => {
                let n = self.number(el, "photons")?;
                let max = crate::settings::MAX_PHOTONS;
                if n.fract() != 0.0 || n < 1.0 || n > max as f64 {
                    return Err(self.error(
                        el,
                        format!(
                            "in <caustics>, attribute 'photons' = \"{text}\" must be a whole number between 1 and {max}"
                        ),
                    ));
                }
                Some(n as u32)
            }
        };
        let radius = match el.attr("radius") {
            None => None,
            Some(text) => {
                let r = self.number(el, "radius")?;
                if r <= 0.0 {
                    return Err(self.error(
                        el,
                        format!("in <caustics>, attribute 'radius' = \"{text}\" must be positive"),
                    ));
                }
                Some(r)
            }
        };
        Ok(CausticsDesc {
            photons,
            radius,
            pos: el.pos,
        })
    }

    fn environment(&self, el: &Element) -> Result<EnvironmentDesc, SceneError> {
        let file = self.attr(el, "file")?;
        if file.is_empty() {
            return Err(self.error(el, "in <environment_map>, 'file' must not be empty"));
        }
        let intensity = match el.attr("intensity") {
            Some(_) => {
                let v = self.number(el, "intensity")?;
                self.non_negative(el, v, "intensity")?
            }
            None => 1.0,
        };
        let rotation = match el.attr("rotation") {
            Some(_) => self.number(el, "rotation")?,
            None => 0.0,
        };
        Ok(EnvironmentDesc {
            file: file.to_string(),
            intensity,
            rotation,
            pos: el.pos,
        })
    }

    fn camera(
        &self,
        el: &Element,
        motions: (&[(&str, usize)], &[&Element]),
    ) -> Result<CameraDesc, SceneError> {
        let fov_el = self.required(el, "fov")?;
        let fov = self.scalar(fov_el)?;
        let near_clip = self.scalar(self.required(el, "near_clip")?)?;
        let far_clip = self.scalar(self.required(el, "far_clip")?)?;
        let position = self.vec3(self.required(el, "position")?)?;
        let orientation = self.orientation(self.required(el, "orientation")?)?;
        if !(fov > 0.0 && fov < std::f64::consts::PI) {
            return Err(self.error(
                fov_el,
                format!("in <fov>, the field of view must lie strictly between 0 and π radians, not {fov}"),
            ));
        }
        // Extensions: a thin lens, a shutter interval and a camera path.
        let aperture = match self.single(el, "aperture")? {
            Some(a) => {
                let v = self.scalar(a)?;
                self.non_negative(a, v, "the aperture radius")?
            }
            None => 0.0,
        };
        let focus_distance = match self.single(el, "focus_distance")? {
            Some(f) => {
                let v = self.scalar(f)?;
                if v <= 0.0 {
                    return Err(self.error(
                        f,
                        format!(
                            "in <focus_distance>, the focus distance must be positive, not {v}"
                        ),
                    ));
                }
                v
            }
            None if aperture > 0.0 => {
                return Err(self.error(
                    el,
                    "in <camera>, an <aperture> above 0 needs a <focus_distance>",
                ))
            }
            None => 1.0,
        };
        let mut focus_keys: Vec<(f64, f64)> = Vec::new();
        for key in el.children_named("focus_key") {
            if aperture <= 0.0 {
                return Err(self.error(
                    key,
                    "a <focus_key> pulls the focus of a thin lens: the camera needs an <aperture> above 0",
                ));
            }
            let time = self.number(key, "time")?;
            let previous = focus_keys.last().map_or(0.0, |k| k.0);
            if time <= previous {
                return Err(self.error(
                    key,
                    format!(
                        "in <focus_key>, time {time} must come after the previous key's time {previous} (<focus_distance> is the key at time 0)"
                    ),
                ));
            }
            let focus = self.number(key, "v")?;
            if focus <= 0.0 {
                return Err(self.error(
                    key,
                    format!("in <focus_key>, the focus distance must be positive, not {focus}"),
                ));
            }
            focus_keys.push((time, focus));
        }
        let shutter = match self.single(el, "shutter")? {
            Some(sh) => {
                let open = self.number(sh, "open")?;
                let close = self.number(sh, "close")?;
                if !(0.0 <= open && open <= close) {
                    return Err(self.error(
                        sh,
                        format!(
                            "in <shutter>, need 0 ≤ open ≤ close, not open {open}, close {close}"
                        ),
                    ));
                }
                [open, close]
            }
            None => [0.0; 2],
        };
        let base = TransformDesc {
            position,
            orientation,
            scale: DVec3::ONE,
        };
        let motion = self.motion(el, &base, motions.0, motions.1)?;
        Ok(CameraDesc {
            fov,
            near_clip,
            far_clip,
            position,
            orientation,
            aperture,
            focus_distance,
            focus_keys,
            shutter,
            motion,
        })
    }

    fn light(&self, el: &Element) -> Result<LightDesc, SceneError> {
        let attenuation = [
            self.optional_scalar(el, "attenuation_constant", 1.0)?,
            self.optional_scalar(el, "attenuation_linear", 0.0)?,
            self.optional_scalar(el, "attenuation_quadratic", 0.0)?,
        ];
        let position = self.vec3(self.required(el, "position")?)?;
        let color = self.color(self.required(el, "color")?)?;
        let radius_el = self.single(el, "radius")?;
        let radius = radius_el.map_or(Ok(0.0), |r| self.scalar(r))?;
        if let Some(r) = radius_el.filter(|_| radius < 0.0) {
            return Err(self.error(r, "in <radius>, a light's radius must not be negative"));
        }
        if attenuation.iter().any(|a| *a < 0.0) {
            return Err(self.error(
                el,
                "in <point_light>, attenuation terms must not be negative",
            ));
        }
        Ok(LightDesc {
            position,
            color,
            attenuation,
            radius,
        })
    }

    fn material(&self, el: &Element) -> Result<MaterialDesc, SceneError> {
        let name = self.attr(el, "name")?.to_string();
        let refractive_index = self.optional_scalar(el, "refractive_index", 0.0)?;
        let ambient = self.optional_color(el, "ambient", DVec3::ONE)?;
        let diffuse = self.optional_color(el, "diffuse", DVec3::ONE)?;
        let specular = self.optional_color(el, "specular", DVec3::ZERO)?;
        // Parsed for the singleton rule and number checks; the ray tracer ignores it.
        self.optional_scalar(el, "shininess", 10.0)?;
        let glossiness = match self.single(el, "glossiness")? {
            Some(g) => {
                let v = self.scalar(g)?;
                self.non_negative(g, v, "glossiness")?
            }
            None => 0.0,
        };
        let absorption = match self.single(el, "absorption")? {
            Some(a) => {
                let c = self.color(a)?;
                if c.min_element() < 0.0 {
                    return Err(self.error(
                        a,
                        "in <absorption>, absorption coefficients must not be negative",
                    ));
                }
                c
            }
            None => DVec3::ZERO,
        };
        Ok(MaterialDesc {
            name,
            texture: el
                .attr("texture")
                .filter(|t| !t.is_empty())
                .map(str::to_string),
            refractive_index,
            ambient,
            diffuse,
            specular,
            glossiness,
            absorption,
            pos: el.pos,
        })
    }
}

/// C `sscanf("%lf")`: skips leading whitespace, reads the longest numeric prefix and ignores
/// the rest ("1.5abc" is 1.5). Returns None when there is no number at all.
pub fn parse_c_double(text: &str) -> Option<f64> {
    let s = text.trim_start();
    let bytes = s.as_bytes();
    let mut end = 0;
    if matches!(bytes.first(), Some(b'+' | b'-')) {
        end = 1;
    }
    let lower = s[end..].to_ascii_lowercase();
    for word in ["infinity", "inf", "nan"] {
        if lower.starts_with(word) {
            let sign = if s.starts_with('-') { -1.0 } else { 1.0 };
            return Some(if word == "nan" {
                f64::NAN
            } else {
                sign * f64::INFINITY
            });
        }
    }
    let digits_from = |mut i: usize| {
        while i < bytes.len() && bytes[i].is_ascii_digit() {
            i += 1;
        }
        i
    };
    let int_end = digits_from(end);
    let mut mantissa_end = int_end;
    let mut has_digits = int_end > end;
    if bytes.get(int_end) == Some(&b'.') {
        let frac_end = digits_from(int_end + 1);
        has_digits |= frac_end > int_end + 1;
        mantissa_end = frac_end;
    }
    if !has_digits {
        return None;
    }
    end = mantissa_end;
    if matches!(bytes.get(end), Some(b'e' | b'E')) {
        let mut exp = end + 1;
        if matches!(bytes.get(exp), Some(b'+' | b'-')) {
            exp += 1;
        }
        let exp_end = digits_from(exp);
        if exp_end > exp {
            end = exp_end;
        }
    }
    s[..end].parse().ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn motion_interpolates_between_keys_and_holds_after_the_last() {
        let base = TransformDesc {
            position: DVec3::ZERO,
            orientation: DQuat::IDENTITY,
            scale: DVec3::ONE,
        };
        let key = |time: f64, x: f64, angle: f64| Keyframe {
            time,
            transform: TransformDesc {
                position: DVec3::new(x, 0.0, 0.0),
                orientation: DQuat::from_axis_angle(DVec3::Y, angle),
                scale: DVec3::ONE,
            },
        };
        let motion = Motion {
            keys: vec![key(2.0, 4.0, 1.0), key(3.0, 6.0, 1.0)],
            ..Motion::default()
        };
        assert!(!motion.is_static() && Motion::default().is_static());
        assert_eq!(motion.at(&base, 0.0), base);
        let half = motion.at(&base, 1.0);
        assert!((half.position.x - 2.0).abs() < 1e-12);
        assert!((half.orientation.angle_between(DQuat::IDENTITY) - 0.5).abs() < 1e-12);
        assert!((motion.at(&base, 2.5).position.x - 5.0).abs() < 1e-12);
        assert_eq!(motion.at(&base, 7.0).position.x, 6.0);
        // Velocity and spin add on top, growing with time.
        let moving = Motion {
            velocity: DVec3::new(0.0, 1.0, 0.0),
            spin: Some((DVec3::Z, 0.25)),
            ..motion
        };
        let late = moving.at(&base, 4.0);
        assert_eq!(late.position, DVec3::new(6.0, 4.0, 0.0));
        let expected =
            DQuat::from_axis_angle(DVec3::Z, 1.0) * DQuat::from_axis_angle(DVec3::Y, 1.0);
        assert!(late.orientation.angle_between(expected) < 1e-9);
    }

    #[test]
    fn c_double_prefixes() {
        assert_eq!(parse_c_double(".785"), Some(0.785));
        assert_eq!(parse_c_double("  1e3"), Some(1000.0));
        assert_eq!(parse_c_double("1.5abc"), Some(1.5));
        assert_eq!(parse_c_double("-2."), Some(-2.0));
        assert_eq!(parse_c_double("3e"), Some(3.0));
        assert_eq!(parse_c_double("-inf"), Some(f64::NEG_INFINITY));
        assert!(parse_c_double("nan").unwrap().is_nan());
        assert_eq!(parse_c_double("abc"), None);
        assert_eq!(parse_c_double("."), None);
        assert_eq!(parse_c_double(""), None);
    }
}
