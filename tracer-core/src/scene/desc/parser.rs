//! The element-level rules every part of the scene file shares: singletons, required
//! children and attributes, numbers read as C's `sscanf` does, names and references.

use std::cell::Cell;
use std::collections::HashMap;

use glam::{DQuat, DVec3};

use crate::scene::xml::Element;
use crate::scene::{LoadLimits, SceneError};

pub(super) struct Parser<'f> {
    pub(super) file: &'f str,
    pub(super) limits: &'f LoadLimits,
    /// Keyframes copied into the description so far. A named `<motion>` is copied into every
    /// element that uses it, so this, unlike the element count, can grow as elements × keys.
    pub(super) keyframes: Cell<u64>,
}

/// Defined names (materials, meshes, vertices, motions) and their indices, looked up in
/// constant time so that a scene of many references parses in linear time.
pub(super) type Names<'e> = HashMap<&'e str, usize>;

/// The root's named `<motion>` definitions, which the camera and any geometry may use.
#[derive(Default)]
pub(super) struct Motions<'e> {
    pub(super) names: Names<'e>,
    pub(super) definitions: Vec<&'e Element>,
}

impl<'f> Parser<'f> {
    pub(super) fn new(file: &'f str, limits: &'f LoadLimits) -> Self {
        Self {
            file,
            limits,
            keyframes: Cell::new(0),
        }
    }

    /// Counts `count` more keyframes copied for `el`, refused past the element budget that
    /// `max_primitives` sets, so that named motions cannot multiply the scene's memory.
    pub(super) fn copy_keyframes(&self, el: &Element, count: usize) -> Result<(), SceneError> {
        let total = self.keyframes.get().saturating_add(count as u64);
        self.keyframes.set(total);
        if total > self.limits.max_elements() {
            return Err(SceneError::over_element_bound(
                self.file,
                el.pos.line,
                el.pos.column,
                self.limits,
                total,
                "keyframes (a named motion's counted for each element that uses it)",
            ));
        }
        Ok(())
    }
    pub(super) fn error(&self, at: &Element, message: impl Into<String>) -> SceneError {
        SceneError::new(self.file, at.pos.line, at.pos.column, message)
    }

    /// At most one child called `tag`; a second one is fatal even for optional fields (§1.1).
    pub(super) fn single<'e>(
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

    pub(super) fn required<'e>(
        &self,
        parent: &'e Element,
        tag: &'e str,
    ) -> Result<&'e Element, SceneError> {
        self.single(parent, tag)?.ok_or_else(|| {
            self.error(
                parent,
                format!("in <{}>, required element <{tag}> is missing", parent.name),
            )
        })
    }

    pub(super) fn attr<'e>(&self, el: &'e Element, name: &str) -> Result<&'e str, SceneError> {
        el.attr(name).ok_or_else(|| {
            self.error(
                el,
                format!("in <{}>, required attribute '{name}' is missing", el.name),
            )
        })
    }

    pub(super) fn number(&self, el: &Element, name: &str) -> Result<f64, SceneError> {
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

    pub(super) fn scalar(&self, el: &Element) -> Result<f64, SceneError> {
        self.number(el, "v")
    }

    pub(super) fn vec3(&self, el: &Element) -> Result<DVec3, SceneError> {
        Ok(DVec3::new(
            self.number(el, "x")?,
            self.number(el, "y")?,
            self.number(el, "z")?,
        ))
    }

    pub(super) fn color(&self, el: &Element) -> Result<DVec3, SceneError> {
        Ok(DVec3::new(
            self.number(el, "r")?,
            self.number(el, "g")?,
            self.number(el, "b")?,
        ))
    }

    pub(super) fn optional_scalar(
        &self,
        parent: &Element,
        tag: &str,
        default: f64,
    ) -> Result<f64, SceneError> {
        self.single(parent, tag)?
            .map_or(Ok(default), |el| self.scalar(el))
    }

    pub(super) fn optional_color(
        &self,
        parent: &Element,
        tag: &str,
        default: DVec3,
    ) -> Result<DVec3, SceneError> {
        self.single(parent, tag)?
            .map_or(Ok(default), |el| self.color(el))
    }

    /// `a x y z`: angle in radians about an axis that need not be unit length (§2.1).
    pub(super) fn orientation(&self, el: &Element) -> Result<DQuat, SceneError> {
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

    pub(super) fn non_negative(
        &self,
        el: &Element,
        value: f64,
        what: &str,
    ) -> Result<f64, SceneError> {
        if value < 0.0 {
            return Err(self.error(
                el,
                format!("in <{}>, {what} must not be negative, not {value}", el.name),
            ));
        }
        Ok(value)
    }

    pub(super) fn lookup(
        &self,
        el: &Element,
        attr: &str,
        what: &str,
        names: &Names,
    ) -> Result<usize, SceneError> {
        let name = self.attr(el, attr)?;
        names.get(name).copied().ok_or_else(|| {
            self.error(
                el,
                format!(
                    "in <{}>, attribute '{attr}' names {what} \"{name}\", which is not defined",
                    el.name
                ),
            )
        })
    }

    pub(super) fn check_unique(
        &self,
        el: &Element,
        what: &str,
        name: &str,
        seen: &Names,
    ) -> Result<(), SceneError> {
        if seen.contains_key(name) {
            return Err(self.error(el, format!("{what} \"{name}\" is defined twice")));
        }
        Ok(())
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
