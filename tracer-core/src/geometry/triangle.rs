use glam::DVec3;

use super::TriangleRay;

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TriangleHit {
    pub t: f64,
    /// Barycentric weights of vertices 0, 1 and 2.
    pub bary: [f64; 3],
}

/// Watertight ray–triangle test (Woop, Benthin, Wald 2013): edge functions evaluated in a
/// sheared frame, so a ray through a shared edge or vertex hits at least one of the triangles
/// and never slips between them. Degenerate triangles (zero determinant) are never hit.
#[inline(always)]
pub fn intersect_triangle(
    ray: &TriangleRay,
    v0: DVec3,
    v1: DVec3,
    v2: DVec3,
    t_min: f64,
    t_max: f64,
) -> Option<TriangleHit> {
    // One body per axis permutation, each reading its coordinates by constant position: the
    // permutation is the same for every triangle a ray meets, so the branch predicts, where
    // reading `v[k]` through `DVec3`'s index match (or a stack array) cost a third of the test.
    macro_rules! permuted {
        ($($kx:literal $ky:literal $kz:literal),*) => {
            match (ray.kx, ray.ky, ray.kz) {
                $(($kx, $ky, $kz) => {
                    sheared::<$kx, $ky, $kz>(ray, v0, v1, v2, t_min, t_max)
                })*
                _ => unreachable!("TriangleRay::new makes (kx, ky, kz) a permutation"),
            }
        };
    }
    permuted!(1 2 0, 2 1 0, 2 0 1, 0 2 1, 0 1 2, 1 0 2)
}

/// [`intersect_triangle`] for the axis permutation (KX, KY, KZ) of `ray`.
#[inline(always)]
fn sheared<const KX: usize, const KY: usize, const KZ: usize>(
    ray: &TriangleRay,
    v0: DVec3,
    v1: DVec3,
    v2: DVec3,
    t_min: f64,
    t_max: f64,
) -> Option<TriangleHit> {
    let a = (v0 - ray.origin).to_array();
    let b = (v1 - ray.origin).to_array();
    let c = (v2 - ray.origin).to_array();
    let s = ray.shear;
    let ax = a[KX] - s.x * a[KZ];
    let ay = a[KY] - s.y * a[KZ];
    let bx = b[KX] - s.x * b[KZ];
    let by = b[KY] - s.y * b[KZ];
    let cx = c[KX] - s.x * c[KZ];
    let cy = c[KY] - s.y * c[KZ];
    let u = cx * by - cy * bx;
    let v = ax * cy - ay * cx;
    let w = bx * ay - by * ax;
    if (u < 0.0 || v < 0.0 || w < 0.0) && (u > 0.0 || v > 0.0 || w > 0.0) {
        return None;
    }
    let det = u + v + w;
    if det == 0.0 || !det.is_finite() {
        return None;
    }
    let t_scaled = u * (s.z * a[KZ]) + v * (s.z * b[KZ]) + w * (s.z * c[KZ]);
    let t = t_scaled / det;
    if !(t > t_min && t < t_max) {
        return None;
    }
    let inv = 1.0 / det;
    Some(TriangleHit {
        t,
        bary: [u * inv, v * inv, w * inv],
    })
}

/// Triangles per [`TriangleBlock`].
pub const BLOCK: usize = 4;

/// Four triangles' corners rounded to f32, in SoA order, for [`TriangleRayF32::may_hit`]: a
/// conservative test that rejects most triangles a ray misses while reading a third of the
/// memory of their f64 corners. Unused lanes hold zeros.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(32))]
pub struct TriangleBlock {
    /// `corners[k][axis]`: corner k of each lane, on `axis`, rounded to nearest.
    corners: [[[f32; BLOCK]; 3]; 3],
    /// Per lane: the largest |coordinate| of the three f64 corners, rounded up, which bounds
    /// their rounding error; +∞ where f32 cannot represent the triangle safely.
    scale: [f32; BLOCK],
}

/// Coordinates this large or larger could overflow f32 products in the pre-test.
const F32_LIMIT: f64 = 1e15;

impl TriangleBlock {
    /// One block per [`BLOCK`] triangles; the last block's missing lanes stay empty.
    pub fn pack(triangles: &[[DVec3; 3]]) -> Vec<TriangleBlock> {
        triangles.chunks(BLOCK).map(TriangleBlock::new).collect()
    }

