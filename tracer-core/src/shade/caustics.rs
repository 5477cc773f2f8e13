//! The caustic photon map a render gathers from: photons in a uniform grid, the kernel
//! estimate of their irradiance, and the per-scene slot that shares one map between
//! renderers. `photon.rs` emits and traces the photons that fill it.

use std::collections::HashMap;
use std::f64::consts::PI;
use std::fmt;
use std::sync::{Arc, Mutex};

use glam::DVec3;

use crate::texture::TextureFilter;

/// A photon counts only on surfaces facing within 60° of the one it landed on, so light does
/// not leak round corners.
const MIN_NORMAL_COS: f64 = 0.5;
/// What a render asks of the caustic map once the scene and the settings are combined.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CausticsParams {
    pub photons: u32,
    /// Gather radius; None derives it from the casters
    /// ([`crate::photon::DEFAULT_RADIUS_FRACTION`]).
    pub radius: Option<f64>,
}

/// Everything a map depends on besides the scene.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct MapKey {
    pub(crate) params: CausticsParams,
    pub(crate) seed: u64,
    pub(crate) filter: TextureFilter,
}

/// The last map built for a scene. A cloned scene starts with an empty cache, so a clone that
/// is then changed can never be handed a stale map.
#[derive(Default)]
pub struct CausticCache(pub(crate) Mutex<Option<(MapKey, Arc<CausticMap>)>>);

impl Clone for CausticCache {
    fn clone(&self) -> Self {
        Self::default()
    }
}

impl fmt::Debug for CausticCache {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let built = self.0.lock().map(|s| s.is_some()).unwrap_or(false);
        f.debug_struct("CausticCache")
            .field("built", &built)
            .finish()
    }
}

/// One photon's landing: where, how much flux, and the normal of the side it arrived on.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Photon {
    pub(crate) position: DVec3,
    pub(crate) power: [f32; 3],
    pub(crate) normal: [f32; 3],
}

/// Caustic photons in a uniform grid of cells twice the gather radius wide, so that a gather
/// looks at no more than 2×2×2 cells.
pub struct CausticMap {
    radius: f64,
    cell: f64,
    /// Sorted by cell, then by emission order.
    photons: Vec<Photon>,
    cells: HashMap<[i32; 3], (u32, u32)>,
    emitted: u32,
}

impl fmt::Debug for CausticMap {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("CausticMap")
            .field("radius", &self.radius)
            .field("emitted", &self.emitted)
            .field("stored", &self.photons.len())
            .finish()
    }
}

impl CausticMap {
    pub(crate) fn from_photons(photons: Vec<Photon>, radius: f64, emitted: u32) -> CausticMap {
        let cell = 2.0 * radius;
        let key_of = |p: DVec3| cell_key(p, cell);
        // (cell, emission order) is a total order: the layout cannot depend on the sort.
        let mut order: Vec<([i32; 3], u32)> = photons
            .iter()
            .enumerate()
            .map(|(i, ph)| (key_of(ph.position), i as u32))
            .collect();
        order.sort_unstable();
        let sorted: Vec<Photon> = order.iter().map(|&(_, i)| photons[i as usize]).collect();
        let mut cells = HashMap::new();
        let mut start = 0;
        while start < order.len() {
            let key = order[start].0;
            let end = start + order[start..].partition_point(|(k, _)| *k == key);
            cells.insert(key, (start as u32, end as u32));
            start = end;
        }
        CausticMap {
            radius,
            cell,
            photons: sorted,
            cells,
            emitted,
        }
    }

    pub fn radius(&self) -> f64 {
        self.radius
    }

    /// Photons emitted from the lights.
    pub fn emitted(&self) -> u32 {
        self.emitted
    }

    /// Photons stored (landings on diffuse surfaces).
    pub fn len(&self) -> usize {
        self.photons.len()
    }

    pub fn is_empty(&self) -> bool {
        self.photons.is_empty()
    }

    /// The flux of every stored photon together.
    pub fn total_power(&self) -> DVec3 {
        self.photons
            .iter()
            .map(|p| DVec3::from(p.power.map(f64::from)))
            .sum()
    }

    /// Caustic irradiance at `p` (in the scene's frame, relative to `Scene::origin()`) on a
    /// surface whose unit normal `n` faces the viewer: the photons within the radius, weighted
    /// by the Epanechnikov kernel 1 − d²/r², whose integral over the disc is πr²/2.
    pub fn irradiance(&self, p: DVec3, n: DVec3) -> DVec3 {
        let r2 = self.radius * self.radius;
        let lo = cell_key(p - DVec3::splat(self.radius), self.cell);
        let hi = cell_key(p + DVec3::splat(self.radius), self.cell);
        // At most two cells per axis, unless coordinates are so large that keys saturate.
        if (0..3).any(|a| hi[a] as i64 - lo[a] as i64 > 2) {
            return DVec3::ZERO;
        }
        let mut sum = DVec3::ZERO;
        for x in lo[0]..=hi[0] {
            for y in lo[1]..=hi[1] {
                for z in lo[2]..=hi[2] {
                    let Some(&(start, end)) = self.cells.get(&[x, y, z]) else {
                        continue;
                    };
                    for ph in &self.photons[start as usize..end as usize] {
                        let d2 = (ph.position - p).length_squared();
                        if d2 < r2 && DVec3::from(ph.normal.map(f64::from)).dot(n) >= MIN_NORMAL_COS
                        {
                            sum += DVec3::from(ph.power.map(f64::from)) * (1.0 - d2 / r2);
                        }
                    }
                }
            }
        }
        sum * (2.0 / (PI * r2))
    }
}

/// The grid cell holding `p` (saturating for coordinates beyond the i32 range).
fn cell_key(p: DVec3, cell: f64) -> [i32; 3] {
    (p / cell).floor().to_array().map(|v| v as i32)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grid_gathers_with_a_normalised_kernel() {
        // Photons of power 1 on a fine lattice of the plane y = 0 with spacing h: the
        // irradiance anywhere well inside is 1/h².
        let h = 0.01;
        let mut photons = Vec::new();
        for i in -100..=100 {
            for j in -100..=100 {
                photons.push(Photon {
                    position: DVec3::new(i as f64 * h, 0.0, j as f64 * h),
                    power: [1.0; 3],
                    normal: [0.0, 1.0, 0.0],
                });
            }
        }
        let map = CausticMap::from_photons(photons, 0.1, 1);
        let e = map.irradiance(DVec3::new(0.013, 0.0, -0.021), DVec3::Y);
        assert!((e.x * h * h - 1.0).abs() < 0.02, "{e}");
        // The other side of the surface sees none of it.
        assert_eq!(map.irradiance(DVec3::ZERO, DVec3::NEG_Y), DVec3::ZERO);
        // Nor does a point beyond the radius.
        assert_eq!(
            map.irradiance(DVec3::new(1.2, 0.0, 0.0), DVec3::Y),
            DVec3::ZERO
        );
    }
}
