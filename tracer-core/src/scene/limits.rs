//! What loading one scene may make the process allocate: decoded texture pixels and primitives,
//! checked before the memory is spent. The `tracer` CLI loads without limits; the farm applies
//! them to every submitted scene.

/// Budgets for loading one scene. A scene over one of them is refused with a [`SceneError`]
/// whose [`limit`](SceneError::limit) names the field, and whose message gives the limit and
/// the count that passed it, at `file:line:column` of the element (or OBJ face) that crossed it.
///
/// [`SceneError`]: super::SceneError
#[derive(Clone, Debug, PartialEq)]
pub struct LoadLimits {
    /// Decoded texture pixels (width*height summed over the textures the scene uses), checked from
    /// the PNG header before anything is decoded.
    pub max_texture_pixels: u64,
    /// Spheres + scene triangles + models (one each: an instance in the top-level BVH) +
    /// triangles of each distinct mesh file (counted once per file, not per instance), checked
    /// while parsing, before the tree/BVHs are allocated.
    ///
    /// It also bounds the XML element tree the parser holds: at most
    /// [`ELEMENTS_PER_PRIMITIVE`](Self::ELEMENTS_PER_PRIMITIVE) elements per allowed primitive
    /// plus [`ELEMENT_ALLOWANCE`](Self::ELEMENT_ALLOWANCE), so a file of millions of
    /// non-geometry elements is refused too.
    pub max_primitives: u64,
}

impl Default for LoadLimits {
    /// A farm's defaults: 256 million texture pixels (about 768 MB of 8-bit RGB texels, more
    /// than the course's textures by far) and 20 million primitives (the course's largest
    /// scene, the dragon, has under a million triangles).
    fn default() -> Self {
        Self {
            max_texture_pixels: 256_000_000,
            max_primitives: 20_000_000,
        }
    }
}

impl LoadLimits {
    /// No budget at all: what [`SceneDescription::parse`](super::SceneDescription::parse) and
    /// [`Scene::build`](super::Scene::build) use, for local renders of trusted files.
    pub const UNLIMITED: LoadLimits = LoadLimits {
        max_texture_pixels: u64::MAX,
        max_primitives: u64::MAX,
    };

    /// XML elements allowed per primitive of `max_primitives`: a triangle with its own three
    /// vertices, a transform and a few keyframes takes about 30.
    pub const ELEMENTS_PER_PRIMITIVE: u64 = 64;

    /// XML elements allowed on top of the per-primitive share (camera, materials, lights, …).
    pub const ELEMENT_ALLOWANCE: u64 = 65_536;

    /// The most XML elements a scene file may hold under these limits.
    pub fn max_elements(&self) -> u64 {
        self.max_primitives
            .saturating_mul(Self::ELEMENTS_PER_PRIMITIVE)
            .saturating_add(Self::ELEMENT_ALLOWANCE)
    }
}