    /// The block of up to [`BLOCK`] triangles; missing lanes stay empty.
    pub fn new(triangles: &[[DVec3; 3]]) -> TriangleBlock {
        let mut block = TriangleBlock {
            corners: [[[0.0; BLOCK]; 3]; 3],
            scale: [0.0; BLOCK],
        };
        for (lane, tri) in triangles.iter().take(BLOCK).enumerate() {
            let mut scale = 0f64;
            for (k, corner) in tri.iter().enumerate() {
                for axis in 0..3 {
                    block.corners[k][axis][lane] = corner[axis] as f32;
                }
                scale = scale.max(corner.abs().max_element());
            }
            let finite = tri.iter().all(|c| c.is_finite());
            block.scale[lane] = if finite && scale < F32_LIMIT {
                round_up(scale)
            } else {
                f32::INFINITY
            };
        }
        block
    }

    /// The corners of lane `lane`'s triangle as f64: exactly the triangle's own where its
    /// corners are f32 values (zeros for an empty lane).
    #[inline(always)]
    pub fn corners(&self, lane: usize) -> [DVec3; 3] {
        std::array::from_fn(|k| {
            let c = &self.corners[k];
            DVec3::new(c[0][lane] as f64, c[1][lane] as f64, c[2][lane] as f64)
        })
    }
}

/// The smallest f32 not below `v`.
fn round_up(v: f64) -> f32 {
    let f = v as f32;
    if (f as f64) < v {
        f.next_up()
    } else {
        f
    }
}

/// Per-ray constants of [`TriangleRayF32::may_hit`], from the same [`TriangleRay`] the exact
/// test uses. The SSE test's operands are kept four times over, ready to load: made once per
/// ray, they spare each block of a leaf its broadcasts and index checks.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(16))]
pub struct TriangleRayF32 {
    /// The origin's coordinates on the sheared frame's axes kx, ky, kz (in that order), then
    /// the shear's x and y, then the origin's rounding-error scale (its largest |coordinate|,
    /// rounded up), each in four lanes.
    lanes: [[f32; BLOCK]; 6],
    /// kx, ky, kz: a permutation of 0..3 (checked where it is made).
    axes: [usize; 3],
}

/// Rows of [`TriangleRayF32::lanes`].
const ORIGIN_X: usize = 0;
const SHEAR_X: usize = 3;
const SHEAR_Y: usize = 4;
const ORIGIN_SCALE: usize = 5;

/// f32 unit roundoff (2^-24).
const U32: f32 = 1.0 / (1u32 << 24) as f32;

impl TriangleRayF32 {
    // Inlined: as a call, the packet walks' per-ray set-up went through memory (shadow and
    // primary packets 0.966 and 0.969 of the time with it out of line; renders level).
    #[inline(always)]
    pub fn new(ray: &TriangleRay) -> TriangleRayF32 {
        let axes = [ray.kx, ray.ky, ray.kz];
        assert!(
            axes.iter().all(|&k| k < 3)
                && axes[0] != axes[1]
                && axes[1] != axes[2]
                && axes[0] != axes[2],
            "the sheared frame's axes {axes:?} are a permutation"
        );
        let o = ray.origin;
        let scale = if o.is_finite() {
            o.abs().max_element()
        } else {
            f64::INFINITY
        };
        // Rounded up without `round_up`'s branch on which way the conversion went, which
        // differs from ray to ray (a mispredicted branch per ray): moved up by 2^-22 of itself
        // and an absolute 1e-37 first, rounding to nearest cannot come out below it.
        let scale = if scale < F32_LIMIT {
            (scale * (1.0 + 1.0 / (1u32 << 22) as f64) + 1e-37) as f32
        } else {
            f32::INFINITY
        };
        let o = [o.x as f32, o.y as f32, o.z as f32];
        let lanes = [
            o[axes[0]],
            o[axes[1]],
            o[axes[2]],
            ray.shear.x as f32,
            ray.shear.y as f32,
            scale,
        ]
        .map(|v| [v; BLOCK]);
        TriangleRayF32 { lanes, axes }
    }

