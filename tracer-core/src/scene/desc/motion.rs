//! Transforms and how they change over time: `<position>`/`<orientation>`/`<scale>`, keyframes,
//! velocity and spin, inline or from a named root `<motion>`.

use glam::{DQuat, DVec3};

use super::parser::{Motions, Parser};
use crate::scene::xml::Element;
use crate::scene::SceneError;

pub use crate::geometry::{Keyframe, Motion, TransformDesc};

impl Parser<'_> {
    pub(super) fn transform(&self, el: &Element) -> Result<TransformDesc, SceneError> {
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

    /// The motion of `el`: its own `<keyframe>`, `<velocity>` and `<spin>` children, or those
    /// of the root `<motion>` its `motion` attribute names. Keys start from `base`.
    pub(super) fn motion(
        &self,
        el: &Element,
        base: &TransformDesc,
        motions: &Motions,
    ) -> Result<Motion, SceneError> {
        let inline = ["keyframe", "velocity", "spin"]
            .iter()
            .any(|tag| el.children_named(tag).next().is_some());
        let source = if el.attr("motion").is_some() {
            let index = self.lookup(el, "motion", "motion", &motions.names)?;
            if inline {
                return Err(self.error(
                    el,
                    format!(
                        "in <{}>, give either a 'motion' attribute or keyframe/velocity/spin children, not both",
                        el.name
                    ),
                ));
            }
            motions.definitions[index]
        } else {
            el
        };
        self.copy_keyframes(el, source.children_named("keyframe").count())?;
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
    pub(super) fn scale(&self, el: &Element, default: DVec3) -> Result<DVec3, SceneError> {
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
}
