//! Materials and what they look like at a hit: the world says where a ray landed and which
//! material applies; this adds the material's colours and its texture's colour there.

use glam::{DVec2, DVec3};

use crate::texture::{Texture, TextureFilter};
use crate::world::{MaterialAt, Patch};

#[derive(Clone, Debug)]
pub struct Material {
    pub ambient: DVec3,
    pub diffuse: DVec3,
    pub specular: DVec3,
    /// 0 is opaque; anything else a dielectric.
    pub ior: f64,
    pub texture: Option<u32>,
    /// Spread of reflections; 0 is a perfect mirror.
    pub glossiness: f64,
    /// Beer's-law coefficients inside a dielectric.
    pub absorption: DVec3,
}

/// Everything shading needs at a hit point.
#[derive(Clone, Copy, Debug)]
pub struct Surface {
    pub position: DVec3,
    /// Interpolated shading normal, unit length, pointing out of the surface as modelled.
    pub normal: DVec3,
    /// Geometric normal (same side as `normal`'s intent), for offsetting spawned rays.
    pub geometric_normal: DVec3,
    pub ambient: DVec3,
    pub diffuse: DVec3,
    pub specular: DVec3,
    pub ior: f64,
    /// Texture colour at the hit (white where there is no texture).
    pub texture: DVec3,
    pub glossiness: f64,
    pub absorption: DVec3,
}

/// A scene's materials with the textures they name, sampled with one filter.
#[derive(Clone, Copy, Debug)]
pub struct Materials<'a> {
    pub materials: &'a [Material],
    pub textures: &'a [Texture],
    pub filter: TextureFilter,
}

impl Materials<'_> {
    /// The surface at `patch`: a triangle's vertex materials blend by its barycentrics.
    #[inline(always)]
    pub fn surface(&self, patch: &Patch) -> Surface {
        match patch.material {
            MaterialAt::One(m) => {
                let m = &self.materials[m as usize];
                Surface {
                    position: patch.position,
                    normal: patch.normal,
                    geometric_normal: patch.geometric_normal,
                    ambient: m.ambient,
                    diffuse: m.diffuse,
                    specular: m.specular,
                    ior: m.ior,
                    texture: self.texture(m, patch.uv),
                    glossiness: m.glossiness,
                    absorption: m.absorption,
                }
            }
            MaterialAt::Blend { materials, bary } => self.blend(patch, materials, bary),
        }
    }

    #[inline(always)]
    fn blend(&self, patch: &Patch, materials: [u32; 3], bary: [f64; 3]) -> Surface {
        let [b0, b1, b2] = bary;
        let ms = materials.map(|m| &self.materials[m as usize]);
        let blend = |f: &dyn Fn(&Material) -> DVec3| b0 * f(ms[0]) + b1 * f(ms[1]) + b2 * f(ms[2]);
        let scalar = |f: &dyn Fn(&Material) -> f64| b0 * f(ms[0]) + b1 * f(ms[1]) + b2 * f(ms[2]);
        let ior = scalar(&|m| m.ior);
        Surface {
            position: patch.position,
            normal: patch.normal,
            geometric_normal: patch.geometric_normal,
            ambient: blend(&|m| m.ambient),
            diffuse: blend(&|m| m.diffuse),
            specular: blend(&|m| m.specular),
            ior,
            texture: blend(&|m| self.texture(m, patch.uv)),
            // The effects' blends only where a vertex material uses them.
            glossiness: if ms.iter().any(|m| m.glossiness != 0.0) {
                scalar(&|m| m.glossiness)
            } else {
                0.0
            },
            absorption: if ior != 0.0 {
                blend(&|m| m.absorption)
            } else {
                DVec3::ZERO
            },
        }
    }

    #[inline(always)]
    fn texture(&self, material: &Material, uv: DVec2) -> DVec3 {
        match material.texture {
            Some(t) => self.textures[t as usize].sample(uv, self.filter),
            None => DVec3::ONE,
        }
    }
}