    /// The lanes of `block` whose triangle [`intersect_triangle`] might hit (ignoring the
    /// distance range). A lane is left out only when its edge functions, evaluated in f32,
    /// have opposite signs by more than their error bound, so the exact test would miss too.
    ///
    /// Error bound, with u = 2^-24 and M = the triangle's plus the origin's coordinate scale:
    /// the sheared corner coordinates (ax, ay, …) are each within e = 8uM of the exact ones
    /// (rounding the corners, origin and shear, and at most five operations); an edge function
    /// cx·by − cy·bx is then within e(sb+sc) + 2e² + 2u(|cx·by|+|cy·bx|), where sb = |bx|+|by|
    /// and sc = |cx|+|cy|, and |cx·by|+|cy·bx| ≤ sb·sc. The bound used doubles every term
    /// (covering the f64 test's own error and the bound's rounding) and adds 1e-30 for
    /// underflow. Fused multiply-adds, where the build has them, only round less, so the same
    /// bound holds with or without. Overflow or NaN never passes a comparison, so it rejects
    /// nothing.
    #[inline(always)]
    pub fn may_hit(&self, block: &TriangleBlock) -> u32 {
        #[cfg(target_arch = "x86_64")]
        {
            self.may_hit_sse(block)
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            self.may_hit_scalar(block)
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    #[allow(unused_unsafe)]
    fn may_hit_sse(&self, block: &TriangleBlock) -> u32 {
        use std::arch::x86_64::*;
        // `a·b + c`, `c − a·b` and `a·b − c`, fused where the build targets FMA (the
        // project's x86-64-v3 default), in the same form as `may_hit_scalar`'s.
        // SAFETY (all three): FMA is enabled for the build where they use it; SSE is baseline.
        #[inline(always)]
        fn madd(a: __m128, b: __m128, c: __m128) -> __m128 {
            #[cfg(target_feature = "fma")]
            return unsafe { _mm_fmadd_ps(a, b, c) };
            #[cfg(not(target_feature = "fma"))]
            return unsafe { _mm_add_ps(_mm_mul_ps(a, b), c) };
        }
        #[inline(always)]
        fn nmadd(a: __m128, b: __m128, c: __m128) -> __m128 {
            #[cfg(target_feature = "fma")]
            return unsafe { _mm_fnmadd_ps(a, b, c) };
            #[cfg(not(target_feature = "fma"))]
            return unsafe { _mm_sub_ps(c, _mm_mul_ps(a, b)) };
        }
        #[inline(always)]
        fn msub(a: __m128, b: __m128, c: __m128) -> __m128 {
            #[cfg(target_feature = "fma")]
            return unsafe { _mm_fmsub_ps(a, b, c) };
            #[cfg(not(target_feature = "fma"))]
            return unsafe { _mm_sub_ps(_mm_mul_ps(a, b), c) };
        }
        let [kx, ky, kz] = self.axes;
        let lanes = |row: usize| self.lanes[row].as_ptr();
        // SAFETY: SSE is part of the x86_64 baseline; loads read 16-byte [f32; 4] rows, and
        // `axes` holds row indices below 3 (asserted in `new`).
        unsafe {
            let ox = _mm_loadu_ps(lanes(ORIGIN_X));
            let oy = _mm_loadu_ps(lanes(ORIGIN_X + 1));
            let oz = _mm_loadu_ps(lanes(ORIGIN_X + 2));
            let sx = _mm_loadu_ps(lanes(SHEAR_X));
            let sy = _mm_loadu_ps(lanes(SHEAR_Y));
            let project = |k: usize| {
                let c = &block.corners[k];
                let x = _mm_sub_ps(_mm_loadu_ps(c.get_unchecked(kx).as_ptr()), ox);
                let y = _mm_sub_ps(_mm_loadu_ps(c.get_unchecked(ky).as_ptr()), oy);
                let z = _mm_sub_ps(_mm_loadu_ps(c.get_unchecked(kz).as_ptr()), oz);
                (nmadd(sx, z, x), nmadd(sy, z, y))
            };
            let (ax, ay) = project(0);
            let (bx, by) = project(1);
            let (cx, cy) = project(2);
            let sign = _mm_set1_ps(-0.0);
            let abs = |v: __m128| _mm_andnot_ps(sign, v);
            let scale = _mm_add_ps(
                _mm_loadu_ps(block.scale.as_ptr()),
                _mm_loadu_ps(lanes(ORIGIN_SCALE)),
            );
            // e doubled: 16uM.
            let e = _mm_mul_ps(scale, _mm_set1_ps(16.0 * U32));
            // 2e² doubled, plus the underflow margin.
            let base = madd(e, _mm_mul_ps(e, _mm_set1_ps(4.0)), _mm_set1_ps(1e-30));
            let (sa, sb, sc) = (
                _mm_add_ps(abs(ax), abs(ay)),
                _mm_add_ps(abs(bx), abs(by)),
                _mm_add_ps(abs(cx), abs(cy)),
            );
            let rel = _mm_set1_ps(4.0 * U32);
            let (ra, rb) = (_mm_mul_ps(rel, sa), _mm_mul_ps(rel, sb));
            // One edge function p·q − r·s and its bound, given its corners' |x|+|y| sums
            // (`rel_s0` is 4u times the first).
            let edge = |p, q, r, s, rel_s0, s0, s1| {
                let f = msub(p, q, _mm_mul_ps(r, s));
                let bound = madd(rel_s0, s1, madd(e, _mm_add_ps(s0, s1), base));
                (f, bound)
            };
            let (u, eu) = edge(cx, by, cy, bx, rb, sb, sc);
            let (v, ev) = edge(ax, cy, ay, cx, ra, sa, sc);
            let (w, ew) = edge(bx, ay, by, ax, ra, sa, sb);
            let neg = |f: __m128, b: __m128| _mm_cmplt_ps(f, _mm_xor_ps(b, sign));
            let pos = |f: __m128, b: __m128| _mm_cmpgt_ps(f, b);
            let any_neg = _mm_or_ps(_mm_or_ps(neg(u, eu), neg(v, ev)), neg(w, ew));
            let any_pos = _mm_or_ps(_mm_or_ps(pos(u, eu), pos(v, ev)), pos(w, ew));
            let miss = _mm_movemask_ps(_mm_and_ps(any_neg, any_pos)) as u32;
            !miss & 0xf
        }
    }

    /// The same test lane by lane, for targets without SSE (and as the SSE version's check).
    #[cfg_attr(target_arch = "x86_64", allow(dead_code))]
    fn may_hit_scalar(&self, block: &TriangleBlock) -> u32 {
        // Fused exactly where `may_hit_sse` fuses.
        let madd = |a: f32, b: f32, c: f32| {
            if cfg!(target_feature = "fma") {
                a.mul_add(b, c)
            } else {
                a * b + c
            }
        };
        let nmadd = |a: f32, b: f32, c: f32| madd(-a, b, c);
        let msub = |a: f32, b: f32, c: f32| madd(a, b, -c);
        let [kx, ky, kz] = self.axes;
        let [ox, oy, oz, sx, sy, origin_scale] = self.lanes.map(|row| row[0]);
        let mut mask = 0;
        for lane in 0..BLOCK {
            let project = |k: usize| {
                let c = &block.corners[k];
                let z = c[kz][lane] - oz;
                (
                    nmadd(sx, z, c[kx][lane] - ox),
                    nmadd(sy, z, c[ky][lane] - oy),
                )
            };
            let (ax, ay) = project(0);
            let (bx, by) = project(1);
            let (cx, cy) = project(2);
            let e = (block.scale[lane] + origin_scale) * (16.0 * U32);
            let base = madd(e, e * 4.0, 1e-30);
            let (sa, sb, sc) = (
                ax.abs() + ay.abs(),
                bx.abs() + by.abs(),
                cx.abs() + cy.abs(),
            );
            let rel = 4.0 * U32;
            let (ra, rb) = (rel * sa, rel * sb);
            let edge = |p: f32, q: f32, r: f32, s: f32, rel_s0: f32, s0: f32, s1: f32| {
                (msub(p, q, r * s), madd(rel_s0, s1, madd(e, s0 + s1, base)))
            };
            let (u, eu) = edge(cx, by, cy, bx, rb, sb, sc);
            let (v, ev) = edge(ax, cy, ay, cx, ra, sa, sc);
            let (w, ew) = edge(bx, ay, by, ax, ra, sa, sb);
            let any_neg = u < -eu || v < -ev || w < -ew;
            let any_pos = u > eu || v > ev || w > ew;
            if !(any_neg && any_pos) {
                mask |= 1 << lane;
            }
        }
        mask
    }
}

/// Calls `test` on each slot in `slots` whose triangle the f32 pre-test cannot rule out, in
/// slot order, until it returns true (then returns true). `blocks[i]` holds slots 4i..4i+4,
/// whose f64 corners `corners` holds (prefetched with the blocks, before the pre-test), or
/// is empty where the blocks hold the corners exactly ([`TriangleBlock::corners`]).
#[inline(always)]
pub fn any_candidate(
    blocks: &[TriangleBlock],
    corners: &[[DVec3; 3]],
    ray: &TriangleRayF32,
    slots: std::ops::Range<usize>,
    mut test: impl FnMut(usize) -> bool,
) -> bool {
    let first = slots.start / BLOCK;
    let leaf_blocks = &blocks[first..slots.end.div_ceil(BLOCK)];
    prefetch_leaf_blocks(leaf_blocks);
    // The f64 corners of the whole leaf too, now rather than for the pre-test's survivors
    // once it is done: their load then overlaps the block's instead of following it (the
    // two misses in a row were most of the leaf's time for incoherent rays).
    if let Some(leaf_corners) = corners.get(slots.clone()) {
        prefetch(leaf_corners.as_ptr(), size_of_val(leaf_corners));
    }
    for (b, block) in leaf_blocks.iter().enumerate() {
        let base = (first + b) * BLOCK;
        // Lanes inside `slots`.
        let lo = slots.start.saturating_sub(base);
        let hi = (slots.end - base).min(BLOCK);
        let lanes = ((1u32 << hi) - 1) & !((1u32 << lo) - 1);
        let mut mask = ray.may_hit(block) & lanes;
        while mask != 0 {
            let lane = mask.trailing_zeros() as usize;
            mask &= mask - 1;
            if test(base + lane) {
                return true;
            }
        }
    }
    false
}

/// Starts fetching the f32 blocks and the f64 corners of the triangles in `slots` (a hint:
/// nothing is read), so that a caller about to test several leaves has all their loads in
/// flight at once.
#[inline(always)]
pub fn prefetch_leaf(
    blocks: &[TriangleBlock],
    corners: &[[DVec3; 3]],
    slots: std::ops::Range<usize>,
) {
    prefetch_blocks(blocks, slots.clone());
    if let Some(leaf_corners) = corners.get(slots) {
        prefetch(leaf_corners.as_ptr(), size_of_val(leaf_corners));
    }
}

/// Starts fetching the f32 blocks of the triangles in `slots` (a hint: nothing is read).
#[inline(always)]
pub fn prefetch_blocks(blocks: &[TriangleBlock], slots: std::ops::Range<usize>) {
    if let Some(leaf_blocks) = blocks.get(slots.start / BLOCK..slots.end.div_ceil(BLOCK)) {
        prefetch(leaf_blocks.as_ptr(), size_of_val(leaf_blocks));
    }
}

/// Bytes of the blocks of a leaf the builder makes: at most two blocks (see
/// `accel::build`'s `MAX_LEAF_BLOCKS`).
const LEAF_BLOCK_BYTES: usize = 2 * size_of::<TriangleBlock>();

/// Starts fetching `blocks` (a leaf's): the lines of two blocks unconditionally, without the
/// loop [`prefetch`] runs, whose count differs from leaf to leaf (its exit branch mispredicted
/// about twice an incoherent ray); only a longer run of blocks takes the loop for the rest.
/// A one-block leaf fetches the lines after it too (the next leaf's, harmless).
#[inline(always)]
#[allow(unused_unsafe)]
fn prefetch_leaf_blocks(blocks: &[TriangleBlock]) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        let p = blocks.as_ptr() as *const i8;
        // Lines at p, p + 64, …: they cover [p, p + LEAF_BLOCK_BYTES] wherever p starts in
        // its line.
        for line in 0..LEAF_BLOCK_BYTES.div_ceil(64) + 1 {
            // SAFETY: prefetching never faults, whatever the address.
            unsafe { _mm_prefetch::<_MM_HINT_T0>(p.wrapping_add(64 * line)) };
        }
        let bytes = size_of_val(blocks);
        if bytes > LEAF_BLOCK_BYTES {
            prefetch(p.wrapping_add(LEAF_BLOCK_BYTES), bytes - LEAF_BLOCK_BYTES);
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = blocks;
}

/// Starts fetching the cache lines of `bytes` bytes at `p` (a hint: nothing is read).
#[inline(always)]
#[allow(unused_unsafe)]
fn prefetch<T>(p: *const T, bytes: usize) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        let p = p as *const i8;
        let mut offset = 0;
        while offset < bytes {
            // SAFETY: prefetching never faults, whatever the address.
            unsafe { _mm_prefetch::<_MM_HINT_T0>(p.wrapping_add(offset)) };
            offset += 64;
        }
        if bytes > 0 {
            // The last line, when `p` does not start on a line boundary.
            // SAFETY: as above.
            unsafe { _mm_prefetch::<_MM_HINT_T0>(p.wrapping_add(bytes - 1)) };
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (p, bytes);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Ray;

    fn shoot(origin: DVec3, dir: DVec3, tri: [DVec3; 3]) -> Option<TriangleHit> {
        intersect_triangle(
            &TriangleRay::new(&Ray::new(origin, dir)),
            tri[0],
            tri[1],
            tri[2],
            0.0,
            f64::INFINITY,
        )
    }

    fn point(next: &mut impl FnMut() -> f64) -> DVec3 {
        DVec3::new(next(), next(), next())
    }

    #[test]
    fn the_f32_pretest_never_rejects_a_hit_and_rejects_clear_misses() {
        let mut next = crate::test_rng::uniform(42);
        for (size, offset) in [
            (1.0, 0.0),
            (1e-3, 0.0),
            (1e-3, 50.0),
            (1e4, -1e5),
            (1e-6, 1.0),
        ] {
            let (mut rejected, mut misses) = (0, 0);
            for _ in 0..300 {
                let centre = point(&mut next) * 10.0 * size + DVec3::splat(offset);
                let tris: Vec<[DVec3; 3]> = (0..4)
                    .map(|_| [0, 1, 2].map(|_| centre + (point(&mut next) - 0.5) * size))
                    .collect();
                let blocks = TriangleBlock::pack(&tris);
                // Aim at a corner, a point on an edge or inside, from near or far.
                let target = (next() * 4.0) as usize;
                let t = &tris[target];
                let (w1, w2) = match (next() * 3.0) as usize {
                    0 => (0.0, 0.0),
                    1 => (next(), 0.0),
                    _ => (next() * 0.5, next() * 0.5),
                };
                let aim = t[0] + (t[1] - t[0]) * w1 + (t[2] - t[0]) * w2;
                let dir = (point(&mut next) - 0.5).normalize() * (0.1 + next() * 10.0);
                let origin = aim - dir * (next() * 100.0 * size / dir.length());
                let ray = TriangleRay::new(&Ray::new(origin, dir));
                let ray32 = TriangleRayF32::new(&ray);
                let mask = ray32.may_hit(&blocks[0]);
                assert_eq!(mask, ray32.may_hit_scalar(&blocks[0]));
                for (lane, tri) in tris.iter().enumerate() {
                    let hit = intersect_triangle(
                        &ray,
                        tri[0],
                        tri[1],
                        tri[2],
                        f64::NEG_INFINITY,
                        f64::INFINITY,
                    );
                    if hit.is_some() {
                        assert!(mask & (1 << lane) != 0, "hit rejected at size {size}");
                    } else if lane != target {
                        // The target may be grazed, a miss that f32 cannot tell.
                        misses += 1;
                        rejected += (mask & (1 << lane) == 0) as usize;
                    }
                }
            }
            // Where f32 resolves the triangles well, almost every miss is rejected: only rays
            // grazing an edge are left to the f64 test.
            if size >= 1e-2 * offset.abs() {
                assert!(
                    rejected * 10 > misses * 9,
                    "{rejected} of {misses} misses rejected"
                );
            }
        }
    }

    #[test]
    fn candidates_stay_inside_the_slot_range_across_blocks() {
        // Eleven triangles stacked along z, all under the ray, and one beside it.
        let mut tris: Vec<[DVec3; 3]> = (0..11)
            .map(|i| [DVec3::ZERO, DVec3::X, DVec3::Y].map(|c| c + DVec3::Z * i as f64))
            .collect();
        tris[5] = tris[5].map(|c| c + DVec3::X * 5.0);
        let blocks = TriangleBlock::pack(&tris);
        let ray = TriangleRay::new(&Ray::new(DVec3::new(0.25, 0.25, 20.0), -DVec3::Z));
        let ray32 = TriangleRayF32::new(&ray);
        for (start, end) in [(0, 11), (2, 7), (4, 8), (3, 4), (9, 11)] {
            let mut seen = Vec::new();
            any_candidate(&blocks, &tris, &ray32, start..end, |slot| {
                seen.push(slot);
                false
            });
            let expected: Vec<usize> = (start..end).filter(|&i| i != 5).collect();
            assert_eq!(seen, expected);
        }
        // Returning true stops at once.
        let mut calls = 0;
        assert!(any_candidate(&blocks, &tris, &ray32, 0..11, |_| {
            calls += 1;
            true
        }));
        assert_eq!(calls, 1);
    }

    #[test]
    fn the_f32_pretest_rejects_nothing_it_cannot_represent() {
        let far = [
            DVec3::splat(1e20),
            DVec3::new(1e20, 2e20, 1e20),
            DVec3::splat(3e20),
        ];
        let nan = [DVec3::ZERO, DVec3::X, DVec3::splat(f64::NAN)];
        let blocks = TriangleBlock::pack(&[far, nan]);
        let ray = TriangleRay::new(&Ray::new(DVec3::new(0.0, 5.0, 0.0), DVec3::Z));
        assert_eq!(TriangleRayF32::new(&ray).may_hit(&blocks[0]) & 0b11, 0b11);
        // An origin out of f32's safe range disables rejection too.
        let tri = [DVec3::ZERO, DVec3::X, DVec3::Y];
        let blocks = TriangleBlock::pack(&[tri]);
        let ray = TriangleRay::new(&Ray::new(DVec3::new(1e17, 0.0, 1.0), DVec3::Z));
        assert_eq!(TriangleRayF32::new(&ray).may_hit(&blocks[0]) & 1, 1);
    }

    #[test]
    fn barycentrics_and_distance() {
        let tri = [DVec3::ZERO, DVec3::X, DVec3::Y];
        let hit = shoot(DVec3::new(0.25, 0.5, 2.0), -DVec3::Z, tri).unwrap();
        assert!((hit.t - 2.0).abs() < 1e-15);
        let [b0, b1, b2] = hit.bary;
        assert!((b0 - 0.25).abs() < 1e-15 && (b1 - 0.25).abs() < 1e-15 && (b2 - 0.5).abs() < 1e-15);
        // Both sides are hit (back faces are shaded with a flipped normal).
        assert!(shoot(DVec3::new(0.25, 0.25, -2.0), DVec3::Z, tri).is_some());
        assert!(shoot(DVec3::new(1.0, 1.0, 2.0), -DVec3::Z, tri).is_none());
    }

    #[test]
    fn shared_edges_and_vertices_leave_no_gap() {
        // A fan of 6 triangles around the origin; rays through the shared edges and the centre.
        let ring: Vec<DVec3> = (0..6)
            .map(|i| {
                let a = i as f64 * std::f64::consts::TAU / 6.0 + 0.1;
                DVec3::new(a.cos() * 3.3, a.sin() * 1.7, 0.37 * a.sin())
            })
            .collect();
        let tris: Vec<[DVec3; 3]> = (0..6)
            .map(|i| [DVec3::ZERO, ring[i], ring[(i + 1) % 6]])
            .collect();
        let origin = DVec3::new(0.123, -0.456, 9.0);
        let mut targets = vec![DVec3::ZERO];
        for r in &ring {
            for k in 1..50 {
                targets.push(*r * (k as f64 / 50.0));
            }
        }
        for target in targets {
            let dir = target - origin;
            let hits = tris
                .iter()
                .filter(|t| shoot(origin, dir, **t).is_some())
                .count();
            assert!(hits >= 1, "ray through {target} slipped between triangles");
        }
    }

    #[test]
    fn degenerate_triangles_are_never_hit() {
        let flat = [DVec3::ZERO, DVec3::X, DVec3::X * 2.0];
        assert!(shoot(DVec3::new(1.0, 0.0, 1.0), -DVec3::Z, flat).is_none());
        let point = [DVec3::ONE; 3];
        assert!(shoot(DVec3::new(1.0, 1.0, 2.0), -DVec3::Z, point).is_none());
    }
}
