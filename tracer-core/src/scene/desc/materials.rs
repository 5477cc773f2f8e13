//! What surfaces and lights look like: `<material>`, `<point_light>`, `<environment_map>` and
//! `<caustics>`.

use glam::DVec3;

use super::parser::Parser;
use crate::scene::xml::{Element, Pos};
use crate::scene::SceneError;

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

/// `<caustics photons="…" radius="…"/>`: caustic photon mapping on, with optional overrides
/// of the photon count and gather radius (defaults in `photon.rs`).
#[derive(Clone, Debug, PartialEq)]
pub struct CausticsDesc {
    pub photons: Option<u32>,
    pub radius: Option<f64>,
    pub pos: Pos,
}

impl Parser<'_> {
    pub(super) fn caustics(&self, el: &Element) -> Result<CausticsDesc, SceneError> {
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

    pub(super) fn environment(&self, el: &Element) -> Result<EnvironmentDesc, SceneError> {
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

    pub(super) fn light(&self, el: &Element) -> Result<LightDesc, SceneError> {
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

    pub(super) fn material(&self, el: &Element) -> Result<MaterialDesc, SceneError> {
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
