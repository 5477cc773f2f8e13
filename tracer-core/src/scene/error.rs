use std::fmt;

/// A scene or asset that cannot be loaded, located at `file:line:column` (1-based; 0:0 when the
/// file itself cannot be read or the check has no element to point at).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SceneError {
    pub file: String,
    pub line: u32,
    pub column: u32,
    pub message: String,
    /// The [`LoadLimits`](super::LoadLimits) field that refused the scene, if a budget did.
    limit: Option<&'static str>,
}

impl SceneError {
    pub fn new(
        file: impl Into<String>,
        line: u32,
        column: u32,
        message: impl Into<String>,
    ) -> Self {
        Self {
            file: file.into(),
            line,
            column,
            message: message.into(),
            limit: None,
        }
    }

    /// A budget refusal: `count` (what the scene needs, at least) passed `limit`'s value `max`.
    /// The message names the limit and both numbers; `what` says what was counted.
    pub(crate) fn over_limit(
        file: impl Into<String>,
        line: u32,
        column: u32,
        limit: &'static str,
        count: u64,
        max: u64,
        what: &str,
    ) -> Self {
        Self {
            limit: Some(limit),
            ..Self::new(
                file,
                line,
                column,
                format!("{what}: {count} is over the load limit {limit} = {max}"),
            )
        }
    }

    /// A refusal by the element bound that `max_primitives` sets (`limits.max_elements()`):
    /// `count` of `what` passed it.
    pub(crate) fn over_element_bound(
        file: impl Into<String>,
        line: u32,
        column: u32,
        limits: &super::LoadLimits,
        count: u64,
        what: &str,
    ) -> Self {
        Self {
            limit: Some("max_primitives"),
            ..Self::new(
                file,
                line,
                column,
                format!(
                    "{what}: {count} is over {}, the most the load limit max_primitives = {} allows ({} per primitive + {})",
                    limits.max_elements(),
                    limits.max_primitives,
                    super::LoadLimits::ELEMENTS_PER_PRIMITIVE,
                    super::LoadLimits::ELEMENT_ALLOWANCE,
                ),
            )
        }
    }

    /// The name of the [`LoadLimits`](super::LoadLimits) field a budget refusal passed
    /// (`"max_texture_pixels"` or `"max_primitives"`); None for every other error.
    pub fn limit(&self) -> Option<&'static str> {
        self.limit
    }
}

impl fmt::Display for SceneError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{}:{}:{}: {}",
            self.file, self.line, self.column, self.message
        )
    }
}

impl std::error::Error for SceneError {}
