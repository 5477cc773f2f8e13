//! The refraction-index stack: which media a ray is inside, shared by the camera's tracer
//! and the caustic photons.

use glam::DVec3;

/// Deepest nesting of media tracked; entries past it are not pushed (wrong colour, no crash).
pub const MAX_MEDIA: usize = 16;

/// Refractive indices of the media the ray is inside, outermost first, with each medium's
/// Beer's-law absorption. Copied per branch, so reflected and refracted rays each carry their
/// own.
#[derive(Clone, Copy, Debug)]
pub struct MediumStack {
    indices: [f64; MAX_MEDIA],
    absorption: [DVec3; MAX_MEDIA],
    len: usize,
    /// Whether the innermost medium absorbs: read for every ray, where the entry itself is
    /// not (most scenes have no absorbing medium).
    absorbs: bool,
}

impl MediumStack {
    pub fn new(outer: f64) -> Self {
        let mut indices = [0.0; MAX_MEDIA];
        indices[0] = outer;
        Self {
            indices,
            absorption: [DVec3::ZERO; MAX_MEDIA],
            len: 1,
            absorbs: false,
        }
    }

    pub fn current(&self) -> f64 {
        self.indices[self.len - 1]
    }

    /// Absorption coefficients of the innermost medium (zero outside absorbing dielectrics).
    pub fn absorption(&self) -> DVec3 {
        self.absorption[self.len - 1]
    }

    /// Whether the innermost medium absorbs (its [`MediumStack::absorption`] is not zero).
    #[inline(always)]
    pub fn absorbs(&self) -> bool {
        self.absorbs
    }

    /// How many media the stack holds, the outermost included.
    pub fn depth(&self) -> usize {
        self.len
    }

    /// Entering a medium of index `ior`.
    pub fn entered(self, ior: f64) -> Self {
        self.entered_absorbing(ior, DVec3::ZERO)
    }

    /// Entering a medium of index `ior` that absorbs `absorption` per unit distance.
    pub fn entered_absorbing(mut self, ior: f64, absorption: DVec3) -> Self {
        if self.len < MAX_MEDIA {
            self.indices[self.len] = ior;
            self.absorption[self.len] = absorption;
            self.len += 1;
            self.absorbs = absorption != DVec3::ZERO;
        }
        self
    }

    /// Leaving a medium of index `ior`: removes its innermost entry. An exit that matches no
    /// entry (a camera inside glass, overlapping objects) leaves the stack as it is; the
    /// outermost medium is never removed.
    pub fn left(mut self, ior: f64) -> Self {
        if let Some(i) = (1..self.len).rev().find(|&i| self.indices[i] == ior) {
            self.indices.copy_within(i + 1..self.len, i);
            self.absorption.copy_within(i + 1..self.len, i);
            self.len -= 1;
            self.absorbs = self.absorption() != DVec3::ZERO;
        }
        self
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn medium_stack_survives_unmatched_exits_and_overflow() {
        let air = MediumStack::new(1.0);
        let water = air.entered(1.33);
        let glass = water.entered(1.5);
        assert_eq!(glass.current(), 1.5);
        assert_eq!(glass.left(1.5).current(), 1.33);
        // Leaving water while still in glass (overlap) removes water, keeps glass.
        assert_eq!(glass.left(1.33).current(), 1.5);
        // An exit nothing matches, and an exit of the outer medium, change nothing.
        assert_eq!(air.left(2.0).current(), 1.0);
        assert_eq!(air.left(1.0).current(), 1.0);
        assert_eq!(glass.left(1.2).depth(), glass.depth());
        let mut deep = air;
        for _ in 0..100 {
            deep = deep.entered(1.5);
        }
        assert_eq!(deep.depth(), MAX_MEDIA);
    }

    #[test]
    fn absorption_follows_the_medium_it_belongs_to() {
        let sigma = DVec3::new(0.5, 0.0, 2.0);
        let air = MediumStack::new(1.0);
        let tinted = air.entered_absorbing(1.5, sigma);
        assert_eq!(tinted.absorption(), sigma);
        assert!(tinted.absorbs() && !air.absorbs());
        assert!(!tinted.entered(1.33).absorbs());
        assert!(tinted.entered(1.33).left(1.33).absorbs());
        assert!(!tinted.entered(1.33).left(1.5).absorbs());
        assert!(!tinted.left(1.5).absorbs());
        assert_eq!(tinted.entered(1.33).absorption(), DVec3::ZERO);
        assert_eq!(tinted.entered(1.33).left(1.33).absorption(), sigma);
        // Leaving the tinted glass from inside water that overlaps it keeps water's (none).
        assert_eq!(tinted.entered(1.33).left(1.5).absorption(), DVec3::ZERO);
        assert_eq!(tinted.left(1.5).absorption(), DVec3::ZERO);
    }
}
