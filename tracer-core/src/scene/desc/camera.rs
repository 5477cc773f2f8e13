//! `<camera>`: the course's pinhole plus the thin-lens, shutter and camera-path extensions.

use glam::{DQuat, DVec3};

use super::motion::{Motion, TransformDesc};
use super::parser::{Motions, Parser};
use crate::scene::xml::Element;
use crate::scene::SceneError;

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

impl Parser<'_> {
    pub(super) fn camera(&self, el: &Element, motions: &Motions) -> Result<CameraDesc, SceneError> {
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
        let motion = self.motion(el, &base, motions)?;
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
}
