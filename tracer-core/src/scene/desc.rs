//! The scene as the XML file describes it: plain values with their file positions, names
//! resolved to indices, no assets read. Follows conventions.md §1 and §2.

use glam::{DQuat, DVec2, DVec3};

use super::xml::{parse_document, Element, Pos};
use super::SceneError;

#[derive(Clone, Debug, PartialEq)]
pub struct CameraDesc {
    /// Vertical field of view in radians.
    pub fov: f64,
    pub near_clip: f64,
    pub far_clip: f64,
    pub position: DVec3,
    pub orientation: DQuat,
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
    pub pos: Pos,
}

#[derive(Clone, Debug, PartialEq)]
pub struct MeshDesc {
    pub name: String,
    pub filename: Option<String>,
    pub pos: Pos,
}

/// Position, orientation and scale of a geometry: world = T·R·S·local.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TransformDesc {
    pub position: DVec3,
    pub orientation: DQuat,
    pub scale: DVec3,
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
    pub radius: f64,
    pub material: usize,
}

#[derive(Clone, Debug, PartialEq)]
pub struct TriangleDesc {
    pub transform: TransformDesc,
    pub vertices: [VertexDesc; 3],
}

#[derive(Clone, Debug, PartialEq)]
pub struct ModelDesc {
    pub transform: TransformDesc,
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
        let mut out: Vec<String> = Vec::new();
        for path in textures.chain(meshes) {
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
            None => DVec3::ONE,
        };
        Ok(TransformDesc {
            position,
            orientation,
            scale,
        })
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
        // The passes run in the order of §1.1, whatever the document order.
        let camera = self.camera(self.required(root, "camera")?)?;
        let background = self.color(self.required(root, "background_color")?)?;
        let refractive_index = self.scalar(self.required(root, "refractive_index")?)?;
        let ambient = self.optional_color(root, "ambient_light", DVec3::ZERO)?;
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
                radius,
                material,
            });
        }

        let mut triangles = Vec::new();
        for el in root.children_named("triangle") {
            let transform = self.transform(el)?;
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
                vertices,
            });
        }

        let mut models = Vec::new();
        for el in root.children_named("model") {
            let transform = self.transform(el)?;
            let mesh = self.lookup(el, "mesh", "mesh", &mesh_names)?;
            let material = self.lookup(el, "material", "material", &material_names)?;
            models.push(ModelDesc {
                transform,
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
                let max = crate::photon::MAX_PHOTONS;
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

    fn camera(&self, el: &Element) -> Result<CameraDesc, SceneError> {
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
        Ok(CameraDesc {
            fov,
            near_clip,
            far_clip,
            position,
            orientation,
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
