//! Materials and what they look like at a hit: the world says where a ray landed and which
//! material applies; this adds the material's colours and its texture's colour there.

use glam::DVec3;

use crate::texture::{Texture, TextureFilter};
use crate::world::{MaterialAt, Patch, Uv};

/// Aligned to a cache line, so a scene's materials (read by every render thread at every
/// hit) share no line with anything a thread writes. The embedded farm builds its scene on a
/// render thread, whose per-row buffers then came from the same heap arena: on spheres.scene
/// (one material) a third of the farm's renders took 7–10% more CPU, stalled on that load,
/// while `tracer render` never did.
#[derive(Clone, Debug)]
#[repr(align(64))]
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
        // Plain functions rather than `&dyn Fn`: these run at every scene-triangle hit.
        #[inline(always)]
        fn blend3(b: [f64; 3], v: [DVec3; 3]) -> DVec3 {
            b[0] * v[0] + b[1] * v[1] + b[2] * v[2]
        }
        #[inline(always)]
        fn scalar3(b: [f64; 3], v: [f64; 3]) -> f64 {
            b[0] * v[0] + b[1] * v[1] + b[2] * v[2]
        }
        let ior = scalar3(bary, ms.map(|m| m.ior));
        // A vertex sharing the previous vertex's material reuses its texture sample (the same
        // value, so the blend is unchanged): scene triangles mostly carry one material, and a
        // texture look-up costs more than the rest of the blend.
        let t0 = self.texture(ms[0], patch.uv);
        let t1 = if materials[1] == materials[0] {
            t0
        } else {
            self.texture(ms[1], patch.uv)
        };
        let t2 = if materials[2] == materials[1] {
            t1
        } else if materials[2] == materials[0] {
            t0
        } else {
            self.texture(ms[2], patch.uv)
        };
        Surface {
            position: patch.position,
            normal: patch.normal,
            geometric_normal: patch.geometric_normal,
            ambient: blend3(bary, ms.map(|m| m.ambient)),
            diffuse: blend3(bary, ms.map(|m| m.diffuse)),
            specular: blend3(bary, ms.map(|m| m.specular)),
            ior,
            texture: b0 * t0 + b1 * t1 + b2 * t2,
            // The effects' blends only where a vertex material uses them.
            glossiness: if ms.iter().any(|m| m.glossiness != 0.0) {
                scalar3(bary, ms.map(|m| m.glossiness))
            } else {
                0.0
            },
            absorption: if ior != 0.0 {
                blend3(bary, ms.map(|m| m.absorption))
            } else {
                DVec3::ZERO
            },
        }
    }

    #[inline(always)]
    fn texture(&self, material: &Material, uv: Uv) -> DVec3 {
        match material.texture {
            Some(t) => self.textures[t as usize].sample(uv.get(), self.filter),
            None => DVec3::ONE,
        }
    }
}
