//! Keyed transforms: where a moving sphere, triangle, model or camera is at a given time.

use glam::{DQuat, DVec3};

/// Position, orientation and scale of a geometry: world = T·R·S·local.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TransformDesc {
    pub position: DVec3,
    pub orientation: DQuat,
    pub scale: DVec3,
}

/// A keyed transform: fields a `<keyframe>` leaves out keep the previous key's values.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Keyframe {
    /// In frames; keys are strictly increasing and after time 0, where the element's own
    /// transform is the first key.
    pub time: f64,
    pub transform: TransformDesc,
}

/// How a geometry or the camera moves over time (in frames): keyframes interpolated
/// piecewise linearly (orientations by slerp) and held past the last key, then a constant
/// velocity and spin on top. The default is no motion.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Motion {
    pub keys: Vec<Keyframe>,
    /// Units per frame.
    pub velocity: DVec3,
    /// Unit axis and radians per frame, turning the object about its own position.
    pub spin: Option<(DVec3, f64)>,
}

impl Motion {
    pub fn is_static(&self) -> bool {
        self.keys.is_empty() && self.velocity == DVec3::ZERO && self.spin.is_none()
    }

    /// The transform at `time`, `base` being the key at time 0.
    pub fn at(&self, base: &TransformDesc, time: f64) -> TransformDesc {
        let mut current = *base;
        let mut previous_time = 0.0;
        for key in &self.keys {
            if time >= key.time {
                current = key.transform;
                previous_time = key.time;
                continue;
            }
            // Equal keys hold still exactly (slerp would re-normalise the orientation).
            if time > previous_time && key.transform != current {
                let f = (time - previous_time) / (key.time - previous_time);
                let next = &key.transform;
                current = TransformDesc {
                    position: current.position.lerp(next.position, f),
                    orientation: current.orientation.slerp(next.orientation, f).normalize(),
                    scale: current.scale.lerp(next.scale, f),
                };
            }
            break;
        }
        if self.velocity != DVec3::ZERO {
            current.position += self.velocity * time;
        }
        if let Some((axis, rate)) = self.spin {
            current.orientation =
                (DQuat::from_axis_angle(axis, rate * time) * current.orientation).normalize();
        }
        current
    }

    /// Times at which sampling the path bounds it: every key, plus the span's ends.
    pub fn key_times(&self) -> impl Iterator<Item = f64> + '_ {
        std::iter::once(0.0).chain(self.keys.iter().map(|k| k.time))
    }
}
